"""The Monte Carlo free run as one plain loop evaluating eq. 8-9 exactly at every path and step: the baseline the
tests and benchmarks compare ``mc.run_mc`` with (the product never calls it). ``simulate_linear_reference`` is the
stepwise linearised run (``linear_stepwise``), the three-pass run's baseline, under the name they call.
"""
from __future__ import annotations

import numpy as np

from .linear_stepwise import run_linear_stepwise
from .mc_paths import McPaths
from .results import FreeRun
from .spec import LAG_CLIP, Predictor, RunSpec


def simulate_mc_reference(posterior, x_scaler, y_scaler, ny: int, nu: int, u: np.ndarray, *,
                          diverge_limit: float | None = None, **options) -> FreeRun:
    """``mc.simulate_mc``'s arguments (``local`` unused) and result, every step eq. 8 and eq. 9 at every path
    (``posterior.predict``). A ``state`` continues its paths and generator; the result carries no end state."""
    spec = RunSpec(method="mc", **options)
    st = McPaths(Predictor.of(posterior, x_scaler, y_scaler, ny, nu), u, spec)
    xm, xs, Xs, n = st.xm, st.xs, st.Xs, st.n
    for i in range(st.i0, n):
        np.subtract(st.ylag_raw, xm[:ny], out=Xs[:, :ny])
        Xs[:, :ny] /= xs[:ny]
        np.clip(Xs[:, :ny], -LAG_CLIP, LAG_CLIP, out=Xs[:, :ny])  # a diverging path cannot overflow
        Xs[:, ny:] = st.Ulag[i]
        mu, var = posterior.predict(Xs, float32=spec.float32)
        st.draw(i, mu, var)
        if spec.progress is not None and (i % 256 == 0 or i == n - 1):
            spec.progress(i + 1, n)
    return st.result(diverge_limit)


def simulate_linear_reference(posterior, x_scaler, y_scaler, ny: int, nu: int, u: np.ndarray, **options) -> FreeRun:
    """``linear_stepwise.run_linear_stepwise`` with ``linear.simulate_linear``'s arguments."""
    return run_linear_stepwise(Predictor.of(posterior, x_scaler, y_scaler, ny, nu), u,
                               RunSpec(method="linear", **options))
