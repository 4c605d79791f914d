"""The one novelty assessment (gpnarx.model.novelty.assess_novelty / judge) the CLI, the service and
training share."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from gpnarx.model.novelty import UnusableProbeContract, assess_novelty, judge, record_envelope
from gpnarx.model.probe import probe_contract

FS = 100.0


def _record(amp=1.0, f=5.0, n=800):
    t = np.arange(n) / FS
    u = amp * np.sin(2 * np.pi * f * t)
    return u, 0.5 * u


def _calibration():
    recs = [_record(1.0), _record(1.1)]
    return {"threshold": 2.0, "false_alarm_rate": 0.01, "method": "rms_standardised_residual",
            "envelope": record_envelope(recs), "probe": probe_contract([u for u, _ in recs], FS, start="measured")}


def test_a_matching_record_is_scored_and_judged():
    nov = _calibration()
    u, y = _record(1.05)
    run = SimpleNamespace(mean=y + 0.01, std=np.full(y.size, 0.01))
    a = assess_novelty(nov, u, y, FS, run, flags={"out_of_range": [], "diverged_paths": 0})
    assert a["score"] == pytest.approx(1.0) and a["verdict"] == "healthy" and a["out_of_range"] == []
    assert a["probe_match"] is True and a["threshold"] == 2.0 and a["false_alarm_rate"] == 0.01
    assert a["score_method"] == "rms_standardised_residual" and a["n_samples"] == y.size
    far = SimpleNamespace(mean=y + 0.05, std=np.full(y.size, 0.01))
    assert assess_novelty(nov, u, y, FS, far)["verdict"] == "novel"


def test_flags_envelope_and_probe_are_merged_in_order():
    nov = _calibration()
    u, y = _record(10.0, f=9.0)  # 10x the healthy peak and another frequency
    j = judge(nov, 0.5, u, y, FS, flags={"out_of_range": ["u"]})
    # the drive is not the probe: unjudged (the envelope left with it is no evidence of damage), reasons kept
    assert j["verdict"] == "unjudged" and j["out_of_range"][0] == "u" and j["out_of_range"][-1] == "probe"
    assert j["probe_reasons"] and j["drive"]["frequency"] == pytest.approx(9.0, abs=0.2)
    assert j["out_of_range"].count("u") == 1 and "y" in j["out_of_range"] and j["probe_match"] is False
    assert judge(nov, 0.5, u, y, FS, check_probe=False)["out_of_range"] == ["u", "y"]


def test_an_unusable_probe_contract_is_its_own_error():
    nov = {**_calibration(), "probe": {"kind": "nonsense"}}
    u, y = _record()
    run = SimpleNamespace(mean=y, std=np.full(y.size, 0.01))
    with pytest.raises(UnusableProbeContract):
        assess_novelty(nov, u, y, FS, run)
    with pytest.raises(ValueError) as err:  # a record that cannot be scored is a plain ValueError
        assess_novelty(_calibration(), u[:5], y[:5], FS, SimpleNamespace(mean=y[:5], std=np.zeros(5)))
    assert not isinstance(err.value, UnusableProbeContract)


def test_verdict_unjudged_on_a_probe_mismatch_whatever_the_score_and_envelope():
    from gpnarx.model.novelty import VERDICTS, verdict

    assert VERDICTS == ("healthy", "novel", "unjudged")
    assert verdict(0.041, 1.01, ["y", "probe"], probe_match=False) == "unjudged"  # low score: not "healthy"
    assert verdict(9.0, 1.01, ["probe"], probe_match=False) == "unjudged"  # high score: not an alarm either
    assert verdict(0.5, 1.0, ["y"], probe_match=True) == "novel"  # the envelope left on the probe: an alarm
    assert verdict(1.5, 1.0, [], probe_match=True) == "novel" and verdict(0.5, 1.0, [], None) == "healthy"
    assert verdict(1.5, 1.0, [], None) == "novel"
