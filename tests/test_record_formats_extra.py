"""Lab record formats (extra ``formats``): UFF-58 (pyuff), TDMS (npTDMS), HDF5 and MATLAB v7.3 (h5py).

Each test writes a file with the format's own library and reads it back through the one
record-reading function (``storage.record_files.read_record``) and the service's upload parser.
"""
from __future__ import annotations

import sys

import numpy as np
import pytest

from gpnarx.storage.record_files import read_record
from gpnarx.storage.record_formats import FORMATS, RecordFileError, parse_record

FS = 1024.0
N = 600


def signals():
    t = np.arange(N) / FS
    u = 0.15 * np.sin(2 * np.pi * 18.0 * t) + 0.01 * np.cos(2 * np.pi * 3.0 * t)
    y = 0.02 * np.sin(2 * np.pi * 18.0 * t - 0.7)
    return u, y


def uff58(name: str, data: np.ndarray, unit: str, binary: int = 0) -> dict:
    """A complete UFF-58 time-response data set for pyuff's writer."""
    n = data.size
    return {"type": 58, "binary": binary, "func_type": 1, "func_id": 0, "ver_num": 0, "load_case_id": 0,
            "id1": name, "id2": "", "id3": "", "id4": "", "id5": "",
            "rsp_ent_name": "pt", "rsp_node": 1, "rsp_dir": 1, "ref_ent_name": "pt", "ref_node": 1, "ref_dir": 1,
            "ord_data_type": 4, "num_pts": n, "abscissa_spacing": 1, "abscissa_min": 0.0, "abscissa_inc": 1.0 / FS,
            "z_axis_value": 0.0, "abscissa_spec_data_type": 17, "abscissa_len_unit_exp": 0,
            "abscissa_force_unit_exp": 0, "abscissa_temp_unit_exp": 0, "abscissa_axis_lab": "Time",
            "abscissa_axis_units_lab": "s", "ordinate_spec_data_type": 0, "ordinate_len_unit_exp": 0,
            "ordinate_force_unit_exp": 0, "ordinate_temp_unit_exp": 0, "ordinate_axis_lab": name,
            "ordinate_axis_units_lab": unit, "orddenom_spec_data_type": 0, "orddenom_len_unit_exp": 0,
            "orddenom_force_unit_exp": 0, "orddenom_temp_unit_exp": 0, "orddenom_axis_lab": "",
            "orddenom_axis_units_lab": "", "z_axis_spec_data_type": 0, "z_axis_len_unit_exp": 0,
            "z_axis_force_unit_exp": 0, "z_axis_temp_unit_exp": 0, "z_axis_axis_lab": "", "z_axis_axis_units_lab": "",
            "data": data, "x": np.arange(n) / FS}


@pytest.mark.parametrize("binary, ext", [(0, ".uff"), (1, ".unv")])
def test_uff58_round_trip(tmp_path, binary, ext):
    pyuff = pytest.importorskip("pyuff")
    u, y = signals()
    path = tmp_path / f"run{ext}"
    f = pyuff.UFF(str(path))
    # y first: the reader picks the sets by their id1, not their order
    for ds in (uff58("y", y, "m/s", binary), uff58("u", u, "V", binary)):
        f.write_sets(ds, mode="add")
    rec = read_record(path)
    assert rec.fs == FS and rec.n == N
    np.testing.assert_allclose(rec.u, u, rtol=1e-10, atol=1e-12 if binary else 1e-11)
    np.testing.assert_allclose(rec.y, y, rtol=1e-10, atol=1e-12 if binary else 1e-11)
    assert rec.units == {"u": "V", "y": "m/s"} and rec.meta["format"] == "uff-58"
    # the service's upload parser reads the same bytes
    same = parse_record(path.read_bytes(), path.name)
    np.testing.assert_array_equal(same.u, rec.u)


def test_uff58_unnamed_sets_and_refusals(tmp_path):
    pyuff = pytest.importorskip("pyuff")
    u, y = signals()
    two = tmp_path / "two.uff"
    f = pyuff.UFF(str(two))
    for ds in (uff58("Shaker", u, "V"), uff58("Laser", y, "m/s")):
        f.write_sets(ds, mode="add")
    rec = read_record(two)  # two unnamed sets: u then y
    np.testing.assert_allclose(rec.u, u, atol=1e-11)
    np.testing.assert_allclose(rec.y, y, atol=1e-11)
    three = tmp_path / "three.uff"
    f = pyuff.UFF(str(three))
    for ds in (uff58("a", u, "V"), uff58("b", y, "m/s"), uff58("c", y, "m/s")):
        f.write_sets(ds, mode="add")
    with pytest.raises(RecordFileError, match="none named 'u'"):
        read_record(three)
    with pytest.raises(RecordFileError, match="disagree|fs given as"):
        read_record(two, fs=500.0)


def test_tdms_round_trip(tmp_path):
    nptdms = pytest.importorskip("nptdms")
    u, y = signals()
    path = tmp_path / "run.tdms"
    with nptdms.TdmsWriter(str(path)) as w:
        w.write_segment([
            nptdms.GroupObject("other"),
            nptdms.ChannelObject("other", "temperature", np.ones(4)),
            nptdms.ChannelObject("Measurement", "U", u, properties={"wf_increment": 1.0 / FS, "unit_string": "V"}),
            nptdms.ChannelObject("Measurement", "y", y, properties={"wf_increment": 1.0 / FS,
                                                                    "unit_string": "m/s"}),
        ])
    rec = read_record(path)
    assert rec.fs == FS and rec.n == N and rec.units == {"u": "V", "y": "m/s"}
    np.testing.assert_array_equal(rec.u, u)
    np.testing.assert_array_equal(rec.y, y)
    assert rec.meta["group"] == "Measurement"
    # fs as a group property [Hz], no y
    path2 = tmp_path / "u-only.tdms"
    with nptdms.TdmsWriter(str(path2)) as w:
        w.write_segment([nptdms.GroupObject("g", properties={"fs": 750.0}), nptdms.ChannelObject("g", "u", u)])
    rec2 = read_record(path2)
    assert rec2.fs == 750.0 and rec2.y is None
    path3 = tmp_path / "nothing.tdms"
    with nptdms.TdmsWriter(str(path3)) as w:
        w.write_segment([nptdms.ChannelObject("g", "force", u)])
    with pytest.raises(RecordFileError, match="no channel named 'u'.*g/force"):
        read_record(path3, fs=FS)
    with pytest.raises(RecordFileError, match="no sampling frequency"):
        read_record(_tdms_u_without_fs(nptdms, tmp_path, u))


def _tdms_u_without_fs(nptdms, tmp_path, u):
    path = tmp_path / "nofs.tdms"
    with nptdms.TdmsWriter(str(path)) as w:
        w.write_segment([nptdms.ChannelObject("g", "u", u)])
    return path


def _matlab_v73(path, u, y, fs, units_u="V"):
    """A MATLAB -v7.3 file as MATLAB lays it out: 512-byte header block, column vectors as (1, n)."""
    h5py = pytest.importorskip("h5py")
    with h5py.File(path, "w", userblock_size=512) as f:
        for k, v in (("u", u), ("y", y)):
            ds = f.create_dataset(k, data=np.asarray(v, dtype=np.float64).reshape(1, -1))
            ds.attrs["MATLAB_class"] = np.bytes_("double")
        ds = f.create_dataset("fs", data=np.array([[fs]]))
        ds.attrs["MATLAB_class"] = np.bytes_("double")
        ds = f.create_dataset("units_u", data=np.array([[ord(c)] for c in units_u], dtype=np.uint16))
        ds.attrs["MATLAB_class"] = np.bytes_("char")
    head = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: test HDF5 schema 1.00 ."
    with open(path, "r+b") as fh:
        fh.write(head.ljust(116, b" ") + b"\0" * 8 + b"\x00\x02IM")


def test_matlab_v73_round_trip(tmp_path):
    pytest.importorskip("h5py")
    u, y = signals()
    path = tmp_path / "run.mat"
    _matlab_v73(path, u, y, FS)
    assert path.read_bytes()[:10] == b"MATLAB 7.3"
    rec = read_record(path)
    assert rec.fs == FS and rec.n == N and rec.units["u"] == "V" and rec.meta["format"] == "matlab-v7.3"
    np.testing.assert_array_equal(rec.u, u)
    np.testing.assert_array_equal(rec.y, y)


def test_hdf5_round_trip(tmp_path):
    h5py = pytest.importorskip("h5py")
    u, y = signals()
    path = tmp_path / "run.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("u", data=u).attrs["units"] = "N"
        f.create_dataset("y", data=y).attrs["units"] = "m"
        f.attrs["fs"] = FS
    rec = read_record(path)
    assert rec.fs == FS and rec.units == {"u": "N", "y": "m"} and rec.meta["format"] == "hdf5"
    np.testing.assert_array_equal(rec.u, u)
    with h5py.File(tmp_path / "bad.hdf5", "w") as f:
        f.create_dataset("force", data=u)
    with pytest.raises(RecordFileError, match="missing dataset 'u'.*force"):
        read_record(tmp_path / "bad.hdf5", fs=FS)
    with h5py.File(tmp_path / "cplx.h5", "w") as f:
        f.create_dataset("u", data=u.astype(complex))
    with pytest.raises(RecordFileError, match="complex"):
        read_record(tmp_path / "cplx.h5", fs=FS)


def test_every_lab_extension_is_a_format():
    assert {".uff", ".unv", ".tdms", ".h5", ".hdf5", ".mat"} <= set(FORMATS)


@pytest.mark.parametrize("module, ext", [("pyuff", ".uff"), ("nptdms", ".tdms"), ("h5py", ".h5")])
def test_missing_extra_names_it(monkeypatch, tmp_path, module, ext):
    monkeypatch.setitem(sys.modules, module, None)  # import fails as if not installed
    path = tmp_path / f"r{ext}"
    path.write_bytes(b"\0" * 64)
    with pytest.raises(RecordFileError, match=r"pip install 'gpnarx\[formats\]'"):
        read_record(path, fs=FS)


def test_missing_extra_for_a_v73_mat(monkeypatch, tmp_path):
    pytest.importorskip("h5py")
    u, y = signals()
    path = tmp_path / "run.mat"
    _matlab_v73(path, u, y, FS)
    monkeypatch.setitem(sys.modules, "h5py", None)
    with pytest.raises(RecordFileError, match=r"MATLAB v7.3.*gpnarx\[formats\]"):
        read_record(path)


def test_upload_parser_route_reads_a_tdms_file(tmp_path):
    nptdms = pytest.importorskip("nptdms")
    from fastapi.testclient import TestClient

    from gpnarx.service.app import create_app
    from gpnarx.service.settings import Settings

    u, y = signals()
    path = tmp_path / "run.tdms"
    with nptdms.TdmsWriter(str(path)) as w:
        w.write_segment([nptdms.ChannelObject("g", "u", u, properties={"wf_increment": 1.0 / FS}),
                         nptdms.ChannelObject("g", "y", y, properties={"wf_increment": 1.0 / FS})])
    c = TestClient(create_app(None, Settings(workers=1, queue_size=2)))
    r = c.post("/v1/records/parse", files={"files": ("run.tdms", path.read_bytes(), "application/octet-stream")})
    assert r.status_code == 200, r.text
    d = r.json()
    assert d["fs"] == FS and d["n_samples"] == N and np.allclose(d["u"], u)
