"""The real-rig monitor default ``bert-real-monitor``: bert-real's GP with a novelty calibration from
healthy real windows, derived without a refit, judging unseen healthy windows and flagging a drive
outside its probe. Skipped, with the reason, when the lab records are not beside the repository."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from gpnarx.training import defaults
from gpnarx.training.config import bert_data_dir

DATA = bert_data_dir()
pytestmark = pytest.mark.skipif(not (DATA / "Sine").is_dir(),
                                reason=f"real BERT records not found under {DATA} (set GPNARX_BERT_DATA)")


def test_plan_skips_the_monitor_when_its_source_is_neither_present_nor_built(tmp_path):
    plan = defaults.plan_defaults(tmp_path, ["bert-real-monitor"])
    assert plan["missing"] == [] and "derived from bert-real" in plan["skipped"]["bert-real-monitor"]
    plan = defaults.plan_defaults(tmp_path, ["bert-real", "bert-real-monitor"])
    assert plan["missing"] == ["bert-real", "bert-real-monitor"]


@pytest.fixture(scope="module")
def registry(bert_real_registry, tmp_path_factory):
    """bert-real as trained once for the session (conftest), copied, with the monitor derived from it."""
    root = tmp_path_factory.mktemp("reg") / "registry"
    shutil.copytree(bert_real_registry, root)
    defaults.build_default("bert-real-monitor", root)
    return root


def test_monitor_is_the_same_gp_with_a_probe_and_threshold(registry):
    from gpnarx.storage.registry import Registry
    from gpnarx.training.real_monitor import CALIBRATION, WINDOW_SECONDS

    reg = Registry(registry).scan()
    src, mon = reg.get("bert-real"), reg.get("bert-real-monitor")
    assert mon.manifest["derived_from"]["version"] == src.version
    assert mon.manifest["files"] == src.manifest["files"]  # the very same arrays (sha256)
    nov = mon.manifest["novelty"]
    n_windows = sum(int((t1 - t0) // WINDOW_SECONDS) for t0, t1 in CALIBRATION.values())
    assert len(nov["calibration"]["records"]) == n_windows and nov["calibration"]["refit"] is False
    assert nov["method"] == "segment_median_rms" and nov["threshold"] >= max(nov["healthy_scores"])
    # the threshold's spread is the one between recordings: one group per calibration recording
    assert nov["n_groups"] == len(CALIBRATION) and sorted(set(nov["calibration"]["groups"])) == sorted(CALIBRATION)
    assert nov["log_std"] ** 2 >= nov["log_std_between"] ** 2 + nov["log_std_within"] ** 2 - 1e-12
    # linearised calibration, so the monitor scores linearised by default (a score is compared with its kind)
    assert nov["calibration"]["propagation"] == "linear" and nov["mc_paths"] == 0
    assert mon.default_method("novelty") == "linear"
    lo = nov["probe"]["frequency"] - nov["probe"]["frequency_tolerance"]
    hi = nov["probe"]["frequency"] + nov["probe"]["frequency_tolerance"]
    assert 4.5 <= lo <= 5.5 and 9.5 <= hi <= 10.0  # the calibrated drives, 5-9.75 Hz, and no more
    assert src.manifest.get("novelty") is None  # the source model is left as it was


def test_monitor_judges_an_unseen_healthy_window_and_refuses_an_off_probe_drive(registry):
    from gpnarx.model.novelty import novelty_score, novelty_start
    from gpnarx.model.probe import probe_check
    from gpnarx.storage.registry import Registry
    from gpnarx.training.real_monitor import OFF_PROBE, TEST, windows

    mon = Registry(registry).scan().get("bert-real-monitor")
    nov = mon.manifest["novelty"]
    test = windows(DATA, {k: TEST[k] for k in list(TEST)[:1]})[:3]
    for w in test:
        assert probe_check(w.u, w.fs, nov["probe"], "measured")["probe_match"] is True
        run = mon.model.simulate(w.u, method="linear", y0=novelty_start(w.y, mon.model.ny))
        score = novelty_score(w.y, run.mean, run.std, nov["method"])["score"]
        assert np.isfinite(score) and score < nov["threshold"], (w.name, score, nov["threshold"])
    off = windows(DATA, OFF_PROBE)[0]
    check = probe_check(off.u, off.fs, nov["probe"], "measured")
    assert check["probe_match"] is False and check["probe_reasons"]
