"""HTTP wire formats: gzip answers, NPZ request bodies and answers, ETags and 304 (service.wire)."""
from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from test_service_support import FS, built_registry, copy_registry, multisine

from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings
from gpnarx.service.ui import REPORT_FILE
from gpnarx.service.wire import NPZ_MEDIA_TYPE, json_loads_npz_meta

PROBLEM = "application/problem+json"


@pytest.fixture(scope="module")
def registry(tmp_path_factory):
    root = copy_registry(tmp_path_factory.mktemp("wire") / "reg")
    report = root / "boucwen" / "2" / REPORT_FILE
    report.parent.mkdir(parents=True, exist_ok=True)
    report.write_text("<html><body><h1>report of version 2</h1>" + "<p>x</p>" * 400 + "</body></html>")
    return root


@pytest.fixture(scope="module")
def client(registry):
    return TestClient(create_app(registry, Settings(workers=1, queue_size=4)), raise_server_exceptions=False)


def npz(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def post_npz(client, body: bytes, query: str = "", op: str = "predict", **headers):
    return client.post(f"/v1/models/boucwen/{op}{query}", content=body,
                       headers={"content-type": NPZ_MEDIA_TYPE, **headers})


def test_gzip_when_accepted_and_identical_content(client):
    u = multisine(512, 3)
    body = {"u": u.tolist(), "fs": FS, "mc_paths": 8, "seed": 1}
    plain = client.post("/v1/models/boucwen/predict", json=body, headers={"accept-encoding": "identity"})
    zipped = client.post("/v1/models/boucwen/predict", json=body, headers={"accept-encoding": "gzip"})
    assert plain.status_code == zipped.status_code == 200
    assert "content-encoding" not in plain.headers
    assert zipped.headers["content-encoding"] == "gzip" and "Accept-Encoding" in zipped.headers["vary"]
    assert int(zipped.headers["content-length"]) < 0.7 * len(plain.content)
    assert zipped.json() == plain.json()  # httpx decodes it
    # a small answer is not worth compressing
    small = client.get("/health/live", headers={"accept-encoding": "gzip"})
    assert "content-encoding" not in small.headers


def test_npz_body_equals_json_body(client):
    u = multisine(400, 4)
    ref = client.post("/v1/models/boucwen/predict", json={"u": u.tolist(), "fs": FS, "mc_paths": 16, "seed": 3})
    assert ref.status_code == 200, ref.text
    r = post_npz(client, npz(u=u, fs=np.float64(FS)), "?mc_paths=16&seed=3")
    assert r.status_code == 200, r.text
    assert r.json()["mean"] == ref.json()["mean"] and r.json()["upper"] == ref.json()["upper"]
    # fs as a query parameter, float32 and int arrays accepted
    r2 = post_npz(client, npz(u=u.astype(np.float32)), f"?fs={FS}&mc_paths=16&seed=3&confidence=0.95")
    assert r2.status_code == 200, r2.text and len(r2.json()["mean"]) == u.size
    r3 = post_npz(client, npz(u=np.round(u).astype(np.int32), fs=FS), "?mc_paths=4")
    assert r3.status_code == 200, r3.text


def test_npz_answer(client):
    u = multisine(300, 5)
    y = multisine(300, 6) * 1e-4
    ref = client.post("/v1/models/boucwen/predict", json={"u": u.tolist(), "y": y.tolist(), "fs": FS,
                                                          "mc_paths": 8})
    r = post_npz(client, npz(u=u, y=y, fs=FS), "?mc_paths=8", accept=NPZ_MEDIA_TYPE)
    assert r.status_code == 200 and r.headers["content-type"] == NPZ_MEDIA_TYPE
    with np.load(io.BytesIO(r.content), allow_pickle=False) as z:
        assert z["mean"].dtype == np.float64 and z["mean"].shape == (300,)
        np.testing.assert_array_equal(z["mean"], np.array(ref.json()["mean"]))
        np.testing.assert_array_equal(z["std"], np.array(ref.json()["std"]))
        assert float(z["fit"]) == pytest.approx(ref.json()["fit"])
        meta = json_loads_npz_meta(z["json"])
    assert meta["out_of_range"] == ref.json()["out_of_range"]
    # a JSON body can ask for an NPZ answer too, and a problem stays JSON
    r = client.post("/v1/models/boucwen/predict", json={"u": u.tolist(), "fs": FS, "mc_paths": 8},
                    headers={"accept": NPZ_MEDIA_TYPE})
    assert r.headers["content-type"] == NPZ_MEDIA_TYPE
    bad = client.post("/v1/models/boucwen/predict", json={"u": [], "fs": FS}, headers={"accept": NPZ_MEDIA_TYPE})
    assert bad.status_code == 422 and bad.headers["content-type"] == PROBLEM


def test_npz_novelty_and_loops(client):
    u = multisine(384, 11)
    y = multisine(384, 12) * 1e-4
    r = post_npz(client, npz(u=u, y=y, fs=FS), "?mc_paths=8", op="novelty")
    assert r.status_code == 200, r.text and "score" in r.json()
    r = post_npz(client, npz(u=u, fs=FS), "?mc_paths=8", op="loops")
    assert r.status_code == 200, r.text


def zip_bomb(n_bytes: int) -> bytes:
    """An archive whose one member inflates to ``n_bytes`` of zeros (a valid .npy header)."""
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False,
                                                  "shape": ((n_bytes - 128) // 8,)})
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        with zf.open("u.npy", "w", force_zip64=True) as fh:
            fh.write(header.getvalue())
            chunk = b"\0" * (1 << 20)
            left = (n_bytes - 128) // 8 * 8
            while left > 0:
                fh.write(chunk[:min(left, len(chunk))])
                left -= len(chunk)
    return buf.getvalue()


def test_npz_zip_bomb_is_413_before_inflating(client):
    body = zip_bomb(64 << 20)  # 64 MiB of zeros, a few tens of kB on the wire
    assert len(body) < 200_000
    r = post_npz(client, body)
    assert r.status_code == 413 and r.headers["content-type"] == PROBLEM
    p = r.json()
    assert p["field"] == "u" and p["limit"] == 32 * 1024 * 1024 and "decompresses" in p["detail"]


def test_npz_lying_header_and_hostile_members(client):
    # the .npy header claims far more samples than the member holds: refused before any allocation
    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, {"descr": "<f8", "fortran_order": False, "shape": (10**11,)})
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("u.npy", head.getvalue() + b"\0" * 64)
    r = post_npz(client, buf.getvalue(), f"?fs={FS}")
    assert r.status_code == 413 and r.json()["field"] == "u", r.text
    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, {"descr": "<f8", "fortran_order": False, "shape": (1000,)})
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("u.npy", head.getvalue() + b"\0" * 64)
    r = post_npz(client, buf.getvalue(), f"?fs={FS}")
    assert r.status_code == 422 and r.json()["field"] == "u" and "corrupt" in r.json()["detail"], r.text
    cases = [
        (npz(u=np.array(["a", "b"]), fs=FS), "u", "dtype"),
        (npz(u=np.ones(4, dtype=complex), fs=FS), "u", "dtype"),
        (npz(u=np.ones((4, 2)), fs=FS), "u", "1-D"),
        (npz(u=np.ones(8), y=np.ones(8, dtype=np.bool_), fs=FS), "y", "dtype"),
        (npz(u=np.ones(8), fs=np.ones(3)), "fs", "scalar"),
        (npz(u=np.ones(8), fs=FS, evil=np.ones(2)), "evil", "unexpected"),
        (npz(u=np.ones(8), y=np.ones(5), fs=FS), None, None),  # length mismatch: the schema's own check
        (npz(u=np.array([1.0, np.inf]), fs=FS), "u", None),  # a NaN is a gap (null); an infinity is refused
    ]
    for body, field, needle in cases:
        r = post_npz(client, body, "?mc_paths=4")
        assert r.status_code == 422 and r.headers["content-type"] == PROBLEM, (field, r.status_code, r.text)
        if field:
            assert r.json()["field"].split(".")[0] == field, r.json()
        if needle:
            assert needle in r.json()["detail"], r.json()
    # an object array is refused without unpickling it
    obj = io.BytesIO()
    np.save(obj, np.array([{"x": 1}], dtype=object), allow_pickle=True)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("u.npy", obj.getvalue())
    r = post_npz(client, buf.getvalue(), f"?fs={FS}")
    assert r.status_code == 422 and r.json()["field"] == "u" and "dtype" in r.json()["detail"]


def test_npz_malformed_archive_and_query(client):
    r = post_npz(client, b"this is not a zip archive")
    assert r.status_code == 400 and r.json()["field"] == "body" and "zip" in r.json()["detail"]
    good = npz(u=np.ones(16), fs=FS)
    truncated = good[: len(good) // 2]
    r = post_npz(client, truncated)
    assert r.status_code in (400, 422) and r.headers["content-type"] == PROBLEM
    r = post_npz(client, good, "?mc_paths=lots")
    assert r.status_code == 422 and r.json()["field"] == "mc_paths"
    r = post_npz(client, good, "?colour=red")
    assert r.status_code == 422 and r.json()["field"] == "colour"
    r = post_npz(client, good, f"?fs={FS}")
    assert r.status_code == 422 and r.json()["field"] == "fs" and "both" in r.json()["detail"]
    r = post_npz(client, npz(u=np.ones(16)))
    assert r.status_code == 422 and r.json()["field"] == "fs"


def test_npz_sample_limit(registry):
    c = TestClient(create_app(registry, Settings(workers=1, queue_size=2, max_samples=100)),
                   raise_server_exceptions=False)
    r = post_npz(c, npz(u=np.ones(101), fs=FS))
    assert r.status_code == 413 and r.json()["field"] == "u" and r.json()["limit"] == 100


def test_etag_and_304_on_version_metadata_and_report(client):
    for path, cc in (("/v1/models/boucwen/versions/2", "no-cache"),
                     ("/v1/models/boucwen/versions/2/report", "max-age=31536000, immutable")):
        r = client.get(path)
        assert r.status_code == 200, r.text
        etag = r.headers["etag"]
        assert etag.startswith('W/"') and r.headers["cache-control"] == cc
        again = client.get(path, headers={"if-none-match": etag})
        assert again.status_code == 304 and again.content == b"" and again.headers["etag"] == etag
        assert client.get(path, headers={"if-none-match": 'W/"other", ' + etag}).status_code == 304
        assert client.get(path, headers={"if-none-match": '"other"'}).status_code == 200
        zipped = client.get(path, headers={"accept-encoding": "gzip"})
        assert zipped.headers["etag"] == etag  # weak: the same answer, encoded or not
    v1 = client.get("/v1/models/boucwen/versions/1")
    assert v1.headers["etag"] != client.get("/v1/models/boucwen/versions/2").headers["etag"]


def test_etag_changes_when_the_metadata_does(tmp_path):
    root = copy_registry(tmp_path / "reg")
    c = TestClient(create_app(root, Settings(workers=1, queue_size=2)), raise_server_exceptions=False)
    etag = c.get("/v1/models/boucwen/versions/1").headers["etag"]
    from gpnarx.storage.bundle import save_bundle

    save_bundle(built_registry().model, root, "boucwen", "3", fs=FS, units={"u": "N", "y": "m"})
    assert c.post("/v1/admin/reload").status_code == 200
    r = c.get("/v1/models/boucwen/versions/1", headers={"if-none-match": etag})
    assert r.status_code == 200 and "3" in r.json()["versions"] and r.headers["etag"] != etag


def test_private_cache_behind_an_api_key(registry):
    c = TestClient(create_app(registry, Settings(workers=1, queue_size=2, api_key="k")),
                   raise_server_exceptions=False)
    r = c.get("/v1/models/boucwen/versions/2/report", headers={"x-api-key": "k"})
    assert r.status_code == 200 and r.headers["cache-control"].startswith("private, ")


def test_openapi_documents_the_wire_formats(client):
    doc = client.get("/openapi.json").json()
    op = doc["paths"]["/v1/models/{name}/predict"]["post"]
    # the NPZ body under the generic binary type, which client generators understand (x-npz is the same body)
    assert set(op["requestBody"]["content"]) == {"application/json", "application/octet-stream"}
    assert NPZ_MEDIA_TYPE in op["requestBody"]["content"]["application/octet-stream"]["schema"]["description"]
    assert NPZ_MEDIA_TYPE in op["responses"]["200"]["content"]
    assert {p["name"] for p in op["parameters"] if p["in"] == "query"} >= {"fs", "mc_paths", "seed"}
    for path in ("/v1/models/{name}/versions/{version}", "/v1/models/{name}/versions/{version}/report"):
        get = doc["paths"][path]["get"]
        assert "304" in get["responses"] and "ETag" in get["responses"]["200"]["headers"]
    # gzip is negotiated per request, not per route: the document's description says when it applies
    from gpnarx.service.wire import GZIP_MIN_BYTES

    assert f"{GZIP_MIN_BYTES} bytes or more is gzip-compressed" in doc["info"]["description"]
    assert "Accept-Encoding: gzip" in doc["info"]["description"]


def test_npz_body_with_stream_query_fields(client):
    u = multisine(300, 9)
    r = post_npz(client, npz(u=u, fs=FS), "?method=linear&return_state=true", accept=NPZ_MEDIA_TYPE)
    assert r.status_code == 200, r.text
    with np.load(io.BytesIO(r.content), allow_pickle=False) as z:
        token = str(z["state"].item())
    assert token
    r2 = post_npz(client, npz(u=u, fs=FS), f"?method=linear&state={token}")
    assert r2.status_code == 200, r2.text
    assert r2.json()["start"] == "state"


def test_docs_wire_table_is_the_render_of_its_stored_run():
    """docs/api.md's table of one 64 s predict answer as JSON, gzip JSON and NPZ is the render of the stored run
    docs/runs/bench/wire.txt of bench/bench_wire.py (``gpnarx.training.pages.wire``; re-render:
    ``python bench/bench_wire.py --render docs/api.md``)."""
    from gpnarx.training.pages import wire

    root = Path(__file__).resolve().parents[1]
    about, command, kv = wire.last_result(root / "docs" / "runs" / "bench" / "wire.txt")
    assert int(kv["samples"]) == 65536 and "--seconds 64" in command  # the 64 s record at 1024 Hz
    assert int(kv["json_bytes"]) > int(kv["npz_bytes"]) > 0 and int(kv["json_bytes"]) > int(kv["gzip_bytes"]) > 0
    page = (root / "docs" / "api.md").read_text()
    block = page[page.index(wire.BEGIN):page.index(wire.END) + len(wire.END)]
    assert block == wire.render(about, command, kv), "docs/api.md's wire table differs from its stored run's render"


def _member_data_offset(raw: bytes, name: str) -> int:
    """Offset of a member's compressed data in a zip archive (after its local header)."""
    info = zipfile.ZipFile(io.BytesIO(raw)).getinfo(name)
    n, extra = int.from_bytes(raw[info.header_offset + 26: info.header_offset + 28], "little"), \
        int.from_bytes(raw[info.header_offset + 28: info.header_offset + 30], "little")
    return info.header_offset + 30 + n + extra


def _lzma_npz(u: np.ndarray) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_LZMA) as zf:
        arr = io.BytesIO()
        np.save(arr, u)
        zf.writestr("u.npy", arr.getvalue())
    return buf.getvalue()


def test_npz_damaged_streams_and_headers_are_a_422_on_the_array(client):
    """A damaged deflate stream, a damaged LZMA stream and a .npy header numpy cannot tokenize: each a 422
    naming the array, never a 500."""
    u = np.random.default_rng(0).normal(size=2000)
    deflate = bytearray(npz(u=u, fs=FS))
    deflate[_member_data_offset(bytes(deflate), "u.npy")] = 0x07  # an invalid deflate block type
    lz = bytearray(_lzma_npz(np.random.default_rng(0).normal(size=20000)))
    off = _member_data_offset(bytes(lz), "u.npy")
    for k in range(off + 200, off + 400):
        lz[k] ^= 0x5A
    head = b"{'descr': '<f8"  # an unclosed brace
    head += b" " * ((64 - (10 + len(head) + 1) % 64) % 64) + b"\n"
    untokenizable = io.BytesIO()
    with zipfile.ZipFile(untokenizable, "w") as zf:
        zf.writestr("u.npy", b"\x93NUMPY\x01\x00" + len(head).to_bytes(2, "little") + head + b"\0" * 32)
    for body, query in ((bytes(deflate), ""), (bytes(lz), f"?fs={FS}"), (untokenizable.getvalue(), f"?fs={FS}")):
        r = post_npz(client, body, query)
        assert r.status_code == 422 and r.headers["content-type"] == PROBLEM, r.text
        assert r.json()["field"] == "u", r.json()


@pytest.mark.parametrize("kind", ["deflate", "lzma", "stored"])
def test_npz_reader_refuses_any_damaged_byte_with_a_problem(kind):
    """Every single-byte change of a valid archive (a sample of them) gives an answer or a 4xx ProblemError:
    no other exception leaves the reader."""
    from gpnarx.service.problems import ProblemError
    from gpnarx.service.wire import read_npz_body

    u = np.random.default_rng(1).normal(size=300)
    if kind == "lzma":
        raw = _lzma_npz(u)
    else:
        buf = io.BytesIO()
        (np.savez_compressed if kind == "deflate" else np.savez)(buf, u=u, fs=np.float64(FS))
        raw = buf.getvalue()
    rng = np.random.default_rng(2)
    problems = 0
    for pos, val in zip(rng.integers(0, len(raw), 600), rng.integers(0, 256, 600)):
        bad = bytearray(raw)
        bad[pos] = val
        try:
            read_npz_body(bytes(bad), 1 << 20, 10_000)
        except ProblemError as exc:
            assert 400 <= exc.status < 500, (pos, val, exc.status, str(exc))
            problems += 1
    assert problems > 0


def test_gzip_request_bodies_are_decoded_and_bounded(registry):
    """A gzip-encoded body (Content-Encoding: gzip) gets the plain body's answer on a record route and in a batch;
    its decoded size is under the body cap (413, without inflating the rest); a body that is not gzip, ends early
    or has bytes after its end is a 400, and another encoding a 415, each naming content-encoding."""
    import gzip
    import json

    cap = 1 << 20
    c = TestClient(create_app(registry, Settings(workers=1, queue_size=4, max_body_bytes=cap)),
                   raise_server_exceptions=False)
    body = {"u": multisine(256, 3).tolist(), "fs": FS, "method": "linear"}
    raw = json.dumps(body).encode()
    gz = {"content-type": "application/json", "content-encoding": "gzip"}
    plain = c.post("/v1/models/boucwen/predict", json=body)
    r = c.post("/v1/models/boucwen/predict", content=gzip.compress(raw), headers=gz)
    assert r.status_code == 200 and r.json()["mean"] == plain.json()["mean"], r.text[:300]
    batch = json.dumps({"requests": [{"model": "boucwen", **body}]}).encode()
    r = c.post("/v1/batch", content=gzip.compress(batch), headers=gz)
    assert r.status_code == 200 and r.json()["results"][0]["mean"] == plain.json()["mean"], r.text[:300]
    bomb = gzip.compress(b" " * (64 * cap))  # 64 MiB of spaces, about 65 kB on the wire
    r = c.post("/v1/models/boucwen/predict", content=bomb, headers=gz)
    assert r.status_code == 413 and r.json()["field"] == "body" and r.json()["limit"] == cap, r.text[:300]
    half = len(raw) // 2  # two gzip members one after the other are one body (RFC 1952)
    r = c.post("/v1/models/boucwen/predict", content=gzip.compress(raw[:half]) + gzip.compress(raw[half:]), headers=gz)
    assert r.status_code == 200 and r.json()["mean"] == plain.json()["mean"], r.text[:300]
    for bad in (raw, gzip.compress(raw)[:-12], gzip.compress(raw) + b"junk"):
        r = c.post("/v1/models/boucwen/predict", content=bad, headers=gz)
        assert r.status_code == 400 and r.headers["content-type"] == PROBLEM, r.text[:300]
        assert r.json()["field"] == "content-encoding" and "gzip" in r.json()["detail"]
    r = c.post("/v1/models/boucwen/predict", content=raw, headers={**gz, "content-encoding": "br"})
    assert r.status_code == 415 and r.json()["field"] == "content-encoding" and "gzip" in r.json()["accepted"]
    r = c.post("/v1/models/boucwen/predict", content=raw,
               headers={"content-type": "application/json", "content-encoding": "identity"})
    assert r.status_code == 200


def test_accept_prefers_json_when_it_ranks_json_higher(client):
    from gpnarx.service.wire import wants_npz

    assert wants_npz("application/x-npz") and wants_npz("application/x-npz, */*")
    assert wants_npz("application/json, application/x-npz")  # a tie goes to NPZ, as before
    assert not wants_npz("application/json;q=1, application/x-npz;q=0.5")
    assert not wants_npz("application/x-npz;q=0") and not wants_npz("*/*") and not wants_npz(None)
    body = {"u": multisine(64, 3).tolist(), "fs": FS, "method": "linear"}
    r = client.post("/v1/models/boucwen/predict", json=body,
                    headers={"accept": "application/json;q=1, application/x-npz;q=0.5"})
    assert r.status_code == 200 and r.headers["content-type"].startswith("application/json")


def test_head_on_get_routes_answers_the_headers_without_a_body(client):
    for path in ("/health/live", "/health/ready", "/metrics", "/v1/models", "/v1/models/boucwen"):
        get, head = client.get(path), client.head(path)
        assert head.status_code == get.status_code == 200, (path, head.status_code)
        assert head.content == b"" and head.headers["content-type"] == get.headers["content-type"], path
    assert client.head("/v1/models/nosuchmodel").status_code == 404
