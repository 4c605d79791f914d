"""JSON encoding of numpy values: the one converter the CLI output, bundle manifests, reports and
the service share."""
from __future__ import annotations

import math

import numpy as np


def to_json_safe(obj):
    """Arrays to lists, numpy scalars to Python values, NaN/inf to None, recursively (keys to str)."""
    if isinstance(obj, dict):
        return {str(k): to_json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
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


__all__ = ["to_json_safe", "json_default"]
