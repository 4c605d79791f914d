"""Stability of the shipped simulated-system models over their operating range and beyond it.

Bouc-Wen (configs/bouc-wen.toml, trained on 10 N and 80 N sweeps): free run from rest on swept
sines and 35.59 Hz sines at 10, 50 and 80 N must not diverge (mean peak within 3x the true peak, no
divergence flag, no 'prediction' flag); at 160 N, twice the largest training amplitude, the answer
must say the input is outside (``out_of_range`` starts with 'u') whatever the mean does.
BERT stand-in (configs/bert-standin.toml): the same on 0.05-0.20 V sweeps and an 18 Hz sine, and
a 0.6 V sweep flagged.

Slow (trains the shipped configs as shipped); the quick suite covers the flags on a small model in
test_envelope.py.
"""
from __future__ import annotations

import numpy as np
import pytest

from gpnarx.model.envelope import assess

pytestmark = pytest.mark.slow


def _trained(name):
    from gpnarx.training.config import load_config
    from gpnarx.training.defaults import shipped_config
    from gpnarx.training.pipeline import model_from_config

    cfg = load_config(shipped_config(name))
    return model_from_config(cfg, None, None).fit(cfg.records_for("train"))


def _check(model, rec, inside: bool):
    run = model.simulate(rec.u, method="linear")
    flags = assess(model.envelope_, run, rec.u, rec.y)
    ratio = float(np.max(np.abs(run.mean)) / np.max(np.abs(rec.y)))
    if inside:
        assert ratio <= 3.0 and flags["diverged_paths"] == 0 and "prediction" not in flags["out_of_range"], \
            (rec.name, ratio, flags)
        assert "u" not in flags["out_of_range"], (rec.name, flags)
    else:
        assert flags["out_of_range"][:1] == ["u"], (rec.name, ratio, flags)
    return ratio


def _sim(system, excitation, amplitude, **kw):
    from gpnarx.training.config import simulate_record

    return simulate_record({"system": system, "excitation": excitation, "amplitude": amplitude, "seed": 3, **kw})


def test_bouc_wen_inside_and_beyond_its_training_amplitudes():
    model = _trained("bouc-wen")
    for a in (10.0, 50.0, 80.0):
        _check(model, _sim("bouc-wen", "sweep", a), inside=True)
        _check(model, _sim("bouc-wen", "sine", a), inside=True)
    _check(model, _sim("bouc-wen", "sweep", 160.0), inside=False)


def test_bert_standin_inside_and_beyond_its_training_amplitudes():
    model = _trained("bert-standin")
    for a in (0.05, 0.10, 0.20):
        _check(model, _sim("bert-standin", "sweep", a), inside=True)
    _check(model, _sim("bert-standin", "sine", 0.15, freq=18.0), inside=True)
    _check(model, _sim("bert-standin", "sweep", 0.6), inside=False)
