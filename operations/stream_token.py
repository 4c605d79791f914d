"""A free run's state (``freerun.FreeRunState``) as an opaque, signed token a client carries between calls.

A stream is a record sent in chunks: each answer can return the state where its free run ended, and the
next call sends it back to continue that run exactly where it stopped (no server-side session: any
replica can continue any stream). The token is URL-safe base64 of::

    b"GS1" | HMAC-SHA256(key, body) (32 bytes) | body = zlib(JSON header + NPZ arrays)

The header names the model and version the state belongs to, so a token for another version is refused
(``StateMismatch``), and the arrays are read back without pickle. ``key``: a deployment's secret
(``GPNARX_STREAM_KEY``) makes the signature an authentication: a client cannot forge or edit a state;
without one, the signature is a checksum of the fixed public key ``PUBLIC_KEY`` and catches truncated or
damaged tokens only.

Sizes. A linearised state holds ny means, nu - 1 inputs and an L x L covariance (L = ny, or a loops call's
cycle window): a few kB to a few hundred kB. A Monte Carlo state holds every path's ny lags: about
8 P ny bytes before compression (200 kB at P = 1024, ny = 24). An operation's ``carry`` adds its arrays
(loops: the unfinished cycle, ``operations.cycle_stream``; novelty: the rolling window,
``operations.novelty_window``) and JSON values (in the header). ``max_state_bytes`` adds these up for a call (its
model's lags and fs, its Monte Carlo paths): the most a legitimate state of that call holds, ``max_bytes`` of
``decode_state``. A token is hostile input (without a secret key anyone can sign one), so ``decode_state``
decides every size before it inflates or allocates anything (``storage.archive_bounds``): the token's length
(``max_token_chars``), its zlib body inflated at most to that bound, the archive's member count
(``MAX_MEMBERS``), each member's declared shape and dtype (float64 arrays of at most 2 dimensions and a uint8
JSON header, together at most ``max_bytes``) and the header's nesting (``MAX_HEADER_DEPTH``). Each refusal is
a ``StateTokenError`` naming what and, for a size, the limit (``.limit``).
"""
from __future__ import annotations

import base64
import binascii
import hashlib
import hmac
import io
import json
import math
import re
import zlib

import numpy as np

from gpnarx.checks import is_int
from gpnarx.model.freerun import FreeRunState
from gpnarx.storage.archive_bounds import NPY_READ_ERRORS, ArchiveError, member, member_name, open_archive, read

from .cycle_stream import MARGIN, MAX_CYCLE_SAMPLES, STREAM_COV_WINDOW
from .novelty_window import HTTP_WINDOW_SECONDS

MAGIC = b"GS1"
PUBLIC_KEY = b"gpnarx-stream-state"  # the checksum key when a deployment sets no secret
MAX_TOKEN_CHARS = 16 * 1024 * 1024  # characters of base64 text (the request schema's bound)
MAX_BODY_BYTES = 64 * 1024 * 1024  # arrays and header of a state decoded without a call's own bound
#: most members of a token's archive: the header, the state's 7 arrays and 4 arrays of each of 2 carries
MAX_MEMBERS = 32
#: deepest nesting of a token's JSON header (a state's nests 6 deep: header, carry, novelty, chunks, chunk, flags)
MAX_HEADER_DEPTH = 16
_ARRAYS = ("u_tail", "mean_tail", "cov", "paths", "path_peak", "amp_tail", "amp_hold")
_CARRY = "carry."  # array names of an operation's carry: carry.OPERATION.KEY
_ARCHIVE_BYTES = MAX_MEMBERS * 1024  # zip entries and .npy headers around the arrays, at most
_HEADER_BYTES = 64 * 1024  # JSON header besides its carries' lists
_ENTRY_BYTES = 256  # JSON of one entry of a carry's list (a loops cut, a novelty chunk and its flags)
_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"')  # a JSON string


class StateTokenError(ValueError):
    """The token is not a state this server can read (damaged, truncated, forged or too large); ``limit``: the
    bound it exceeds, when it is one of size."""

    def __init__(self, detail: str, limit: int | None = None):
        super().__init__(detail)
        self.limit = limit


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


def max_state_bytes(ny: int, nu: int, fs: float, paths: int = 0, amp_window: int = 0) -> int:
    """The most bytes of arrays and JSON header a legitimate state of a call holds (``decode_state``'s
    ``max_bytes``): ny, nu: the model's lags; fs: its sampling frequency [Hz]; paths: the call's Monte Carlo paths
    (0 when linearised); amp_window: its band discrepancy window [samples] (0 without one). The sum, 8 bytes a
    value, of the free run's lags (nu - 1 inputs, ny means and an L x L covariance, L = max(ny,
    ``STREAM_COV_WINDOW``); paths x (ny + 1) for Monte Carlo), the discrepancy tail, a loops carry
    (``MAX_CYCLE_SAMPLES + 2 MARGIN + 2`` samples of 3 + max(paths, L) values) and a novelty carry (4 series of
    ``HTTP_WINDOW_SECONDS`` x fs samples), with the header's JSON for each carried sample."""
    lags = max(int(ny), STREAM_COV_WINDOW)
    held = MAX_CYCLE_SAMPLES + 2 * MARGIN + 2
    window = math.ceil(HTTP_WINDOW_SECONDS * float(fs))
    values = (int(nu) - 1 + int(ny) + lags * lags + int(paths) * (int(ny) + 1) + int(amp_window) + 1
              + held * (3 + max(int(paths), lags)) + 4 * window)
    return 8 * values + _HEADER_BYTES + _ENTRY_BYTES * (held + window + 2)


def _inflated_max(max_bytes: int) -> int:
    """Bytes of a token's zlib body inflated: its arrays and header, and the archive around them."""
    return max_bytes + _ARCHIVE_BYTES


def max_token_chars(max_bytes: int) -> int:
    """Characters of the longest token of a state of ``max_bytes`` (zlib's bound on what it writes for that
    many bytes, then the prefix, the signature and base64)."""
    n = _inflated_max(max_bytes)
    body = n + (n >> 12) + (n >> 14) + (n >> 25) + 13  # zlib's compressBound
    return 4 * math.ceil((len(MAGIC) + 32 + body) / 3)


def decode_state(token: str, model: str, version: str, key: bytes | str | None = None,
                 max_bytes: int = MAX_BODY_BYTES) -> FreeRunState:
    """The ``FreeRunState`` in ``token``; ``StateTokenError`` or ``StateMismatch`` when it cannot be used here.

    max_bytes: the most bytes of arrays and header the state may hold (``max_state_bytes`` of the call that
    continues it); every size is checked against it before anything is inflated or allocated (module doc)."""
    if not isinstance(token, str) or not token:
        raise StateTokenError("state must be a non-empty token string (a previous answer's 'state')")
    chars = min(MAX_TOKEN_CHARS, max_token_chars(max_bytes))
    if len(token) > chars:
        raise StateTokenError(f"state token of {len(token)} characters exceeds the limit of {chars} (the longest "
                              f"token of a state of this call)", chars)
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
    arrays = _unpack(_inflate(body, _inflated_max(max_bytes)), max_bytes)
    header = _header(arrays.pop("header"))
    try:
        carry = {op: dict(d) for op, d in (header.get("carry") or {}).items()}
        for name, a in arrays.items():
            if name.startswith(_CARRY):
                op, _, k = name[len(_CARRY):].partition(".")
                carry.setdefault(op, {})[k] = a
    except (TypeError, ValueError, AttributeError):
        raise StateTokenError("state token header holds a malformed carry") from None
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


def _inflate(body: bytes, limit: int) -> bytes:
    """The token's zlib body inflated, at most to ``limit`` bytes (a longer one is refused while inflating)."""
    d = zlib.decompressobj()
    try:
        data = d.decompress(body, limit + 1)
    except zlib.error as exc:
        raise StateTokenError(f"state token body is unreadable (zlib: {exc})"[:300]) from None
    if len(data) > limit:
        raise StateTokenError(f"state token body inflates past {limit} bytes, the limit for a state of this call",
                              limit)
    return data


def _unpack(data: bytes, max_bytes: int) -> dict:
    """The arrays of the token's archive ``data`` (``header``: the JSON header's bytes), each member's name, dtype
    and declared size checked first (module doc)."""
    try:
        zf = open_archive(data, MAX_MEMBERS)
    except ArchiveError as exc:
        raise StateTokenError(f"state token: {exc}", exc.limit) from None
    except NPY_READ_ERRORS as exc:
        raise StateTokenError(f"state token body is unreadable ({type(exc).__name__})") from None
    with zf:
        members, total = {}, 0
        for info in zf.infolist():
            name = member_name(info)
            if name != "header" and name not in _ARRAYS and not name.startswith(_CARRY):
                raise StateTokenError(f"state token holds an unknown array {name[:60]!r}")
            if name in members:
                raise StateTokenError(f"state token holds the array {name[:60]!r} twice")
            try:
                m = member(zf, info)
            except ArchiveError as exc:
                raise StateTokenError(f"state token holds a {exc}"[:300]) from None
            except NPY_READ_ERRORS as exc:
                raise StateTokenError(f"state token array {name[:60]!r} is unreadable ({type(exc).__name__})") \
                    from None
            if m is None:
                raise StateTokenError(f"state token member {name[:60]!r} is not an .npy array")
            total += m.nbytes
            if total > max_bytes:
                raise StateTokenError(f"state token array {name[:60]!r} declares {m.nbytes} bytes (shape {m.shape}, "
                                      f"dtype {m.dtype}): a state of this call holds at most {max_bytes} bytes",
                                      max_bytes)
            kind, ndim = (np.dtype(np.uint8), 1) if name == "header" else (np.dtype(np.float64), 2)
            if m.dtype != kind or len(m.shape) > ndim:
                raise StateTokenError(f"state token array {name[:60]!r} is {m.dtype} of shape {m.shape}; a state "
                                      f"holds {kind} arrays of at most {ndim} dimension(s)")
            members[name] = m
        if "header" not in members:
            raise StateTokenError("state token lacks its header")
        try:
            return {name: read(zf, m) for name, m in members.items()}
        except NPY_READ_ERRORS as exc:
            raise StateTokenError(f"state token body is unreadable ({type(exc).__name__})") from None


def _header(raw: np.ndarray) -> dict:
    """The JSON header (a dict), its nesting checked before it is parsed (``MAX_HEADER_DEPTH``)."""
    try:
        text = raw.tobytes().decode()
    except UnicodeDecodeError:
        raise StateTokenError("state token header is not UTF-8 JSON") from None
    depth = _nesting(text)
    if depth > MAX_HEADER_DEPTH:
        raise StateTokenError(f"state token header nests {depth} levels deep; a state's nests at most "
                              f"{MAX_HEADER_DEPTH}", MAX_HEADER_DEPTH)
    try:
        header = json.loads(text)
    except ValueError as exc:
        raise StateTokenError(f"state token header is not JSON ({exc})"[:300]) from None
    if not isinstance(header, dict):
        raise StateTokenError("state token header is not a JSON object")
    return header


def _nesting(text: str) -> int:
    """The deepest nesting of arrays and objects in the JSON ``text`` (brackets inside strings not counted), from
    the text itself: no recursion, whatever the depth."""
    bare = _STRING.sub("", text).encode()
    codes = np.frombuffer(bare, dtype=np.uint8)
    step = np.isin(codes, (ord("["), ord("{"))).astype(np.int64) - np.isin(codes, (ord("]"), ord("}")))
    return int(np.cumsum(step).max(initial=0))


#: largest position (samples) a state may carry: 2^53, a float64's exact integers (over 2.7 million years at 1 kHz)
MAX_POSITION = 1 << 53


def _integer(header: dict, key: str, lo: int, hi: int, default=None) -> int:
    """header[key] (or ``default`` when absent) as an integer in [lo, hi]; ValueError otherwise."""
    v = header.get(key, default)
    if not is_int(v, lo, hi):
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
