"""Streams: a record sent in chunks, each call carrying the previous answer's state, gets the answers of
the record sent whole (model level, state tokens, HTTP with two replicas and a restart)."""
from __future__ import annotations

import json

import numpy as np
import pytest
from fastapi.testclient import TestClient
from test_service_support import FS, built_registry, short_record

from gpnarx.operations.stream_token import StateMismatch, StateTokenError, decode_state, encode_state
from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings

CHUNK = 150


def _chunked(model, u, method, chunk=CHUNK, **kw):
    parts, state = [], None
    for c in range(0, u.size, chunk):
        r = model.simulate(u[c:c + chunk], method=method, state=state, open_end=c + chunk < u.size, **kw)
        parts.append(r)
        state = r.state
    return {k: np.concatenate([getattr(p, k) for p in parts]) for k in ("mean", "std", "lower", "upper")}, state


@pytest.mark.parametrize("method", ["linear", "mc"])
def test_chunks_give_the_whole_record(sdof_model, sdof_data, method):
    model = sdof_model
    u = np.asarray(sdof_data["u2"], float)[:900]
    kw = {"n_paths": 64, "seed": 7} if method == "mc" else {}
    whole = model.simulate(u, method=method, **kw)
    parts, state = _chunked(model, u, method, **kw)
    for k in ("mean", "std", "lower", "upper"):
        ref = getattr(whole, k)
        if method == "mc" or k == "mean":  # the same paths and draws, the same mean recursion: identical
            assert np.array_equal(parts[k], ref), k
        else:  # eq. 9 in row blocks of another size: round-off (k(x,x) - k A k cancels)
            assert np.max(np.abs(parts[k] - ref)) <= 1e-7 * np.max(np.abs(ref)), k
    assert state.position == u.size and state.method == method


def test_discrepancy_band_differs_only_in_a_chunks_last_half_window(sdof_model, sdof_data):
    import copy

    model = copy.deepcopy(sdof_model)
    model.band_discrepancy_ = {"scale": 0.2, "window": 20}
    u = np.asarray(sdof_data["u2"], float)[:900]
    whole = model.simulate(u, method="linear")
    parts, _ = _chunked(model, u, "linear")
    near_end = np.zeros(u.size, bool)
    for c in range(CHUNK, u.size, CHUNK):
        near_end[c - 10: c] = True  # the last half-window of every chunk but the record's last
    diff = np.abs(parts["lower"] - whole.lower)
    assert np.max(diff[~near_end]) <= 1e-7 * np.max(np.abs(whole.lower))
    assert np.max(diff[near_end]) > 0  # there the chunk could not see the amplitude to come
    assert np.array_equal(parts["mean"], whole.mean)


@pytest.mark.parametrize("method", ["linear", "mc"])
def test_a_trailing_discrepancy_window_gives_the_whole_records_band_in_chunks(sdof_model, sdof_data, method):
    import copy

    model = copy.deepcopy(sdof_model)
    model.band_discrepancy_ = {"scale": 0.2, "window": 20, "window_kind": "trailing"}
    u = np.asarray(sdof_data["u2"], float)[:900]
    kw = {"n_paths": 32, "seed": 3} if method == "mc" else {}
    whole = model.simulate(u, method=method, **kw)
    parts, state = _chunked(model, u, method, **kw)
    plain = copy.deepcopy(sdof_model).simulate(u, method=method, **kw)
    assert np.min(whole.upper - plain.upper) >= 0 and np.max(whole.upper - plain.upper) > 0  # the term is on
    assert state.amp_tail.size == 19  # window - 1 means: all a trailing window sees of the past
    for k in ("mean", "std", "lower", "upper"):
        if method == "mc" or k == "mean":  # the same numbers, chunk ends included
            assert np.array_equal(parts[k], getattr(whole, k)), k
        else:  # eq. 9 in row blocks of another size: round-off
            assert np.max(np.abs(parts[k] - getattr(whole, k))) <= 1e-7 * np.max(np.abs(getattr(whole, k))), k


def test_stream_cycles_in_chunks_are_the_whole_records():
    from gpnarx.operations.cycle_stream import MAX_CYCLE_SAMPLES, advance

    fs, n = 750.0, 3000
    t = np.arange(n) / fs
    rng = np.random.default_rng(1)
    u = np.sin(2 * np.pi * 20 * t) * (1 + 0.3 * np.sin(2 * np.pi * 0.7 * t))
    m = 0.01 * np.sin(2 * np.pi * 20 * t - 0.5) * (t < 2.0) + 1e-4 * rng.normal(size=n)  # then no cycle for 2 s
    m[2600:] = 0.01 * np.sin(2 * np.pi * 9 * t[2600:])
    y = m + 1e-4 * rng.normal(size=n)
    paths = m[:, None] + 1e-4 * rng.normal(size=(n, 16))
    phys = {"mass": 2.0, "input_gain": 1.0, "output": "displacement"}
    whole, _ = advance(None, u, m, fs=fs, physics=phys, y=y, paths=paths)
    assert len(whole) > 30 and all(c["energy_lower"] <= c["energy"] <= c["energy_upper"] for c in whole)
    for chunk in (17, 150, 1000):
        got, carry = [], None
        for c in range(0, n, chunk):
            cyc, carry = advance(carry, u[c:c + chunk], m[c:c + chunk], fs=fs, physics=phys, y=y[c:c + chunk],
                                 paths=paths[c:c + chunk])
            got += cyc
            assert carry["u"].size <= MAX_CYCLE_SAMPLES + 40  # the carry stays bounded
        assert got == whole, chunk  # the same cycles, to the last bit, whatever the chunks


@pytest.mark.parametrize("method,paths", [("linear", None), ("mc", 32)])
def test_http_loops_in_chunks_report_the_whole_records_cycles_once(method, paths):
    registry = built_registry().root
    u, y = short_record(900, 12)
    a, b = _app(registry), _app(registry)
    body = {"fs": FS, "method": method, "seed": 2, "return_state": True, **({"mc_paths": paths} if paths else {})}
    whole = a.post("/v1/models/boucwen/loops", json={**body, "u": u.tolist(), "y": y.tolist()}).json()
    assert whole["cycle_basis"]["basis"] == "stream" and len(whole["cycles"]) >= 5, whole.get("cycle_basis")
    state, got = None, []
    for k, c in enumerate(range(0, u.size, 125)):  # chunks shorter than some cycles: cycles straddle them
        req = {**body, "u": u[c:c + 125].tolist(), "y": y[c:c + 125].tolist(), **({"state": state} if state else {})}
        r = (a if k % 2 == 0 else b).post("/v1/models/boucwen/loops", json=req)
        assert r.status_code == 200, r.text
        state = r.json()["state"]
        got += r.json()["cycles"]
    if method == "mc":  # the same paths: the same numbers
        assert got == whole["cycles"]
    else:  # the linearised mean to round-off (eq. 9's covariance band in row blocks of another size)
        assert len(got) == len(whole["cycles"])
        for g, w in zip(got, whole["cycles"]):
            assert g.keys() == w.keys() and all(
                g[k] == pytest.approx(w[k], rel=1e-9, abs=1e-12) for k in w if w[k] is not None), (g, w)
    assert all(c["energy_lower"] <= c["energy"] <= c["energy_upper"] and c["measured_energy"] is not None
               for c in got)


def test_a_token_round_trips_and_refuses_damage_and_other_versions(sdof_model, sdof_data):
    u = np.asarray(sdof_data["u2"], float)[:300]
    run = sdof_model.simulate(u, method="mc", n_paths=32, seed=1)
    tok = encode_state(run.state, "m", "3", key="secret")
    back = decode_state(tok, "m", "3", key="secret")
    assert np.array_equal(back.paths, run.state.paths) and back.rng == run.state.rng
    assert back.check_rng == run.state.check_rng and back.position == 300
    with pytest.raises(StateMismatch, match="m:3"):
        decode_state(tok, "m", "4", key="secret")
    with pytest.raises(StateTokenError, match="signature"):
        decode_state(tok, "m", "3", key="another")
    raw = bytearray(tok.encode())
    raw[len(raw) // 2] = ord("A") if raw[len(raw) // 2] != ord("A") else ord("B")
    with pytest.raises(StateTokenError):
        decode_state(raw.decode(), "m", "3", key="secret")
    with pytest.raises(StateTokenError):
        decode_state(tok[: len(tok) // 2], "m", "3", key="secret")


# ------------------------------------------------------------------------------------------------ HTTP

def _app(registry, key="k1"):
    return TestClient(create_app(registry, Settings(workers=1, queue_size=8, stream_key=key)),
                      raise_server_exceptions=False)


@pytest.mark.parametrize("method,paths", [("linear", None), ("mc", 32)])
def test_http_chunks_alternating_replicas_and_a_restart_equal_the_whole_record(method, paths):
    registry = built_registry().root
    u, _ = short_record(600, 11)
    a, b = _app(registry), _app(registry)
    body = {"fs": FS, "method": method, "seed": 2, **({"mc_paths": paths} if paths else {})}
    whole = a.post("/v1/models/boucwen/predict", json={**body, "u": u.tolist()}).json()
    state, means, lowers = None, [], []
    for k, c in enumerate(range(0, u.size, 200)):
        if k == 2:
            b = _app(registry)  # a replica restarted between chunks: the token alone carries the stream
        client = a if k % 2 == 0 else b
        req = {**body, "u": u[c:c + 200].tolist(), "return_state": True, **({"state": state} if state else {})}
        r = client.post("/v1/models/boucwen/predict", json=req)
        assert r.status_code == 200, r.text
        ans = r.json()
        assert ans["start"] == ("state" if state else "rest") and ans["stream_position"] == c + 200
        state = ans["state"]
        means += ans["mean"]
        lowers += ans["lower"]
    assert np.max(np.abs(np.array(means) - whole["mean"])) <= 1e-9 * np.max(np.abs(whole["mean"]))
    assert np.max(np.abs(np.array(lowers) - whole["lower"])) <= 1e-7 * np.max(np.abs(whole["lower"]))


def test_http_bad_tokens_are_problems_naming_state():
    registry = built_registry().root
    u, _ = short_record(200, 3)
    c = _app(registry)
    body = {"u": u.tolist(), "fs": FS, "method": "linear", "return_state": True}
    tok = c.post("/v1/models/boucwen/versions/1/predict", json=body).json()["state"]
    for bad, status in ((tok[:-8], 422), (tok[::-1], 422)):
        r = c.post("/v1/models/boucwen/versions/1/predict", json={**body, "state": bad})
        assert r.status_code == status and r.json()["field"] == "state", r.text
    r = c.post("/v1/models/boucwen/versions/2/predict", json={**body, "state": tok})
    assert r.status_code == 409 and r.json()["field"] == "state", r.text
    r = c.post("/v1/models/boucwen/versions/1/predict", json={**body, "state": tok, "method": "mc"})
    assert r.status_code == 422 and "linear" in r.json()["detail"], r.text
    r = _app(registry, key="k2").post("/v1/models/boucwen/versions/1/predict", json={**body, "state": tok})
    assert r.status_code == 422 and "signature" in r.json()["detail"], r.text


# ------------------------------------------------------------------------------------------------- CLI

def test_gpnarx_stream_reads_stdin_csv_and_prints_a_line_per_chunk():
    import json
    import subprocess
    import sys

    from gpnarx.operations.novelty_window import HTTP_WINDOW_SECONDS

    registry = built_registry().root
    u, y = short_record(700, 4)
    csv = "u,y\n" + "".join(f"{float(a)!r},{float(b)!r}\n" for a, b in zip(u, y))
    chunk_s = 200 / FS
    cmd = [sys.executable, "-m", "gpnarx", "stream", "--registry", str(registry), "--model", "boucwen:2",
           "--chunk", repr(chunk_s), "--method", "linear", "--window", "2", "-"]
    proc = subprocess.run(cmd, input=csv, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    lines = [json.loads(x) for x in proc.stdout.splitlines()]
    assert [x["chunk"] for x in lines] == [0, 1, 2, 3] and [x["n_samples"] for x in lines] == [200, 200, 200, 100]
    assert lines[-1]["end_s"] == pytest.approx(700 / FS)
    for x in lines:
        assert x["novelty"]["verdict"] in ("healthy", "novel", "unjudged") and 0 <= x["coverage"] <= 100
    # the window holds the last 2 x 200 samples: after the short last chunk, parts of three chunks
    assert [x["novelty_window"]["samples"] for x in lines] == [200, 400, 400, 400]
    assert [x["novelty_window"]["chunks"] for x in lines] == [1, 2, 2, 3]
    # cycles completed so far: each once, in order, across the chunks
    ends = [c["end"] for x in lines for c in x["cycles"]]
    assert len(ends) >= 3 and ends == sorted(ends) and all(c["end"] <= x["end_s"] for x in lines for c in x["cycles"])
    # the HTTP novelty stream's window is the same code: with the CLI's window as long (8 s), the same scores
    n_win = int(round(HTTP_WINDOW_SECONDS * FS / 200))
    cli = subprocess.run(cmd[:-3] + ["--window", str(n_win), "-"], input=csv, capture_output=True, text=True,
                         timeout=300)
    assert cli.returncode == 0, cli.stderr
    c = _app(registry)
    state = None
    for x, start in zip([json.loads(v) for v in cli.stdout.splitlines()], range(0, 700, 200)):
        req = {"u": u[start:start + 200].tolist(), "y": y[start:start + 200].tolist(), "fs": FS, "method": "linear",
               "return_state": True, **({"state": state} if state else {})}
        r = c.post("/v1/models/boucwen/versions/2/novelty", json=req)
        assert r.status_code == 200, r.text
        state = r.json()["state"]
        assert r.json()["score"] == pytest.approx(x["novelty"]["score"], rel=1e-9)
        got, want = r.json()["novelty_window"], x["novelty_window"]
        assert set(got) == set(want), (got, want)
        for k, v in want.items():  # numbers to round-off, the rest (verdict, reasons) equal
            assert got[k] == (pytest.approx(v, rel=1e-9) if isinstance(v, (int, float)) else v), (k, got, want)
    bad = subprocess.run(cmd, input="u,y\n1.0,2.0\n1.0,oops\n", capture_output=True, text=True, timeout=300)
    assert bad.returncode == 1 and "stdin line 3" in bad.stderr, bad.stderr


# ------------------------------------------------------------------------------------- forged tokens
def _unpack(token: str):
    import base64
    import io
    import json
    import zlib

    raw = base64.urlsafe_b64decode(token)
    with np.load(io.BytesIO(zlib.decompress(raw[35:])), allow_pickle=False) as z:
        return json.loads(bytes(z["header"]).decode()), {k: np.array(z[k]) for k in z.files if k != "header"}


def _forge(header, arrays) -> str:
    """A token rebuilt and re-signed with the public key, as any client can when no GPNARX_STREAM_KEY is set."""
    import base64
    import hashlib
    import hmac
    import io
    import json
    import zlib

    from gpnarx.operations.stream_token import MAGIC, PUBLIC_KEY

    buf = io.BytesIO()
    np.savez(buf, header=np.frombuffer(json.dumps(header).encode(), dtype=np.uint8), **arrays)
    body = zlib.compress(buf.getvalue())
    return base64.urlsafe_b64encode(MAGIC + hmac.new(PUBLIC_KEY, body, hashlib.sha256).digest() + body).decode()


def _edited(header, arrays, path: str, value):
    """(header, arrays) with one value replaced: ``path`` a header key, ``carry.OP.KEY`` or an array name."""
    h, a = json.loads(json.dumps(header)), dict(arrays)
    if path in a or path.startswith("array:"):
        a[path.removeprefix("array:")] = value
    elif path.startswith("carry."):
        _, op, key = path.split(".", 2)
        h.setdefault("carry", {}).setdefault(op, {})[key] = value
    else:
        h[path] = value
    return h, a


FORGED = {  # what a client could write into a token it rebuilds: each must be a 422 on state, never a 500
    "predict": [("position", "abc"), ("position", None), ("position", 1e30), ("position", -5), ("floor", "x"),
                ("retry_in", [1]), ("rng", [1, 2]), ("array:cov", np.ones((3, 3))), ("array:cov", np.full((10, 10),
                np.nan)), ("array:mean_tail", np.ones(3)), ("array:amp_hold", np.ones(4))],
    "predict_mc": [("rng", None), ("rng", {"bit_generator": "MT19937"}), ("check_rng", [1, 2]),
                   ("array:path_peak", np.ones(3))],
    "loops": [("carry.loops.position", None), ("carry.loops.base", [1, 2]), ("carry.loops.cuts", "x"),
              ("carry.loops.cuts", -1), ("carry.loops.cuts", [1, 2]), ("carry.loops.cuts", [[10 ** 12, 0.5, True]]),
              ("carry.loops.peak", None), ("carry.loops.last", [1, 2]), ("carry.loops.armed", "yes"),
              ("array:carry.loops.extra", np.ones(7)), ("array:carry.loops.mean", np.ones(3))],
    "novelty": [("carry.novelty.chunks", [1, 2]), ("carry.novelty.chunks", [["a", 1, []]]),
                ("array:carry.novelty.std", np.full(5, np.nan))],
}


@pytest.mark.parametrize("op", list(FORGED))
def test_http_forged_tokens_are_422_on_state_never_500(op):
    """Without GPNARX_STREAM_KEY the signature is a checksum with a public key: a client can rebuild a token with
    any values. Each is refused as a problem naming state (in a batch: that slot only)."""
    registry = built_registry().root
    c = _app(registry, key=None)
    u, y = short_record(300, 4)
    route = "predict" if op.startswith("predict") else op
    body = {"u": u.tolist(), "fs": FS, "method": "mc" if op == "predict_mc" else "linear", "return_state": True,
            **({"mc_paths": 16} if op == "predict_mc" else {}), **({"y": y.tolist()} if op == "novelty" else {})}
    if op == "novelty":
        body["start"] = "measured"
    r = c.post(f"/v1/models/boucwen/{route}", json=body)
    assert r.status_code == 200, r.text[:300]
    header, arrays = _unpack(r.json()["state"])
    nxt = {k: v for k, v in body.items() if k != "start"}
    ok = c.post(f"/v1/models/boucwen/{route}", json={**nxt, "state": _forge(header, arrays)})
    assert ok.status_code == 200, ok.text[:300]  # a faithful rebuild is a valid token
    for path, value in FORGED[op]:
        token = _forge(*_edited(header, arrays, path, value))
        r = c.post(f"/v1/models/boucwen/{route}", json={**nxt, "state": token})
        assert r.status_code == 422 and r.json()["field"] == "state", (path, value, r.status_code, r.text[:300])
    bad = _forge(*_edited(header, arrays, *FORGED[op][0]))
    good = {"model": "boucwen", "operation": route, **nxt}
    res = c.post("/v1/batch", json={"requests": [good, {**good, "state": bad}, good]}).json()["results"]
    assert "status" not in res[0] and "status" not in res[2], res
    assert res[1]["status"] == 422 and res[1]["field"] == "requests.1.state", res[1]
