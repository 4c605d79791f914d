"""The GP-NARX estimator (scikit-learn style; a worked example is in ``GPNARX``'s docstring).

A scikit-learn estimator (its parameter protocol, ``params.ParamsMixin``: ``sklearn.base.clone`` and
``get_params`` / ``set_params`` work without this module importing scikit-learn): keyword-only parameters
set in ``__init__``, learned attributes ending in ``_``.
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from gpnarx.checks import is_int
from gpnarx.runtime import free_run_blas

from . import freerun
from .backend import check_backend
from .discrepancy import calibrate_scale, check_discrepancy, widen_chunk
from .envelope import check_envelope, divergence_limit, training_envelope
from .freerun import Predictor, RunSpec
from .freerun.horizon import check_horizon, join_runs, run_horizon
from .gaps import find_gaps, pieces
from .gp import ExactPosterior, SparsePosterior, choose_inducing
from .kernels import DEFAULT_CONSTANT_CAP, Kernel, check_constant_cap, kernel_from_dict, make_kernel
from .ml2 import default_warm_start_subset, fit_ml2
from .params import ParamsMixin
from .record import Record, RecordError, allowing_gaps
from .regressors import check_lags, first_index, narx_regressors, stack_regressors
from .scaling import Standardizer
from .selection import SELECTIONS, select_rows

MODES = ("exact", "sparse")
MAX_PATHS = 65536
#: floats of one row block's cross-covariance K(X_block, points) in ``_predict_rows``: 4 Mi (32 MiB)
ROW_BLOCK_FLOATS = 1 << 22
#: a row block holds a multiple of this many rows (see ``_predict_rows``)
ROW_BLOCK_ALIGN = 256


def _predict_rows(posterior, Xs: np.ndarray, return_var: bool = True, block_floats: int | None = None):
    """``posterior.predict`` (eqs. 8-9) at the rows of Xs, in blocks of rows: the largest multiple of
    ``ROW_BLOCK_ALIGN`` rows within ``block_floats`` (default ``ROW_BLOCK_FLOATS``, read at the call) floats of
    K(X_block, points), at least ``ROW_BLOCK_ALIGN``.

    One call over every row holds K(Xs, points) and its kernel and eq. 9 temporaries at once: the held-out
    noise calibration of the exact bert-real (157 k rows x 1500 points, 1.9 GB per array) peaked at 9.4 GB.
    Each row's mean and variance depend on that row alone; with every block starting at a multiple of 256
    rows, OpenBLAS's products round each row as in one call (byte-equal means and variances on bert-real's
    157 k rows, 1 and 2 BLAS threads; blocks of 2796 rows differed in a few hundred rows by round-off).
    """
    Xs = np.asarray(Xs, dtype=float)
    n = Xs.shape[0]
    floats = ROW_BLOCK_FLOATS if block_floats is None else int(block_floats)
    rows = max(ROW_BLOCK_ALIGN, floats // max(1, int(posterior.n_points)) // ROW_BLOCK_ALIGN * ROW_BLOCK_ALIGN)
    if n <= rows:
        return posterior.predict(Xs, return_var=return_var)
    mean = np.empty(n)
    var = np.empty(n) if return_var else None
    for r0 in range(0, n, rows):
        r1 = min(n, r0 + rows)
        m, v = posterior.predict(Xs[r0:r1], return_var=return_var)
        mean[r0:r1] = m
        if return_var:
            var[r0:r1] = v
    return mean, var


def _as_pairs(records) -> list[tuple[np.ndarray, np.ndarray]]:
    """Accept Record objects, (u, y) tuples, or a single one of either."""
    if isinstance(records, Record) or (isinstance(records, tuple) and len(records) == 2
                                        and not isinstance(records[0], (Record, tuple))):
        records = [records]
    if not isinstance(records, (list, tuple)) or len(records) == 0:
        raise ValueError("records must be a non-empty list of Record or (u, y) pairs")
    pairs = []
    for k, r in enumerate(records):
        if not isinstance(r, Record):
            try:
                u, y = r
            except (TypeError, ValueError):
                raise ValueError(f"records[{k}] must be a Record or a (u, y) pair") from None
            with allowing_gaps():  # NaN samples are gaps: no lag window crosses them (model.regressors)
                r = Record(u, y, 1.0, name=f"records[{k}]")
        if r.y is None:
            raise ValueError(f"records[{k}] ({r.name}) has no output y; training needs u and y")
        pairs.append((r.u, r.y))
    return pairs


def _row_weights(records) -> list[float] | None:
    """Each training record's ``meta["row_weight"]`` (its share of the ML-II rows per sample relative to
    the others, ``model.selection``), or None when no record names one."""
    if isinstance(records, Record):
        records = [records]
    if not isinstance(records, (list, tuple)):
        return None
    found = [r.meta.get("row_weight") if isinstance(r, Record) else None for r in records]
    if all(v is None for v in found):
        return None
    out = []
    for k, v in enumerate(found):
        v = 1.0 if v is None else v
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v <= 0:
            raise ValueError(f"records[{k}] ({records[k].name}): row_weight must be a positive number, got {v!r}")
        out.append(float(v))
    return out


def _gap_free(pairs, need: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The (u, y) pairs cut at their gaps (``model.gaps``): the gap-free pieces of at least ``need`` samples
    (every piece of a record without gaps: the record itself)."""
    out = []
    for u, y in pairs:
        gaps = find_gaps(u, y)
        if not gaps:
            out.append((u, y))
            continue
        out.extend((u[a:b], y[a:b]) for a, b in pieces(u.size, gaps) if b - a >= need)
    if not out:
        raise ValueError(f"records: no gap-free piece of at least {need} samples")
    return out


def _has_nan(u) -> bool:
    try:
        return bool(np.isnan(np.asarray(u, dtype=float)).any())
    except (TypeError, ValueError):
        return False  # ``_as_input`` names what is wrong


def _as_record_series(a, name: str) -> np.ndarray:
    """A 1-D, non-empty series of numbers or NaN (a gap, ``model.gaps``); ValueError naming ``name`` otherwise
    (an infinite value too)."""
    try:
        arr = np.asarray(a, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a 1-D array of numbers") from None
    if arr.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {arr.shape}")
    if arr.size == 0:
        raise ValueError(f"{name} is empty")
    if np.isinf(arr).any():
        raise ValueError(f"{name} holds infinite values (a gap is NaN)")
    if np.isnan(arr).all():
        raise ValueError(f"{name} holds no sample: every one is NaN (a gap)")
    return arr


def _held(y: np.ndarray, confidence: float, method: str):
    """The measured outputs as a run that holds them (no uncertainty): a piece after a gap too short to predict
    from its first ny measured outputs."""
    y = np.asarray(y, dtype=float)
    z = np.zeros(y.size)
    return freerun.FreeRun(y.copy(), z, y.copy(), y.copy(), float(confidence), 0, method,
                           latent_lower=y.copy(), latent_upper=y.copy())


def _as_input(u, name: str = "u") -> np.ndarray:
    try:
        arr = np.asarray(u, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a 1-D array of numbers") from None
    if arr.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {arr.shape}")
    if arr.size == 0:
        raise ValueError(f"{name} is empty")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} holds non-finite values (NaN/inf)")
    return arr


def check_gp_params(est) -> None:
    """The settings every GP-NARX estimator shares (``GPNARX``, ``mimo.MIMOGPNARX``), checked on ``est``: lags
    (normalised in place), mode, selection, row cap, inducing points, sparse hyperparameters, restarts, constant cap.
    ValueError naming the setting and its limit."""
    est.ny, est.nu = check_lags(est.ny, est.nu)
    if est.mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {est.mode!r}")
    if est.selection not in SELECTIONS:
        raise ValueError(f"selection must be one of {SELECTIONS}, got {est.selection!r}")
    if est.max_train_points is not None and int(est.max_train_points) < 2:
        raise ValueError(f"max_train_points must be at least 2, got {est.max_train_points}")
    if est.mode == "sparse" and not 1 <= int(est.n_inducing) <= 4096:
        raise ValueError(f"n_inducing must be between 1 and 4096, got {est.n_inducing}")
    if est.hyper not in ("subset", "vfe"):
        raise ValueError(f"hyper must be 'subset' or 'vfe', got {est.hyper!r}")
    if int(est.n_restarts) < 0:
        raise ValueError(f"n_restarts must be >= 0, got {est.n_restarts}")
    check_constant_cap(est.constant_cap)


class GPNARX(ParamsMixin):
    """GP-NARX model of eqs. (1)-(3) with the kernel of eq. (12) by default.

    A scikit-learn estimator: parameters are keyword-only and set in ``__init__`` (so
    ``get_params``, ``set_params`` and ``sklearn.base.clone`` work); everything learned by ``fit``
    is an attribute ending in ``_``.

    Parameters
    ----------
    ny, nu : int, default=2
        Output and input lag orders of eq. (3) (1..200 each).
    kernel : Kernel or str, default='matern32+cubic'
        A ``Kernel`` or a name for ``make_kernel`` (eq. 12 by default).
    mode : {'exact', 'sparse'}, default='exact'
        'exact' (full GP) or 'sparse' (M inducing points; hyperparameters from exact ML-II on the
        capped training set, posterior over all rows at O(N M^2)).
    n_inducing : int, default=256
        M for sparse mode (1..4096).
    max_train_points : int or None, default=2000
        Cap on GP training rows for ML-II (and the exact posterior).
    selection : {'stride', 'random', 'resonance'}, default='stride'
        How the cap selects rows (section 4.2).
    n_restarts : int, default=2
        Extra seeded L-BFGS-B starts for ML-II (stops early when two agree). From 2000 ML-II rows,
        the first start is warm-started on a quarter of them (strided) before the full-N L-BFGS-B
        (``fit_ml2(warm_start_subset=N // 4)``: fewer O(N^3) evaluations), and the redundant cubic
        scale s is held fixed (``hold_redundant``, see ``fit_ml2``).
    seed : int, default=0
        Seed of the selection, restarts and inducing-point k-means.
    include_noise : bool, default=True
        Free-run samples include the likelihood noise sigma_y^2 (eq. 2).
    sparse_max_rows : int or None, default=50000
        Cap on the (strided) rows of the sparse posterior and of the VFE refinement.
    hyper : {'subset', 'vfe'}, default='subset'
        How sparse mode sets hyperparameters: 'subset' (exact ML-II, eq. 13, on the capped rows) or
        'vfe' (that, then refined on all rows by maximising the Titsias VFE bound with analytic
        gradients, O(N M^2) per evaluation; see ``model.vfe``).
    constant_cap : float or None, default=1.0
        Cap on the constant term sigma_p^2 b^3 of the cubic kernel (eq. 11) for the predictive
        variance, in standardised output variance units (None: no cap). ML-II can leave that term at
        1e4 while the latent variance is 1e-4, and eq. 9 then cancels below float64 precision; with
        the cap (1: the variance of the standardised output) the variance is exact to ~1e-10. The
        mean (eq. 8) keeps the uncapped kernel (see ``CubicPolynomial``).

    Attributes
    ----------
    kernel_ : Kernel
        The fitted kernel (hyperparameters of ML-II or ``theta``).
    theta_ : ndarray
        Log-hyperparameters: the kernel's, then log sigma_y^2.
    nlml_ : float
        Negative log marginal likelihood at ``theta_`` (NaN when ``theta`` was given).
    ml2_restarts_ : list
        The ML-II starts that were run.
    noise_var_ : float
        Likelihood noise variance sigma_y^2 in use (standardised units).
    noise_var_ml2_ : float
        sigma_y^2 from ML-II, before any held-out calibration.
    noise_calibration_ : dict or None
        What the held-out noise calibration did (``fit(heldout=...)``), else None.
    band_discrepancy_ : dict or None
        The band's model-discrepancy term set by ``calibrate_band``, else None.
    posterior_ : ExactPosterior or SparsePosterior
        The GP posterior over the standardised training rows.
    x_scaler_, y_scaler_ : Standardizer
        Standardisation of the regressors and of the output.
    envelope_ : dict
        The training envelope (``model.envelope``) a free run is checked against.
    n_train_ : int
        Rows used by ML-II (and the exact posterior).
    n_rows_ : int
        Regressor rows of all training records.
    fit_seconds_ : float
        Wall time of ``fit``.

    Examples
    --------
    >>> import numpy as np
    >>> from gpnarx.model.estimator import GPNARX
    >>> u = np.random.default_rng(0).normal(size=400)
    >>> y = np.convolve(u, [0.5, 0.3, 0.1])[:400]
    >>> m = GPNARX(ny=2, nu=3, max_train_points=200, n_restarts=0).fit([(u, y)])
    >>> run = m.simulate(u[:100], n_paths=64, seed=0)      # free-run mean, std, 99% band
    >>> run.mean.shape
    (100,)
    >>> mean, std = m.predict_one_step([(u, y)])          # eqs. (8)-(9)
    """

    def __init__(self, *, ny: int = 2, nu: int = 2, kernel: Kernel | str = "matern32+cubic", mode: str = "exact",
                 n_inducing: int = 256, max_train_points: int | None = 2000, selection: str = "stride",
                 n_restarts: int = 2, seed: int = 0, include_noise: bool = True,
                 sparse_max_rows: int | None = 50000, hyper: str = "subset",
                 constant_cap: float | None = DEFAULT_CONSTANT_CAP, fit_backend: str = "numpy"):
        self.ny = ny
        self.nu = nu
        self.kernel = kernel
        self.mode = mode
        self.n_inducing = n_inducing
        self.max_train_points = max_train_points
        self.selection = selection
        self.n_restarts = n_restarts
        self.seed = seed
        self.include_noise = include_noise
        self.sparse_max_rows = sparse_max_rows
        self.hyper = hyper
        self.constant_cap = constant_cap
        self.fit_backend = fit_backend

    # ------------------------------------------------------------------------------------------
    def _check_params(self) -> None:
        check_gp_params(self)
        self.fit_backend = check_backend(self.fit_backend, "fit_backend")

    def fit(self, records, theta: np.ndarray | None = None, heldout=None, progress=None) -> "GPNARX":
        """Learn standardisation, hyperparameters (ML-II, eq. 13) and the posterior.

        records: Record objects or (u, y) pairs; each must have more than max(ny, nu-1) samples. A Record's
            ``meta["row_weight"]`` (positive, 1 when absent) scales its share of the ML-II rows
            (``selection.select_rows``).
        theta: optional fixed log-hyperparameters (kernel then log sigma_y^2); skips ML-II.
        heldout: optional records NOT in ``records`` (Record objects or (u, y) pairs). When given,
            sigma_y^2 is raised to the held-out maximum-likelihood value of their one-step residuals
            (``model.heldout_noise``; never below ML-II's) and the posterior is rebuilt with it. The
            ML-II value stays in ``noise_var_ml2_``; ``noise_calibration_`` records what was done.
        progress: optional callable taking one line of text (``print`` will do): the regressor rows, ML-II's
            evaluations as it goes (``ml2.fit_ml2``) and the posterior; the fit does not depend on it.
        """
        self._check_params()
        say = progress or (lambda line: None)
        t0 = time.perf_counter()
        pairs = _as_pairs(records)
        weights = _row_weights(records)
        held = None
        if heldout is not None:  # checked before ML-II, so a bad held-out record fails fast
            try:
                held = _as_pairs(heldout)
            except ValueError as exc:
                raise ValueError(f"heldout: {exc}") from None
        need = first_index(self.ny, self.nu) + 2
        for label, group in (("records", pairs), ("heldout", held or [])):
            for k, (u, _y) in enumerate(group):
                if u.size < need:
                    raise ValueError(f"{label}[{k}] has {u.size} samples; ny={self.ny}, nu={self.nu} "
                                     f"need at least {need}")
        X, Y, rec_idx = stack_regressors(pairs, self.ny, self.nu)
        self.envelope_ = training_envelope(_gap_free(pairs, need))
        self.x_scaler_ = Standardizer().fit(X)
        self.y_scaler_ = Standardizer().fit(Y[:, None])
        Xs = self.x_scaler_.transform(X)
        Ys = (Y - self.y_scaler_.mean_[0]) / self.y_scaler_.scale_[0]
        rows = select_rows(Ys, rec_idx, self.max_train_points, self.selection, self.seed, weights=weights)
        Xt, Yt = Xs[rows], Ys[rows]
        say(f"regressors: {X.shape[0]} rows from {len(pairs)} record(s) (ny={self.ny}, nu={self.nu}); "
            f"ML-II on {Xt.shape[0]} of them")
        # ML-II and the posterior mean use the uncapped kernel (eqs. 13, 8); the variance its capped copy
        self.kernel_ = make_kernel(self.kernel) if isinstance(self.kernel, str) else self.kernel.for_posterior(None)
        if theta is None:
            sub = default_warm_start_subset(Xt.shape[0])
            res = fit_ml2(self.kernel_, Xt, Yt, n_restarts=int(self.n_restarts), seed=int(self.seed),
                          warm_start_subset=sub, hold_redundant=sub is not None, backend=self.fit_backend,
                          progress=progress)
            self.theta_, self.nlml_, self.ml2_restarts_ = res.theta, res.nlml, res.restarts
            say(f"ML-II done: NLML {res.nlml:.6g} nats after {res.n_evals} evaluations, {res.seconds:.0f} s")
        else:
            theta = np.asarray(theta, dtype=float)
            self.kernel_.set_theta(theta[:-1])
            self.theta_, self.nlml_, self.ml2_restarts_ = theta, float("nan"), []
        self.noise_var_ = float(np.exp(self.theta_[-1]))
        if self.mode == "exact":
            def build(nv):
                post = ExactPosterior.fit(self.kernel_, nv, Xt, Yt, var_kernel=self._posterior_kernel(),
                                          backend=self.fit_backend)
                post.y_train = Yt  # its targets, which an update or a refinement refactors on (not in bundles)
                return post
        else:
            all_rows = select_rows(Ys, rec_idx, self.sparse_max_rows, "stride", self.seed, weights=weights)
            Z = choose_inducing(Xs[all_rows], int(self.n_inducing), self.seed)
            if self.hyper == "vfe" and theta is None:
                from .vfe import fit_vfe  # here: training-only, kept out of a predict process's start-up

                res = fit_vfe(self.kernel_, Xs[all_rows], Ys[all_rows], Z, theta0=self.theta_)
                self.theta_, self.nlml_ = res.theta, res.nlml
                self.noise_var_ = float(np.exp(self.theta_[-1]))
            def build(nv):
                return SparsePosterior.fit(self.kernel_, nv, Xs[all_rows], Ys[all_rows], Z,
                                           var_kernel=self._posterior_kernel())
        self.posterior_ = build(self.noise_var_)
        self.noise_var_ml2_ = self.noise_var_
        self.noise_calibration_ = None
        self.band_discrepancy_ = None  # set by calibrate_band (model.discrepancy)
        if held is not None:
            self._calibrate_noise(held, build)
        self.n_train_ = int(Xt.shape[0])
        self.n_rows_ = int(X.shape[0])
        self.fit_seconds_ = time.perf_counter() - t0
        say(f"fitted: {self.mode} posterior on {self.n_train_} rows in {self.fit_seconds_:.0f} s")
        return self

    def _calibrate_noise(self, pairs, build) -> None:
        """Raise sigma_y^2 to its held-out ML value (model.heldout_noise) and rebuild the posterior."""
        from .heldout_noise import heldout_noise_var  # here: training-only, kept out of a predict start-up

        X, Y, _ = stack_regressors(pairs, self.ny, self.nu)
        if self.fit_backend == "jax" and self.posterior_.kind == "exact":
            from .ml2_jax import predict_exact_jax  # here: the optional backend stays out of numpy runs

            mu, var = predict_exact_jax(self.posterior_, self.x_scaler_.transform(X))
        else:
            mu, var = _predict_rows(self.posterior_, self.x_scaler_.transform(X))  # row blocks: bounded memory
        resid = (Y - self.y_scaler_.mean_[0]) / self.y_scaler_.scale_[0] - mu
        s2 = heldout_noise_var(resid, var, floor=self.noise_var_)  # >= the ML-II value
        self.noise_calibration_ = {
            "method": "heldout_ml", "n_records": len(pairs), "n_residuals": int(resid.size),
            "noise_var_ml2": self.noise_var_, "noise_var": s2,
            "residual_var": float(np.mean(resid * resid)), "latent_var_mean": float(np.mean(var)),
        }
        if s2 > self.noise_var_:
            self.noise_var_ = s2
            self.theta_ = np.concatenate([np.asarray(self.theta_, dtype=float)[:-1], [np.log(s2)]])
            self.posterior_ = build(s2)

    def partial_fit(self, records, rows: int | None = None) -> "GPNARX":
        """Condition the fitted exact posterior also on new records, hyperparameters, scalers and lags held.

        records: Record objects or (u, y) pairs, in the model's units (each longer than max(ny, nu-1) + 1
            samples); a Record's ``meta["row_weight"]`` weighs its share of the rows as in ``fit``.
        rows: how many of the new records' regressor rows join the posterior, chosen by the model's
            ``selection`` rule (``model.selection.select_rows``). Default: the parent's rows per regressor row,
            ``n_train_ / n_rows_``, times the new records' regressor rows (at least 1); when that would pass the
            row budget, the budget's share of the new regressor rows, ``max_train_points / (n_rows_ + new)``.

        The rows are appended by a rank update of the posterior's factor (``model.gp_update.append_rows``,
        O(N^2 k) for k rows on N; no refactorisation). The row budget ``max_train_points`` is kept by the
        selection rule, not a sliding window: when the posterior would hold more, the rule picks which of its
        present rows stay (``select_rows`` over them in their order: stride keeps every record's share, so an
        update does not forget the records it was trained on), those are refactored (``gp_update.keep_rows``,
        O(N^3 / 3), the one step that is not a rank update), then the new rows are appended. The training
        envelope grows to cover the new records. The noise variance stays as it is (``recalibrate_noise`` redoes
        the held-out calibration); so do the band's discrepancy term and the novelty threshold (the training layer's
        ``gpnarx update`` recalibrates them). What was done is in ``update_``. The sparse posterior cannot take
        rows (it keeps no N-row statistics): ``ValueError`` saying it needs a retrain.
        """
        from .envelope import extend_envelope
        from .gp_update import append_rows, keep_rows, targets

        self._check_fitted()
        if self.posterior_.kind != "exact":
            raise ValueError(f"partial_fit: the {self.posterior_.kind} posterior keeps no statistics of its N "
                             "training rows to update; it needs a retrain (fit, or gpnarx train)")
        pairs = _as_pairs(records)
        weights = _row_weights(records)
        need = first_index(self.ny, self.nu) + 2
        for k, (u, _y) in enumerate(pairs):
            if u.size < need:
                raise ValueError(f"records[{k}] has {u.size} samples; ny={self.ny}, nu={self.nu} need at least "
                                 f"{need}")
        X, Y, rec_idx = stack_regressors(pairs, self.ny, self.nu)
        n_new = int(X.shape[0])
        n_rows = getattr(self, "n_rows_", None)
        budget = None if self.max_train_points is None else int(self.max_train_points)
        post = self.posterior_
        if rows is None:
            if not n_rows:
                raise ValueError("rows: this model does not know its training regressor rows (n_rows_); give the "
                                 "number of new rows to take")
            rows = max(1, int(round(n_new * self.n_train_ / n_rows)))
            if budget is not None and post.n_points + rows > budget:
                rows = max(1, int(round(n_new * budget / (n_rows + n_new))))
        if not is_int(rows, 1, None):
            raise ValueError(f"rows must be an integer >= 1, got {rows!r}")
        take = min(int(rows), n_new, budget or n_new)
        Ys = (Y - self.y_scaler_.mean_[0]) / self.y_scaler_.scale_[0]
        sel = select_rows(Ys, rec_idx, take, self.selection, self.seed, weights=weights)
        drop = 0 if budget is None else max(0, post.n_points + sel.size - budget)
        if drop:
            keep = budget - sel.size
            if keep < 1:
                raise ValueError(f"rows: {sel.size} new rows leave none of the {post.n_points} present rows within "
                                 f"max_train_points={budget}")
            kept = select_rows(targets(post), np.zeros(post.n_points, dtype=int), keep, self.selection, self.seed)
            post = keep_rows(post, kept)
        self.posterior_ = append_rows(post, self.x_scaler_.transform(X[sel]), Ys[sel])
        self.envelope_ = extend_envelope(getattr(self, "envelope_", None), _gap_free(pairs, need))
        self.n_train_ = int(self.posterior_.n_points)
        self.n_rows_ = None if not n_rows else int(n_rows) + n_new
        self.update_ = {"rule": f"selection:{self.selection}", "new_regressor_rows": n_new,
                        "rows_added": int(sel.size), "rows_dropped": int(drop), "rows": self.n_train_,
                        "budget": budget,
                        "factor": "rank update" if not drop else "kept rows refactored, then rank update"}
        return self

    def recalibrate_noise(self, heldout) -> dict | None:
        """Redo ``fit(heldout=...)``'s noise calibration on the posterior's present rows (after ``partial_fit``):
        the posterior at ML-II's sigma_y^2 (``noise_var_ml2_``), then sigma_y^2 raised to the held-out maximum-
        likelihood value of ``heldout``'s one-step residuals (``_calibrate_noise``, the same rule). Exact posterior
        only; each sigma_y^2 that differs from the present one refactors the posterior (O(N^3), hyperparameters
        otherwise held). Returns ``noise_calibration_``."""
        from .gp_update import refactor, targets

        self._check_fitted()
        if self.posterior_.kind != "exact":
            raise ValueError("recalibrate_noise: exact posterior only (a sparse one needs a retrain)")
        try:
            held = _as_pairs(heldout)
        except ValueError as exc:
            raise ValueError(f"heldout: {exc}") from None
        X, y = self.posterior_.X_train, targets(self.posterior_)
        kernel = self.posterior_.kernel

        def build(nv):
            return refactor(kernel, nv, X, y)

        ml2 = float(self.noise_var_ml2_)
        if self.noise_var_ != ml2:
            self.noise_var_ = ml2
            self.theta_ = np.concatenate([np.asarray(self.theta_, dtype=float)[:-1], [np.log(ml2)]])
            self.posterior_ = build(ml2)
        self._calibrate_noise(held, build)
        return self.noise_calibration_

    def calibrate_band(self, records, window: int, method: str = "linear", n_paths: int = 256,
                       confidence: float = 0.99, kind: str = "centred", hold: int = 0,
                       gp_scales=(1.0,)) -> dict:
        """Calibrate the band's model-discrepancy term (``model.discrepancy``) on held-out records.

        records: (name, u, y, start) tuples of records NOT used by ``fit``; ``start`` is 'rest' or
            'measured' (the first ny measured outputs are taken as known and not scored).
        window: samples of the local-amplitude RMS (``discrepancy.DEFAULT_WINDOW_SECONDS`` x fs).
        method, n_paths: how the calibration records are predicted (the linearised method by default:
            seconds per whole record).
        kind: where the amplitude window lies, ``"centred"`` or ``"trailing"`` (causal: a stream's
            chunks get the whole record's band; ``discrepancy.WINDOW_KINDS``).
        hold: time constant of the held amplitude in samples (``discrepancy.held_amplitude``; 0: none).
        gp_scales: factors on the propagated band to calibrate with the scale (``discrepancy.GP_SCALE_GRID``;
            the default keeps eqs. 8-9's band as propagated; ``discrepancy.calibrate_scale``).
        Sets and returns ``band_discrepancy_``.
        """

        self._check_fitted()
        for name, _u, _y, start in records:
            if start not in ("rest", "measured"):
                raise ValueError(f"records[{name!r}].start must be 'rest' or 'measured', got {start!r}")
        self.band_discrepancy_ = None  # the calibration runs are predicted without the term
        runs = []
        for name, u, y, start in records:
            y = np.asarray(y, dtype=float).ravel()
            y0 = y[: self.ny] if start == "measured" else None
            run = self.simulate(u, n_paths=n_paths, seed=0, y0=y0, confidence=confidence, method=method)
            runs.append((name, y, run, self.ny if start == "measured" else 0))
        self.band_discrepancy_ = {**calibrate_scale(runs, int(window), kind=kind, hold=int(hold), gp_scales=gp_scales),
                                  "calibration_method": method,
                                  "records": [name for name, *_ in records]}
        return self.band_discrepancy_

    # ------------------------------------------------------------------------------------------
    def _check_fitted(self) -> None:
        if not hasattr(self, "posterior_"):
            raise RuntimeError("this GPNARX is not fitted yet; call fit(records) first")

    @property
    def n_features_(self) -> int:
        return self.ny + self.nu

    def predict_one_step(self, records, return_std: bool = True):
        """One-step-ahead mean and std (eqs. 8-9) from measured lags, output units.

        Returns arrays aligned with samples max(ny, nu-1) onwards of each record (concatenated).
        The std includes the likelihood noise sigma_y^2 when ``include_noise``.
        """
        self._check_fitted()
        X, _, _ = stack_regressors(_as_pairs(records), self.ny, self.nu)
        mu, var = _predict_rows(self.posterior_, self.x_scaler_.transform(X), return_var=return_std)
        ys, ym = self.y_scaler_.scale_[0], self.y_scaler_.mean_[0]
        mean = mu * ys + ym
        if not return_std:
            return mean
        noise = self.noise_var_ if self.include_noise else 0.0
        return mean, np.sqrt(var + noise) * ys

    def _posterior_kernel(self) -> Kernel:
        return self.kernel_.for_posterior(None if self.constant_cap is None else float(self.constant_cap))

    def simulate(self, u, n_paths: int = 1024, seed: int | None = 0, y0=None, confidence: float = 0.99,
                 method: str = "mc", float32: bool = False, keep_paths: bool = False, progress=None,
                 cov_window: int = 0, backend: str | None = None, state=None, open_end: bool = False,
                 local: bool = True, y=None, horizon: int | None = None):
        """Free-run prediction for input u (input units) with uncertainty propagation.

        method: 'mc' (Monte Carlo over n_paths, seeded) or 'linear' (first-order propagation).
        y0: optional first ny measured outputs; else the system starts from rest.
        float32: the variance product of eq. 9 in single precision (faster; predictive std within
            2 % on the Bouc-Wen model). Not for models whose noise variance sits near ML-II's
            floor (real BERT): their latent variance (1e-7, standardised) is below float32's
            resolution of k(x, x) (about 1), and the band would be rounding noise.
        keep_paths: Monte Carlo only, keep every path in ``FreeRun.paths`` (n x n_paths).
        cov_window: linearised only, also return ``FreeRun.cov_band``, the output covariance over
            that many lags (``freerun.linear``).
        backend: 'numpy' or 'jax' (``model.backend``; None: ``GPNARX_BACKEND``, else numpy). 'jax'
            runs the free run as one compiled program (``freerun.jax_backend``): Monte Carlo with
            eq. 8-9 exact at every path, on a GPU when JAX has one.
        state: the ``FreeRun.state`` of an earlier call, to continue that run with the next chunk of
            the same record (a stream; numpy backend): the chunks together give the record's run
            whole, the linearised one to round-off and Monte Carlo's identically at the same seed
            (``seed`` is then unused: the state carries the generator).
        open_end: more of the record follows this call (a stream's chunk). The band's discrepancy
            term (``model.discrepancy``) averages the amplitude over a window: a trailing window
            (``window_kind`` "trailing") sees only the past, and the chunks' band is the whole
            record's; a centred one (bundles calibrated before the choice) averages, in the last
            half-window of a chunk, what the chunk holds, so there the chunked band may differ
            slightly from the whole record's (elsewhere it is the same).
        local: Monte Carlo on the numpy backend, serve steps from the checked local model of eq. 8-9
            (``freerun.mc``); False evaluates eq. 8-9 exactly at every path.
        y: the record's measured output (output units, u's length), or None: what a k-step prediction and a
            restart after a gap start from.
        horizon: k-step-ahead prediction (``freerun.horizon``, numpy backend): every k = ``horizon`` samples
            the run restarts from the measured outputs (y required; the run starts from y's first ny samples, so
            y0 does not apply). Its band is eqs. 8-9 propagated over the at most k steps since the last measured
            outputs, without the discrepancy term; k = 1 is ``predict_one_step``'s, k >= len(u) - ny the free
            run from y's first ny samples.
        Gaps (``model.gaps``): NaN samples in u, or in y when given, are gaps. The answer holds NaN through each
        gap; after it the run restarts as at a record's start, from the measured outputs (the piece's first ny
        samples) when y is given, from rest otherwise; the piece before the first gap starts as asked (y0 or
        rest). Each piece's Monte Carlo paths draw with the seed plus the piece's index. Neither gaps nor a
        horizon continue a stream (``state``).
        Returns a ``freerun.FreeRun`` (mean, std, lower, upper in output units); Monte Carlo runs
        count in ``diverged_paths`` the paths that left the training envelope (``model.envelope``).
        When the band was calibrated (``calibrate_band``), std and both bands include the
        model-discrepancy term of ``model.discrepancy``. ``FreeRun.state`` is where the run ended.

        BLAS threads: the free run is thousands of small products, which a multi-threaded BLAS (OpenBLAS's
        default: every core) runs many times slower on shared cores. In a process that has not set them (the
        Python API; the CLI and the service set them for the process) the run limits BLAS to
        ``GPNARX_BLAS_THREADS`` threads (default 1; 0 leaves BLAS as it is) with ``threadpoolctl`` and restores
        the caller's settings when it returns (``gpnarx.runtime.free_run_blas``, the CLI's tuning).
        """
        self._check_fitted()
        backend = check_backend(backend)
        if horizon is not None or y is not None or _has_nan(u):
            return self._simulate_pieces(u, y, horizon, n_paths=n_paths, seed=seed, y0=y0, confidence=confidence,
                                         method=method, float32=float32, progress=progress, backend=backend,
                                         state=state, open_end=open_end, local=local)
        if state is not None and backend != "numpy":
            raise ValueError("state: continuing a stream runs on the numpy backend only, got backend "
                             f"{backend!r}")
        spec = RunSpec(method=method, backend=backend, n_paths=n_paths, seed=seed, confidence=confidence, y0=y0,
                       state=state, include_noise=self.include_noise, float32=float32, keep_paths=keep_paths,
                       local=local, cov_window=cov_window, progress=progress)
        with free_run_blas():
            run = self._run(u, spec)
        disc = getattr(self, "band_discrepancy_", None)
        if not disc:
            return run
        held = None if state is None or state.amp_hold is None else float(np.ravel(state.amp_hold)[0])
        out, tail, last = widen_chunk(run, disc, None if state is None else state.amp_tail, open_end, held)
        if out.state is not None:
            out.state.amp_tail = tail
            out.state.amp_hold = None if last is None else np.array([last])
        return out

    def _simulate_pieces(self, u, y, horizon, *, n_paths, seed, y0, confidence, method, float32, progress, backend,
                         state, open_end, local):
        """``simulate`` of a record with gaps or a horizon: each gap-free piece on its own (``model.gaps``), the
        k-step prediction of each when ``horizon`` is given (``freerun.horizon``), joined with NaN in the gaps."""
        u = _as_record_series(u, "u")
        if y is not None:
            y = _as_record_series(y, "y")
            if y.size != u.size:
                raise ValueError(f"y has {y.size} samples but u has {u.size}; they must have the same length")
        if horizon is not None:
            horizon = check_horizon(horizon, y, u.size)
            if y0 is not None and np.asarray(y0).size:
                raise ValueError("horizon: a k-step prediction starts from y's first ny samples; y0 does not apply")
            if u.size <= self.ny:
                raise ValueError(f"u must be longer than ny={self.ny} samples for a k-step prediction, got {u.size}")
            if backend != "numpy":
                raise ValueError(f"horizon: a k-step prediction runs on the numpy backend, got backend {backend!r}")
        gaps = find_gaps(u, y)
        if state is not None or open_end:
            what = "a k-step prediction (horizon)" if horizon is not None else "a record with gaps (NaN)"
            if horizon is not None or gaps:
                raise ValueError(f"state: {what} does not continue a stream; send the record whole")
        if not gaps and horizon is None:
            return self.simulate(u, n_paths=n_paths, seed=seed, y0=y0, confidence=confidence, method=method,
                                 float32=float32, progress=progress, backend=backend, state=state,
                                 open_end=open_end, local=local)
        n, ny = u.size, self.ny
        parts = []
        for j, (a, b) in enumerate(pieces(n, gaps)):
            seed_j = seed if (seed is None or j == 0) else int(seed) + j
            measured = y is not None and (horizon is not None or a > 0)
            if measured and b - a <= ny:  # too short to predict from measured outputs: the measured outputs
                parts.append((a, _held(y[a:b], confidence, method)))
                continue
            if horizon is not None:
                self._check_fitted()
                if method == "mc" and not is_int(n_paths, 1, MAX_PATHS):
                    raise ValueError(f"n_paths must be an integer between 1 and {MAX_PATHS}, got {n_paths!r}")
                spec = RunSpec(method=freerun.check_method(method), n_paths=int(n_paths), seed=seed_j,
                               confidence=confidence, include_noise=self.include_noise, float32=float32,
                               local=local, progress=progress)
                with free_run_blas():
                    parts.append((a, run_horizon(self.predictor(), u[a:b], y[a:b], spec, horizon)))
                continue
            start = y[a:a + ny] if measured else (y0 if a == 0 else None)
            parts.append((a, self.simulate(u[a:b], n_paths=n_paths, seed=seed_j, y0=start, confidence=confidence,
                                           method=method, float32=float32, progress=progress, backend=backend,
                                           local=local)))
        return join_runs(n, parts)

    def predictor(self) -> Predictor:
        """The fitted model as the free runs read it (``freerun.Predictor``): posterior, scalers, lags and the
        divergence limit of the training envelope (``model.envelope``)."""
        self._check_fitted()
        limit = divergence_limit(check_envelope(getattr(self, "envelope_", None)))
        return Predictor.of(self.posterior_, self.x_scaler_, self.y_scaler_, self.ny, self.nu, diverge_limit=limit)

    def _run(self, u, spec: RunSpec):
        """The free run of ``spec`` on input u, without the band's discrepancy term (``simulate`` adds it)."""
        u = _as_input(u)
        predictor = self.predictor()
        freerun.check_method(spec.method)
        if spec.method == "mc":
            n_paths = spec.n_paths
            if not is_int(n_paths, 1, MAX_PATHS):
                raise ValueError(f"n_paths must be an integer between 1 and {MAX_PATHS}, got {n_paths!r}")
            spec = replace(spec, n_paths=int(n_paths))
        return freerun.run(predictor, u, spec)

    def _simulate(self, u, n_paths, seed, y0, confidence, method, float32, keep_paths, progress, cov_window,
                  backend="numpy", state=None, local=True):
        """``_run`` with the spec's fields as positional arguments (studies/split_study.py calls it)."""
        return self._run(u, RunSpec(method=method, backend=backend, n_paths=n_paths, seed=seed, confidence=confidence,
                                    y0=y0, state=state, include_noise=self.include_noise, float32=float32,
                                    keep_paths=keep_paths, local=local, cov_window=cov_window, progress=progress))

    # ------------------------------------------------------------------------------------------
    # The fitted model as plain values: what a bundle stores (gpnarx.storage.bundle lays them out in files)
    def fitted_arrays(self) -> dict:
        """Every array needed to predict, by name: the scalers, ``theta`` and the posterior's (``posterior_*``)."""
        self._check_fitted()
        arrays = {
            "x_mean": self.x_scaler_.mean_, "x_scale": self.x_scaler_.scale_,
            "y_mean": self.y_scaler_.mean_, "y_scale": self.y_scaler_.scale_,
            "theta": self.theta_,
        }
        for k, v in self.posterior_.arrays().items():
            arrays[f"posterior_{k}"] = v
        return arrays

    def fitted_description(self) -> dict:
        """The fitted model's values other than its arrays, JSON-able: lags, mode, kernel (the posterior's,
        constant cap included), hyperparameters, noise variance and its held-out calibration, band
        discrepancy, training envelope, NLML, training rows and the estimator's settings."""
        self._check_fitted()
        return {
            "lags": {"ny": self.ny, "nu": self.nu},
            "mode": self.posterior_.kind,
            "kernel": self.posterior_.kernel.to_dict(),  # the posterior's (constant cap included)
            "hyperparameters": {**self.kernel_.params, "noise_var": self.noise_var_},
            "noise_var": self.noise_var_,
            "noise_calibration": getattr(self, "noise_calibration_", None),
            "band_discrepancy": getattr(self, "band_discrepancy_", None),
            "hyper_refinement": getattr(self, "hyper_refinement_", None),
            "training_envelope": getattr(self, "envelope_", None),
            "nlml": None if not np.isfinite(self.nlml_) else self.nlml_,
            "n_train": self.n_train_,
            "estimator": {"include_noise": bool(self.include_noise), "n_inducing": int(self.n_inducing),
                          "max_train_points": self.max_train_points, "selection": self.selection,
                          "seed": int(self.seed), "hyper": self.hyper,
                          "constant_cap": self.constant_cap,
                          "kernel_spec": self.kernel if isinstance(self.kernel, str) else None},
        }

    @classmethod
    def from_fitted(cls, description: dict, arrays: dict) -> "GPNARX":
        """The fitted model of ``fitted_description()`` and ``fitted_arrays()`` (no refit: the same posterior).

        ``description`` may hold more keys (a bundle manifest); ``ValueError``/``KeyError`` when it or the
        arrays are inconsistent.
        """
        ny, nu = int(description["lags"]["ny"]), int(description["lags"]["nu"])
        est = description["estimator"]
        kernel = kernel_from_dict(description["kernel"])
        model = cls(ny=ny, nu=nu, kernel=est["kernel_spec"] or kernel, mode=description["mode"],
                    n_inducing=int(est["n_inducing"]), max_train_points=est["max_train_points"],
                    selection=est["selection"], seed=int(est["seed"]),
                    include_noise=bool(est["include_noise"]), hyper=est["hyper"],
                    constant_cap=est["constant_cap"])
        model._check_params()
        model.kernel_ = kernel
        model.theta_ = arrays["theta"]
        model.noise_var_ = float(description["noise_var"])
        model.envelope_ = check_envelope(description["training_envelope"])  # None: no range checks
        model.noise_calibration_ = description["noise_calibration"]  # None: no held-out calibration
        # None: no model-discrepancy term in the band (model.discrepancy); absent in older bundles
        model.band_discrepancy_ = check_discrepancy(description.get("band_discrepancy"))
        # None: ML-II's hyperparameters as they are (training.hyper_refine); absent in older bundles
        model.hyper_refinement_ = description.get("hyper_refinement")
        model.noise_var_ml2_ = float(model.noise_calibration_["noise_var_ml2"]) if model.noise_calibration_ \
            else model.noise_var_
        model.nlml_ = float("nan") if description["nlml"] is None else float(description["nlml"])
        model.n_train_ = int(description["n_train"])
        # the training regressor rows (a bundle manifest's training block), which partial_fit's row share reads
        n_rows = (description.get("training") or {}).get("n_rows")
        model.n_rows_ = int(n_rows) if is_int(n_rows, 1, None) else None
        model.x_scaler_ = Standardizer.from_arrays(arrays["x_mean"], arrays["x_scale"])
        model.y_scaler_ = Standardizer.from_arrays(arrays["y_mean"], arrays["y_scale"])
        post = {k[len("posterior_"):]: v for k, v in arrays.items() if k.startswith("posterior_")}
        if description["mode"] == "exact":
            model.posterior_ = ExactPosterior.from_arrays(kernel, model.noise_var_, post)
        elif description["mode"] == "sparse":
            model.posterior_ = SparsePosterior.from_arrays(kernel, model.noise_var_, post)
        else:
            raise ValueError(f"mode {description['mode']!r} unknown")
        return model

    def __repr__(self) -> str:
        return f"GPNARX(ny={self.ny}, nu={self.nu}, kernel={self.kernel!r}, mode={self.mode!r})"


__all__ = ["GPNARX", "RecordError", "narx_regressors"]
