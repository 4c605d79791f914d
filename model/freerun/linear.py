"""The linearised free run on numpy (section 2.2 step 3): first-order propagation of the mean and covariance of
the lagged outputs through the GP mean's Jacobian.

State: mean m and covariance S of [y_{i-1}, ..., y_{i-L}] (output units, L = max(ny, cov_window)). With
J = d mu / d y_lags at the mean regressor (chain rule through the standardisation): var(y_i) = sigma_f^2 +
sigma_y^2 + J S J^T, cov(y_i, y_{i-k}) = (S J^T)_k, and the state shifts. The band: mean -/+ z std at the run's
confidence; the latent band leaves the reporting step's sigma_y^2 out. With cov_window = L > ny,
``FreeRun.cov_band`` holds cov(y_i, y_{i-k}) for k < L, shape (n, L) (J is zero beyond the ny lags, so mean
and std are unchanged): what a linear functional of a window of outputs (a cycle's energy, ``model.cycles``)
needs for its variance.

Three passes, the numbers of one ``mean_grad`` call per step (``linear_stepwise``) to round-off:

1. the mean recursion alone (eq. 8 at the mean regressor), which does not depend on the variances: a few numpy
   calls on (M,) vectors a step (``_MeanRecursion``);
2. sigma_f^2 (eq. 9) and J at every mean regressor in row blocks (the posterior's ``mean_var_grad``, BLAS-3
   without the GIL, ``linalg.lower_times_rows``), each chunk of pass 1's steps as soon as pass 1 has finished
   it: on ``workers`` threads while pass 1 goes on, then on the calling thread too. Same rows, same blocks: the
   same numbers, bit for bit, with any number of workers;
3. the covariance recursion, chunk by chunk in order as pass 2 finishes them, on the calling thread once pass 1
   has ended, so that it overlaps the workers' pass 2 (``_CovarianceRecursion``).

Where numba is installed (the extra ``fast``; ``GPNARX_COMPILED=0`` turns it off), pass 1 is compiled
(``linear_compiled``): the same kernel-row evaluation serves the mean, its gradient J and eq. 9's rows, so pass 2
is only the triangular products on those rows; the numbers are the numpy passes' to round-off.
``RunSpec.variance_stride`` s > 1 (opt-in): eq. 9 at every s-th step of each chunk (and its last), linearly
interpolated between (``gp.stride_rows``, ``gp.interpolate_rows``); the band's difference per real record is in
docs/numerics.md.

A posterior other than a ``posterior.Posterior`` whose kernel gives ``MeanTerms`` (e.g. an object with only
``mean_grad`` and ``noise_var``) runs stepwise (``linear_stepwise``).
"""
from __future__ import annotations

import math
import queue
import threading
import time

import numpy as np

from ..gp import interpolate_rows, stride_rows
from ..kernels import LinearisableKernel, require
from ..linalg import two_cpus
from ..normal import band_z
from ..posterior import Posterior
from .linear_compiled import CompiledMean
from .linear_stepwise import run_linear_stepwise
from .results import FreeRun, FreeRunState, check_state
from .spec import LAG_CLIP, VAR_CAP, Predictor, RunSpec, check_confidence, check_stride, next_u_tail, start_index


def run_linear(predictor: Predictor, u: np.ndarray, spec: RunSpec) -> FreeRun:
    """The linearised free run of input ``u`` (input units); see the module docstring.

    ``spec.workers``: pass 2's worker threads (None: one where this process may use two or more CPUs and the run
    has more than one chunk; 0: none). ``spec.state``: the ``FreeRun.state`` of an earlier run to continue: its
    last means, input lags and state covariance, so a record run in chunks gives the numbers of the record run
    whole (to round-off); a state with a smaller covariance window than ``cov_window`` is padded with zeros, a
    larger one cut.
    """
    posterior, ny, nu = predictor.posterior, predictor.ny, predictor.nu
    y0, state, workers, progress = spec.y0, spec.state, spec.workers, spec.progress
    fast = _MeanRecursion.build(predictor)
    if workers is not None and int(workers) < 0:
        raise ValueError(f"workers must be >= 0 (0: no worker thread), got {workers}")
    stride = check_stride(spec.variance_stride)
    if state is not None:
        check_state(state, "linear", ny, nu, y0)
        if fast is None:
            raise ValueError("state: this posterior's linearised run cannot continue a stream")
    if fast is None:
        return run_linear_stepwise(predictor, u, spec)
    t_start = time.perf_counter()
    confidence = check_confidence(spec.confidence)
    z = band_z(confidence)
    u = np.asarray(u, dtype=float)
    n = u.size
    i0, y0v = start_index(n, ny, y0)
    xm, xs = predictor.x_mean, predictor.x_scale
    ym, ys = predictor.y_mean, predictor.y_scale
    Ulag = predictor.input_lags(u, state)
    # pass 1: hist[t + ny] = mean output at time t (output units); hist[:ny] = 0 (at rest) or the state's means
    hist = np.zeros(n + ny)
    if i0:
        hist[ny: 2 * ny] = y0v
    elif state is not None:
        hist[:ny] = state.mean_tail
    # pass 2 of the steps k0 <= i - i0 < k1, once pass 1 has finished them: the mean regressors
    # (standardised, clipped as in pass 1), sigma_f^2 and the mean's gradient, in rows of X blocked from
    # i0 as ``mean_var_grad`` blocks them (so any split in multiples of the chunk gives the same numbers)
    rows = max(n - i0, 0)
    X = np.empty((rows, ny + nu))
    var_f = np.empty(rows)
    grad = np.empty((rows, ny + nu))
    win = np.lib.stride_tricks.sliding_window_view(hist, ny)[:, ::-1]  # row i: [y_{i-1}, ..., y_{i-ny}]

    def regressors(k0: int, k1: int) -> np.ndarray:
        Xb = X[k0:k1]
        np.subtract(win[i0 + k0: i0 + k1], xm[:ny], out=Xb[:, :ny])
        Xb[:, :ny] /= xs[:ny]
        np.clip(Xb[:, :ny], -LAG_CLIP, LAG_CLIP, out=Xb[:, :ny])
        Xb[:, ny:] = Ulag[i0 + k0: i0 + k1]
        return Xb

    def pass2(k0: int, k1: int) -> None:
        Xb = regressors(k0, k1)
        if stride > 1:
            _, var_f[k0:k1], grad[k0:k1] = posterior.mean_var_grad(Xb, stride=stride)
        else:
            _, var_f[k0:k1], grad[k0:k1] = posterior.mean_var_grad(Xb)

    rows_of: dict = {}  # compiled pass 1: the kernel rows of each chunk (by its first step) until pass 2 takes them

    def want_rows(c0: int, c1: int):
        keep = stride_rows(c1 - c0, stride)
        slots = np.full(c1 - c0, -1, dtype=np.int64)
        slots[keep] = np.arange(keep.size)
        return slots, np.empty((keep.size, posterior.n_points))

    def pass2_rows(k0: int, k1: int) -> None:
        # eq. 9 on the kernel rows pass 1 left (every stride-th step of the chunk and its last)
        K = rows_of.pop(k0)
        keep = stride_rows(k1 - k0, stride)
        Xk = regressors(k0, k1)[keep]
        v = posterior.kernel.diag(Xk) - posterior.reduction_rows(K)
        var_f[k0:k1] = v if stride == 1 else interpolate_rows(v, keep, k1 - k0)
        np.maximum(var_f[k0:k1], 1e-300, out=var_f[k0:k1])

    L = max(ny, int(spec.cov_window or 0))
    band = np.zeros((n, L)) if L > ny else None
    S_end = None if state is None else _resize(np.asarray(state.cov, dtype=float), L)
    noise = predictor.noise(spec)
    q = np.empty(rows)  # sigma_f^2 + sigma_y^2 in output units
    Jall = np.empty((rows, ny))  # d mu_out / d y_lag (output units)
    cov = _CovarianceRecursion(rows, ny, L, ys, band, i0, S_end)
    compiled = CompiledMean.build(fast, posterior)
    if compiled is not None:
        cov.compiled = compiled.cov_steps

    def pass3(k0: int, k1: int) -> None:
        np.add(var_f[k0:k1], noise, out=q[k0:k1])
        q[k0:k1] *= ys * ys
        if compiled is None:
            np.multiply(grad[k0:k1, :ny], ys / xs[:ny], out=Jall[k0:k1])
        cov.advance(q[k0:k1], Jall[k0:k1])

    n_workers = _linear_workers(workers, rows, _PASS1_CHUNK)
    if compiled is None:
        with _Workers(pass2, n_workers, then=pass3) as pool:
            fast.run(hist, Ulag, i0, n, ym, ys, progress, chunk=_PASS1_CHUNK,
                     on_chunk=lambda c0, c1: pool.submit(c0 - i0, c1 - i0))
    else:
        # the compiled pass 1 outruns pass 2: the caller takes queued chunks itself past two, which bounds the
        # kernel rows held at once
        with _Workers(pass2_rows, n_workers, then=pass3, queued=2) as pool:
            def chunk_done(c0, c1, K):
                rows_of[c0 - i0] = K
                pool.submit(c0 - i0, c1 - i0)

            compiled.run(hist, Ulag, i0, n, ym, ys, Jall, want_rows, progress, chunk=_PASS1_CHUNK,
                         on_chunk=chunk_done)
    mean = hist[ny:].copy()
    std = np.zeros(n)
    lstd = np.zeros(n)  # latent std: var(y_i) without the reporting step's sigma_y^2
    if n > i0:
        var_y, prop, S_end = cov.out, cov.prop, cov.state()
        std[i0:] = np.sqrt(np.maximum(var_y, 0.0))
        # latent: var(y_i) without the reporting step's sigma_y^2 (as the reference loop)
        var_lat = var_f * (ys * ys) + prop
        ok = np.isfinite(var_lat)
        lstd[i0:] = np.where(ok, np.sqrt(np.maximum(np.minimum(np.where(ok, var_lat, 0.0), var_y), 0.0)),
                             std[i0:])
    if progress is not None:
        progress(n, n)
    end = FreeRunState("linear", (0 if state is None else state.position) + n, next_u_tail(u, nu, state),
                       mean_tail=hist[n: n + ny].copy(), cov=np.zeros((L, L)) if S_end is None else S_end)
    return FreeRun(mean, std, mean - z * std, mean + z * std, confidence, 0, "linear",
                   time.perf_counter() - t_start, n - i0, cov_band=band,
                   latent_lower=mean - z * lstd, latent_upper=mean + z * lstd, state=end)


def simulate_linear(posterior, x_scaler, y_scaler, ny: int, nu: int, u: np.ndarray, **options) -> FreeRun:
    """``run_linear`` from a posterior, its scalers and lags (``Predictor.of``) with the ``RunSpec`` fields as
    keywords."""
    return run_linear(Predictor.of(posterior, x_scaler, y_scaler, ny, nu), u, RunSpec(method="linear", **options))


_PASS1_CHUNK = 1024  # steps of pass 1 per chunk: pass 2's unit of work (a multiple of mean_var_grad's block)


def _linear_workers(workers: int | None, rows: int, chunk: int) -> int:
    """Worker threads for pass 2 of ``run_linear``: ``workers`` when given, else one where this
    process may run on two or more CPUs and the run has more than one chunk; none otherwise."""
    if workers is not None:
        return int(workers)
    return 1 if rows > chunk and two_cpus() else 0


class _Workers:
    """Runs ``fn(*task)`` for every submitted task: on ``n`` worker threads while the caller goes on,
    and, on leaving the ``with`` block, on the calling thread too until none is left (n = 0: at once,
    on the caller). ``then(*task)``, when given, runs on the calling thread for every task after ``fn`` has
    finished it, in the order the tasks were submitted: on leaving the block, between the caller's own
    tasks (n = 0: right after ``fn``). The first error a task raises is raised on leaving the block.
    ``queued``: with workers, the caller runs a queued task itself at ``submit`` while more than that many wait
    (bounds what the waiting tasks hold)."""

    def __init__(self, fn, n: int, then=None, queued: int | None = None):
        self.fn, self.n, self.then, self.queued = fn, int(n), then, queued
        self.tasks: queue.SimpleQueue = queue.SimpleQueue()
        self.errors: list[BaseException] = []
        self.order: list[tuple] = []  # submitted tasks, in order
        self.finished: set[tuple] = set()  # tasks fn has finished
        self.cond = threading.Condition()
        self.threads = [threading.Thread(target=self._work, daemon=True, name=f"gpnarx-pass2-{k}")
                        for k in range(self.n)]

    def __enter__(self):
        for t in self.threads:
            t.start()
        return self

    def submit(self, *task) -> None:
        if self.n:
            self.order.append(task)
            self.tasks.put(task)
            while self.queued is not None and self.tasks.qsize() > self.queued and not self.errors:
                try:  # more than ``queued`` waiting: the caller runs one
                    self._run(self.tasks.get_nowait())
                except queue.Empty:
                    break
        else:
            self.fn(*task)
            if self.then is not None:
                self.then(*task)

    def _work(self) -> None:
        while True:
            task = self.tasks.get()
            if task is None:
                return
            self._run(task)

    def _run(self, task) -> None:
        if self.errors:
            return
        try:
            self.fn(*task)
        except BaseException as e:  # raised again on the calling thread
            self.errors.append(e)
        with self.cond:
            self.finished.add(task)
            self.cond.notify_all()

    def __exit__(self, exc_type, exc, tb):
        if self.n:
            try:
                if exc_type is None:
                    self._drain()
            finally:  # also when ``then`` raises: the workers stop
                while True:  # what is left after an error: dropped
                    try:
                        self.tasks.get_nowait()
                    except queue.Empty:
                        break
                for _ in self.threads:
                    self.tasks.put(None)
                for t in self.threads:
                    t.join()
        if exc_type is None and self.errors:
            raise self.errors[0]
        return False

    def _drain(self) -> None:
        """The calling thread: ``then`` for each finished task in order, else a queued task, else waits for a
        worker, until every task is done and followed (or one failed)."""
        done = 0  # tasks followed by ``then``
        while not self.errors:
            while done < len(self.order) and self.order[done] in self.finished:
                if self.then is not None:
                    self.then(*self.order[done])
                done += 1
            try:
                task = self.tasks.get_nowait()
            except queue.Empty:
                if done == len(self.order):
                    return
                want = self.order[done]
                with self.cond:
                    self.cond.wait_for(lambda want=want: want in self.finished or bool(self.errors))
                continue
            self._run(task)


def _resize(S: np.ndarray, L: int) -> np.ndarray:
    """A state covariance as L x L: cut, or padded with zeros (square, symmetric input)."""
    if S.ndim != 2 or S.shape[0] != S.shape[1] or not np.all(np.isfinite(S)):
        raise ValueError("state: cov must be a finite square matrix")
    out = np.zeros((L, L))
    k = min(L, S.shape[0])
    out[:k, :k] = S[:k, :k]
    return out


class _CovarianceRecursion:
    """Pass 3 of ``run_linear``: var(y_i) for every step of the linearised propagation (``out``) and its
    propagated part J S J^T (``prop``), and cov(y_i, y_{i-k}) into ``band``, ``advance``d chunk by chunk in
    order.

    S (L x L, output units) is the covariance of [y_{i-1}, ..., y_{i-L}]; one step is
    SJ = S[:, :ny] J, var_y = q_i + J . SJ[:ny], then S shifts down the diagonal with [var_y, SJ]
    as its new first row and column. The shift costs nothing: S is a moving diagonal window of a
    larger buffer (rebased every ``block`` steps). Same caps as the reference loop. ``S0``: the
    covariance to start from (None: zeros, at rest or at known outputs). ``state()``: S after the steps done.
    """

    block = 512
    _NO_BAND = np.zeros((1, 1))

    def __init__(self, steps: int, ny: int, L: int, ys: float, band, i0: int, S0: np.ndarray | None = None):
        self.ny, self.L, self.band, self.i0 = ny, L, band, i0
        self.cap = VAR_CAP * ys * ys
        self.out = np.empty(steps)
        self.prop = np.empty(steps)
        self.k = 0  # steps done
        self.B = np.zeros((L + self.block, L + self.block))
        self.o = self.block  # S = B[o:o+L, o:o+L]
        if S0 is not None:
            self.B[self.o:self.o + L, self.o:self.o + L] = S0

    compiled = None  # linear_kernels.cov_steps where the compiled pass runs: the same loop compiled

    def advance(self, q: np.ndarray, Jall: np.ndarray) -> None:
        """The next q.size steps: q = sigma_f^2 + sigma_y^2 and Jall (steps, ny) = d mu / d y_lag of each."""
        ny, L, band, i0, cap = self.ny, self.L, self.band, self.i0, self.cap
        if self.compiled is not None:
            self.o = self.compiled(self.B, self.o, self.block, L, ny, np.ascontiguousarray(q),
                                   np.ascontiguousarray(Jall), self.k, self.out, self.prop, cap,
                                   self._NO_BAND if band is None else band, i0, band is not None)
            self.k += q.size
            return
        B, o, block, out, prop = self.B, self.o, self.block, self.out, self.prop
        isfinite = math.isfinite
        dot = np.dot
        safe = 0.25 * cap
        for j in range(q.size):
            k = self.k + j
            if o == 0:  # rebase: move S to the bottom-right corner
                B[block:, block:] = B[:L, :L]
                o = block
            S = B[o: o + L, o: o + L]
            J = Jall[j]
            SJ = dot(S[:, :ny], J)
            t = float(dot(J, SJ[:ny]))  # J S J^T
            if not (isfinite(t) and -safe < t < safe):
                # the reference loop's guards. Otherwise they change nothing: S is a covariance with
                # diagonal <= cap, so |(S J)_a| <= sqrt(S_aa J S J^T) < cap / 2 (Cauchy-Schwarz)
                if not np.all(np.isfinite(SJ)):  # a diverging run keeps a finite state covariance
                    SJ = np.nan_to_num(SJ, nan=cap, posinf=cap, neginf=-cap)
                np.clip(SJ, -cap, cap, out=SJ)
                t = float(dot(J, SJ[:ny]))
            prop[k] = t
            v = q[j] + t
            v = min(v, cap) if isfinite(v) else cap
            out[k] = v
            o -= 1
            B[o, o] = v
            B[o, o + 1: o + L] = SJ[:-1]
            B[o + 1: o + L, o] = SJ[:-1]
            if band is not None:
                band[i0 + k, 0] = v
                band[i0 + k, 1:] = SJ[:-1]
        self.o = o
        self.k += q.size

    def state(self) -> np.ndarray:
        """S after the steps done (L x L)."""
        return self.B[self.o: self.o + self.L, self.o: self.o + self.L].copy()


class _MeanRecursion:
    """Pass 1 of ``run_linear``: the free-run mean y_i = mu(x_i) (eq. 8) fed back as a lag.

    For a posterior whose kernel gives its share of the mean as ``MeanTerms`` (``LinearisableKernel.
    mean_terms``: Matern32, RBF, CubicPolynomial, White and sums of them), one step is about twenty
    numpy calls on (M,) vectors instead of a general kernel evaluation: g = Z x (the input part Z_u x_u
    of every step of a block is one BLAS-3 product before the block), r^2 = |x|^2 + |z|^2 - 2 g, then
    every profile's row f(r^2) into one (rows x M) buffer F next to g, g^2, g^3, and one product F w;
    the kernel's moments, profile scales and constant turn F w into the mean.
    """
    def __init__(self, Z, terms, w, ny, nu, xm, xs):
        self.Z = Z
        self.w = w
        self.ny, self.nu = ny, nu
        self.xm, self.xs = xm, xs
        self.Zy_rev = np.ascontiguousarray(Z[:, :ny][:, ::-1])  # columns in time order y_{i-ny}..y_{i-1}
        self.Zu = np.ascontiguousarray(Z[:, ny:])
        self.sqZ = np.einsum("ij,ij->i", Z, Z)
        self.xm_rev = np.ascontiguousarray(xm[:ny][::-1])
        self.inv_rev = np.ascontiguousarray(1.0 / xs[:ny][::-1])
        self.const = terms.const
        self.has_moments = terms.moments is not None
        self.moments = terms.moments if self.has_moments else (0.0, 0.0, 0.0)  # coefficients of S1, S2, S3
        self.profiles = terms.profiles  # (scale, fill) per row 3, 4, ... of F
        # F rows: 0 = g, 1 = g^2, 2 = g^3 (filled when the kernel has moments), then one row per profile
        self.n_rows = 3 + len(self.profiles)

    @classmethod
    def build(cls, predictor: Predictor):
        """A recursion for the predictor's posterior, or None when it is not a ``posterior.Posterior`` or its
        kernel has no ``MeanTerms``."""
        posterior = predictor.posterior
        if not isinstance(posterior, Posterior):
            return None
        require(posterior.kernel, LinearisableKernel, "the linearised free run (freerun.simulate_linear)")
        w = np.asarray(posterior.mean_weights, dtype=float)
        terms = posterior.kernel.mean_terms(w)
        if terms is None:
            return None
        return cls(np.ascontiguousarray(posterior.points, dtype=float), terms, w, predictor.ny, predictor.nu,
                   np.asarray(predictor.x_mean, float), np.asarray(predictor.x_scale, float))

    def run(self, hist, Ulag, i0, n, ym, ys, progress=None, chunk=1024, on_chunk=None):
        """Fill hist[ny + i] with the mean output of every step i0 <= i < n (output units), ``chunk``
        steps at a time; ``on_chunk(c0, c1)`` after the steps c0 <= i < c1 are final."""
        ny = self.ny
        M = self.Z.shape[0]
        F = np.zeros((self.n_rows, M))
        g, g2, g3 = F[0], F[1], F[2]
        gy, gy2 = np.empty(M), np.empty(M)  # Z_y x_y and -2 Z_y x_y (scaling by -2 is exact: the same
        Zy = self.Zy_rev  # numbers as a product with -2 Z_y, at half the matrix's size in cache)
        r = np.empty(M)
        xy = np.empty(ny)
        wv = self.w
        c1, c2, c3 = self.moments
        const = self.const
        has_moments = self.has_moments
        profiles = list(enumerate(self.profiles, start=3))  # (F row, (scale, fill))
        single = len(profiles) == 1
        xm_r, inv_r = self.xm_rev, self.inv_rev
        # conservative range of a lag value whose standardised value needs no clipping (any column)
        lo = float(np.max(self.xm[:ny] - LAG_CLIP * self.xs[:ny]))
        hi = float(np.min(self.xm[:ny] + LAG_CLIP * self.xs[:ny]))
        clip_until = -1
        for k in range(ny):  # initial lags (y0) outside that range
            v = hist[i0 + k]
            if not lo <= v <= hi:
                clip_until = i0 + ny
        dot, multiply, subtract, add = np.dot, np.multiply, np.subtract, np.add
        maximum = np.maximum
        for c0 in range(i0, n, chunk):
            c1_ = min(n, c0 + chunk)
            Uc = Ulag[c0:c1_]
            GU = Uc @ self.Zu.T  # input part of g = Z x for every step of the chunk
            # |z|^2 + |x_u|^2 - 2 Z_u x_u: r^2 = that + |x_y|^2 - 2 Z_y x_y
            R0 = GU * -2.0
            R0 += self.sqZ
            R0 += np.einsum("ij,ij->i", Uc, Uc)[:, None]
            for i in range(c0, c1_):
                j = i - c0
                subtract(hist[i: i + ny], xm_r, out=xy)
                xy *= inv_r
                if i <= clip_until:
                    np.clip(xy, -LAG_CLIP, LAG_CLIP, out=xy)
                dot(Zy, xy, out=gy)
                add(gy, GU[j], out=g)
                if profiles:
                    multiply(gy, -2.0, out=gy2)
                    add(gy2, R0[j], out=r)
                    r += float(dot(xy, xy))
                    maximum(r, 0.0, out=r)
                    for row, (_, fill) in profiles:
                        fill(r if single else r.copy(), F[row])
                if has_moments:
                    multiply(g, g, out=g2)
                    multiply(g2, g, out=g3)
                vals = dot(F, wv)
                mu = const + c1 * vals[0] + c2 * vals[1] + c3 * vals[2]
                for row, (scale, _) in profiles:
                    mu += scale * vals[row]
                y = mu * ys + ym
                hist[ny + i] = y
                if not lo <= y <= hi:
                    clip_until = i + ny
                if progress is not None and (i % 4096 == 0):
                    progress(i + 1, n)
            if on_chunk is not None:
                on_chunk(c0, c1_)
