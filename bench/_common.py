"""Shared set-up for the benchmarks: the Bouc-Wen protocol, the baselines, timing helpers.

Every script under ``bench/`` measures the product and a baseline in the same run and prints one
line ``RESULT key=value ...`` with the product's figure, the baseline's (``baseline=``, described by
``baseline_what=``) and ``ratio=``. ``ratio=`` compares EQUAL WORK: the same model size (N or M),
precision, BLAS thread count and process tuning on both sides, repetitions interleaved (A, B, A, B,
...) so load from other processes hits both, and the median of the per-repetition ratios. A
comparison with what a user would otherwise run (scikit-learn exact at the protocol's size, library
defaults) is a separate field, ``user_ratio...=``, labelled by ``user_baseline=``.

Bouc-Wen protocol (section 3 of the paper; docs/results-bouc-wen.md): training records are the 10 N and 80 N
sweeps with Gaussian output noise of variance 0.1 * mean(y10^2) added to both; ny=20, nu=17
(D=37); the 50 N sweep is the free-run record. Regressors are standardised per column and the
GP training points are a stride selection of the stacked rows (4064 rows in all).
"""
from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
import warnings
from functools import lru_cache
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from gpnarx.model.gp import ExactPosterior  # noqa: E402
from gpnarx.model.kernels import make_kernel  # noqa: E402
from gpnarx.model.ml2 import fit_ml2  # noqa: E402
from gpnarx.model.regressors import stack_regressors  # noqa: E402
from gpnarx.model.scaling import Standardizer  # noqa: E402
from gpnarx.model.selection import select_rows  # noqa: E402

NY, NU = 20, 17
D = NY + NU
NOISE_SEED = 1234
# ML-II (eq. 13, one start) on a 500-point stride subset of this protocol: Matern var, lengthscale,
# cubic var, scale, bias, noise var (log). Used by --quick runs, where ML-II itself is not measured.
THETA_REF = np.log([0.9916, 35.71, 0.05503, 2.794e-4, 12.13, 0.01076])


_LIMITS = []


def parse_args(doc: str | None = None, extra=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small sizes (whole script < 30 s), for the smoke test")
    ap.add_argument("--threads", type=int, default=None,
                    help="BLAS threads for both product and baseline (default: the library default). On a "
                         "machine oversubscribed by other processes, multi-threaded OpenBLAS pays a scheduler "
                         "wake-up (ms) per call, which dominates small products; --threads 1 avoids it")
    if extra is not None:
        extra(ap)
    args = ap.parse_args()
    if args.threads is not None:
        from threadpoolctl import threadpool_limits

        _LIMITS.append(threadpool_limits(limits=int(args.threads), user_api="blas"))
    return args


def blas_threads() -> int:
    """BLAS threads in use (numpy's OpenBLAS)."""
    try:
        from threadpoolctl import threadpool_info

        info = [i for i in threadpool_info() if i.get("user_api") == "blas"]
        return int(info[0]["num_threads"]) if info else -1
    except Exception:  # pragma: no cover - threadpoolctl missing
        return -1


@lru_cache(maxsize=None)
def record(amplitude: float):
    from gpnarx.training.config import simulate_record

    return simulate_record({"system": "bouc-wen", "excitation": "sweep", "amplitude": float(amplitude)})


@lru_cache(maxsize=None)
def protocol():
    """Training pairs [(u10, y10 + noise), (u80, y80 + noise)], the noise variance, the 50 N record."""
    r10, r80 = record(10.0), record(80.0)
    nv = 0.1 * float(np.mean(r10.y ** 2))
    rng = np.random.default_rng(NOISE_SEED)
    pairs = [(r10.u, r10.y + rng.normal(0.0, math.sqrt(nv), r10.y.size)),
             (r80.u, r80.y + rng.normal(0.0, math.sqrt(nv), r80.y.size))]
    return pairs, nv, record(50.0)


@lru_cache(maxsize=None)
def _stacked():
    pairs, _, _ = protocol()
    X, Y, idx = stack_regressors(pairs, NY, NU)
    xsc = Standardizer().fit(X)
    ysc = Standardizer().fit(Y[:, None])
    Xs = xsc.transform(X)
    Ys = (Y - ysc.mean_[0]) / ysc.scale_[0]
    return Xs, Ys, idx, xsc, ysc


def training_set(n: int):
    """Standardised (X, y) with n stride-selected rows, and the x/y standardisers."""
    Xs, Ys, idx, xsc, ysc = _stacked()
    rows = select_rows(Ys, idx, n, "stride", 0)
    return np.ascontiguousarray(Xs[rows]), Ys[rows].copy(), xsc, ysc


def n_rows() -> int:
    return _stacked()[0].shape[0]


def ml2_theta(n_fit: int) -> tuple[np.ndarray, float]:
    """ML-II hyperparameters (eq. 13, one start) on an n_fit-point stride subset; (theta, seconds)."""
    X, y, _, _ = training_set(n_fit)
    k = make_kernel("matern32+cubic")
    t0 = time.perf_counter()
    res = fit_ml2(k, X, y, n_restarts=0, seed=0)
    return res.theta, time.perf_counter() - t0


def hyperparameters(quick: bool, n_fit: int = 500) -> tuple[np.ndarray, float, str]:
    """(theta, seconds, description): ML-II on n_fit stride points, or THETA_REF when quick."""
    if quick:
        return THETA_REF.copy(), 0.0, "fixed THETA_REF (quick)"
    theta, s = ml2_theta(n_fit)
    return theta, s, f"ML-II on {n_fit} pts, {s:.1f} s"


def env_note() -> str:
    return f"load avg {load():.1f}, BLAS threads {blas_threads()}"


def load() -> float:
    """1-minute load average (other processes share the 2 cores; both sides see the same load)."""
    import os

    return float(os.getloadavg()[0])


def exact_posterior(theta: np.ndarray, X: np.ndarray, y: np.ndarray) -> ExactPosterior:
    k = make_kernel("matern32+cubic")
    k.set_theta(theta[:-1])
    return ExactPosterior.fit(k, float(np.exp(theta[-1])), X, y)


# --- the scikit-learn baseline ---------------------------------------------------------------------
def sk_kernel(theta: np.ndarray, fixed: bool = True, white: bool = False):
    """scikit-learn kernel equal to eq. (12) with our log-parameters theta.

    var_p (s x.x' + b)^3 = (var_p s^3) (x.x' + b/s)^3, so the cubic part is
    ConstantKernel(var_p s^3) * DotProduct(sigma_0=sqrt(b/s)) ** 3.
    fixed=True freezes every hyperparameter (reproducing our posterior); fixed=False gives wide
    bounds for sklearn's own optimiser (and white=True adds a WhiteKernel for the noise).
    """
    from sklearn.gaussian_process.kernels import ConstantKernel, DotProduct, Matern, WhiteKernel

    var_m, ls, var_p, s, b = np.exp(np.asarray(theta[:5], float))
    wide = (1e-8, 1e8)
    cb = "fixed" if fixed else wide
    k = (ConstantKernel(var_m, constant_value_bounds=cb)
         * Matern(length_scale=ls, nu=1.5, length_scale_bounds="fixed" if fixed else (1e-5, 1e5))
         + ConstantKernel(var_p * s ** 3, constant_value_bounds=cb)
         * DotProduct(sigma_0=math.sqrt(b / s), sigma_0_bounds="fixed" if fixed else (1e-6, 1e6)) ** 3)
    if white:
        k = k + WhiteKernel(float(np.exp(theta[-1])), noise_level_bounds="fixed" if fixed else (1e-8, 10.0))
    return k


def sk_gpr(theta: np.ndarray, X: np.ndarray, y: np.ndarray):
    """GaussianProcessRegressor reproducing our exact posterior (same kernel, alpha = noise, no optimiser)."""
    from sklearn.gaussian_process import GaussianProcessRegressor

    gpr = GaussianProcessRegressor(sk_kernel(theta), alpha=float(np.exp(theta[-1])), optimizer=None,
                                   normalize_y=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gpr.fit(X, y)
    return gpr


def lagged_inputs(u: np.ndarray, nu: int = NU) -> np.ndarray:
    """(n, nu) rows [u_i, ..., u_{i-nu+1}], zeros before the record."""
    upad = np.concatenate([np.zeros(nu - 1), u])
    return np.stack([upad[nu - 1 - j: nu - 1 - j + u.size] for j in range(nu)], axis=1)


def mc_freerun(predict, noise_var, xsc, ysc, u, y0, n_paths, seed=0, keep_X=(), confidence=0.99, ny=NY, nu=NU):
    """The per-step Monte Carlo loop a user would write around a predictor ``predict(Xs) -> (mu, std)``.

    Starts from the first ny outputs y0 (like ``simulate_mc(..., y0=y0)``); each step builds the
    (n_paths, ny + nu) regressor block, standardises it, calls ``predict``, samples
    y ~ N(mu, std^2 + noise) per path and feeds it back. Returns (mean, lower, upper, seconds,
    path_steps, {step: standardised X block} for the steps in keep_X).
    """
    t0 = time.perf_counter()
    P = int(n_paths)
    n = u.size
    rng = np.random.default_rng(seed)
    Ulag = lagged_inputs(u, nu)
    ylag = np.tile(np.asarray(y0, float)[:ny][::-1], (P, 1))
    ym, ys = float(ysc.mean_[0]), float(ysc.scale_[0])
    q = (1.0 - confidence) / 2.0
    mean, lower, upper = np.zeros(n), np.zeros(n), np.zeros(n)
    mean[:ny] = lower[:ny] = upper[:ny] = np.asarray(y0, float)[:ny]
    kept = {}
    for i in range(ny, n):
        Xraw = np.hstack([ylag, np.tile(Ulag[i], (P, 1))])
        Xs = xsc.transform(Xraw)
        if i in keep_X:
            kept[i] = Xs.copy()
        mu, sd = predict(Xs)
        ysamp = (mu + np.sqrt(sd ** 2 + noise_var) * rng.standard_normal(P)) * ys + ym
        mean[i] = mu.mean() * ys + ym
        lower[i], upper[i] = np.quantile(ysamp, [q, 1.0 - q])
        ylag = np.hstack([ysamp[:, None], ylag[:, :-1]])
    return mean, lower, upper, time.perf_counter() - t0, (n - ny) * P, kept


def sklearn_freerun(gpr, noise_var, xsc, ysc, u, y0, n_paths, seed=0, keep_X=(), confidence=0.99, ny=NY, nu=NU):
    """``mc_freerun`` around scikit-learn's ``GaussianProcessRegressor.predict(X, return_std=True)``."""
    return mc_freerun(lambda Xs: gpr.predict(Xs, return_std=True), noise_var, xsc, ysc, u, y0, n_paths, seed=seed,
                      keep_X=keep_X, confidence=confidence, ny=ny, nu=nu)


class NumpySparse:
    """Plain numpy/scipy predictive of the SAME sparse posterior as the product (equal-work baseline).

    scikit-learn has no sparse GP, so the equal-work baseline of the sparse mode is the
    straightforward implementation of its equations on the product's own posterior arrays
    (inducing inputs Z, weights w, variance factor G; kernel parameters of eq. 12 including the
    constant cap of ``CubicPolynomial``): per call, K(Xs, Z) from ``scipy.spatial.distance.cdist``
    and numpy elementwise operations over all rows at once, mean K w, latent variance
    k(x, x) - rowsum((K G^T)^2). Same M, float64, same process. What it lacks, by design, is the
    product's engineering (one Gram product shared by both kernel parts, in-place kernels,
    cache-sized row blocks). ``predict(Xs)`` returns (mean, std) in standardised units.
    """

    def __init__(self, post):
        from gpnarx.model.kernels import CubicPolynomial, Matern32

        parts = getattr(post.kernel, "parts", [post.kernel])
        mat = [p for p in parts if isinstance(p, Matern32)]
        cub = [p for p in parts if isinstance(p, CubicPolynomial)]
        if len(mat) != 1 or len(cub) != 1 or len(parts) != 2 or getattr(post, "G", None) is None:
            raise ValueError("NumpySparse reproduces the eq. (12) kernel (Matern 3/2 + cubic) with a G factor")
        self.var_m, self.ls = np.exp(mat[0].theta)
        self.var_p, self.s, self.b = np.exp(cub[0].theta)
        const = float(self.var_p * self.b ** 3)
        cap = cub[0].constant_cap
        self.const_var = const if cap is None else min(const, float(cap))  # the variance's kernel
        self.const_mean = const  # the mean's kernel (eq. 8) is uncapped
        self.Z = np.asarray(post.points, float)
        self.w = np.asarray(post.w, float)
        self.GT = np.asarray(post.G, float).T

    def _poly(self, T):
        """var_p [t (3 b^2 + 3 b t + t^2)]: the cubic kernel of eq. (11) without its constant term."""
        b = self.b
        return self.var_p * T * (3.0 * b * b + 3.0 * b * T + T * T)

    def predict(self, Xs):
        from scipy.spatial.distance import cdist

        a = math.sqrt(3.0) / self.ls * cdist(Xs, self.Z)
        K = self.var_m * (1.0 + a) * np.exp(-a) + self._poly(self.s * (Xs @ self.Z.T))
        mean = K @ self.w + self.const_mean * float(np.sum(self.w))
        K += self.const_var
        diag = self.var_m + self._poly(self.s * np.sum(Xs * Xs, axis=1)) + self.const_var
        var = diag - np.sum((K @ self.GT) ** 2, axis=1)
        return mean, np.sqrt(np.maximum(var, 1e-300))


# --- timing helpers --------------------------------------------------------------------------------
def best(fn, repeat: int = 3):
    """min wall time of fn() over repeat calls (and the last return value)."""
    ts, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return min(ts), out


def dgemm_gflops(n: int = 2000, p: int = 1024, repeat: int = 3) -> float:
    """numpy's measured dgemm rate: (n x n) @ (n x p), best of repeat."""
    rng = np.random.default_rng(0)
    A = rng.standard_normal((n, n))
    B = rng.standard_normal((n, p))
    A @ B
    t, _ = best(lambda: A @ B, repeat)
    return 2.0 * n * n * p / t / 1e9


def interleave(sides: dict, reps: int) -> dict:
    """Call each side's function in turn, ``reps`` times: A, B, A, B, ... (so a change of machine load hits
    every side alike); returns {name: [return value of each repetition]}."""
    out = {k: [] for k in sides}
    for _ in range(int(reps)):
        for k, fn in sides.items():
            out[k].append(fn())
    return out


def median_ratio(num, den) -> float:
    """Median over repetitions of num[i] / den[i] (the RESULT ``ratio=`` of interleaved repetitions)."""
    return float(statistics.median([a / b for a, b in zip(num, den, strict=True)]))


def median(xs):
    return float(statistics.median(xs))


def fmt(v) -> str:
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, str):
        return v
    v = float(v)
    if v != 0 and (abs(v) >= 1e5 or abs(v) < 1e-3):
        return f"{v:.3e}"
    return f"{v:.4g}"


def bundle_fidelity(bundle) -> dict:
    """What a timed bundle keeps of the method's fidelity, for its RESULT line: its posterior (``posterior=``:
    exact or sparse) and its training report's lowest fit % over the held-out (validate) records with that
    record's name (``heldout_fit_min=``, ``heldout_fit_min_record=``), so that a speed is quoted with the
    fidelity it comes with. {} for a bundle without a training report."""
    man = getattr(bundle, "manifest", None) or {}
    recs = (man.get("training") or {}).get("records") or {}
    held = {k: float(v["fit"]) for k, v in recs.items()
            if isinstance(v, dict) and v.get("role") == "validate" and v.get("fit") is not None}
    if not held:
        return {}
    worst = min(held, key=held.get)
    return {"posterior": str(man.get("mode", "unknown")), "heldout_fit_min": held[worst],
            "heldout_fit_min_record": worst}


def result(**kv) -> None:
    """Print the contract line: RESULT key=value ..."""
    print("RESULT " + " ".join(f"{k}={fmt(v)}" for k, v in kv.items()), flush=True)


def loglog_slope(x, y) -> float:
    return float(np.polyfit(np.log(np.asarray(x, float)), np.log(np.asarray(y, float)), 1)[0])


def free_port() -> int:
    """A free loopback TCP port for a server started by a bench."""
    import socket

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def wait_ready(url: str, proc, timeout: float, log_path: Path | None = None) -> None:
    """Poll ``url``/health/ready until 200; exits with the server's log tail if ``proc`` dies."""
    import httpx

    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if proc.poll() is not None:
            tail = f":\n{log_path.read_text()[-2000:]}" if log_path is not None else ""
            raise SystemExit(f"server exited with code {proc.returncode}{tail}")
        try:
            if httpx.get(url + "/health/ready", timeout=2).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    raise SystemExit("server did not become ready")


def stop_server(proc, timeout: float = 30.0) -> None:
    """Terminate a bench's server subprocess; kill it if it does not exit within ``timeout`` s."""
    import subprocess

    proc.terminate()
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=timeout)
