"""Dataset config: loading, simulated records, noise, windows, errors, ranges."""
from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest

from gpnarx.model.records import Record
from gpnarx.training.config import ConfigError, DatasetConfig, load_config, parse_range
from gpnarx.training.records import write_record

DATA = Path(__file__).resolve().parents[1].parent / "shared/data/bert-t5nm"

SMALL = """
name = "bw-small"
description = "small Bouc-Wen config for tests"
[system]
fs = 750.0
units = { u = "N", y = "m" }
output = "displacement"
[physics]
mass = 2.0
input_gain = 1.0
[model]
ny = 3
nu = 2
kernel = "rbf+cubic"
selection = "resonance"
[lags]
ny = "1:6"
nu = "2:8:3"
[predict]
mc_paths = 64
[[records]]
name = "sweep-10N"
roles = ["train", "lags"]
simulate = { system = "bouc-wen", excitation = "sweep", amplitude = 10.0, f0 = 5.0, f1 = 150.0, rate = 200.0 }
noise = { fraction = 0.1, seed = 11 }
[[records]]
name = "sine-10N"
roles = ["validate"]
simulate = { system = "bouc-wen", excitation = "sine", amplitude = 10.0, freq = 35.59, duration = 1.0 }
noise = { fraction = 0.1, reference = "sweep-10N", seed = 12 }
window = [0.2, 0.6]
meta = { note = "validation sine" }
"""


def _write(tmp_path: Path, text: str, name="cfg.toml") -> Path:
    p = tmp_path / name
    p.write_text(textwrap.dedent(text))
    return p


def test_small_config_loads_and_materialises(tmp_path):
    cfg = load_config(_write(tmp_path, SMALL))
    assert isinstance(cfg, DatasetConfig)
    assert cfg.name == "bw-small" and cfg.fs == 750.0 and cfg.units == {"u": "N", "y": "m"}
    assert cfg.model["ny"] == 3 and cfg.model["kernel"] == "rbf+cubic" and cfg.model["mode"] == "exact"
    assert cfg.model["max_train_points"] == 2000 and cfg.predict == {"mc_paths": 64, "confidence": 0.99, "method": "mc"}
    assert cfg.novelty["false_alarm_rate"] == 0.01 and cfg.physics["mass"] == 2.0
    assert cfg.novelty["method"] == "rms_standardised_residual"  # the default score
    assert parse_range(cfg.lags["nu"]) == [2, 5, 8]
    assert [s.name for s in cfg.records] == ["sweep-10N", "sine-10N"]
    assert cfg.records_for("damaged") == []

    train = cfg.records_for("train")
    assert len(train) == 1
    sweep = train[0]
    assert isinstance(sweep, Record) and sweep.fs == 750.0 and sweep.units == {"u": "N", "y": "m"}
    assert sweep.n == round((150 - 5) / 200 * 750)
    clean = sweep.meta["clean_y"]
    noise = sweep.y - clean
    # variance = 10 % of the clean response energy
    assert np.var(noise) == pytest.approx(0.1 * np.mean(clean**2), rel=0.2)
    assert cfg.records_for("lags")[0] is sweep  # cached

    sine = cfg.records_for("validate")[0]
    assert sine.n == 300 and sine.name == "sine-10N"
    assert sine.meta["note"] == "validation sine" and sine.meta["window"] == [0.2, 0.6]
    # noise level taken from the sweep's clean output, not the sine's
    assert sine.meta["noise_std"] == pytest.approx(sweep.meta["noise_std"])
    assert sine.meta["noise_reference"] == "sweep-10N"

    # deterministic: a second load gives the same noisy samples
    again = load_config(cfg.path).records_for("train")[0]
    np.testing.assert_array_equal(again.y, sweep.y)


def test_file_records_relative_path_and_units_fill(tmp_path):
    rng = np.random.default_rng(0)
    (tmp_path / "data").mkdir()
    write_record(tmp_path / "data" / "a.csv", Record(rng.standard_normal(50), rng.standard_normal(50), 750.0))
    np.save(tmp_path / "data" / "b.npy", rng.standard_normal((40, 2)))
    text = """
    name = "files"
    [system]
    fs = 750.0
    units = { u = "N", y = "m" }
    [[records]]
    name = "a"
    roles = ["train"]
    path = "data/a.csv"
    [[records]]
    name = "b"
    roles = ["verify"]
    path = "data/b.npy"
    """
    cfg = load_config(_write(tmp_path, text))
    a = cfg.records_for("train")[0]
    assert a.n == 50 and a.units == {"u": "N", "y": "m"}  # CSV has no units: the config's apply
    b = cfg.records_for("verify")[0]
    assert b.n == 40 and b.fs == 750.0  # npy has no fs: system.fs applies


def test_fs_mismatch_names_both_records(tmp_path):
    rng = np.random.default_rng(1)
    write_record(tmp_path / "ok.npz", Record(rng.standard_normal(20), rng.standard_normal(20), 750.0))
    write_record(tmp_path / "fast.npz", Record(rng.standard_normal(20), rng.standard_normal(20), 1000.0))
    text = """
    name = "mismatch"
    [system]
    fs = 750.0
    [[records]]
    name = "slow-one"
    roles = ["train"]
    path = "ok.npz"
    [[records]]
    name = "fast-one"
    roles = ["train"]
    path = "fast.npz"
    """
    cfg = load_config(_write(tmp_path, text))
    with pytest.raises(ConfigError) as ei:
        cfg.records_for("train")
    msg = str(ei.value)
    assert "cfg.toml" in msg and "fast-one" in msg and "fast.npz" in msg and "slow-one" in msg and "ok.npz" in msg
    assert "1000 Hz" in msg and "750 Hz" in msg and "\n" not in msg


def test_unit_mismatch(tmp_path):
    rng = np.random.default_rng(2)
    write_record(tmp_path / "v.npz",
                 Record(rng.standard_normal(20), rng.standard_normal(20), 750.0, {"u": "N", "y": "m/s"}))
    text = """
    name = "units"
    [system]
    fs = 750.0
    units = { u = "N", y = "m" }
    [[records]]
    name = "vel"
    roles = ["train"]
    path = "v.npz"
    """
    with pytest.raises(ConfigError, match=r"cfg.toml: records.vel: .*'m/s' but system.units.y is 'm'"):
        load_config(_write(tmp_path, text)).records_for("train")


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("[system]\nfs = 750.0\n[[records]]\nname='a'\nroles=['train']\npath='x.npz'\n", "name: missing required key"),
        ("name='x'\n[system]\nunits={u='N', y='m'}\n[[records]]\nname='a'\nroles=['train']\npath='x.npz'\n",
         "system.fs: missing required key"),
        ("name='x'\n[system]\nfs=750.0\n", "records: missing required key"),
        ("name='x'\n[system]\nfs=750.0\n[[records]]\nname='a'\nroles=['verify']\npath='x.npz'\n",
         "no record has role 'train'"),
        ("name='x'\n[system]\nfs=750.0\n[[records]]\nname='a'\nroles=['train','tesst']\npath='x.npz'\n",
         "records.a.roles: unknown role 'tesst'"),
        ("name='x'\n[system]\nfs=750.0\n[[records]]\nname='a'\nroles=['train']\n",
         "give exactly one of path or simulate"),
        ("name='x'\n[system]\nfs=750.0\n[model]\nkernel='laplace'\n[[records]]\nname='a'\nroles=['train']\npath='x'\n",
         "model.kernel: must be one of"),
        ("name='x'\n[system]\nfs=750.0\n[lags]\nny='24:1'\n[[records]]\nname='a'\nroles=['train']\npath='x'\n",
         "lags.ny"),
        ("name='x'\n[system]\nfs=750.0\nunits={u='N', y='furlong'}\n[[records]]\nname='a'\nroles=['train']\npath='x'\n",
         "system.units"),
        ("name='x'\n[system]\nfs=750.0\n[[records]]\nname='a'\nroles=['train']\npath='x'\n"
         "noise={fraction=0.1, reference='zz'}\n",
         "no record named 'zz'"),
        ("name='x'\n[system]\nfs=750.0\n[[records]]\nname='a'\nroles=['train']\n"
         "simulate={system='duffing', amplitude=1.0}\n",
         "records.a.simulate.system"),
        ("name='x'\n[system]\nfs=750.0\n[[records]]\nname='a'\nroles=['train']\npath='x'\ncolour='red'\n",
         "unknown key(s) colour"),
        ("name = [broken", "invalid TOML"),
        ("name='x'\n[system]\nfs=750.0\n[model]\nnoise_calibration='cv'\n[[records]]\nname='a'\nroles=['train']\n"
         "path='x'\n", "model.noise_calibration: must be one of 'none', 'lags', got 'cv'"),
        ("name='x'\n[system]\nfs=750.0\n[model]\nnoise_calibration='lags'\n[[records]]\nname='a'\nroles=['train']\n"
         "path='x'\n", "model.noise_calibration: 'lags' needs at least one record with role 'lags'"),
        ("name='x'\n[system]\nfs=750.0\n[model]\nnoise_calibration='lags'\n[[records]]\nname='a'\n"
         "roles=['train', 'lags']\npath='x'\n", "records.a.roles: a 'lags' record calibrates the band"),
        ("name='x'\n[system]\nfs=750.0\n[model]\nband_calibration='all'\n[[records]]\nname='a'\nroles=['train']\n"
         "path='x'\n", "model.band_calibration: must be one of 'none', 'lags', got 'all'"),
        ("name='x'\n[system]\nfs=750.0\n[model]\nband_calibration='lags'\n[[records]]\nname='a'\nroles=['train']\n"
         "path='x'\n", "model.band_calibration: 'lags' needs at least one record with role 'lags'"),
        ("name='x'\n[system]\nfs=750.0\n[model]\nband_window=0\n[[records]]\nname='a'\nroles=['train']\n"
         "path='x'\n", "model.band_window: must be a number of seconds in (0, 10], got 0"),
        ("name='x'\n[system]\nfs=750.0\n[novelty]\nmethod='max'\n[[records]]\nname='a'\nroles=['train']\npath='x'\n",
         "novelty.method: must be one of rms_standardised_residual, segment_median_rms, got 'max'"),
    ],
)
def test_config_errors(tmp_path, text, fragment):
    p = _write(tmp_path, text)
    with pytest.raises(ConfigError) as ei:
        load_config(p)
    msg = str(ei.value)
    assert str(p) in msg and fragment in msg, msg
    assert "\n" not in msg


def test_unknown_role_query_and_missing_file(tmp_path):
    cfg = load_config(_write(tmp_path, SMALL))
    with pytest.raises(ConfigError, match="unknown role 'test'"):
        cfg.records_for("test")
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "nope.toml")
    text = "name='x'\n[system]\nfs=750.0\n[[records]]\nname='a'\nroles=['train']\npath='missing.npz'\n"
    cfg = load_config(_write(tmp_path, text, "c2.toml"))
    with pytest.raises(ConfigError, match=r"c2.toml: records.a.path: .*missing.npz: no such file"):
        cfg.records_for("train")


def test_simulate_option_errors(tmp_path):
    text = SMALL.replace("rate = 200.0 }", "rate = 200.0, torque = 7.0 }")
    cfg = load_config(_write(tmp_path, text))
    with pytest.raises(ConfigError, match="records.sweep-10N.simulate: torque applies only to bert-standin"):
        cfg.records_for("train")
    cfg = load_config(_write(tmp_path, SMALL.replace("rate = 200.0 }", "rate = 200.0, scatter = 2.0 }")))
    with pytest.raises(ConfigError, match="records.sweep-10N.simulate: scatter applies only to bert-standin"):
        cfg.records_for("train")


def test_standin_scatter_reaches_the_simulator(tmp_path):
    from gpnarx.training.simulators.bert_standin import BertStandin

    text = """
    name = "bert"
    [system]
    fs = 1024.0
    output = "velocity"
    [[records]]
    name = "wide"
    roles = ["train"]
    [records.simulate]
    system = "bert-standin"
    excitation = "noise"
    amplitude = 0.05
    duration = 1.0
    seed = 3
    scatter = 10.0
    [[records]]
    name = "bad"
    roles = ["verify"]
    [records.simulate]
    system = "bert-standin"
    excitation = "noise"
    amplitude = 0.05
    duration = 1.0
    seed = 3
    scatter = 500.0
    """
    cfg = load_config(_write(tmp_path, text))
    rec = cfg.records_for("train")[0]
    assert rec.meta["scatter"] == 10.0
    direct = BertStandin(seed=3, scatter=10.0).simulate(rec.u)["y"]
    np.testing.assert_array_equal(rec.y, direct)
    assert not np.array_equal(rec.y, BertStandin(seed=3).simulate(rec.u)["y"])
    with pytest.raises(ConfigError, match="scatter must be between 0 and 100"):
        cfg.records_for("verify")


def test_bert_standin_and_real_data_records(tmp_path, monkeypatch):
    text = """
    name = "bert"
    [system]
    fs = 1024.0
    units = { u = "V", y = "m/s" }
    output = "velocity"
    [[records]]
    name = "noise-9Nm"
    roles = ["train", "healthy"]
    simulate = {system = "bert-standin", excitation = "noise", amplitude = 0.01, duration = 1.0, seed = 3, torque = 9.0}
    [[records]]
    name = "rig-rand"
    roles = ["verify"]
    path = "${BERT_DATA}/Rand/Rand0p25"
    window = [1.0, 3.0]
    """
    cfg = load_config(_write(tmp_path, text))
    rec = cfg.records_for("healthy")[0]
    assert rec.n == 1024 and rec.meta["torque"] == 9.0 and rec.units == {"u": "V", "y": "m/s"}
    if DATA.is_dir():
        monkeypatch.delenv("GPNARX_BERT_DATA", raising=False)
        rig = load_config(cfg.path).records_for("verify")[0]
        assert rig.n == 2048 and rig.fs == 1024.0 and rig.units == {"u": "V", "y": "m/s"}
    monkeypatch.setenv("GPNARX_BERT_DATA", str(tmp_path / "elsewhere"))
    with pytest.raises(ConfigError, match="elsewhere/Rand/Rand0p25: no such file"):
        load_config(cfg.path).records_for("verify")


def test_parse_range():
    assert parse_range("1:24") == list(range(1, 25))
    assert parse_range("1:24:2") == list(range(1, 25, 2))
    assert parse_range(" 5 ") == [5]
    assert parse_range(7) == [7]
    assert parse_range("1,3,5") == [1, 3, 5]
    assert parse_range([2, 4]) == [2, 4]
    assert parse_range(parse_range("3:5")) == [3, 4, 5]
    for bad in ("24:1", "1:", "a:b", "1:5:0", "", "-1:3", True, 1.5, []):
        with pytest.raises(ConfigError):
            parse_range(bad)
    assert issubclass(ConfigError, ValueError)


def test_every_shipped_config_loads_and_is_named_after_its_file():
    from gpnarx.training.defaults import CONFIG_DIR, DEFAULT_BUNDLES, DERIVED

    names = sorted(p.stem for p in CONFIG_DIR.glob("*.toml"))
    assert set(DEFAULT_BUNDLES) - set(DERIVED) <= set(names)  # derived defaults have no config of their own
    assert set(DERIVED.values()) <= set(names)
    for name in names:
        cfg = load_config(CONFIG_DIR / f"{name}.toml")
        assert cfg.name == name
        assert cfg.records_for("train"), name


def test_monitor_config_trains_on_healthy_probes_only():
    from gpnarx.training.defaults import CONFIG_DIR

    cfg = load_config(CONFIG_DIR / "bert-standin-monitor.toml")
    specs = {role: [s for s in cfg.records if role in s.roles] for role in ("train", "healthy", "damaged")}
    assert specs["train"] and all(s.simulate["torque"] == 5.0 and s.simulate["freq"] == 9.0 for s in specs["train"])
    assert all(s.simulate["torque"] == 5.0 for s in specs["healthy"]) and len(specs["healthy"]) >= 2
    assert {s.simulate["torque"] for s in specs["damaged"]} == {4.0, 7.0, 9.0}
    train_seeds = {s.simulate["seed"] for s in specs["train"]}
    assert not train_seeds & {s.simulate["seed"] for s in specs["healthy"] + specs["damaged"]}
