"""Streams: a record sent in chunks, each call carrying the previous answer's state, gets the answers of
the record sent whole (model level, state tokens, HTTP with two replicas and a restart)."""
from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient
from test_service_support import FS, built_registry, short_record

from gpnarx.model.stream_token import StateMismatch, StateTokenError, decode_state, encode_state
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
        assert x["novelty_window"]["chunks"] == min(x["chunk"] + 1, 2)
    bad = subprocess.run(cmd, input="u,y\n1.0,2.0\n1.0,oops\n", capture_output=True, text=True, timeout=300)
    assert bad.returncode == 1 and "stdin line 3" in bad.stderr, bad.stderr
