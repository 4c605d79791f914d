"""Leave one noise level out (studies.noise_lolo): the fold config never holds the held-out run, its noise
windows move onto the other runs, and the table scores the held-out run against an ARX that never saw it."""
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from gpnarx.training.config import load_config
from gpnarx.training.datapaths import bert_data_dir
from gpnarx.training.defaults import shipped_config
from studies import noise_lolo as nl

DATA = bert_data_dir()
NOISE = ("Rand0p10", "Rand0p15", "Rand0p25")


def _folders():
    return {n: DATA / "Rand" / n for n in NOISE}


def test_fold_config_moves_the_noise_windows_off_the_held_out_run():
    cfg = load_config(shipped_config("bert-real"))
    f = _folders()
    fold = nl.fold_config(cfg, f["Rand0p25"], [f["Rand0p10"], f["Rand0p15"]])
    paths = {str(Path(s.path).resolve()) for s in fold.records if s.path is not None}
    assert str(f["Rand0p25"].resolve()) not in paths
    shipped_noise = [s for s in cfg.records if s.path is not None and Path(s.path).parent.name == "Rand"]
    moved = [s for s in fold.records if "@" in s.name]
    # every train / lags window of a noise run becomes the same window on each other run; validate ones go
    want = sorted((s.window, tuple(r for r in s.roles if r in ("train", "lags")), o.name)
                  for s in shipped_noise if set(s.roles) & {"train", "lags"} for o in (f["Rand0p10"], f["Rand0p15"]))
    got = sorted((s.window, tuple(s.roles), Path(s.path).name) for s in moved)
    assert got == want and got
    # the other records are the shipped config's, untouched
    assert [s for s in fold.records if "@" not in s.name] == [s for s in cfg.records if s not in shipped_noise]
    with pytest.raises(ValueError, match="no train window"):
        nl.fold_config(dataclasses.replace(fold, records=[s for s in fold.records if "@" not in s.name]),
                       f["Rand0p25"], [f["Rand0p10"]])


def test_lolo_checks_apply_every_target_to_every_run():
    def row(fit, arx, cov, sharp):
        return {"arx_class": {"fit": arx}, "whole_linear": {"fit": fit, "coverage": cov, "sharpness": sharp}}

    ok = {"runs": {"a": row(80.0, 75.0, 99.0, 1.2), "b": row(70.0, 70.0, 95.0, 1.5)}}
    assert nl.lolo_checks(ok)["whole_linear"]["met"]
    for bad in (row(69.9, 70.0, 99.0, 1.0), row(80.0, 70.0, 89.9, 1.0), row(80.0, 70.0, 99.0, 1.51)):
        c = nl.lolo_checks({"runs": {**ok["runs"], "c": bad}})["whole_linear"]
        assert not c["met"]
    c = nl.lolo_checks({"runs": {**ok["runs"], "c": row(60.0, 70.0, 99.0, 1.0)}})["whole_linear"]
    assert c["below_arx"] == ["c"]


@pytest.mark.skipif(not all((DATA / "Rand" / n).is_dir() for n in NOISE),
                    reason=f"the lab's noise runs are not under {DATA}")
def test_lolo_table_scores_each_held_out_run_with_a_model_that_never_saw_it():
    from gpnarx.model.estimator import GPNARX

    cfg = load_config(shipped_config("bert-real"))
    seen = []

    def fit(fold):
        train = fold.records_for("train")
        seen.append({Path(s.path).name for s in fold.records if s.path is not None})
        short = [r.window(0.0, min(1.0, r.n / r.fs)) for r in train]
        return GPNARX(ny=2, nu=2, max_train_points=150, n_restarts=0).fit(short)

    table = nl.lolo_table(cfg, DATA, mc_paths=8, max_seconds=2.0, fit=fit)
    assert sorted(table["runs"]) == sorted(NOISE)
    for name, r in table["runs"].items():
        assert sorted(r["trained_on"]) == sorted(n for n in NOISE if n != name)
        for key in ("whole_linear", "whole_mc"):
            assert np.isfinite(r[key]["fit"]) and 0.0 <= r[key]["coverage"] <= 100.0 and r[key]["sharpness"] > 0
        assert r["arx_class"]["fit"] is not None
    assert set(table["checks"]) == {"whole_linear", "whole_mc"}
    assert [name not in s for name, s in zip(table["runs"], seen)] == [True] * len(NOISE)
    md = nl.markdown(table)
    assert all(n in md for n in NOISE) and "targets" in md
