"""Answers outside the model's knowledge: ``diverged_paths`` and ``out_of_range`` (model.envelope).

The registry is the shared small Bouc-Wen GP-NARX (test_service_support: 10 N RMS multisines and a
30 N sweep). A record far outside it (100x the training input) must be answered with the flags set,
over HTTP (single call, batch slot, loops), on the CLI (--json), and counted per model in /metrics.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
from fastapi.testclient import TestClient
from test_service_support import FS, built_registry, multisine, noisy, simulate

from gpnarx.model.envelope import (
    DIVERGENCE_FACTOR,
    FREQUENCY_SHARE,
    RANGE_FACTOR,
    assess,
    check_envelope,
    frequency_share,
    out_of_range,
    training_envelope,
)
from gpnarx.model.freerun import FreeRun
from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings


def _run(mean, method="linear", diverged=0):
    mean = np.asarray(mean, float)
    return FreeRun(mean, np.zeros_like(mean), mean, mean, 0.99, 0 if method == "linear" else 8, method,
                   diverged_paths=diverged)


def test_envelope_is_the_training_peaks_and_checks_each_field():
    env = training_envelope([(np.array([0.0, 2.0, -1.0]), np.array([0.5, -3.0])),
                             (np.array([1.0, -4.0]), np.array([1.0, 2.0]))])
    assert {k: env[k] for k in ("u_peak", "y_peak", "n_records")} == {"u_peak": 4.0, "y_peak": 3.0, "n_records": 2}
    assert len(env["u_bands"]) == 65 and check_envelope(env)["u_bands"] == env["u_bands"]
    inside_u = np.array([RANGE_FACTOR * 4.0 * 0.99])
    assert out_of_range(env, inside_u, y=[RANGE_FACTOR * 3.0 * 0.99], mean=[-4.4]) == []
    assert out_of_range(env, [RANGE_FACTOR * 4.0 * 1.01]) == ["u"]
    assert out_of_range(env, [0.0], y=[-RANGE_FACTOR * 3.0 * 1.01]) == ["y"]
    assert out_of_range(env, [0.0], mean=[np.nan]) == ["prediction"]  # non-finite counts as outside
    assert out_of_range(None, [1e30], [1e30], [1e30]) == []  # a model without an envelope: no check


def test_linearised_run_reports_zero_or_one_diverged_path():
    env = {"u_peak": 1.0, "y_peak": 2.0}
    assert assess(env, _run([0.0, DIVERGENCE_FACTOR * 2.0 * 0.99]), [0.5])["diverged_paths"] == 0
    out = assess(env, _run([0.0, DIVERGENCE_FACTOR * 2.0 * 1.01]), [0.5])
    assert out == {"diverged_paths": 1, "out_of_range": ["prediction"]}
    assert assess(env, _run([0.0], method="mc", diverged=7), [0.5])["diverged_paths"] == 7


def _sweep(f0, f1, rate, amp, fs=1024.0):
    t = np.arange(int((f1 - f0) / rate * fs)) / fs
    return amp * np.sin(2 * np.pi * (f0 * t + 0.5 * rate * t * t))


def test_frequency_flag_fires_for_a_drive_beyond_the_trained_band_and_not_inside_it():
    """Trained on 0-40 Hz sweeps at 0.2 V and a weak 0-110 Hz noise run: a 0-110 Hz sweep at 0.05 V holds
    most of its power above 40 Hz, where the training inputs were 100x weaker, so it is flagged; a sine or a
    0-40 Hz sweep inside the trained band and level, and a weaker noise run, are not."""
    fs = 1024.0
    rng = np.random.default_rng(0)
    from scipy.signal import butter, sosfilt

    noise = sosfilt(butter(8, 110.0, fs=fs, output="sos"), rng.normal(scale=0.003, size=16384))
    train = [(_sweep(0.0, 40.0, 5.0, 0.2), np.zeros(1)), (noise, np.zeros(1))]
    env = training_envelope(train)
    t = np.arange(int(8 * fs)) / fs
    assert out_of_range(env, _sweep(0.0, 110.0, 5.0, 0.05)) == ["frequency"]
    assert frequency_share(env["u_bands"], _sweep(0.0, 110.0, 5.0, 0.05)) > 0.5
    assert out_of_range(env, _sweep(0.0, 40.0, 5.0, 0.15)) == []
    for f in (3.0, 12.0, 25.0, 38.0):
        assert out_of_range(env, 0.15 * np.sin(2 * np.pi * f * t)) == [], f
    assert out_of_range(env, 0.5 * noise) == []
    assert out_of_range(env, np.zeros(4096)) == []  # no power: nothing outside
    # a strong 60 Hz sine (never trained at that level) is flagged; a sine 2x the envelope's edge is the limit
    assert out_of_range(env, 0.15 * np.sin(2 * np.pi * 60.0 * t)) == ["frequency"]
    assert FREQUENCY_SHARE == 0.10
    # a bundle trained before the rule (no u_bands) is not checked for it
    old = {"u_peak": env["u_peak"], "y_peak": 1.0}
    assert out_of_range(old, _sweep(0.0, 110.0, 5.0, 0.05)) == []


@pytest.mark.parametrize("bad", [{"u_peak": 1.0}, {"u_peak": 1.0, "y_peak": 0.0}, {"u_peak": "x", "y_peak": 1.0},
                                 {"u_peak": 1.0, "y_peak": float("inf")},
                                 {"u_peak": 1.0, "y_peak": 1.0, "u_bands": [1.0, 2.0]},
                                 {"u_peak": 1.0, "y_peak": 1.0, "u_bands": [float("nan")] * 65}])
def test_bad_envelope_is_refused(bad):
    with pytest.raises(ValueError, match="envelope"):
        check_envelope(bad)


@pytest.fixture(scope="module")
def client():
    reg = built_registry().root
    return TestClient(create_app(reg, Settings(registry=reg, workers=1)), raise_server_exceptions=False)


def test_model_learns_and_bundles_its_training_envelope():
    built = built_registry()
    env = built.model.envelope_
    assert env["u_peak"] > 0 and env["y_peak"] > 0
    from gpnarx.storage.registry import Registry

    loaded = Registry(built.root).scan().get("boucwen")
    assert loaded.model.envelope_["u_peak"] == pytest.approx(env["u_peak"], rel=1e-12)
    assert loaded.manifest["training_envelope"]["y_peak"] == pytest.approx(env["y_peak"], rel=1e-12)


def test_inside_record_has_no_flags_and_far_record_has_them_over_http(client):
    u = multisine(512, 31)
    base = {"u": u.tolist(), "fs": FS, "mc_paths": 16, "seed": 0}
    ok = client.post("/v1/models/boucwen/predict", json={**base, "y": noisy(simulate(u), 31).tolist()}).json()
    assert ok["diverged_paths"] == 0 and ok["out_of_range"] == [] and ok["start"] == "rest", ok
    far = client.post("/v1/models/boucwen/predict", json={**base, "u": (100 * u).tolist()})
    assert far.status_code == 200
    body = far.json()
    assert body["out_of_range"][0] == "u", body  # the input is 100x the training peak
    peak = max(abs(v) for v in body["mean"])
    env = built_registry().model.envelope_
    # the flags tell the truth about the mean: prediction flagged iff its peak is beyond the range factor
    assert ("prediction" in body["out_of_range"]) == (peak > RANGE_FACTOR * env["y_peak"]), (peak, env)
    lin = client.post("/v1/models/boucwen/predict", json={**base, "u": (100 * u).tolist(), "method": "linear"}).json()
    assert lin["diverged_paths"] == int(max(abs(v) for v in lin["mean"]) > DIVERGENCE_FACTOR * env["y_peak"])
    loops = client.post("/v1/models/boucwen/loops", json={**base, "u": (100 * u).tolist()}).json()
    assert loops["out_of_range"][0] == "u" and "diverged_paths" in loops, loops


def test_far_record_flags_in_a_batch_slot_and_metrics_count_them(client):
    u = multisine(256, 32)
    items = [{"model": "boucwen", "u": u.tolist(), "fs": FS, "mc_paths": 8},
             {"model": "boucwen", "u": (100 * u).tolist(), "fs": FS, "mc_paths": 8},
             {"model": "boucwen", "operation": "novelty", "u": u.tolist(), "y": (1e6 * simulate(u)).tolist(),
              "fs": FS, "mc_paths": 8}]
    res = client.post("/v1/batch", json={"requests": items}).json()["results"]
    assert res[0]["out_of_range"] == [] and res[1]["out_of_range"][0] == "u", res[:2]
    assert res[2]["verdict"] == "novel" and "y" in res[2]["out_of_range"] and res[2]["diverged_paths"] == 8
    metrics = client.get("/metrics").text
    assert 'gpnarx_out_of_range_total{field="u",model="boucwen"}' in metrics
    assert 'gpnarx_diverged_answers_total{model="boucwen"}' in metrics
    assert 'gpnarx_novelty_verdicts_total{model="boucwen",verdict="novel"}' in metrics
    assert 'gpnarx_answers_total{model="boucwen",operation="predict"}' in metrics


def test_measured_start_needs_a_measured_output(client):
    u = multisine(128, 33)
    r = client.post("/v1/models/boucwen/predict", json={"u": u.tolist(), "fs": FS, "start": "measured"})
    assert r.status_code == 422 and r.json()["field"] == "start", r.json()
    y = simulate(u)
    ok = client.post("/v1/models/boucwen/predict", json={"u": u.tolist(), "y": y.tolist(), "fs": FS,
                                                          "start": "measured", "method": "linear"}).json()
    ny = built_registry().model.ny
    assert ok["start"] == "measured" and np.allclose(ok["mean"][:ny], y[:ny]), ok["start"]


def test_cli_predict_json_flags_a_far_record(tmp_path, capsys):
    from gpnarx.cli.main import main

    u = multisine(384, 34)
    far = tmp_path / "far.npz"
    np.savez(far, u=100 * u, y=100 * simulate(u), fs=FS)
    assert main(["predict", "--registry", str(built_registry().root), "--model", "boucwen", str(far), "--mc", "8",
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["out_of_range"][:2] == ["u", "y"] and isinstance(out["diverged_paths"], int), out


@pytest.mark.parametrize("n", [1, 1023, 1024, 1025, 1536, 5000, 65536 + 7])
def test_band_strengths_stft_is_scipys(n):
    """The frequency check's STFT (numpy's FFT, so a CLI start does not import scipy.signal) is
    scipy.signal.stft's: Hann frames, half overlap, zero-padded ends, spectrum scaling."""
    from scipy.signal import stft

    from gpnarx.model.envelope import BAND_BINS, FRAME, _stft, band_strengths

    u = np.random.default_rng(n).normal(size=n)
    padded = np.pad(u, (0, max(FRAME - n, 0)))
    _, _, z = stft(padded, nperseg=FRAME, noverlap=FRAME // 2, window="hann", detrend=False)
    mine = _stft(padded)
    assert mine.shape == z.shape
    np.testing.assert_allclose(np.abs(mine), np.abs(z), rtol=0, atol=1e-12 * np.abs(z).max())
    p = np.abs(z) ** 2
    p = np.pad(p, ((0, -p.shape[0] % BAND_BINS), (0, 0)))
    np.testing.assert_allclose(band_strengths(u), np.sqrt(p.reshape(-1, BAND_BINS, p.shape[1]).sum(axis=1)),
                               rtol=1e-10, atol=1e-14)
