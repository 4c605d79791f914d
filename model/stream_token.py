"""A free run's state (``freerun_core.FreeRunState``) as an opaque, signed token a client carries between calls.

A stream is a record sent in chunks: each answer can return the state where its free run ended, and the
next call sends it back to continue that run exactly where it stopped (no server-side session: any
replica can continue any stream). The token is URL-safe base64 of::

    b"GS1" | HMAC-SHA256(key, body) (32 bytes) | body = zlib(JSON header + NPZ arrays)

The header names the model and version the state belongs to, so a token for another version is refused
(``StateMismatch``), and the arrays are read back without pickle. ``key``: a deployment's secret
(``GPNARX_STREAM_KEY``) makes the signature an authentication: a client cannot forge or edit a state;
without one, the signature is a checksum of the fixed public key ``PUBLIC_KEY`` and catches truncated or
damaged tokens only. Sizes: ``MAX_TOKEN_CHARS`` bounds a token, ``MAX_BODY_BYTES`` its decompressed body.
A linearised state holds ny means, nu - 1 inputs and an L x L covariance (L = ny, or a loops call's
cycle window): a few kB to a few hundred kB. A Monte Carlo state holds every path's ny lags: about
8 P ny bytes before compression (200 kB at P = 1024, ny = 24). An operation's ``carry`` adds its arrays
(loops: the unfinished cycle, ``model.cycle_stream``; novelty: the rolling window,
``model.novelty_window``) and JSON values (in the header).
"""
from __future__ import annotations

import base64
import binascii
import hashlib
import hmac
import io
import json
import zlib

import numpy as np

from .freerun_core import FreeRunState

MAGIC = b"GS1"
PUBLIC_KEY = b"gpnarx-stream-state"  # the checksum key when a deployment sets no secret
MAX_TOKEN_CHARS = 16 * 1024 * 1024  # characters of base64 text
MAX_BODY_BYTES = 64 * 1024 * 1024  # decompressed body
_ARRAYS = ("u_tail", "mean_tail", "cov", "paths", "path_peak", "amp_tail", "amp_hold")
_CARRY = "carry."  # array names of an operation's carry: carry.OPERATION.KEY


class StateTokenError(ValueError):
    """The token is not a state this server can read (damaged, truncated, forged or too large)."""


class StateMismatch(ValueError):
    """The token is a valid state of another model or version."""


def _key(key: bytes | str | None) -> bytes:
    if key is None or key == "" or key == b"":
        return PUBLIC_KEY
    return key.encode() if isinstance(key, str) else bytes(key)


def encode_state(state: FreeRunState, model: str, version: str, key: bytes | str | None = None) -> str:
    """The token of ``state`` for model ``model`` version ``version`` (ASCII text)."""
    header = {"model": model, "version": str(version), "method": state.method, "position": int(state.position),
              "floor": int(state.floor), "retry_in": int(state.retry_in),
              "rng": _jsonable(state.rng), "check_rng": _jsonable(state.check_rng)}
    buf = io.BytesIO()
    arrays = {k: np.asarray(getattr(state, k), dtype=np.float64) for k in _ARRAYS if getattr(state, k) is not None}
    carry_json: dict = {}
    for op, d in (state.carry or {}).items():
        carry_json[op] = {}
        for k, v in d.items():
            if isinstance(v, np.ndarray):
                arrays[f"{_CARRY}{op}.{k}"] = np.asarray(v, dtype=np.float64)
            else:
                carry_json[op][k] = v
    if carry_json:
        header["carry"] = carry_json
    np.savez(buf, header=np.frombuffer(json.dumps(header).encode(), dtype=np.uint8), **arrays)
    body = zlib.compress(buf.getvalue(), 6)
    sig = hmac.new(_key(key), body, hashlib.sha256).digest()
    return base64.urlsafe_b64encode(MAGIC + sig + body).decode("ascii")


def decode_state(token: str, model: str, version: str, key: bytes | str | None = None) -> FreeRunState:
    """The ``FreeRunState`` in ``token``; ``StateTokenError`` or ``StateMismatch`` when it cannot be used here."""
    if not isinstance(token, str) or not token:
        raise StateTokenError("state must be a non-empty token string (a previous answer's 'state')")
    if len(token) > MAX_TOKEN_CHARS:
        raise StateTokenError(f"state token of {len(token)} characters exceeds the limit of {MAX_TOKEN_CHARS}")
    try:
        raw = base64.urlsafe_b64decode(token.encode("ascii"))
    except (binascii.Error, ValueError, UnicodeEncodeError):
        raise StateTokenError("state is not a state token (not URL-safe base64)") from None
    if len(raw) < len(MAGIC) + 32 or not raw.startswith(MAGIC):
        raise StateTokenError("state is not a state token of this service (bad prefix or truncated)")
    sig, body = raw[len(MAGIC): len(MAGIC) + 32], raw[len(MAGIC) + 32:]
    if not hmac.compare_digest(sig, hmac.new(_key(key), body, hashlib.sha256).digest()):
        raise StateTokenError("state token failed its signature check (damaged, truncated, edited, or signed "
                              "with another GPNARX_STREAM_KEY)")
    try:
        d = zlib.decompressobj()
        data = d.decompress(body, MAX_BODY_BYTES)
        if d.unconsumed_tail:
            raise StateTokenError(f"state token body exceeds {MAX_BODY_BYTES} bytes decompressed")
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            header = json.loads(bytes(z["header"]).decode())
            if not isinstance(header, dict):
                raise StateTokenError("state token header is not a JSON object")
            arrays = {k: np.array(z[k], dtype=np.float64) for k in _ARRAYS if k in z.files}
            carry = {op: dict(d) for op, d in (header.get("carry") or {}).items()}
            for name in z.files:
                if name.startswith(_CARRY):
                    op, _, k = name[len(_CARRY):].partition(".")
                    carry.setdefault(op, {})[k] = np.array(z[name], dtype=np.float64)
    except StateTokenError:
        raise
    except Exception as exc:  # a signed body that does not parse: written by an incompatible version
        raise StateTokenError(f"state token body is unreadable ({type(exc).__name__})") from None
    if header.get("model") != model or header.get("version") != str(version):
        raise StateMismatch(f"state belongs to model {header.get('model')}:{header.get('version')}, this call "
                            f"uses {model}:{version}; start the stream anew (no state) or send it to that version")
    if "u_tail" not in arrays or header.get("method") not in ("linear", "mc"):
        raise StateTokenError("state token lacks its input lags or method")
    try:  # a token signed with the public key can be rebuilt by anyone: every value is checked before use
        return FreeRunState(header["method"], _integer(header, "position", 0, MAX_POSITION), arrays["u_tail"],
                            mean_tail=arrays.get("mean_tail"), cov=arrays.get("cov"), paths=arrays.get("paths"),
                            path_peak=arrays.get("path_peak"), rng=_rng_state(header.get("rng"), "rng"),
                            check_rng=_rng_state(header.get("check_rng"), "check_rng"),
                            floor=_integer(header, "floor", 0, 1 << 16, 0),
                            retry_in=_integer(header, "retry_in", -1, MAX_POSITION, 0),
                            amp_tail=arrays.get("amp_tail"), amp_hold=arrays.get("amp_hold"), carry=carry or None)
    except (TypeError, ValueError, KeyError, OverflowError) as exc:
        raise StateTokenError(f"state token holds a malformed state: {exc}"[:300]) from None


#: largest position (samples) a state may carry: 2^53, a float64's exact integers (over 2.7 million years at 1 kHz)
MAX_POSITION = 1 << 53


def _integer(header: dict, key: str, lo: int, hi: int, default=None) -> int:
    """header[key] (or ``default`` when absent) as an integer in [lo, hi]; ValueError otherwise."""
    v = header.get(key, default)
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise ValueError(f"{key} must be an integer in [{lo}, {hi}], got {str(v)[:40]}")
    return v


def _rng_state(d, key: str):
    """A bit generator's state from the header (``_from_json``), checked by loading it into a PCG64 (the
    generator ``np.random.default_rng`` makes); None stays None."""
    if d is None:
        return None
    if not isinstance(d, dict):
        raise ValueError(f"{key} must be a random generator state (a JSON object)")
    state = _from_json(d)
    np.random.PCG64().state = state  # raises on anything that is not a PCG64 state
    return state


def _jsonable(rng_state):
    """A numpy bit generator's state with its big integers as strings (JSON keeps 53 bits of a number)."""
    if rng_state is None:
        return None
    return json.loads(json.dumps(rng_state, default=str), parse_int=str)


def _from_json(d):
    """Back from ``_jsonable``: digit strings become integers again."""
    if d is None:
        return None
    if isinstance(d, dict):
        return {k: _from_json(v) for k, v in d.items()}
    if isinstance(d, str) and d.lstrip("-").isdigit():
        return int(d)
    return d
