"""GP-NARX with several inputs and outputs: one GP per output over the shared regressor of eq. (3) for every channel.

``MIMOGPNARX`` is composed of the single-output pieces: the regressors of every input's and every output's lags
(``regressors.mimo_regressors``), one ``Standardizer`` of the shared regressor and one per output, and per output
the row selection, ML-II (eq. 13, ``ml2.fit_ml2``) and the posterior (eqs. 8-9, ``gp.ExactPosterior`` or
``gp.SparsePosterior``) that ``GPNARX.fit`` runs, with each output's own hyperparameters. With several outputs each
GP is fitted with BLAS at one thread, on ``n_jobs`` joblib threads at once: on the shared 2-core machine at load 7
the three ML-IIs of studies/mimo_chain.py's quick model took 38-42 s with OpenBLAS's own two threads, 1.6 s in turn
at one thread and 1.8 s on two joblib threads (the limit, not the parallelism, is the gain there; on idle cores the
threads run two outputs at once). The free run feeds every output back together (``freerun.mimo``: linearised with
the joint covariance across outputs and lags, or Monte Carlo drawing all outputs at each step). With one input and
one output every number is ``GPNARX``'s.

The held-out noise calibration (``fit(heldout=...)``) and the band's discrepancy term (``calibrate_band``) are
``GPNARX``'s rules applied to each output channel. Not built yet for several outputs: streams, the JAX backend, lags
per channel group, and the front ends' answers per channel (HTTP, CLI, batch).
"""
from __future__ import annotations

import copy
import time

import numpy as np

from gpnarx.checks import is_int

from .discrepancy import check_discrepancy
from .envelope import DIVERGENCE_FACTOR
from .estimator import check_gp_params
from .freerun import RunSpec
from .freerun.mimo import MIMOPredictor, check_inputs, run_mimo
from .gp import ExactPosterior, SparsePosterior, choose_inducing
from .kernels import DEFAULT_CONSTANT_CAP, Kernel, kernel_from_dict, make_kernel
from .linalg import two_cpus
from .ml2 import default_warm_start_subset, fit_ml2
from .params import ParamsMixin
from .record import Channel, Record
from .regressors import first_index, stack_mimo_regressors
from .scaling import Standardizer
from .selection import select_rows

MAX_PATHS = 65536


def _as_channel_pairs(records):
    """(pairs of (u (n, n_in), y (n, n_out)), input channels, output channels) from Records or (u, y) pairs."""
    if isinstance(records, Record) or (isinstance(records, tuple) and len(records) == 2
                                        and not isinstance(records[0], (Record, tuple))):
        records = [records]
    if not isinstance(records, (list, tuple)) or len(records) == 0:
        raise ValueError("records must be a non-empty list of Record or (u, y) pairs")
    pairs, cin, cout = [], None, None
    for k, r in enumerate(records):
        if not isinstance(r, Record):
            try:
                u, y = r
            except (TypeError, ValueError):
                raise ValueError(f"records[{k}] must be a Record or a (u, y) pair") from None
            r = Record(u, y, 1.0, name=f"records[{k}]")
        if r.y is None:
            raise ValueError(f"records[{k}] ({r.name}) has no output y; training needs u and y")
        ins, outs = r.input_channels(), r.output_channels()
        if cin is None:
            cin, cout = ins, outs
        elif [c.name for c in ins] != [c.name for c in cin] or [c.name for c in outs] != [c.name for c in cout]:
            raise ValueError(f"records[{k}] ({r.name}) has channels {[c.name for c in ins]} -> "
                             f"{[c.name for c in outs]}; records[0] has {[c.name for c in cin]} -> "
                             f"{[c.name for c in cout]}: every record needs the same channels in the same order")
        pairs.append((r.inputs_2d(), r.outputs_2d()))
    return pairs, cin, cout


class _OutputGP:
    """One output's fitted GP: kernel, log-hyperparameters (kernel's, then log sigma_y^2), NLML, sigma_y^2
    (standardised), the posterior, the output's Standardizer, the ML-II rows and its divergence limit [output
    units]."""

    def __init__(self, kernel_, theta_, nlml_, noise_var_, posterior_, y_scaler_, n_train_, y_peak_):
        self.kernel_, self.theta_, self.nlml_ = kernel_, theta_, nlml_
        self.noise_var_, self.posterior_, self.y_scaler_ = noise_var_, posterior_, y_scaler_
        self.n_train_, self.y_peak_ = n_train_, y_peak_


class MIMOGPNARX(ParamsMixin):
    """GP-NARX with several inputs and outputs (see the module docstring); a scikit-learn style estimator.

    Parameters are ``GPNARX``'s (``ny``, ``nu`` [samples] shared by every channel; ``kernel``, ``mode``,
    ``n_inducing``, ``max_train_points``, ``selection``, ``n_restarts``, ``seed``, ``include_noise``,
    ``sparse_max_rows``, ``hyper``, ``constant_cap``), each output's GP fitted with them, and ``n_jobs``: outputs
    fitted at once (None: two where the process may use two CPUs and there are several outputs; 1: in turn).

    Attributes: ``outputs_`` (one ``_OutputGP`` per output), ``x_scaler_``, ``input_channels_`` and
    ``output_channels_`` (``record.Channel``: name and unit, in column order), ``n_rows_``, ``fit_seconds_``.

    Examples
    --------
    >>> import numpy as np
    >>> from gpnarx.model.mimo import MIMOGPNARX
    >>> u = np.random.default_rng(0).normal(size=300)
    >>> y1 = np.convolve(u, [0.5, 0.3])[:300]
    >>> y = np.column_stack([y1, np.convolve(y1, [0.2, 0.1])[:300]])
    >>> m = MIMOGPNARX(ny=2, nu=2, max_train_points=150, n_restarts=0).fit([(u, y)])
    >>> m.simulate(u[:50], method="linear").mean.shape
    (50, 2)
    """

    def __init__(self, *, ny: int = 2, nu: int = 2, kernel: Kernel | str = "matern32+cubic", mode: str = "exact",
                 n_inducing: int = 256, max_train_points: int | None = 2000, selection: str = "stride",
                 n_restarts: int = 2, seed: int = 0, include_noise: bool = True, sparse_max_rows: int | None = 50000,
                 hyper: str = "subset", constant_cap: float | None = DEFAULT_CONSTANT_CAP, n_jobs: int | None = None):
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
        self.n_jobs = n_jobs

    def _check_params(self) -> None:
        check_gp_params(self)
        if self.n_jobs is not None and not is_int(self.n_jobs, 1, 64):
            raise ValueError(f"n_jobs must be None or an integer between 1 and 64, got {self.n_jobs!r}")

    # ------------------------------------------------------------------------------------------
    def fit(self, records, theta=None, progress=None, heldout=None) -> "MIMOGPNARX":
        """Learn the standardisations and, per output, hyperparameters (ML-II, eq. 13) and the posterior.

        records: Record objects (u (n,) or (n, n_inputs), y (n,) or (n, n_outputs), the same channels in every
            record) or (u, y) pairs; each longer than max(ny, nu - 1) + 1 samples. A Record's
            ``meta["row_weight"]`` weighs its share of each output's ML-II rows, as ``GPNARX.fit``.
        theta: optional fixed log-hyperparameters, one array per output (kernel's, then log sigma_y^2).
        progress: optional callable taking one line of text.
        heldout: optional records NOT in ``records`` (the same channels): each output's sigma_y^2 is raised to the
            held-out maximum-likelihood value of its one-step residuals (``model.heldout_noise``, never below
            ML-II's) and its posterior rebuilt, as ``GPNARX.fit(heldout=...)`` does for one output; each output's
            ``noise_calibration_`` records it.
        """
        from .estimator import _row_weights  # the single-output estimator's rule, shared

        self._check_params()
        say = progress or (lambda line: None)
        t0 = time.perf_counter()
        pairs, cin, cout = _as_channel_pairs(records)
        weights = _row_weights(records)
        need = first_index(self.ny, self.nu) + 2
        for k, (u, _y) in enumerate(pairs):
            if u.shape[0] < need:
                raise ValueError(f"records[{k}] has {u.shape[0]} samples; ny={self.ny}, nu={self.nu} need at least "
                                 f"{need}")
        X, Y, rec_idx = stack_mimo_regressors(pairs, self.ny, self.nu)
        no = Y.shape[1]
        held = None
        if heldout is not None:  # checked before ML-II, so a bad held-out record fails fast
            try:
                hpairs, hin, hout = _as_channel_pairs(heldout)
            except ValueError as exc:
                raise ValueError(f"heldout: {exc}") from None
            if [c.name for c in hin] != [c.name for c in cin] or [c.name for c in hout] != [c.name for c in cout]:
                raise ValueError("heldout: the held-out records need the training records' channels")
            held = stack_mimo_regressors(hpairs, self.ny, self.nu)[:2]
        if theta is not None and len(theta) != no:
            raise ValueError(f"theta must hold one array per output ({no}), got {len(theta)}")
        self.input_channels_, self.output_channels_ = list(cin), list(cout)
        self.x_scaler_ = Standardizer().fit(X)
        Xs = self.x_scaler_.transform(X)
        say(f"regressors: {X.shape[0]} rows from {len(pairs)} record(s), {len(cin)} input(s), {no} output(s) "
            f"(ny={self.ny}, nu={self.nu}, {X.shape[1]} columns)")
        peaks = [max(float(np.max(np.abs(y[:, o]))) for _, y in pairs) for o in range(no)]

        Xh = None if held is None else self.x_scaler_.transform(held[0])

        def one(o: int) -> _OutputGP:
            return self._fit_output(Xs, Y[:, o], rec_idx, weights, None if theta is None else theta[o], peaks[o],
                                    None if held is None else (Xh, held[1][:, o]))

        jobs = self._jobs(no)
        if no > 1:  # one BLAS thread per output's fit, in turn or on joblib threads
            from threadpoolctl import threadpool_limits

            with threadpool_limits(limits=1, user_api="blas"):
                if jobs > 1:
                    from joblib import Parallel, delayed

                    self.outputs_ = Parallel(n_jobs=jobs, prefer="threads")(delayed(one)(o) for o in range(no))
                else:
                    self.outputs_ = [one(o) for o in range(no)]
        else:  # one output: GPNARX.fit's calls as it makes them
            self.outputs_ = [one(0)]
        for o, g in enumerate(self.outputs_):
            say(f"output {o} ({cout[o].name}): NLML {g.nlml_:.6g}, sigma_y^2 {g.noise_var_:.3g} (standardised)")
        self.band_discrepancy_ = None  # set by calibrate_band (model.discrepancy), one per output
        self.n_rows_ = int(X.shape[0])
        self.fit_seconds_ = time.perf_counter() - t0
        return self

    def _jobs(self, no: int) -> int:
        if self.n_jobs is not None:
            return min(int(self.n_jobs), no)
        return min(2, no) if two_cpus() else 1

    def _fit_output(self, Xs, y, rec_idx, weights, theta, y_peak, held=None) -> _OutputGP:
        """``GPNARX.fit``'s steps for one output on the shared standardised regressor (same calls, same order);
        held: (standardised held-out regressors, that output's held-out targets) for the noise calibration."""
        y_scaler = Standardizer().fit(y[:, None])
        Ys = (y - y_scaler.mean_[0]) / y_scaler.scale_[0]
        rows = select_rows(Ys, rec_idx, self.max_train_points, self.selection, self.seed, weights=weights)
        Xt, Yt = Xs[rows], Ys[rows]
        if isinstance(self.kernel, str):
            kernel = make_kernel(self.kernel)
        else:
            kernel = copy.deepcopy(self.kernel).for_posterior(None)
        if theta is None:
            sub = default_warm_start_subset(Xt.shape[0])
            res = fit_ml2(kernel, Xt, Yt, n_restarts=int(self.n_restarts), seed=int(self.seed),
                          warm_start_subset=sub, hold_redundant=sub is not None)
            th, nlml = res.theta, res.nlml
        else:
            th = np.asarray(theta, dtype=float)
            kernel.set_theta(th[:-1])
            nlml = float("nan")
        noise_var = float(np.exp(th[-1]))
        var_kernel = kernel.for_posterior(None if self.constant_cap is None else float(self.constant_cap))
        if self.mode == "exact":
            def build(nv):
                return ExactPosterior.fit(kernel, nv, Xt, Yt, var_kernel=var_kernel)
        else:
            all_rows = select_rows(Ys, rec_idx, self.sparse_max_rows, "stride", self.seed, weights=weights)
            Z = choose_inducing(Xs[all_rows], int(self.n_inducing), self.seed)
            if self.hyper == "vfe" and theta is None:
                from .vfe import fit_vfe

                res = fit_vfe(kernel, Xs[all_rows], Ys[all_rows], Z, theta0=th)
                th, nlml = res.theta, res.nlml
                noise_var = float(np.exp(th[-1]))

            def build(nv):
                return SparsePosterior.fit(kernel, nv, Xs[all_rows], Ys[all_rows], Z, var_kernel=var_kernel)
        post = build(noise_var)
        th = np.asarray(th, dtype=float)
        calibration = None
        if held is not None:  # GPNARX._calibrate_noise's rule for this output
            from .estimator import _predict_rows
            from .heldout_noise import heldout_noise_var

            mu, var = _predict_rows(post, held[0])
            resid = (held[1] - y_scaler.mean_[0]) / y_scaler.scale_[0] - mu
            s2 = heldout_noise_var(resid, var, floor=noise_var)
            calibration = {"method": "heldout_ml", "n_residuals": int(resid.size), "noise_var_ml2": noise_var,
                           "noise_var": s2, "residual_var": float(np.mean(resid * resid)),
                           "latent_var_mean": float(np.mean(var))}
            if s2 > noise_var:
                noise_var = s2
                th = np.concatenate([th[:-1], [np.log(s2)]])
                post = build(s2)
        g = _OutputGP(kernel, th, float(nlml), noise_var, post, y_scaler, int(Xt.shape[0]), float(y_peak))
        g.noise_calibration_ = calibration
        return g

    # ------------------------------------------------------------------------------------------
    def _check_fitted(self) -> None:
        if not hasattr(self, "outputs_"):
            raise RuntimeError("this MIMOGPNARX is not fitted yet; call fit(records) first")

    @property
    def n_inputs_(self) -> int:
        return len(self.input_channels_)

    @property
    def n_outputs_(self) -> int:
        return len(self.outputs_)

    @property
    def n_features_(self) -> int:
        return self.n_outputs_ * self.ny + self.n_inputs_ * self.nu

    def predict_one_step(self, records, return_std: bool = True):
        """One-step-ahead mean and std (eqs. 8-9) of every output from measured lags, (rows, n_outputs) [output
        units], rows aligned with samples max(ny, nu - 1) onwards of each record; std with sigma_y^2 when
        ``include_noise``. Predicted in row blocks (``estimator._predict_rows``), so memory stays bounded."""
        self._check_fitted()
        pairs, _, _ = _as_channel_pairs(records)
        X, _, _ = stack_mimo_regressors(pairs, self.ny, self.nu)
        Xs = self.x_scaler_.transform(X)
        mean = np.empty((X.shape[0], self.n_outputs_))
        std = np.empty_like(mean)
        from .estimator import _predict_rows  # row blocks of bounded memory, as GPNARX.predict_one_step

        for o, g in enumerate(self.outputs_):
            mu, var = _predict_rows(g.posterior_, Xs, return_var=return_std)
            ys, ym = g.y_scaler_.scale_[0], g.y_scaler_.mean_[0]
            mean[:, o] = mu * ys + ym
            if return_std:
                std[:, o] = np.sqrt(var + (g.noise_var_ if self.include_noise else 0.0)) * ys
        return (mean, std) if return_std else mean

    def predictor(self) -> MIMOPredictor:
        """The fitted model as its free runs read it (``freerun.mimo.MIMOPredictor``)."""
        self._check_fitted()
        gs = self.outputs_
        return MIMOPredictor(tuple(g.posterior_ for g in gs), self.x_scaler_.mean_, self.x_scaler_.scale_,
                             np.array([g.y_scaler_.mean_[0] for g in gs]),
                             np.array([g.y_scaler_.scale_[0] for g in gs]),
                             self.ny, self.nu, self.n_inputs_,
                             np.array([DIVERGENCE_FACTOR * g.y_peak_ for g in gs]))

    def simulate(self, u, n_paths: int = 1024, seed: int | None = 0, y0=None, confidence: float = 0.99,
                 method: str = "linear", keep_paths: bool = False, progress=None):
        """Free run of input u ((n,) with one input, else (n, n_inputs) [input units]) feeding every output back
        (``freerun.mimo``). method: 'linear' (joint covariance across outputs and lags) or 'mc' (``n_paths``
        paths, seeded, every output drawn at each step). y0: the first ny measured outputs, (ny, n_outputs).
        Returns a ``FreeRun`` with mean, std, lower, upper (and the latent band) of shape (n, n_outputs)
        [output units]; ``channel_run`` takes one output's as a single-output ``FreeRun``. When the band was
        calibrated (``calibrate_band``), each output's std and bands include its discrepancy term."""
        from gpnarx.runtime import free_run_blas

        self._check_fitted()
        if method == "mc" and not is_int(n_paths, 1, MAX_PATHS):
            raise ValueError(f"n_paths must be an integer between 1 and {MAX_PATHS}, got {n_paths!r}")
        spec = RunSpec(method=method, n_paths=int(n_paths) if method == "mc" else 0, seed=seed,
                       confidence=confidence, y0=y0, include_noise=self.include_noise, keep_paths=keep_paths,
                       progress=progress)
        u = check_inputs(u, self.n_inputs_)
        with free_run_blas():
            return self._widened(run_mimo(self.predictor(), u, spec))

    def calibrate_band(self, records, window: int, method: str = "linear", n_paths: int = 256,
                       confidence: float = 0.99, kind: str = "centred", hold: int = 0, gp_scales=(1.0,)) -> list:
        """Each output's model-discrepancy term of the band (``model.discrepancy``), calibrated on held-out records:
        ``GPNARX.calibrate_band``'s rule for every output channel, on that channel's share of one free run of each
        record (every output fed back together). records: (name, u, y, start) with y (n, n_outputs) and start
        'rest' or 'measured'; window [samples], kind, hold [samples], gp_scales: as ``GPNARX.calibrate_band``.
        Sets and returns ``band_discrepancy_``, one ``calibrate_scale`` record per output (with its ``channel``)."""
        from .discrepancy import calibrate_scale

        self._check_fitted()
        for name, _u, _y, start in records:
            if start not in ("rest", "measured"):
                raise ValueError(f"records[{name!r}].start must be 'rest' or 'measured', got {start!r}")
        self.band_discrepancy_ = None  # the calibration runs are predicted without the term
        runs = []
        for name, u, y, start in records:
            Y = np.asarray(y, dtype=float)
            Y = Y[:, None] if Y.ndim == 1 else Y
            y0 = Y[: self.ny] if start == "measured" else None
            run = self.simulate(u, n_paths=n_paths, seed=0, y0=y0, confidence=confidence, method=method)
            runs.append((name, Y, run, self.ny if start == "measured" else 0))
        per = []
        for o, ch in enumerate(self.output_channels_):
            d = calibrate_scale([(name, Y[:, o], self.channel_run(run, o), skip) for name, Y, run, skip in runs],
                                int(window), kind=kind, hold=int(hold), gp_scales=gp_scales)
            per.append({**d, "calibration_method": method, "records": [name for name, *_ in records],
                        "channel": ch.name})
        self.band_discrepancy_ = per
        return per

    def _widened(self, run):
        """``run`` with each output's band discrepancy term (``band_discrepancy_``), as ``GPNARX.simulate`` adds
        its one (``discrepancy.widen_chunk`` on each channel's share)."""
        from dataclasses import replace

        from .discrepancy import widen_chunk

        disc = getattr(self, "band_discrepancy_", None)
        if not disc:
            return run
        cols = {k: np.array(getattr(run, k), copy=True) for k in ("std", "lower", "upper", "latent_lower",
                                                                  "latent_upper") if getattr(run, k) is not None}
        for o, d in enumerate(disc):
            out, _, _ = widen_chunk(self.channel_run(run, o), d)
            for k in cols:
                cols[k][:, o] = getattr(out, k)
        return replace(run, **cols)

    @staticmethod
    def channel_run(run, o: int):
        """Output ``o``'s share of a run of ``simulate`` as a single-output ``FreeRun`` (1-D arrays)."""
        from .freerun import FreeRun

        def col(a):
            return None if a is None else np.ascontiguousarray(a[:, o])

        return FreeRun(col(run.mean), col(run.std), col(run.lower), col(run.upper), run.confidence, run.n_paths,
                       run.method, run.seconds, run.path_steps, None if run.paths is None else run.paths[..., o],
                       run.diverged_paths, latent_lower=col(run.latent_lower), latent_upper=col(run.latent_upper))

    # ------------------------------------------------------------------------------------------
    # The fitted model as plain values (gpnarx.storage.bundle lays them out in files)
    def fitted_arrays(self) -> dict:
        """Every array needed to predict: the shared ``x_mean``, ``x_scale``, and per output o ``out{o}_y_mean``,
        ``out{o}_y_scale``, ``out{o}_theta`` and ``out{o}_posterior_*``."""
        self._check_fitted()
        arrays = {"x_mean": self.x_scaler_.mean_, "x_scale": self.x_scaler_.scale_}
        for o, g in enumerate(self.outputs_):
            arrays[f"out{o}_y_mean"] = g.y_scaler_.mean_
            arrays[f"out{o}_y_scale"] = g.y_scaler_.scale_
            arrays[f"out{o}_theta"] = g.theta_
            for k, v in g.posterior_.arrays().items():
                arrays[f"out{o}_posterior_{k}"] = v
        return arrays

    def fitted_description(self) -> dict:
        """The fitted model's values other than its arrays, JSON-able. ``model_class`` "mimo"; ``channels``: the
        inputs' and outputs' names and units in column order; ``outputs``: per output its kernel (the posterior's),
        hyperparameters, noise variance, NLML, ML-II rows and training peak |y|. ``kernel``, ``noise_var`` and
        ``hyperparameters`` at the top are output 0's (the keys every bundle manifest holds)."""
        self._check_fitted()
        outs = [{"name": c.name, "unit": c.unit, "kernel": g.posterior_.kernel.to_dict(),
                 "hyperparameters": {**g.kernel_.params, "noise_var": g.noise_var_}, "noise_var": g.noise_var_,
                 "nlml": None if not np.isfinite(g.nlml_) else g.nlml_, "n_train": g.n_train_, "y_peak": g.y_peak_,
                 "noise_calibration": getattr(g, "noise_calibration_", None)}
                for c, g in zip(self.output_channels_, self.outputs_)]
        return {
            "model_class": "mimo",
            "lags": {"ny": self.ny, "nu": self.nu},
            "mode": self.outputs_[0].posterior_.kind,
            "kernel": outs[0]["kernel"],
            "hyperparameters": outs[0]["hyperparameters"],
            "noise_var": outs[0]["noise_var"],
            "channels": {"inputs": [c.to_dict() for c in self.input_channels_],
                         "outputs": [c.to_dict() for c in self.output_channels_]},
            "outputs": outs,
            "nlml": None,
            "n_train": int(sum(g.n_train_ for g in self.outputs_)),
            "noise_calibration": outs[0]["noise_calibration"],
            "band_discrepancy": getattr(self, "band_discrepancy_", None),
            "training_envelope": None,
            "estimator": {"include_noise": bool(self.include_noise), "n_inducing": int(self.n_inducing),
                          "max_train_points": self.max_train_points, "selection": self.selection,
                          "seed": int(self.seed), "hyper": self.hyper, "constant_cap": self.constant_cap,
                          "kernel_spec": self.kernel if isinstance(self.kernel, str) else None},
        }

    @classmethod
    def from_fitted(cls, description: dict, arrays: dict) -> "MIMOGPNARX":
        """The fitted model of ``fitted_description()`` and ``fitted_arrays()`` (no refit); ValueError/KeyError
        when they are inconsistent."""
        if description.get("model_class") != "mimo":
            raise ValueError("not a MIMOGPNARX description (model_class 'mimo')")
        est = description["estimator"]
        model = cls(ny=int(description["lags"]["ny"]), nu=int(description["lags"]["nu"]),
                    kernel=est["kernel_spec"] or kernel_from_dict(description["kernel"]), mode=description["mode"],
                    n_inducing=int(est["n_inducing"]), max_train_points=est["max_train_points"],
                    selection=est["selection"], seed=int(est["seed"]), include_noise=bool(est["include_noise"]),
                    hyper=est["hyper"], constant_cap=est["constant_cap"])
        model._check_params()
        ch = description["channels"]
        model.input_channels_ = [Channel(str(c["name"]), str(c.get("unit", ""))) for c in ch["inputs"]]
        model.output_channels_ = [Channel(str(c["name"]), str(c.get("unit", ""))) for c in ch["outputs"]]
        if len(description["outputs"]) != len(model.output_channels_):
            raise ValueError("outputs and channels.outputs differ in length")
        model.x_scaler_ = Standardizer.from_arrays(arrays["x_mean"], arrays["x_scale"])
        gps = []
        for o, d in enumerate(description["outputs"]):
            kernel = kernel_from_dict(d["kernel"])
            noise_var = float(d["noise_var"])
            pre = f"out{o}_posterior_"
            post = {k[len(pre):]: v for k, v in arrays.items() if k.startswith(pre)}
            if description["mode"] == "exact":
                posterior = ExactPosterior.from_arrays(kernel, noise_var, post)
            elif description["mode"] == "sparse":
                posterior = SparsePosterior.from_arrays(kernel, noise_var, post)
            else:
                raise ValueError(f"mode {description['mode']!r} unknown")
            gps.append(_OutputGP(kernel, arrays[f"out{o}_theta"],
                                 float("nan") if d["nlml"] is None else float(d["nlml"]), noise_var, posterior,
                                 Standardizer.from_arrays(arrays[f"out{o}_y_mean"], arrays[f"out{o}_y_scale"]),
                                 int(d["n_train"]), float(d["y_peak"])))
        for g, d in zip(gps, description["outputs"]):
            g.noise_calibration_ = d.get("noise_calibration")
        model.outputs_ = gps
        disc = description.get("band_discrepancy")
        if disc is not None:
            if not isinstance(disc, list) or len(disc) != len(gps):
                raise ValueError("band_discrepancy must hold one term per output")
            disc = [check_discrepancy(d) for d in disc]
        model.band_discrepancy_ = disc
        D = model.n_features_
        if model.x_scaler_.mean_.shape != (D,) or any(g.posterior_.points.shape[1] != D for g in gps):
            raise ValueError(f"array shapes do not match lags ny={model.ny}, nu={model.nu} and "
                             f"{model.n_outputs_} output(s), {model.n_inputs_} input(s)")
        model.n_rows_ = 0
        model.fit_seconds_ = float("nan")
        return model

    def __repr__(self) -> str:
        return f"MIMOGPNARX(ny={self.ny}, nu={self.nu}, kernel={self.kernel!r}, mode={self.mode!r})"


__all__ = ["MIMOGPNARX"]
