"""The free run (section 2.2 step 3) on the JAX backend: one compiled program per block of steps.

``run_mc_jax`` and ``run_linear_jax`` are the runners of ``RUNNERS[("mc" | "linear", "jax")]`` (``runners``): a
``Predictor`` and a ``RunSpec`` in, the numpy runners' ``FreeRun`` out. They run wherever JAX computes: a GPU
with the CUDA build of jaxlib, else the CPU (so CI tests this code path).

Monte Carlo: every step evaluates eq. 8 (mean) and eq. 9 (latent variance) exactly at every path, no
local model: one kernel block K(x_paths, Z) (P x M), its product with the mean weights and, apart, one
(P x M) x (M x M) product with the posterior's variance factor (a joint product would pad a column of GPU
tiles for the weights' one column). All paths share the input lags, so the
input part of the Gram matrix is one (steps x nu) x (nu x M) product per block of steps, and each step
multiplies only the ny output lags. The steps of a block run in one ``jax.lax.scan``; the block's
samples stay on the device, where their mean, std and band quantiles are computed; only those
statistics come back (and the paths, with ``keep_paths``).

Precision: float64 by default. Eq. 9 is a difference k(x, x) - |F k|^2 in which, on the real rig,
the latent variance is about 1e-7 of k(x, x) (the noise variance sits near ML-II's floor), below
float32's resolution (about 6e-8 relative): float32 would return rounding noise as the band. GPUs
of the H100 class run float64 matrix products on tensor cores at about the float32 rate, so there
is little to gain. ``float32=True`` runs the kernel block and both products in float32 at full
precision (no TF32), for models whose latent variance is well above k(x, x) * 1e-6 (the Bouc-Wen
models); the random draws, the fed-back paths and the statistics stay float64.

Random draws: ``jax.random`` (threefry) from ``seed``, not numpy's generator, so the same seed gives
the numpy backend's bands within Monte Carlo error, not the same paths.
"""
from __future__ import annotations

import time

import numpy as np

from ..backend import require_jax
from ..kernels.jax_forms import jax_kernel, kernel_structure, kernel_theta
from ..normal import band_z
from .results import FreeRun
from .spec import LAG_CLIP, VAR_CAP, Predictor, RunSpec, check_confidence, start_index

BLOCK_ELEMENTS = 1 << 23  # samples (steps x paths) of one block kept on the device: 64 MiB in float64
MAX_BLOCK_STEPS = 4096
SCAN_UNROLL = 8  # steps per iteration of the compiled loop (fewer loop round trips on a GPU)


def _posterior_arrays(posterior):
    """(Z, w, F, mean_shift) of a ``posterior.Posterior``: its points, mean weights and variance factor
    (eq. 9 = k(x,x) - |F k|^2)."""
    F = posterior.variance_factor
    if F is None:
        raise NotImplementedError("a legacy sparse bundle (no variance factor G) runs on backend 'numpy' only")
    return posterior.points, posterior.mean_weights, F, posterior.mean_shift


def _block_steps(n_steps: int, P: int) -> int:
    cap = max(16, min(MAX_BLOCK_STEPS, BLOCK_ELEMENTS // max(P, 1)))
    return int(min(cap, 1 << max(0, int(np.ceil(np.log2(max(n_steps, 1)))))))


_CACHE: dict = {}  # compiled programs, by kernel structure and options (theta is an argument)


def _build_mc(jax, jnp, hi, jk, ny, lat, keep, dt, unroll):
    tiny = float(np.finfo(dt).tiny)

    def program(ystd, peak, Ub, eps, theta, Zy, Zu, sqZ, FT, w, a, c, shift, noise, ym, ysc, qs, n_valid):
        # input part of the Gram matrix and of |x|^2 for every step of the block at once
        Gu = jnp.matmul(Ub.astype(dt), Zu.T, precision=hi)  # (C, M)
        su = jnp.sum(Ub * Ub, axis=1)  # (C,)
        lo_hi = (-LAG_CLIP, LAG_CLIP)

        def step(y_lags, inp):
            gu, s_u, e = inp
            Y = jnp.clip(y_lags * a + c, *lo_hi)  # (P, ny) standardised output lags, clipped like numpy's
            sq = jnp.sum(Y * Y, axis=1) + s_u
            G = jnp.matmul(Y.astype(dt), Zy.T, precision=hi) + gu[None, :]
            K = jk.cross(theta.astype(dt), G, sq.astype(dt), sqZ)
            V = jnp.matmul(K, FT, precision=hi)  # F k of every path (eq. 9)
            mu = jnp.matmul(K, w, precision=hi).astype(jnp.float64) + shift  # k.w (eq. 8)
            var = jk.diag(theta, sq) - jnp.sum(V * V, axis=1).astype(jnp.float64)
            var = jnp.maximum(var, tiny)
            ysamp = mu + jnp.sqrt(var + noise) * e  # standardised output of every path
            fsamp = mu + jnp.sqrt(var) * e  # its latent draw (same eps)
            y_next = jnp.concatenate([ysamp[:, None], y_lags[:, :-1]], axis=1)
            return y_next, (ysamp, fsamp, jnp.mean(mu))

        ystd, (ys, fs, mus) = jax.lax.scan(step, ystd, (Gu, su, eps), unroll=unroll)
        yo = ys * ysc + ym  # (C, P) output units
        valid = (jnp.arange(yo.shape[0]) < n_valid)[:, None]
        peak = jnp.maximum(peak, jnp.max(jnp.where(valid, jnp.abs(yo), 0.0), axis=0))
        out = {"mean": mus * ysc + ym, "std": jnp.std(yo, axis=1), "q": jnp.quantile(yo, qs, axis=1)}
        if lat:
            out["lq"] = jnp.quantile(fs * ysc + ym, qs, axis=1)
        if keep:
            out["paths"] = yo
        return ystd, peak, out

    return jax.jit(program)


def run_mc_jax(predictor: Predictor, u: np.ndarray, spec: RunSpec) -> FreeRun:
    """Monte Carlo free run on the JAX backend (see module docstring); result as ``mc.run_mc`` (output units;
    ``progress(done_steps, total_steps)`` after each block). ``spec.local`` and ``spec.state`` are not read."""
    t_start = time.perf_counter()
    jax = require_jax()
    jnp = jax.numpy
    posterior, ny, nu = predictor.posterior, predictor.ny, predictor.nu
    n_paths, latent, keep_paths, progress = spec.n_paths, spec.latent, spec.keep_paths, spec.progress
    confidence = check_confidence(spec.confidence)
    if int(n_paths) < 1:
        raise ValueError(f"n_paths must be at least 1, got {n_paths}")
    P, n = int(n_paths), u.size
    i0, y0v = start_index(n, ny, spec.y0)
    Z, w, F, shift = _posterior_arrays(posterior)
    theta = kernel_theta(posterior.kernel)
    dt = jnp.float32 if spec.float32 else jnp.float64
    xm, xs = predictor.x_mean, predictor.x_scale
    ym, ysc = predictor.y_mean, predictor.y_scale
    Ulag = predictor.input_lags(u)
    noise = predictor.noise(spec)
    lat = bool(latent and noise > 0.0)
    q = ((1.0 - confidence) / 2.0, 1.0 - (1.0 - confidence) / 2.0)
    mean, std, lower, upper = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
    lat_lo, lat_hi = (lower.copy(), upper.copy()) if latent else (None, None)
    paths = np.zeros((n, P)) if keep_paths else None
    if i0:
        for arr in (mean, lower, upper) + ((lat_lo, lat_hi) if latent else ()):
            arr[:i0] = y0v
        if keep_paths:
            paths[:i0] = y0v[:, None]
    ylag_raw = y0v[::-1] if i0 else np.zeros(ny)
    steps = n - i0
    C = _block_steps(steps, P)
    prog = _build_cached(jax, jnp, posterior.kernel, ny, lat, keep_paths, dt)
    d = lambda x, t=jnp.float64: jnp.asarray(x, dtype=t)  # noqa: E731
    args = dict(theta=d(theta), Zy=d(Z[:, :ny], dt), Zu=d(Z[:, ny:], dt), sqZ=d(np.einsum("ij,ij->i", Z, Z), dt),
                FT=d(np.ascontiguousarray(F.T), dt), w=d(w, dt), a=d(ysc / xs[:ny]), c=d((ym - xm[:ny]) / xs[:ny]),
                shift=d(shift), noise=d(noise), ym=d(ym), ysc=d(ysc), qs=d(q))
    ystd = jnp.broadcast_to(d((ylag_raw - ym) / ysc), (P, ny))
    peak = jnp.zeros(P, dtype=jnp.float64)
    seed = spec.seed
    key = jax.random.PRNGKey(int(np.random.default_rng().integers(2**31)) if seed is None else int(seed))
    Upad = np.zeros((C * -(-steps // C), nu))
    Upad[:steps] = Ulag[i0:]
    for b, s0 in enumerate(range(0, steps, C)):
        nv = min(C, steps - s0)
        eps = jax.random.normal(jax.random.fold_in(key, b), (C, P), dtype=jnp.float64)
        ystd, peak, out = prog(ystd, peak, d(Upad[s0:s0 + C]), eps, n_valid=nv, **args)
        i, j = i0 + s0, i0 + s0 + nv
        mean[i:j] = np.asarray(out["mean"])[:nv]
        std[i:j] = np.asarray(out["std"])[:nv]
        qv = np.asarray(out["q"])
        lower[i:j], upper[i:j] = qv[0, :nv], qv[1, :nv]
        if lat:
            lq = np.asarray(out["lq"])
            lat_lo[i:j], lat_hi[i:j] = lq[0, :nv], lq[1, :nv]
        if keep_paths:
            paths[i:j] = np.asarray(out["paths"])[:nv]
        if progress is not None:
            progress(j, n)
    if latent and not lat:
        lat_lo, lat_hi = lower.copy(), upper.copy()
    pk = np.asarray(peak)
    limit = predictor.diverge_limit
    diverged = 0 if limit is None else int(np.count_nonzero(~(pk <= limit)))
    return FreeRun(mean, std, lower, upper, confidence, P, "mc", time.perf_counter() - t_start, steps * P, paths,
                   diverged, latent_lower=lat_lo, latent_upper=lat_hi, backend="jax")


def _build_cached(jax, jnp, kernel, ny, lat, keep, dt):
    key = ("mc", kernel_structure(kernel), ny, lat, keep, np.dtype(dt).name, SCAN_UNROLL)
    prog = _CACHE.get(key)
    if prog is None:
        prog = _CACHE[key] = _build_mc(jax, jnp, jax.lax.Precision.HIGHEST, jax_kernel(kernel), ny, lat, keep, dt,
                                       SCAN_UNROLL)
    return prog


def _build_linear(jax, jnp, jk, ny, L):
    hi = jax.lax.Precision.HIGHEST

    def program(m0, S0, Ulag, theta, Z, sqZ, w, FT, xm, xs, shift, noise, ym, ysc, cap):
        def mean_var(x):
            sq = jnp.sum(x * x)
            k = jk.cross(theta, jnp.matmul(Z, x, precision=hi)[None, :], sq[None], sqZ)[0]
            v = jnp.matmul(k, FT, precision=hi)
            return jnp.dot(k, w, precision=hi) + shift, jnp.maximum(jk.diag(theta, sq[None])[0] - v @ v, 1e-300)

        def step(state, ulag):
            m, S = state
            x = jnp.concatenate([jnp.clip((m - xm[:ny]) / xs[:ny], -LAG_CLIP, LAG_CLIP), ulag])
            mu, var_f = mean_var(x)
            grad = jax.grad(lambda z: mean_var(z)[0])(x)
            J = grad[:ny] / xs[:ny] * ysc  # d mu_out / d y_lag (output units)
            SJ = jnp.clip(jnp.nan_to_num(S[:, :ny] @ J, nan=cap, posinf=cap, neginf=-cap), -cap, cap)
            jsj = J @ SJ[:ny]
            var_y = (var_f + noise) * ysc * ysc + jsj
            var_y = jnp.where(jnp.isfinite(var_y), jnp.minimum(var_y, cap), cap)
            var_f_out = var_f * ysc * ysc + jsj
            y_mean = mu * ysc + ym
            sd = jnp.sqrt(jnp.maximum(var_y, 0.0))
            lsd = jnp.where(jnp.isfinite(var_f_out), jnp.sqrt(jnp.maximum(jnp.minimum(var_f_out, var_y), 0.0)), sd)
            S_new = jnp.zeros_like(S).at[1:, 1:].set(S[:-1, :-1]).at[0, 1:].set(SJ[:-1]).at[1:, 0].set(SJ[:-1])
            S_new = S_new.at[0, 0].set(var_y)
            m_new = jnp.concatenate([y_mean[None], m[:-1]])
            row = jnp.concatenate([var_y[None], SJ[:-1]])
            return (m_new, S_new), (y_mean, sd, lsd, row)

        _, outs = jax.lax.scan(step, (m0, S0), Ulag)
        return outs

    return jax.jit(program)


def run_linear_jax(predictor: Predictor, u: np.ndarray, spec: RunSpec) -> FreeRun:
    """The linearised free run on the JAX backend: ``linear_stepwise``'s recursion (first-order propagation of the
    lagged outputs' mean and covariance through the GP mean's Jacobian, here by ``jax.grad``) as one compiled
    scan, float64. Result as ``linear.run_linear`` (output units); ``spec.state`` is not read."""
    t_start = time.perf_counter()
    jax = require_jax()
    jnp = jax.numpy
    posterior, ny = predictor.posterior, predictor.ny
    confidence = check_confidence(spec.confidence)
    z = band_z(confidence)
    n = u.size
    i0, y0v = start_index(n, ny, spec.y0)
    Z, w, F, shift = _posterior_arrays(posterior)
    xm, xs = predictor.x_mean, predictor.x_scale
    ym, ysc = predictor.y_mean, predictor.y_scale
    Ulag = predictor.input_lags(u)
    L = max(ny, int(spec.cov_window or 0))
    key = ("linear", kernel_structure(posterior.kernel), ny, L)
    prog = _CACHE.get(key)
    if prog is None:
        prog = _CACHE[key] = _build_linear(jax, jnp, jax_kernel(posterior.kernel), ny, L)
    m0 = np.zeros(ny)
    if i0:
        m0[:] = y0v[::-1]
    noise = predictor.noise(spec)
    d = lambda x: jnp.asarray(x, dtype=jnp.float64)  # noqa: E731
    ym_, sd_, lsd_, rows = prog(d(m0), d(np.zeros((L, L))), d(Ulag[i0:]), d(kernel_theta(posterior.kernel)), d(Z),
                                d(np.einsum("ij,ij->i", Z, Z)), d(w), d(np.ascontiguousarray(F.T)), d(xm), d(xs),
                                d(shift), d(noise), d(ym), d(ysc), d(VAR_CAP * ysc * ysc))
    mean, std, lstd = np.zeros(n), np.zeros(n), np.zeros(n)
    if i0:
        mean[:i0] = y0v
    mean[i0:], std[i0:], lstd[i0:] = np.asarray(ym_), np.asarray(sd_), np.asarray(lsd_)
    band = None
    if L > ny:
        band = np.zeros((n, L))
        band[i0:] = np.asarray(rows)
    if spec.progress is not None:
        spec.progress(n, n)
    return FreeRun(mean, std, mean - z * std, mean + z * std, confidence, 0, "linear", time.perf_counter() - t_start,
                   n - i0, cov_band=band, latent_lower=mean - z * lstd, latent_upper=mean + z * lstd, backend="jax")
