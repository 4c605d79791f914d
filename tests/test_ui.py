"""The service's pages and their routes, without a browser (tests/test_ui_browser.py drives them in one).

/ui, /docs and /redoc reference only the service's own files; vendored files match VENDORED.md;
training reports are served self-contained (GET /v1/models/{name}[/versions/{v}]/report);
POST /v1/records/parse reads what storage.record_files reads, with problem details for bad uploads.
"""
from __future__ import annotations

import base64
import hashlib
import io
import json
import re
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from fastapi.testclient import TestClient
from test_service_support import FS, built_registry, copy_registry, short_record

from gpnarx.model.record import Record
from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings
from gpnarx.service.ui import STATIC_DIR, inline_images
from gpnarx.storage.record_files import read_record, write_record
from gpnarx.training.datapaths import bert_data_dir

ROOT = Path(__file__).resolve().parents[1]
BERT_SINE = bert_data_dir() / "Sine" / "Sine_09Hz"
PROBLEM = "application/problem+json"
PNG = base64.b64decode("iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAYAAAAfFcSJAAAADUlEQVR42mP8z8BQDwAEhQGAhKmMIQ"
                       "AAAABJRU5ErkJggg==")


def make_reports(root: Path) -> Path:
    """boucwen 2: a report written by training.report (figures embedded); boucwen 1: an older report
    whose figure is a PNG next to it; plain 1: none."""
    from gpnarx.training.report import write_report

    u, y = short_record(512, 9)
    model = built_registry().model
    run = model.simulate(u, n_paths=16, seed=0)
    rec = {"name": "multisine", "role": "validation", "fs": FS, "u": u, "y": y, "mean": run.mean,
           "lower": run.lower, "upper": run.upper, "units": {"u": "N", "y": "m"}}
    write_report(root / "boucwen" / "2" / "report", "GP-NARX boucwen (test)", {"n_train": 400}, [rec],
                 physics={"mass": 2.0, "input_gain": 1.0, "output": "displacement"})
    old = root / "boucwen" / "1" / "report"
    (old / "figs").mkdir(parents=True)
    (old / "figs" / "record a.png").write_bytes(PNG)
    (old / "report.html").write_text(
        "<!DOCTYPE html><html><body><h1>old report</h1>"
        "<img src='figs/record%20a.png' alt='a'>"
        '<IMG alt="b" SRC="figs/record a.png">'
        "<img src='../manifest.json' alt='outside'>"
        "<img src='https://example.invalid/x.png' alt='remote'>"
        "<img src='missing.png' alt='missing'></body></html>", encoding="utf-8")
    return root


@pytest.fixture(scope="module")
def registry(tmp_path_factory):
    return make_reports(copy_registry(tmp_path_factory.mktemp("ui") / "registry"))


@pytest.fixture(scope="module")
def client(registry):
    return TestClient(create_app(registry, Settings(workers=1, queue_size=4)), raise_server_exceptions=False)


def assert_problem(r, status, field=None):
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith(PROBLEM)
    p = r.json()
    assert p["status"] == status and p["detail"]
    if field is not None:
        assert p["field"] == field, p
    return p


# ------------------------------------------------------------------------------------------ pages
def _links(html: str) -> list[str]:
    return re.findall(r"""(?:src|href)\s*=\s*["']([^"']+)["']""", html) + re.findall(
        r"""(?:url|spec-url)\s*[:=]\s*["']([^"']+)["']""", html)


@pytest.mark.parametrize("path", ["/ui", "/docs", "/redoc"])
def test_pages_reference_only_the_services_files(client, path):
    r = client.get(path)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    links = _links(r.text)
    assert links, r.text
    for url in links:
        assert not re.match(r"^(https?:)?//", url), f"{path} loads {url} from outside the service"
        if url.startswith("/"):
            asset = client.get(url)
            assert asset.status_code == 200 and asset.content, url


def test_page_modules_and_csp(client):
    r = client.get("/ui")
    csp = r.headers["content-security-policy"]
    assert "default-src 'self'" in csp and "connect-src 'self'" in csp and "script-src 'self'" in csp
    # the ES modules the page imports are served, and import only each other
    for name in ("app.js", "api.js", "dsp.js", "plots.js"):
        js = client.get(f"/static/ui/{name}")
        assert js.status_code == 200 and "javascript" in js.headers["content-type"], name
        for spec in re.findall(r"""from\s+["']([^"']+)["']""", js.text):
            assert spec.startswith("./"), (name, spec)
            assert (STATIC_DIR / "ui" / spec[2:]).is_file(), spec
        assert "http://" not in js.text and "https://" not in js.text, name
    assert client.get("/redoc").headers["content-security-policy"].startswith("default-src 'self'")


def test_vendored_files_match_their_record():
    vendor = STATIC_DIR / "vendor"
    listed = dict((path, digest) for digest, path in
                  re.findall(r"^([0-9a-f]{64})  (\S+)$", (vendor / "VENDORED.md").read_text(), re.M))
    on_disk = {p.relative_to(vendor).as_posix() for p in vendor.rglob("*") if p.is_file() and p.name != "VENDORED.md"}
    assert set(listed) == on_disk
    for path, digest in listed.items():
        assert hashlib.sha256((vendor / path).read_bytes()).hexdigest() == digest, path


# ------------------------------------------------------------------------------------------ reports
def test_report_served_self_contained(client, registry):
    r = client.get("/v1/models/boucwen/versions/2/report")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert "script-src" not in r.headers["content-security-policy"]  # default-src 'none': no script at all
    assert r.headers["content-security-policy"].startswith("default-src 'none'")
    srcs = re.findall(r"<img src='([^']*)'", r.text)
    assert srcs and all(s.startswith("data:image/png;base64,") for s in srcs)
    assert r.text == (registry / "boucwen" / "2" / "report" / "report.html").read_text()
    latest = client.get("/v1/models/boucwen/report")
    assert latest.status_code == 200 and latest.text == r.text


def test_older_report_images_inlined_at_serve_time(client):
    r = client.get("/v1/models/boucwen/versions/1/report")
    assert r.status_code == 200
    inline = "data:image/png;base64," + base64.b64encode(PNG).decode()
    assert r.text.count(inline) == 2  # both spellings of the same figure
    assert "src='../manifest.json'" in r.text  # outside the report folder: left alone
    assert "src='https://example.invalid/x.png'" in r.text and "src='missing.png'" in r.text


def test_report_missing_is_a_problem(client):
    p = assert_problem(client.get("/v1/models/plain/versions/1/report"), 404, "version")
    assert "no training report" in p["detail"]
    assert_problem(client.get("/v1/models/nope/report"), 404, "name")
    assert_problem(client.get("/v1/models/boucwen/versions/9/report"), 404, "version")


def test_inline_images_unit(tmp_path):
    (tmp_path / "a.png").write_bytes(PNG)
    (tmp_path / "notes.txt").write_text("x")
    html = "<img src=\"a.png?v=1\"><img src='notes.txt'><img src='/a.png'><img src='data:image/png;base64,AA=='>"
    out = inline_images(html, tmp_path)
    assert out.startswith('<img src="data:image/png;base64,')
    assert "src='notes.txt'" in out and "src='/a.png'" in out and "src='data:image/png;base64,AA=='" in out


# ------------------------------------------------------------------------------------------ API key
def test_api_key_guards_v1_routes_but_not_pages(registry):
    c = TestClient(create_app(registry, Settings(workers=1, queue_size=2, api_key="s3cret")))
    assert_problem(c.get("/v1/models/boucwen/report"), 401)
    assert_problem(c.post("/v1/records/parse", files={"files": ("r.csv", b"time,u\n0,1\n1,2\n")}), 401)
    assert c.get("/v1/models/boucwen/report", headers={"X-API-Key": "s3cret"}).status_code == 200
    for path in ("/ui", "/docs", "/redoc", "/static/ui/app.js", "/static/examples/index.json"):
        assert c.get(path).status_code == 200, path


# ------------------------------------------------------------------------------------------ record files
def _rec(n=300, with_y=True):
    u, y = short_record(n, 4)
    return Record(u, y if with_y else None, FS, {"u": "N", "y": "m"}, "r")


def _parse(client, *files, fs=None):
    data = {"fs": str(fs)} if fs is not None else None
    return client.post("/v1/records/parse", files=[("files", f) for f in files], data=data)


@pytest.mark.parametrize("ext", [".npz", ".csv", ".mat"])
def test_parse_agrees_with_read_record(client, tmp_path, ext):
    path = write_record(tmp_path / f"rec{ext}", _rec())
    r = _parse(client, (path.name, path.read_bytes()))
    assert r.status_code == 200, r.text
    got = r.json()
    want = read_record(path)
    assert got["format"] == ext[1:] and got["files"] == [path.name]
    assert got["n_samples"] == want.n and got["fs"] == pytest.approx(want.fs, rel=1e-12)
    np.testing.assert_array_equal(got["u"], want.u)
    np.testing.assert_array_equal(got["y"], want.y)
    assert got["units"] == {"u": want.units["u"], "y": want.units["y"]}


def test_parse_csv_without_time_and_npy(client, tmp_path):
    rec = _rec(50, with_y=False)
    csv = "u [N]\n" + "\n".join(f"{v:.17g}" for v in rec.u) + "\n"
    assert_problem(_parse(client, ("probe.csv", csv.encode())), 422, "fs")
    r = _parse(client, ("probe.csv", csv.encode()), fs=FS)
    assert r.status_code == 200, r.text
    got = r.json()
    assert got["fs"] == FS and got["y"] is None and got["units"]["u"] == "N" and got["name"] == "probe"
    np.testing.assert_array_equal(got["u"], rec.u)
    buf = io.BytesIO()
    np.save(buf, np.column_stack([rec.u, rec.u * 2]))
    got = _parse(client, ("two.npy", buf.getvalue()), fs=FS).json()
    np.testing.assert_array_equal(got["y"], rec.u * 2)
    assert_problem(_parse(client, ("probe.csv", csv.encode()), fs="fast"), 422, "fs")
    npz = write_record(tmp_path / "at750.npz", rec)
    p = assert_problem(_parse(client, (npz.name, npz.read_bytes()), fs=1000.0), 422, "fs")
    assert "750" in p["detail"]


def _lms_struct(values, inc, label):
    return {"x_values": {"increment": inc, "number_of_values": float(len(values))},
            "y_values": {"values": np.asarray(values, float), "quantity": {"label": label}}}


def test_parse_lms_pair(client):
    u, y = short_record(256, 3)
    shaker, time = io.BytesIO(), io.BytesIO()
    scipy.io.savemat(shaker, {"Time_Shaker__X": _lms_struct(u, 1 / FS, "V")})
    scipy.io.savemat(time, {"Time_Laser__X": _lms_struct(y, 1 / FS, "m/s")})
    r = _parse(client, ("run7/Time.mat", time.getvalue()), ("run7/TimeShaker.mat", shaker.getvalue()))
    assert r.status_code == 200, r.text
    got = r.json()
    assert got["format"] == "lms-testlab" and got["name"] == "run7" and got["n_samples"] == 256
    assert got["fs"] == pytest.approx(FS) and got["units"] == {"u": "V", "y": "m/s"}
    np.testing.assert_array_equal(got["u"], u)
    np.testing.assert_array_equal(got["y"], y)
    assert_problem(_parse(client, ("Time.mat", time.getvalue())), 422, "files")  # half an export
    assert_problem(_parse(client, ("a.npz", b"x"), ("b.npz", b"y")), 422, "files")


@pytest.mark.skipif(not BERT_SINE.is_dir(), reason=f"real BERT records not found at {BERT_SINE}")
def test_parse_real_lms_export_as_the_cli_reads_it(client):
    files = [(f"Sine_09Hz/{n}", (BERT_SINE / n).read_bytes()) for n in ("TimeShaker.mat", "Time.mat")]
    r = _parse(client, *files)
    assert r.status_code == 200, r.text
    got = r.json()
    want = read_record(BERT_SINE)
    assert got["n_samples"] == want.n == 65536 and got["fs"] == want.fs == 1024.0
    assert got["units"] == {"u": "V", "y": "m/s"} and got["name"] == "Sine_09Hz"
    np.testing.assert_array_equal(got["u"], want.u)
    np.testing.assert_array_equal(got["y"], want.y)


def test_parse_refusals(client, registry):
    assert_problem(client.post("/v1/records/parse", json={"u": [1.0]}), 415, "body")
    assert_problem(client.post("/v1/records/parse", data={"fs": "10"}, files={"other": ("x.csv", b"u\n1\n")}),
                   422, "files")
    assert_problem(_parse(client, ("rec.txt", b"u\n1\n")), 422, "files")
    p = assert_problem(_parse(client, ("rec.npz", b"not a zip")), 422, "files")
    assert "rec.npz" in p["detail"]
    p = assert_problem(_parse(client, ("rec.mat", b"\x00" * 40)), 422, "files")
    assert "truncated" in p["detail"]
    r = client.post("/v1/records/parse", files=[("files", (f"{i}.csv", b"u\n1\n")) for i in range(3)])
    assert_problem(r, 400, "body")
    small = TestClient(create_app(registry, Settings(workers=1, queue_size=2, max_samples=100)))
    big = "u\n" + "1\n" * 101
    p = assert_problem(_parse(small, ("big.csv", big.encode()), fs=FS), 413, "files")
    assert p["limit"] == 100


def test_shipped_examples_parse_as_listed(client):
    from gpnarx.training.defaults import DEFAULT_BUNDLES

    index = json.loads((STATIC_DIR / "examples" / "index.json").read_text())
    files = {p.name for p in (STATIC_DIR / "examples").glob("*.npz")}
    assert {e["file"] for e in index["examples"]} == files
    for e in index["examples"]:
        r = client.get(f"/static/examples/{e['file']}")
        assert r.status_code == 200
        got = _parse(client, (e["file"], r.content)).json()
        assert got["fs"] == e["fs"] and got["n_samples"] == e["samples"] <= 4096 and got["y"] is not None
        assert set(e["models"]) <= set(DEFAULT_BUNDLES) and e["start"] in ("rest", "measured"), e
