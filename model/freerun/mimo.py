"""The free run of a model with several outputs (``model.mimo.MIMOGPNARX``): every output fed back together.

One GP per output over the shared regressor of eq. (3) for several channels (``regressors.mimo_regressors``):
x_i = [y_{i-1..i-ny} of every output, u_{i..i-nu+1} of every input], standardised. At each step every output's
GP gives its mean (eq. 8) and latent variance (eq. 9) at the same regressor; the outputs' GPs are independent
given x, so the step's own noise is diagonal across outputs.

* ``linear`` (``run_mimo_linear``, in three passes as ``freerun.linear``): first-order propagation of the joint
  mean and covariance of every output's lags. The state s = [y_{i-1} (every output), ..., y_{i-ny} (every
  output)] (output units) has mean m and covariance S (n_outputs ny square). With J (n_outputs x n_outputs ny)
  the gradient of each output's GP mean w.r.t. the lagged outputs at the mean regressor (``mean_var_grad``,
  chain rule through the standardisation):
  cov(y_i) = diag(sigma_f^2 + sigma_y^2) + J S J^T (the outputs' joint covariance at step i), cov(y_i, s) = J S,
  and the state shifts by one lag. One output: ``linear_stepwise``'s numbers (the three-pass run's to round-off).
* ``mc`` (``run_mimo_mc``): P paths advance together; at each step every path draws all outputs at once,
  y_i ~ N(mu(x), diag(sigma_f^2 + sigma_y^2)), eq. 8-9 evaluated exactly at every path (no local model yet), and
  feeds them back. One output: the numbers of ``reference.simulate_mc_reference`` (GPNARX's ``local=False``)
  at the same seed. The band: the paths' quantiles per output.

Both return a ``FreeRun`` whose mean, std, lower, upper and latent band are (n, n_outputs) [output units];
``diverged_paths`` counts the paths (linearised: the mean) that passed any output's divergence limit. Streams
(``state``), JAX and float32 are not built for several outputs.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..normal import band_z
from .results import FreeRun
from .spec import LAG_CLIP, VAR_CAP, RunSpec, check_confidence, lagged_inputs


@dataclass(frozen=True, eq=False)
class MIMOPredictor:
    """A fitted model with several outputs as its free runs read it (``MIMOGPNARX.predictor()``).

    posteriors: one GP posterior per output (``posterior.Posterior``), over the shared standardised regressor.
    x_mean, x_scale: the regressor's standardisation (``regressors.mimo_columns`` order). y_mean, y_scale:
    (n_outputs,) [output units]. diverge_limits: (n_outputs,) peak |y| beyond which a path counts as diverged
    (None: not counted).
    """

    posteriors: tuple
    x_mean: np.ndarray
    x_scale: np.ndarray
    y_mean: np.ndarray
    y_scale: np.ndarray
    ny: int
    nu: int
    n_inputs: int
    diverge_limits: np.ndarray | None = None

    @property
    def n_outputs(self) -> int:
        return len(self.posteriors)

    def noise(self, spec: RunSpec) -> np.ndarray:
        """sigma_y^2 of each output (standardised); zeros without ``include_noise``."""
        return np.array([p.noise_var if spec.include_noise else 0.0 for p in self.posteriors])

    def input_lags(self, u: np.ndarray) -> np.ndarray:
        """The standardised lagged inputs (n, n_inputs nu) of u (n, n_inputs), zeros before the record."""
        A = self.n_outputs * self.ny
        cols = np.hstack([lagged_inputs(u[:, k], self.nu) for k in range(self.n_inputs)])
        return (cols - self.x_mean[A:]) / self.x_scale[A:]


def check_inputs(u, n_inputs: int) -> np.ndarray:
    """u as (n, n_inputs) float64, finite; ValueError naming the shape otherwise."""
    try:
        a = np.asarray(u, dtype=float)
    except (TypeError, ValueError):
        raise ValueError("u must be an array of numbers") from None
    if a.ndim == 1 and n_inputs == 1:
        a = a[:, None]
    if a.ndim != 2 or a.shape[1] != n_inputs:
        raise ValueError(f"u must be (n, {n_inputs}) for this model's {n_inputs} input channel(s), got shape "
                         f"{a.shape}")
    if a.shape[0] == 0:
        raise ValueError("u is empty")
    if not np.all(np.isfinite(a)):
        raise ValueError("u holds non-finite values (NaN/inf)")
    return a


def start_of(n: int, ny: int, n_outputs: int, y0) -> tuple[int, np.ndarray]:
    """Where the free run starts and the known first outputs (ny, n_outputs) [output units] (none: from rest)."""
    if y0 is None:
        return 0, np.zeros((0, n_outputs))
    y0 = np.asarray(y0, dtype=float)
    if y0.size == 0:
        return 0, np.zeros((0, n_outputs))
    if y0.ndim == 1 and n_outputs == 1:
        y0 = y0[:, None]
    if y0.ndim != 2 or y0.shape[1] != n_outputs or y0.shape[0] < ny:
        raise ValueError(f"y0 must hold at least ny={ny} initial outputs of each of the {n_outputs} output "
                         f"channel(s), shape (ny, {n_outputs}); got {y0.shape}")
    if not np.all(np.isfinite(y0)):
        raise ValueError("y0 holds non-finite values")
    if n <= ny:
        raise ValueError(f"u must be longer than ny={ny} samples when y0 is given, got {n}")
    return ny, y0[:ny]


def _refuse_unbuilt(spec: RunSpec) -> None:
    if spec.state is not None:
        raise ValueError("state: streams of a model with several outputs are not built yet")
    if spec.backend != "numpy":
        raise ValueError(f"backend: a model with several outputs runs on numpy only, got {spec.backend!r}")


def run_mimo_linear(predictor: MIMOPredictor, u, spec: RunSpec) -> FreeRun:
    """The linearised free run of input u (n, n_inputs) [input units]; see the module docstring.

    Three passes, as the single-output run's (``freerun.linear``): 1. the mean recursion alone (eq. 8 of every
    output at the mean regressor, each fed back; it does not depend on the variances), 2. sigma_f^2 (eq. 9) and
    the mean's gradient of every output at every mean regressor in row blocks (``mean_var_grad``, BLAS-3), 3. the
    joint covariance recursion. Pass 2 and 3 go chunk by chunk (``_CHUNK`` rows), so memory stays bounded.
    """
    _refuse_unbuilt(spec)
    t_start = time.perf_counter()
    confidence = check_confidence(spec.confidence)
    z = band_z(confidence)
    ny, no = predictor.ny, predictor.n_outputs
    A = no * ny
    U = check_inputs(u, predictor.n_inputs)
    n = U.shape[0]
    i0, y0v = start_of(n, ny, no, spec.y0)
    xm, xs = predictor.x_mean, predictor.x_scale
    ym, ys = np.asarray(predictor.y_mean, float), np.asarray(predictor.y_scale, float)
    Ulag = predictor.input_lags(U)
    noise = predictor.noise(spec)
    posts = predictor.posteriors
    caps = VAR_CAP * ys * ys  # variance caps in output units
    xs_y = xs[:A]
    rows = max(n - i0, 0)
    # pass 1: hist[ny + i] = the mean outputs at step i (output units); the mean regressor of every step in X
    hist = np.zeros((n + ny, no))
    if i0:
        hist[ny: 2 * ny] = y0v
    X = np.empty((rows, xm.size))
    weights = [np.asarray(p.mean_weights, float) for p in posts]
    shifts = [float(p.mean_shift) for p in posts]
    mu = np.empty(no)
    for i in range(i0, n):
        x = X[i - i0]
        x[:A] = hist[i: i + ny][::-1].T.ravel()  # [y_{i-1..i-ny} of output 0, ..., of the last output]
        x[:A] -= xm[:A]
        x[:A] /= xs_y
        np.clip(x[:A], -LAG_CLIP, LAG_CLIP, out=x[:A])  # a diverging mean stays finite
        x[A:] = Ulag[i]
        for o, post in enumerate(posts):  # eq. 8 as ``mean_grad`` computes it
            mu[o] = float(post.cross(x[None, :])[0] @ weights[o]) + shifts[o]
        hist[ny + i] = mu * ys + ym
        if spec.progress is not None and (i % 1024 == 0):
            spec.progress(i + 1, 2 * n)
    mean = hist[ny:].copy()
    var = np.zeros((n, no))
    lvar = np.zeros((n, no))
    # state order (lag-major) from the regressor's (output-major): state a = (j - 1) no + o <- column o ny + j - 1
    perm = np.array([o * ny + j for j in range(ny) for o in range(no)])
    S = np.zeros((A, A))
    smax = float(np.max(caps))
    dg = np.diag_indices(no)
    for c0 in range(0, rows, _CHUNK):
        c1 = min(rows, c0 + _CHUNK)
        # pass 2: sigma_f^2 and d mu / d state of every output at the chunk's mean regressors
        vf = np.empty((c1 - c0, no))
        J = np.empty((c1 - c0, no, A))
        for o, post in enumerate(posts):
            _, vf[:, o], grad = post.mean_var_grad(X[c0:c1])
            J[:, o, :] = (grad[:, :A] / xs_y * ys[o])[:, perm]
        q = (vf + noise) * ys * ys
        # pass 3: the joint covariance of every output's lags, step by step
        for k in range(c1 - c0):
            Jk = J[k]
            SJ = S @ Jk.T  # (A, no): cov(state, y_i)
            if not np.all(np.isfinite(SJ)):  # a diverging run keeps a finite state covariance
                SJ = np.nan_to_num(SJ, nan=smax, posinf=smax, neginf=-smax)
            np.clip(SJ, -smax, smax, out=SJ)
            prop = Jk @ SJ  # J S J^T (no, no)
            prop += prop.T  # exactly symmetric: the product's round-off is not, and the recursion
            prop *= 0.5  # grows an asymmetric part of S (its off-diagonal blocks are one product's transposes)
            V = prop.copy()
            V[dg] += q[k]
            d = V[dg]
            d = np.where(np.isfinite(d), np.minimum(d, caps), caps)
            V[dg] = d
            i = i0 + c0 + k
            var[i] = d
            lat = vf[k] * ys * ys + np.diag(prop)
            lvar[i] = np.where(np.isfinite(lat), np.minimum(lat, d), d)
            S[no:, no:] = S[:-no, :-no]  # shift: the new first block is y_i
            S[:no, no:] = SJ[:-no].T
            S[no:, :no] = SJ[:-no]
            S[:no, :no] = V
        if spec.progress is not None:
            spec.progress(n + i0 + c1, 2 * n)
    std = np.sqrt(np.maximum(var, 0.0))
    lstd = np.sqrt(np.maximum(lvar, 0.0))
    diverged = 0
    if predictor.diverge_limits is not None:
        diverged = int(np.any(~(np.max(np.abs(mean), axis=0) <= predictor.diverge_limits)))
    return FreeRun(mean, std, mean - z * std, mean + z * std, confidence, 0, "linear",
                   time.perf_counter() - t_start, n - i0, diverged_paths=diverged,
                   latent_lower=mean - z * lstd, latent_upper=mean + z * lstd)


_CHUNK = 4096  # rows of pass 2 and 3 at a time (a multiple of mean_var_grad's block)


def run_mimo_mc(predictor: MIMOPredictor, u, spec: RunSpec) -> FreeRun:
    """The Monte Carlo free run of input u (n, n_inputs) [input units] over ``spec.n_paths`` paths, seeded by
    ``spec.seed``; see the module docstring. ``spec.keep_paths``: every path in ``FreeRun.paths``
    (n, P, n_outputs)."""
    _refuse_unbuilt(spec)
    t_start = time.perf_counter()
    confidence = check_confidence(spec.confidence)
    P = int(spec.n_paths)
    if P < 1:
        raise ValueError(f"n_paths must be at least 1, got {spec.n_paths}")
    ny, no = predictor.ny, predictor.n_outputs
    A = no * ny
    U = check_inputs(u, predictor.n_inputs)
    n = U.shape[0]
    i0, y0v = start_of(n, ny, no, spec.y0)
    xm, xs = predictor.x_mean, predictor.x_scale
    ym, ys = np.asarray(predictor.y_mean, float), np.asarray(predictor.y_scale, float)
    Ulag = predictor.input_lags(U)
    noise = predictor.noise(spec)
    rng = np.random.default_rng(spec.seed)
    qs = ((1.0 - confidence) / 2.0, 1.0 - (1.0 - confidence) / 2.0)
    mean, std = np.zeros((n, no)), np.zeros((n, no))
    lower, upper = np.zeros((n, no)), np.zeros((n, no))
    lat = spec.latent and bool(np.any(noise > 0))
    lat_lo, lat_hi = np.zeros((n, no)), np.zeros((n, no))
    if i0:
        mean[:i0] = lower[:i0] = upper[:i0] = lat_lo[:i0] = lat_hi[:i0] = y0v
    paths = np.zeros((n, P, no)) if spec.keep_paths else None
    if paths is not None and i0:
        paths[:i0] = y0v[:, None, :]
    lags = np.zeros((P, no, ny))  # every path's lagged outputs [output units], newest first per output
    if i0:
        lags[:] = y0v[::-1].T[None]
    X = np.empty((P, xm.size))
    mu, var = np.empty((P, no)), np.empty((P, no))
    block = max(1, min(256, (1 << 22) // (P * no)))
    buf = np.empty((block, P, no))
    lbuf = np.empty((block, P, no)) if lat else None
    peak = np.zeros((P, no))
    posts = predictor.posteriors
    b0 = i0
    for i in range(i0, n):
        np.subtract(lags.reshape(P, A), xm[:A], out=X[:, :A])
        X[:, :A] /= xs[:A]
        np.clip(X[:, :A], -LAG_CLIP, LAG_CLIP, out=X[:, :A])  # a diverging path cannot overflow
        X[:, A:] = Ulag[i]
        for o, post in enumerate(posts):
            mu[:, o], var[:, o] = post.predict(X)
        sd = np.sqrt(var + noise)
        ysamp = buf[i - b0]
        np.multiply(sd, rng.standard_normal((P, no)), out=ysamp)
        if lat:  # the latent draw mu + sigma_f eps with the output draw's eps
            fsamp = lbuf[i - b0]
            np.multiply(ysamp, np.sqrt(var) / sd, out=fsamp)
            fsamp += mu
        ysamp += mu
        ysamp *= ys
        ysamp += ym
        mean[i] = np.mean(mu, axis=0) * ys + ym
        if paths is not None:
            paths[i] = ysamp
        lags[:, :, 1:] = lags[:, :, :-1]
        lags[:, :, 0] = ysamp
        if i - b0 + 1 == block or i == n - 1:
            chunk = buf[: i - b0 + 1]
            np.maximum(peak, np.max(np.abs(chunk), axis=0), out=peak)
            std[b0: i + 1] = np.std(chunk, axis=1)
            lower[b0: i + 1], upper[b0: i + 1] = np.quantile(chunk, qs, axis=1)
            if lat:
                lo, hi = np.quantile(lbuf[: i - b0 + 1], qs, axis=1)
                lat_lo[b0: i + 1], lat_hi[b0: i + 1] = lo * ys + ym, hi * ys + ym
            b0 = i + 1
        if spec.progress is not None and (i % 256 == 0 or i == n - 1):
            spec.progress(i + 1, n)
    if not lat:
        lat_lo, lat_hi = lower.copy(), upper.copy()
    diverged = 0
    if predictor.diverge_limits is not None:
        diverged = int(np.count_nonzero(np.any(~(peak <= predictor.diverge_limits[None, :]), axis=1)))
    return FreeRun(mean, std, lower, upper, confidence, P, "mc", time.perf_counter() - t_start, (n - i0) * P, paths,
                   diverged, latent_lower=lat_lo, latent_upper=lat_hi)


MIMO_RUNNERS = {"linear": run_mimo_linear, "mc": run_mimo_mc}


def run_mimo(predictor: MIMOPredictor, u, spec: RunSpec) -> FreeRun:
    """The free run ``spec.method`` asks for ('mc' or 'linear')."""
    runner = MIMO_RUNNERS.get(spec.method)
    if runner is None:
        raise ValueError(f"method must be 'mc' or 'linear', got {spec.method!r}")
    return runner(predictor, u, spec)
