"""Plain-JSON conversion shared by the CLI output, bundle manifests and reports."""
from __future__ import annotations

import numpy as np


def to_json_safe(obj):
    """Arrays to lists, numpy scalars to Python numbers, NaN/inf to None, recursively."""
    if isinstance(obj, dict):
        return {str(k): to_json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_json_safe(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if np.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj
