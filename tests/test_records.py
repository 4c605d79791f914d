"""Record readers/writers: round trips, the real LMS exports, bad files, atomic writes."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gpnarx.model.record import Record
from gpnarx.model.velocity import velocity_to_acceleration, velocity_to_displacement
from gpnarx.storage.record_files import (
    RecordFileError,
    read_record,
    write_record,
)
from gpnarx.training.datapaths import bert_data_dir

DATA = bert_data_dir()
SINE_DIRS = sorted((DATA / "Sine").glob("Sine_*")) if DATA.is_dir() else []
needs_data = pytest.mark.skipif(not SINE_DIRS, reason=f"BERT data not found at {DATA}")


def _rec(n=257, fs=750.0, seed=0, units=("N", "m")):
    rng = np.random.default_rng(seed)
    return Record(rng.standard_normal(n), rng.standard_normal(n) * 1e-3, fs, {"u": units[0], "y": units[1]}, "r")


# ---------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("ext", [".npz", ".csv", ".mat"])
def test_round_trip(tmp_path, ext):
    rec = _rec()
    path = write_record(tmp_path / f"rec{ext}", rec)
    back = read_record(path)
    np.testing.assert_array_equal(back.u, rec.u)
    np.testing.assert_array_equal(back.y, rec.y)
    assert back.fs == pytest.approx(750.0, rel=1e-12)
    assert back.u.dtype == np.float64 and back.u.ndim == 1
    if ext != ".csv":  # CSV header is exactly time,u,y: units are not stored
        assert back.units == {"u": "N", "y": "m"}
    assert back.name == ("r" if ext == ".npz" else "rec")  # npz stores the record name


def test_npz_contract_arrays(tmp_path):
    path = write_record(tmp_path / "a.npz", _rec(fs=1024.0, units=("V", "m/s")))
    with np.load(path, allow_pickle=False) as z:
        assert z["u"].dtype == np.float64 and z["u"].ndim == 1
        assert z["y"].dtype == np.float64 and z["y"].ndim == 1
        assert z["fs"].shape == () and float(z["fs"]) == 1024.0
        assert str(z["units_y"]) == "m/s"


def test_csv_header_and_fs_argument(tmp_path):
    path = write_record(tmp_path / "a.csv", _rec(n=10))
    assert path.read_text().splitlines()[0] == "time,u,y"
    p2 = tmp_path / "b.csv"
    p2.write_text("# comment\nY [m],U [N]\n1,2\n3,4\n5,6\n")
    rec = read_record(p2, fs=100.0)
    np.testing.assert_array_equal(rec.u, [2, 4, 6])
    assert rec.units == {"u": "N", "y": "m"} and rec.fs == 100.0
    with pytest.raises(RecordFileError, match="b.csv.*pass fs"):
        read_record(p2)
    with pytest.raises(RecordFileError, match="a.csv.*fs given as 10 Hz but the file says 750 Hz"):
        read_record(path, fs=10.0)


def test_npy_forms(tmp_path):
    arr = np.column_stack([np.arange(5.0), np.arange(5.0) * 2])
    np.save(tmp_path / "a.npy", arr)
    rec = read_record(tmp_path / "a.npy", fs=10.0)
    np.testing.assert_array_equal(rec.y, arr[:, 1])
    st_arr = np.zeros(4, dtype=[("time", "f8"), ("u", "f8"), ("y", "f8")])
    st_arr["time"] = np.arange(4) / 50.0
    np.save(tmp_path / "s.npy", st_arr)
    assert read_record(tmp_path / "s.npy").fs == pytest.approx(50.0)
    np.save(tmp_path / "bad.npy", np.zeros((4, 3)))
    with pytest.raises(RecordFileError, match=r"bad.npy: wrong shape \(4, 3\)"):
        read_record(tmp_path / "bad.npy", fs=10.0)


# ---------------------------------------------------------------------------- real LMS exports
@needs_data
@pytest.mark.parametrize("folder", SINE_DIRS + [DATA / "Rand" / "Rand0p25"], ids=lambda p: p.name)
def test_lms_real_records(folder):
    rec = read_record(folder)
    assert rec.fs == 1024.0
    assert rec.n == (16384 if folder.name.startswith("Rand") else 65536)
    assert rec.units == {"u": "V", "y": "m/s"}
    assert rec.name == folder.name
    assert rec.meta["format"] == "lms-testlab" and rec.meta["run_name"]
    assert 0.001 < np.max(np.abs(rec.u)) < 1.0  # volts
    # the Time.mat file itself also reads as its folder
    assert read_record(folder / "Time.mat").n == rec.n


def _lms_copy(src: Path, dst: Path) -> Path:
    """A modifiable LMS folder in tmp (the shared data is only read, never copied into the repo)."""
    dst.mkdir()
    for f in ("Time.mat", "TimeShaker.mat"):
        (dst / f).write_bytes((src / f).read_bytes())
    return dst


def _edit_lms(folder: Path, fname: str, struct: str, edit) -> None:
    d = scipy.io.loadmat(folder / fname, squeeze_me=True, struct_as_record=False)
    s = d[struct]
    edit(s)
    scipy.io.savemat(folder / fname, {struct: _to_dict(s)})


def _to_dict(s):
    if hasattr(s, "_fieldnames"):
        return {k: _to_dict(getattr(s, k)) for k in s._fieldnames}
    return s


@needs_data
def test_lms_unknown_unit_and_inconsistent_length(tmp_path):
    src = DATA / "Rand" / "Rand0p25"
    a = _lms_copy(src, tmp_path / "a")
    _edit_lms(a, "Time.mat", "Time_Laser__X", lambda s: setattr(s.y_values.quantity, "label", "furlong/s"))
    with pytest.raises(RecordFileError, match="unknown unit label 'furlong/s'") as ei:
        read_record(a)
    assert "Time.mat" in str(ei.value) and "\n" not in str(ei.value)
    b = _lms_copy(src, tmp_path / "b")
    _edit_lms(b, "TimeShaker.mat", "Time_Shaker__X", lambda s: setattr(s.y_values, "values", s.y_values.values[:100]))
    with pytest.raises(RecordFileError, match="TimeShaker.mat.*100 values but x_values.number_of_values says 16384"):
        read_record(b)
    c = _lms_copy(src, tmp_path / "c")
    (c / "TimeShaker.mat").write_bytes((src / "TimeShaker.mat").read_bytes()[:5000])
    with pytest.raises(RecordFileError, match="TimeShaker.mat: .*(corrupt|truncated)"):
        read_record(c)


# ---------------------------------------------------------------------------- bad files
def _bad_cases(tmp_path):
    cases = {}
    p = tmp_path / "missing_u.csv"
    p.write_text("time,y\n0,1\n0.1,2\n")
    cases[p] = "missing column 'u'"
    p = tmp_path / "nan.csv"
    p.write_text("time,u,y\n0,1,2\n0.1,nan,2\n")
    cases[p] = "NaN"
    p = tmp_path / "nonuniform.csv"
    p.write_text("time,u,y\n0,1,2\n0.1,1,2\n0.3,1,2\n")
    cases[p] = "not uniform"
    p = tmp_path / "ragged.csv"
    p.write_text("time,u,y\n0,1,2\n0.1,1\n")
    cases[p] = "2 fields"
    p = tmp_path / "nan.npz"
    np.savez(p, u=np.array([1.0, np.nan]), y=np.zeros(2), fs=10.0)
    cases[p] = "NaN"
    p = tmp_path / "shape.npz"
    np.savez(p, u=np.zeros((3, 4)), y=np.zeros(3), fs=10.0)
    cases[p] = "1-D"
    p = tmp_path / "length.npz"
    np.savez(p, u=np.zeros(3), y=np.zeros(4), fs=10.0)
    cases[p] = "must match"
    p = tmp_path / "nou.npz"
    np.savez(p, y=np.zeros(3), fs=10.0)
    cases[p] = "missing array 'u'"
    p = tmp_path / "unit.npz"
    np.savez(p, u=np.zeros(3), fs=10.0, units_u="parsec")
    cases[p] = "unknown unit label 'parsec'"
    p = tmp_path / "nofs.npz"
    np.savez(p, u=np.zeros(3))
    cases[p] = "no sampling frequency"
    p = tmp_path / "garbage.mat"
    p.write_bytes(bytes(np.random.default_rng(1).integers(0, 256, 4000, dtype=np.uint8)))
    cases[p] = "MATLAB"
    good = tmp_path / "good.mat"
    scipy.io.savemat(good, {"u": np.arange(1000.0), "y": np.arange(1000.0), "fs": 10.0})
    p = tmp_path / "truncated.mat"
    p.write_bytes(good.read_bytes()[:3000])
    cases[p] = "corrupt or truncated"
    p = tmp_path / "tiny.mat"
    p.write_bytes(b"MATLAB")
    cases[p] = "truncated"
    p = tmp_path / "nou.mat"
    scipy.io.savemat(p, {"y": np.arange(3.0), "fs": 10.0})
    cases[p] = "missing variable 'u'"
    p = tmp_path / "garbage.npz"
    p.write_bytes(b"PK\x03\x04 this is not really a zip")
    cases[p] = "npz"
    p = tmp_path / "rec.xlsx"
    p.write_bytes(b"x")
    cases[p] = "unsupported record format"
    cases[tmp_path / "does_not_exist.npz"] = "no such file"
    d = tmp_path / "emptydir"
    d.mkdir()
    cases[d] = "not an LMS"
    return cases


def test_bad_files_raise_one_line_naming_the_file(tmp_path):
    for path, fragment in _bad_cases(tmp_path).items():
        with pytest.raises(RecordFileError) as ei:
            read_record(path, fs=None)
        msg = str(ei.value)
        assert str(path) in msg, msg
        assert fragment in msg, (fragment, msg)
        assert "\n" not in msg
        assert isinstance(ei.value, ValueError)


# ---------------------------------------------------------------------------- atomic writes
def test_atomic_write_leaves_nothing_on_failure(tmp_path, monkeypatch):
    target = tmp_path / "out.npz"

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", boom)
    with pytest.raises(RecordFileError, match="out.npz: cannot write the record.*disk full"):
        write_record(target, _rec())
    assert os.listdir(tmp_path) == []


def test_atomic_write_keeps_old_file_on_failure(tmp_path, monkeypatch):
    target = tmp_path / "out.csv"
    write_record(target, _rec(n=5))
    before = target.read_bytes()
    monkeypatch.setattr(os, "fsync", lambda fd: (_ for _ in ()).throw(OSError("io error")))
    with pytest.raises(RecordFileError):
        write_record(target, _rec(n=9, seed=3))
    assert target.read_bytes() == before
    assert os.listdir(tmp_path) == ["out.csv"]


def test_write_errors(tmp_path):
    with pytest.raises(RecordFileError, match="cannot write format '.txt'"):
        write_record(tmp_path / "a.txt", _rec())
    with pytest.raises(RecordFileError, match="does not exist"):
        write_record(tmp_path / "no" / "a.npz", _rec())
    with pytest.raises(RecordFileError, match="unknown unit"):
        write_record(tmp_path / "a.npz", _rec(units=("N", "cubits")))
    assert os.listdir(tmp_path) == []


# ---------------------------------------------------------------------------- hypothesis
finite = st.floats(min_value=-1e12, max_value=1e12, allow_nan=False, allow_infinity=False)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.lists(st.tuples(finite, finite), min_size=2, max_size=60),
       fs=st.sampled_from([1.0, 750.0, 1024.0, 12345.5]))
def test_csv_round_trip_property(tmp_path, data, fs):
    u = np.array([d[0] for d in data])
    y = np.array([d[1] for d in data])
    path = write_record(tmp_path / "h.csv", Record(u, y, fs, {"u": "V", "y": "m/s"}, "h"))
    back = read_record(path)
    np.testing.assert_array_equal(back.u, u)
    np.testing.assert_array_equal(back.y, y)
    assert back.fs == pytest.approx(fs, rel=1e-9)


csv_garbage = st.one_of(
    st.binary(max_size=300),
    st.text(alphabet=st.sampled_from(list("time,uy0123456789.-e+nainf \n\t;#[]()\"")), max_size=300),
    st.lists(st.lists(st.sampled_from(["time", "u", "y", "1", "-2.5", "nan", "", "x", "1e400", "0.1"]),
                      max_size=4).map(",".join), max_size=8).map("\n".join),
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(blob=csv_garbage, fs=st.sampled_from([None, 10.0]))
def test_csv_garbage_only_raises_record_file_error(tmp_path, blob, fs):
    path = tmp_path / "g.csv"
    path.write_bytes(blob if isinstance(blob, bytes) else blob.encode("utf-8"))
    try:
        rec = read_record(path, fs=fs)
    except RecordFileError as exc:
        assert str(path) in str(exc) and "\n" not in str(exc)
    else:
        assert np.all(np.isfinite(rec.u)) and rec.fs > 0


# ---------------------------------------------------------------------------- integration
def test_velocity_to_displacement_and_acceleration():
    fs = 1024.0
    t = np.arange(8192) / fs
    f = 18.75
    w = 2 * np.pi * f
    v = 0.3 * np.cos(w * t) + 0.01  # offset: drift-free integration removes it
    x = velocity_to_displacement(v, fs, f_highpass=2.0, periodic=True)
    np.testing.assert_allclose(x, 0.3 / w * np.sin(w * t), atol=1e-9)
    x2 = velocity_to_displacement(v, fs, f_highpass=2.0)
    mid = slice(2048, 6144)
    np.testing.assert_allclose(x2[mid], 0.3 / w * np.sin(w * t[mid]), atol=0.02 * 0.3 / w)
    a = velocity_to_acceleration(v, fs)
    np.testing.assert_allclose(a[mid], -0.3 * w * np.sin(w * t[mid]), atol=1e-3 * 0.3 * w)
    # no drift: a random-walk-like offset velocity does not integrate to a ramp
    drift = velocity_to_displacement(np.full(4096, 0.05), fs)
    assert np.max(np.abs(drift)) < 1e-12
