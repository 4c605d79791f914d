"""JSON encoding of numpy values: the one converter the CLI output, bundle manifests, reports and
the service share."""
from __future__ import annotations

import json
import math

import numpy as np

try:  # fast JSON for long float arrays
    import orjson as _orjson
except ImportError:  # pragma: no cover - exercised only without orjson
    _orjson = None


def to_json_safe(obj):
    """Arrays to lists, numpy scalars to Python values, NaN/inf to None, recursively (keys to str)."""
    if isinstance(obj, dict):
        return {str(k): to_json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind in "iub" or (obj.dtype.kind == "f" and bool(np.all(np.isfinite(obj)))):
            return obj.tolist()  # nothing inside to convert
        return to_json_safe(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def json_default(o):
    """``default=`` for ``json.dump`` where non-finite numbers must stay refused (``allow_nan=False``):
    arrays to lists and numpy scalars to Python values, nothing else."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def dumps_json(obj) -> bytes:
    """Compact JSON bytes of ``obj``: numpy arrays and scalars serialised natively (orjson, in C), NaN/inf
    as null, keys as strings; what orjson refuses (e.g. a non-contiguous array) goes through
    ``to_json_safe`` first. The service's bodies and ``gpnarx ... --json`` share it."""
    if _orjson is not None:
        opt = _orjson.OPT_SERIALIZE_NUMPY | _orjson.OPT_NON_STR_KEYS
        try:
            return _orjson.dumps(obj, option=opt)
        except (TypeError, _orjson.JSONEncodeError):
            return _orjson.dumps(to_json_safe(obj), option=opt)
    return json.dumps(to_json_safe(obj), separators=(",", ":"), allow_nan=False).encode()


__all__ = ["to_json_safe", "json_default", "dumps_json"]
