"""Configs with several channels (issue 52): ``[system] inputs`` / ``outputs`` select the records' channels by
name; such a config trains a MIMOGPNARX whose bundle records the channels (names, units, order) and reloads to
the same model; the front ends refuse it until answers per channel exist; single-channel configs are unchanged."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gpnarx.model.mimo import MIMOGPNARX
from gpnarx.model.record import Record
from gpnarx.operations.base import Limits, OperationError
from gpnarx.operations.run import plan
from gpnarx.storage.bundle import load_bundle
from gpnarx.storage.record_files import write_record
from gpnarx.training.baselines import LinearARX
from gpnarx.training.config import ConfigError, load_config
from gpnarx.training.datapaths import bert_data_dir
from gpnarx.training.excitations import band_limited_noise, swept_sine
from gpnarx.training.mimo_pipeline import MIMOLinearARX
from gpnarx.training.pipeline import train
from gpnarx.training.simulators.chain import Chain

FS = 200.0


def _write(folder, name, u, chain, seed):
    x = chain.simulate(u)["y"]
    y = x + 0.01 * np.std(x, axis=0) * np.random.default_rng(seed).normal(size=x.shape)
    rec = Record(u, y, FS, {"u": "N", "y": "m"}, name,
                 channels={"u": [("F3", "N")], "y": [("x1", "m"), ("x2", "m"), ("x3", "m")]})
    return write_record(folder / f"{name}.npz", rec)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    folder = tmp_path_factory.mktemp("chain")
    chain = Chain(fs=FS)
    _write(folder, "sweep3", swept_sine(FS, 3.0, 2.0, 50.0, duration=4.0), chain, 1)
    _write(folder, "noise4", band_limited_noise(FS, 3.0, 0.0, 60.0, 4.0, seed=2), chain, 2)
    _write(folder, "sweep5", swept_sine(FS, 5.0, 2.0, 50.0, duration=4.0), chain, 3)
    return folder


CONFIG = """
name = "chain-{tag}"
[system]
fs = 200.0
units = {{ u = "N", y = "m" }}
inputs = ["F3"]
outputs = {outputs}
[model]
ny = 6
nu = 4
max_train_points = 300
restarts = 0
[predict]
method = "linear"
[[records]]
name = "sweep3"
roles = ["train"]
path = "{folder}/sweep3.npz"
[[records]]
name = "noise4"
roles = ["train"]
path = "{folder}/noise4.npz"
[[records]]
name = "sweep5"
roles = ["validate"]
path = "{folder}/sweep5.npz"
"""


def _config(tmp_path, folder, outputs, tag="a"):
    p = tmp_path / f"{tag}.toml"
    p.write_text(CONFIG.format(folder=folder, outputs=outputs, tag=tag))
    return load_config(p)


def test_config_selects_channels_by_name(tmp_path, data):
    cfg = _config(tmp_path, data, '["x3", "x1"]')
    rec = cfg.record("sweep5")
    assert cfg.several_channels and rec.y.shape == (800, 2)
    assert [c.name for c in rec.output_channels()] == ["x3", "x1"]
    one = _config(tmp_path, data, '["x2"]', tag="b")
    r1 = one.record("sweep5")
    full = _config(tmp_path, data, '["x1", "x2", "x3"]', tag="c").record("sweep5")
    assert not one.several_channels and r1.y.ndim == 1 and np.array_equal(r1.y, full.y[:, 1])
    assert np.array_equal(full.y[:, 2], rec.y[:, 0]) and np.array_equal(full.y[:, 0], rec.y[:, 1])
    bad = _config(tmp_path, data, '["x1", "x9"]', tag="d")
    with pytest.raises(ConfigError, match=r"records.sweep3.path.*no output channel 'x9'"):
        bad.records_for("train")
    with pytest.raises(ConfigError, match="names a channel twice"):
        _config(tmp_path, data, '["x1", "x1"]', tag="e")
    # a config without them is read as before: its system table holds no channel keys
    plain = load_config(Path(__file__).resolve().parent.parent / "configs" / "bouc-wen.toml")
    assert "inputs" not in plain.system and "outputs" not in plain.system and not plain.channels


@pytest.mark.skipif(not (bert_data_dir() / "Sine" / "Sine_20Hz" / "Time.mat").is_file(), reason="no BERT records")
def test_config_reads_the_rig_accelerometers(tmp_path):
    p = tmp_path / "rig.toml"
    p.write_text(f"""
name = "rig"
[system]
fs = 1024.0
units = {{ u = "V" }}
outputs = ["Laser:+X", "Acc1:+X", "Acc4:+X"]
[[records]]
name = "s20"
roles = ["train"]
path = "{bert_data_dir()}/Sine/Sine_20Hz"
window = [1.0, 2.0]
""")
    rec = load_config(p).record("s20")
    assert rec.y.shape == (1024, 3) and rec.u.shape == (1024,)
    assert [(c.name, c.unit) for c in rec.output_channels()] == [("Laser:+X", "m/s"), ("Acc1:+X", "m/s^2"),
                                                                 ("Acc4:+X", "m/s^2")]


def test_mimo_linear_arx_reduces_to_linear_arx():
    rng = np.random.default_rng(0)
    u = rng.normal(size=300)
    y = np.convolve(u, [0.4, 0.3, 0.1])[:300] + 0.01 * rng.normal(size=300)
    rec = Record(u, y, 100.0)
    a = LinearARX(3, 2).fit([rec])
    b = MIMOLinearARX(3, 2).fit([rec])
    assert np.allclose(b.coef_[:, 0], a.coef_)
    assert np.allclose(b.simulate(u[:100])[:, 0], a.simulate(u[:100]), atol=1e-12)
    assert np.allclose(b.simulate(u[:100], y[:3, None])[:, 0], a.simulate(u[:100], y[:3]), atol=1e-12)


def test_train_bundle_records_channels_and_reloads(tmp_path, data):
    cfg = _config(tmp_path, data, '["x1", "x2", "x3"]')
    out = train(cfg, tmp_path / "reg", report=True)
    model = out["model"]
    assert isinstance(model, MIMOGPNARX) and model.n_outputs_ == 3
    b = load_bundle(out["path"])
    m = b.manifest
    assert m["model_class"] == "mimo"
    assert m["channels"] == {"inputs": [{"name": "F3", "unit": "N"}],
                             "outputs": [{"name": f"x{k}", "unit": "m"} for k in (1, 2, 3)]}
    assert m["units"] == {"u": "N", "y": "m"} and m["lags"] == {"ny": 6, "nu": 4}
    scores = m["training"]["records"]["sweep5"]
    for ch in ("x1", "x2", "x3"):
        assert scores["channels"][ch]["fit"] > 85, scores
        assert scores["channels"][ch]["coverage"] > 85, scores
        assert "fit" in scores["baselines"]["linear ARX"][ch]
        assert "fit" in scores["baselines"]["linear ARX per channel"][ch]
    assert (b.path / "report" / "sweep5.png").is_file()
    # the bundle is the model: the same free run to the last bit
    u = cfg.record("sweep5").u[:300]
    r0, r1 = model.simulate(u, method="linear"), b.model.simulate(u, method="linear")
    assert np.array_equal(r0.mean, r1.mean) and np.array_equal(r0.std, r1.std)
    # the front ends refuse it on 'model' until answers per channel exist
    with pytest.raises(OperationError) as err:
        plan("predict", None, b, Limits())
    assert err.value.field == "model" and "several channels" in err.value.detail


def test_lag_surface_scores_each_record_by_its_worst_channel(tmp_path, data):
    from gpnarx.training.lags import lag_surface

    text = CONFIG.format(folder=data, outputs='["x1", "x2", "x3"]', tag="lags").replace(
        'roles = ["validate"]', 'roles = ["lags"]')
    p = tmp_path / "lags.toml"
    p.write_text(text)
    surface = lag_surface(p, [2, 6], [4], jobs=1, cache_dir=tmp_path / "cache", settings={"max_train_points": 150})
    cells = {(c["ny"], c["nu"]): c for c in surface["cells"]}
    assert set(cells) == {(2, 4), (6, 4)}
    for c in cells.values():
        per = c["channel_fits"]["sweep5"]
        assert set(per) == {"x1", "x2", "x3"}
        assert c["fits"]["sweep5"] == min(per.values()) and c["fit"] == c["fits"]["sweep5"]
    assert surface["chosen"]["ny"] in (2, 6) and np.isfinite(surface["chosen"]["fit"])


def test_noise_and_band_calibration_per_channel(tmp_path, data):
    text = CONFIG.format(folder=data, outputs='["x1", "x2", "x3"]', tag="cal").replace(
        'roles = ["validate"]', 'roles = ["lags"]').replace(
        "restarts = 0\n", 'restarts = 0\nnoise_calibration = "lags"\nband_calibration = "lags"\n'
                          'band_window_kind = "trailing"\nband_gp_scale = "calibrated"\n')
    p = tmp_path / "cal.toml"
    p.write_text(text)
    out = train(load_config(p), tmp_path / "reg", report=False)
    m = load_bundle(out["path"]).manifest
    disc = m["band_discrepancy"]
    assert [d["channel"] for d in disc] == ["x1", "x2", "x3"]
    for d in disc:  # each channel's term covers the lags record at the band's confidence
        assert d["reached"] and d["coverage_after"]["sweep5"] >= 0.99 and d["window_kind"] == "trailing"
    assert all(o["noise_calibration"]["noise_var"] >= o["noise_calibration"]["noise_var_ml2"] for o in m["outputs"])
    assert all(ch["coverage"] >= 99.0 for ch in m["training"]["records"]["sweep5"]["channels"].values())
    b = load_bundle(out["path"])
    u = load_config(p).record("sweep5").u
    assert np.array_equal(b.model.simulate(u, method="linear").upper, out["model"].simulate(u, method="linear").upper)


def test_train_summary_has_a_row_per_record_and_channel():
    from gpnarx.cli.cmd_train import summary

    out = {"name": "m", "version": "1", "path": "/nowhere", "metrics": {"records": {
        "s5": {"role": "validate", "channels": {"x1": {"fit": 91.5, "coverage": 99.0},
                                                 "x3": {"fit": 88.25, "coverage": 97.5}}}}}}
    text = summary(out, {"u": "N", "y": "m"})
    rows = [ln for ln in text.splitlines() if ln.startswith("s5 ")]
    assert len(rows) == 2 and "s5 x1" in rows[0] and "91.5" in rows[0] and "s5 x3" in rows[1] and "88.25" in rows[1]
