"""The one JSON converter of numpy values (gpnarx.storage.jsonsafe)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from gpnarx.storage.jsonsafe import json_default, to_json_safe


def test_to_json_safe_converts_numpy_and_nulls_non_finite():
    out = to_json_safe({1: np.arange(3), "f": np.float32(0.5), "i": np.int64(7), "b": np.bool_(True),
                        "nan": float("nan"), "inf": np.array([1.0, np.inf]), "t": (np.float64(-np.inf), "s")})
    assert out == {"1": [0, 1, 2], "f": 0.5, "i": 7, "b": True, "nan": None, "inf": [1.0, None], "t": [None, "s"]}
    json.dumps(out, allow_nan=False)


def test_json_default_keeps_refusing_non_finite():
    assert json.loads(json.dumps({"a": np.arange(2.0), "n": np.int32(3)}, default=json_default)) == {
        "a": [0.0, 1.0], "n": 3}
    with pytest.raises(ValueError):
        json.dumps({"a": np.array([np.nan])}, default=json_default, allow_nan=False)
    with pytest.raises(TypeError):
        json.dumps({"a": object()}, default=json_default)
