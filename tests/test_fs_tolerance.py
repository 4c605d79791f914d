"""A record's sampling frequency against the model's (``operations.check_fs``): a file that stores its
sample interval to a few digits (UFF-58 keeps 6: 1/750 s is 1.33333e-03, read as 750.002 Hz) is the model's
750 Hz within ``FS_RTOL``, through ``gpnarx predict`` and the HTTP routes alike; a rate outside it is refused
with both rates and how to resample."""
from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest
from fastapi.testclient import TestClient
from test_record_formats_extra import uff58
from test_service_support import FS, built_registry, short_record

from gpnarx.cli.main import main
from gpnarx.model.record import FS_RTOL, fs_matches
from gpnarx.operations import OperationError, check_fs
from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings
from gpnarx.storage.record_files import read_record


def cli(*argv) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in argv])
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def uff_750(tmp_path_factory):
    """A UFF-58 file (u and y sets) written by pyuff at 750 Hz."""
    pyuff = pytest.importorskip("pyuff")
    u, y = short_record(240, 7)
    path = tmp_path_factory.mktemp("uff") / "run-750Hz.uff"
    f = pyuff.UFF(str(path))
    for name, data, unit in (("u", u, "N"), ("y", y, "m")):
        ds = uff58(name, data, unit)
        ds.update(abscissa_inc=1.0 / FS, x=np.arange(data.size) / FS)
        f.write_sets(ds, mode="add")
    return path


@pytest.fixture(scope="module")
def client():
    return TestClient(create_app(built_registry().root, Settings(workers=1, queue_size=4)),
                      raise_server_exceptions=False)


def test_the_uff_file_reads_a_few_ppm_off_the_model_rate(uff_750):
    rec = read_record(uff_750)
    assert rec.fs != FS and abs(rec.fs - FS) / FS < FS_RTOL  # 750.002 Hz: the 6 digits of 1.33333e-03 s
    assert FS_RTOL <= 1e-4  # a few ppm: far below any rate a model could be mistaken for


def test_cli_predicts_the_750_hz_uff_file(uff_750):
    for extra in ((), ("--fs", "750")):
        code, out, err = cli("--json", "predict", "--registry", built_registry().root, "--model", "plain", uff_750,
                             "--mc", 8, *extra)
        assert code == 0, err
        d = json.loads(out)
        assert d["n"] == 240 and len(d["mean"]) == 240 and d["fit"] is not None


def test_http_parse_then_predict_the_750_hz_uff_file(client, uff_750):
    r = client.post("/v1/records/parse", files={"files": (uff_750.name, uff_750.read_bytes())})
    assert r.status_code == 200, r.text
    parsed = r.json()
    assert parsed["fs"] == pytest.approx(FS, rel=FS_RTOL)
    body = {"u": parsed["u"], "y": parsed["y"], "fs": parsed["fs"], "mc_paths": 8, "seed": 0}
    r = client.post("/v1/models/plain/predict", json=body)
    assert r.status_code == 200, r.text
    assert len(r.json()["mean"]) == 240
    # the same through the parse route's fs field (what /ui sends when a user types the rate)
    r = client.post("/v1/records/parse", files={"files": (uff_750.name, uff_750.read_bytes())}, data={"fs": "750"})
    assert r.status_code == 200, r.text
    r = client.post("/v1/models/plain/predict", json={**body, "fs": r.json()["fs"]})
    assert r.status_code == 200, r.text


def test_a_rate_outside_the_tolerance_names_both_rates_and_how_to_resample(client, uff_750, tmp_path):
    u, _ = short_record(64, 3)
    r = client.post("/v1/models/plain/predict", json={"u": u.tolist(), "fs": 1000.0, "mc_paths": 8})
    assert r.status_code == 422
    p = r.json()
    assert p["field"] == "fs" and p["model_fs"] == FS
    assert "1000 Hz" in p["detail"] and "750 Hz" in p["detail"]
    assert "resample_poly" in p["detail"] and "up=3, down=4" in p["detail"], p["detail"]
    rec = tmp_path / "fast.npz"
    np.savez(rec, u=u, fs=1000.0)
    code, _, err = cli("predict", "--registry", built_registry().root, "--model", "plain", rec, "--mc", 8)
    assert code == 1 and "1000 Hz" in err and "750 Hz" in err and "resample_poly" in err, err


def test_check_fs_is_the_one_rule():
    class B:
        fs, name, version = 750.0, "m", "1"

    assert check_fs(750.0 * (1 + 0.9 * FS_RTOL), B) == 750.0  # within: the model's fs is used
    with pytest.raises(OperationError) as exc:
        check_fs(750.0 * (1 + 1.1 * FS_RTOL), B)
    assert exc.value.field == "fs" and exc.value.limit == FS_RTOL
    assert fs_matches(750.0, 750.002) and not fs_matches(750.0, 750.1)
    for far in (5e-324, 1e-300, 1e308):  # the advice never fails on a rate at the ends of the double range
        with pytest.raises(OperationError, match="resample"):
            check_fs(far, B)
