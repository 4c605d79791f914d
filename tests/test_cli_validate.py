"""``gpnarx validate``: the free run's fit and coverage as ``gpnarx predict`` gives them, the one-step fit, the
fits by horizon (k = 1 and the free run; the others pending), and the residual tests: a model with the record's
own lags passes them, one with too few fails them; errors one line on stderr with their exit codes."""
from __future__ import annotations

import json

import numpy as np
import pytest

from gpnarx.cli.main import main

FS = 100.0


def _arx(n, seed, noise=0.05):
    r = np.random.default_rng(seed)
    u, w = r.normal(size=n), noise * r.normal(size=n)
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = 1.5 * y[t - 1] - 0.7 * y[t - 2] + 0.5 * u[t] + 0.3 * u[t - 1] + w[t]
    return u, y


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    from gpnarx.model.estimator import GPNARX
    from gpnarx.storage.bundle import save_bundle

    tmp = tmp_path_factory.mktemp("validate")
    reg = tmp / "reg"
    u, y = _arx(1500, 1)
    for name, lags in (("arx", 2), ("arx-short", 1)):
        m = GPNARX(ny=lags, nu=lags, max_train_points=300, n_restarts=0).fit([(u, y)])
        save_bundle(m, reg, name, "1", fs=FS, units={"u": "N", "y": "m"},
                    extra={"predict": {"method": "linear", "mc_paths": 64}})
    ut, yt = _arx(1200, 2)
    rec = tmp / "fresh.npz"
    np.savez(rec, u=ut, y=yt, fs=FS)
    no_y = tmp / "input-only.npz"
    np.savez(no_y, u=ut, fs=FS)
    return reg, rec, no_y


def _validate(capsys, *argv):
    rc = main(["validate", *map(str, argv), "--json"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    return json.loads(out.out)


def test_a_model_with_the_records_lags_passes(setup, capsys):
    reg, rec, _ = setup
    a = _validate(capsys, "--registry", reg, "--model", "arx", rec)
    assert (a["model"], a["version"], a["n"], a["method"], a["start"]) == ("arx", "1", 1200, "linear", "rest")
    # the free run scored as gpnarx predict scores it
    assert main(["predict", "--registry", str(reg), "--model", "arx", str(rec), "--json"]) == 0
    p = json.loads(capsys.readouterr().out)
    for k in ("fit", "rmse", "coverage", "band_width"):
        assert a["free_run"][k] == pytest.approx(p[k], rel=1e-12), k
    one = a["one_step"]
    assert one["n"] == 1200 - 2 and one["fit"] > 95 and one["coverage"] > 97 and 0.9 < one["z_rms"] < 1.1
    fits = a["k_step_fits"]
    assert list(fits) == ["1", "8", "64", "512", "free_run"] and fits["free_run"] == a["free_run"]["fit"]
    # k = 1 is the one-step prediction, scored on every sample after the measured start (the first ny)
    assert fits["1"] == pytest.approx(one["fit"], abs=0.2)
    assert fits["1"] >= fits["8"] >= fits["64"] >= fits["512"] - 1e-9 and fits["512"] >= fits["free_run"] - 5
    assert "k_step_note" not in a
    # each is gpnarx predict --horizon K's fit
    assert main(["predict", "--registry", str(reg), "--model", "arx", str(rec), "--horizon", "8", "--json"]) == 0
    p8 = json.loads(capsys.readouterr().out)
    assert p8["horizon"] == 8 and p8["fit"] == pytest.approx(fits["8"], rel=1e-12)
    t = a["residual_tests"]
    assert t["lags"] == 25 and t["n"] == one["n"] and t["limit"] == pytest.approx(2.5758293035489 / np.sqrt(1198))
    assert len(t["autocorrelation"]["r"]) == 25 and t["cross_correlation"]["lag"] == list(range(-25, 26))
    r = a["residuals"]
    assert r["passed"] is True and r["white"] is True and r["independent"] is True
    assert r["autocorrelation_outside_share"] <= 2 / 25 and r["ljung_box_p"] > 0.01
    assert r["ljung_box_p"] == t["autocorrelation"]["ljung_box"]["p_value"]


def test_a_model_with_too_few_lags_fails_and_lags_option(setup, capsys):
    reg, rec, _ = setup
    a = _validate(capsys, "--registry", reg, "--model", "arx-short:1", rec, "--lags", "10")
    r = a["residuals"]
    assert r["passed"] is False and r["white"] is False and r["independent"] is False
    assert r["lags"] == 10 and len(a["residual_tests"]["cross_correlation"]["r"]) == 21
    assert r["autocorrelation_outside_share"] > 0.3 and r["ljung_box_p"] < 1e-10


def test_human_summary(setup, capsys):
    reg, rec, _ = setup
    assert main(["validate", "--registry", str(reg), "--model", "arx", str(rec), "--lags", "5"]) == 0
    out = capsys.readouterr().out
    assert "free_run: {fit: " in out and "residuals: {white: True" in out and "k_step_fits:" in out


@pytest.mark.parametrize("extra, needle, code", [
    (["--lags", "0"], "--lags", 2),
    (["--confidence", "1.5"], "--confidence", 2),
    (["--lags", "700"], "more than 1400 residuals", 1),  # a record too short for the lags
])
def test_errors(setup, capsys, extra, needle, code):
    reg, rec, _ = setup
    rc = main(["validate", "--registry", str(reg), "--model", "arx", str(rec), *extra])
    err = capsys.readouterr().err
    assert rc == code, err
    assert needle in err and len(err.strip().splitlines()) == 1, err


def test_a_record_without_y_is_refused(setup, capsys):
    reg, _, no_y = setup
    assert main(["validate", "--registry", str(reg), "--model", "arx", str(no_y)]) == 1
    err = capsys.readouterr().err
    assert "measured output y" in err and "input-only.npz" in err and len(err.strip().splitlines()) == 1
