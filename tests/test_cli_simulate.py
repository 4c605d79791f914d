"""``gpnarx simulate``: record contract, defaults, errors, atomic writes."""
import json
import sys
import types

import numpy as np
import pytest

from gpnarx.cli import cmd_simulate
from gpnarx.cli import main as cli
from gpnarx.training.excitations import swept_sine
from gpnarx.training.simulators.boucwen import BoucWen


def _run(*argv):
    return cli.main(["simulate", *map(str, argv)])


def test_bouc_wen_sweep_record_contract(tmp_path, capsys):
    out = tmp_path / "r.npz"
    assert _run("bouc-wen", "--excitation", "sweep", "--amplitude", "10", "--out", out) == 0
    with np.load(out) as d:
        u, y, fs = d["u"], d["y"], d["fs"]
    for a in (u, y):
        assert a.dtype == np.float64 and a.ndim == 1
    assert fs.shape == () and float(fs) == 750.0
    assert u.size == y.size == round((150 - 5) / 53 * 750)
    np.testing.assert_allclose(u, swept_sine(750.0, 10.0, 5.0, 150.0, rate=53.0), atol=1e-12)
    np.testing.assert_allclose(y, BoucWen().simulate(u)["y"], atol=1e-15)
    assert 1e-5 < np.max(np.abs(y)) < 1e-2  # metres
    assert [p.name for p in tmp_path.iterdir()] == ["r.npz"]  # no temp file left behind


def test_json_summary_and_csv(tmp_path, capsys):
    out = tmp_path / "s.csv"
    argv = ["simulate", "bouc-wen", "--excitation", "sine", "--amplitude", "10", "--out", str(out), "--json"]
    assert cli.main(argv) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["fs"] == 750.0 and summary["n"] == 1500 and summary["freq"] == 35.59
    assert summary["units"] == {"u": "N", "y": "m"}
    lines = out.read_text().splitlines()
    assert lines[0] == "time,u,y"
    data = np.loadtxt(out, delimiter=",", skiprows=1)
    assert data.shape == (1500, 3)
    np.testing.assert_allclose(np.diff(data[:, 0]), 1 / 750.0, rtol=1e-9)
    np.testing.assert_allclose(data[:, 1], 10.0 * np.sin(2 * np.pi * 35.59 * data[:, 0]), atol=1e-9)
    # steady state: response starts at a non-zero value (not from rest) and its peak is stable
    y = data[:, 2]
    assert abs(y[0]) > 1e-5
    assert np.max(np.abs(y[:750])) == pytest.approx(np.max(np.abs(y[750:])), rel=0.02)


def test_noise_fraction_is_seeded_and_sized(tmp_path):
    clean, a, b = tmp_path / "c.npz", tmp_path / "a.npz", tmp_path / "b.npz"
    assert _run("bouc-wen", "--amplitude", "10", "--out", clean) == 0
    for path in (a, b):
        assert _run("bouc-wen", "--amplitude", "10", "--noise-fraction", "0.1", "--seed", "4", "--out", path) == 0
    y0, ya, yb = (np.load(p)["y"] for p in (clean, a, b))
    np.testing.assert_array_equal(ya, yb)
    ratio = np.var(ya - y0) / np.mean(y0**2)
    assert 0.085 < ratio < 0.115


def test_multisine_and_noise_defaults(tmp_path):
    m = tmp_path / "m.npz"
    assert _run("bouc-wen", "--excitation", "multisine", "--amplitude", "10", "--seed", "1", "--duration", "2",
                "--out", m) == 0
    d = np.load(m)
    assert d["u"].size == 1500 and np.sqrt(np.mean(d["u"] ** 2)) == pytest.approx(10.0)
    # periodic steady state: equals the periodic simulation of the same period
    np.testing.assert_allclose(d["y"], BoucWen().simulate(d["u"], periodic=True)["y"], atol=1e-15)
    n = tmp_path / "n.npz"
    assert _run("bouc-wen", "--excitation", "noise", "--amplitude", "5", "--duration", "1", "--seed", "2",
                "--out", n) == 0
    assert np.load(n)["u"].size == 750


@pytest.mark.parametrize(
    "argv,fragment",
    [
        (["bouc-wen", "--amplitude", "-10"], "--amplitude"),
        (["bouc-wen", "--excitation", "chirp", "--amplitude", "1"], "--excitation"),
        (["duffing", "--amplitude", "1"], "system"),
        (["bouc-wen", "--amplitude", "1", "--torque", "5"], "--torque"),
        (["bouc-wen", "--amplitude", "1", "--scatter", "2"], "--scatter"),
        (["bert-standin", "--amplitude", "0.1", "--scatter", "101"], "--scatter"),
        (["bert-standin", "--amplitude", "0.1", "--scatter", "-1"], "--scatter"),
        (["bouc-wen", "--amplitude", "1", "--freq", "20"], "--freq"),
        (["bouc-wen", "--amplitude", "1", "--f1", "400"], "f1"),
        (["bouc-wen", "--amplitude", "abc"], "--amplitude"),
        (["bouc-wen", "--amplitude", "1", "--seed", "-3"], "--seed"),
        (["bouc-wen", "--amplitude", "1", "--noise-fraction", "-0.1"], "--noise-fraction"),
        (["bouc-wen"], "--amplitude"),
    ],
)
def test_bad_arguments_exit_2_with_one_line(tmp_path, capsys, argv, fragment):
    out = tmp_path / "bad.npz"
    assert cli.main(["simulate", *argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and fragment in err[0], err
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []


def test_bad_output_paths(tmp_path, capsys):
    assert _run("bouc-wen", "--amplitude", "1", "--out", tmp_path / "missing" / "r.npz") == 1  # runtime: no folder
    assert _run("bouc-wen", "--amplitude", "1") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "--out" in err[1]


def test_local_writer_is_atomic_and_formats(tmp_path):
    u, y = np.arange(4.0), np.arange(4.0) * 2
    p = cmd_simulate._write_record(str(tmp_path / "x.npz"), u, y, 10.0, {"u": "N", "y": "m"})
    with np.load(p) as d:
        assert sorted(d.files) == ["fs", "u", "y"] and float(d["fs"]) == 10.0
    (tmp_path / "x.csv").write_text("old")
    p = cmd_simulate._write_record(str(tmp_path / "x.csv"), u, y, 10.0, {"u": "N", "y": "m"})
    assert open(p).read().splitlines()[:2] == ["time,u,y", "0,0,0"]
    with pytest.raises(cli.CLIError, match="extension"):
        cmd_simulate._write_record(str(tmp_path / "x.txt"), u, y, 10.0, {})
    assert sorted(q.name for q in tmp_path.iterdir()) == ["x.csv", "x.npz"]


class _FakeStandin:
    calls = []

    def __init__(self, torque=5.0, seed=None, scatter=1.0):
        self.torque, self.seed, self.scatter = torque, seed, scatter

    def simulate(self, u, fs=1024.0):
        _FakeStandin.calls.append((self.torque, self.seed, fs, u.size))
        return {"y": 1e-3 * self.torque * np.asarray(u), "x": np.zeros_like(u)}


def test_bert_standin_wiring(tmp_path, monkeypatch):
    fake = types.ModuleType("gpnarx.training.simulators.bert_standin")
    fake.BertStandin = _FakeStandin
    monkeypatch.setitem(sys.modules, "gpnarx.training.simulators.bert_standin", fake)
    _FakeStandin.calls.clear()
    out = tmp_path / "b.npz"
    assert _run("bert-standin", "--amplitude", "0.05", "--torque", "7", "--seed", "3", "--out", out) == 0
    d = np.load(out)
    assert float(d["fs"]) == 1024.0 and d["u"].size == 16384
    t = np.arange(16384) / 1024.0
    # 0 -> 40 Hz at 5 Hz/s for 8 s, then 8 s of zero input
    np.testing.assert_allclose(d["u"][:8192], 0.05 * np.sin(2 * np.pi * 2.5 * t[:8192] ** 2), atol=1e-12)
    assert np.all(d["u"][8192:] == 0.0)
    assert _FakeStandin.calls == [(7.0, 3, 1024.0, 16384)]
    np.testing.assert_allclose(d["y"], 7e-3 * d["u"])
    # steady sine: pre-roll cut off, record starts at phase 0
    s = tmp_path / "s.npz"
    assert _run("bert-standin", "--excitation", "sine", "--amplitude", "0.15", "--out", s) == 0
    d = np.load(s)
    assert d["u"].size == 16384 and d["u"][0] == 0.0
    np.testing.assert_allclose(d["y"], 5e-3 * d["u"], atol=1e-15)
