"""The training pipeline of a config with several channels (``[system] inputs`` / ``outputs``, issue 52).

``train_mimo(config, registry)`` fits a ``model.mimo.MIMOGPNARX`` (one GP per output over the shared regressor,
the config's ``[model]`` settings) on the ``train`` records, runs the free run of every ``lags``, ``verify``,
``validate``, ``healthy`` and ``damaged`` record (the config's ``[predict]`` method, paths and confidence; a
record whose ``meta.initial`` is "measured" starts from its first ny measured outputs) and scores it per output
channel (fit % eq. 14, RMSE, 99 % coverage, band width), and beside it two linear ARX baselines of the same lags
and training records: "linear ARX", one over every channel's lags (``MIMOLinearARX``, every output fed back), and,
with one input, "linear ARX per channel", each output's own ``baselines.LinearARX`` on u and that output's lags. It
writes a bundle whose manifest records the channels (names, units, their order: ``channels``), each output's
GP, and ``training.records[NAME].channels[CHANNEL]`` the metrics; with ``report``, one figure per scored record
(every channel, measured and predicted with the band) in the bundle's ``report/`` folder.

The config's ``noise_calibration = "lags"`` and ``band_calibration = "lags"`` apply each output channel its own
held-out noise variance and band discrepancy term (``MIMOGPNARX.fit(heldout=)``, ``calibrate_band``). Not built yet
for several channels: the novelty calibration, the HTML report and the Dask runner (the single-output
``pipeline.train`` has them).
"""
from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np

from gpnarx.model.metrics import summary
from gpnarx.model.mimo import MIMOGPNARX
from gpnarx.model.record import Record
from gpnarx.model.regressors import stack_mimo_regressors
from gpnarx.storage.bundle import save_bundle
from gpnarx.storage.jsonsafe import to_json_safe
from gpnarx.training.baselines import LinearARX
from gpnarx.training.config import ConfigError, DatasetConfig, load_config
from gpnarx.training.prepare import shorten

__all__ = ["EVAL_ROLES", "MIMOLinearARX", "mimo_from_config", "train_mimo"]

EVAL_ROLES = ("lags", "verify", "validate", "healthy", "damaged")


class MIMOLinearARX:
    """The linear ARX baseline for several channels: each output y_o,i = c_o . x_i, x_i the regressor of every
    output's and input's lags (``regressors.mimo_regressors``), by least squares; free-run with every output fed
    back. One input and one output: ``baselines.LinearARX``."""

    name = "linear ARX"

    def __init__(self, ny: int, nu: int):
        self.ny, self.nu = int(ny), int(nu)

    def fit(self, records) -> "MIMOLinearARX":
        X, Y, _ = stack_mimo_regressors([(r.inputs_2d(), r.outputs_2d()) for r in records], self.ny, self.nu)
        self.coef_ = np.linalg.lstsq(X, Y, rcond=None)[0]  # (columns, n_outputs)
        return self

    def simulate(self, u, y0=None) -> np.ndarray:
        """Free-run outputs (n, n_outputs) for inputs u (n, n_inputs) [input units], from rest or from y0 (the
        first ny outputs, (ny, n_outputs))."""
        ny, nu = self.ny, self.nu
        U = np.asarray(u, float)
        U = U[:, None] if U.ndim == 1 else U
        n, ni = U.shape
        no = self.coef_.shape[1]
        A = no * ny
        Cy, Cu = self.coef_[:A], self.coef_[A:]
        upad = np.vstack([np.zeros((nu - 1, ni)), U])
        lagged = np.hstack([np.stack([upad[nu - 1 - j: nu - 1 - j + n, k] for j in range(nu)], axis=1)
                            for k in range(ni)])
        uterm = lagged @ Cu  # (n, no)
        y = np.zeros((n + ny, no))
        i0 = 0
        if y0 is not None:
            i0 = ny
            y[ny: 2 * ny] = np.asarray(y0, float).reshape(-1, no)[:ny]
        for i in range(i0, n):  # regressor order: output o's lags 1..ny, then the next output's
            lags = y[i: ny + i][::-1].T.ravel()
            y[ny + i] = lags @ Cy + uterm[i]
        return y[ny:]


def mimo_from_config(cfg: DatasetConfig, ny: int | None = None, nu: int | None = None, **overrides) -> MIMOGPNARX:
    """An unfitted MIMOGPNARX with the config's [model] settings (lags overridable; ``overrides``: [model] keys
    such as ``mode`` or ``max_train_points``, None values and other keys ignored, as ``model_from_config``)."""
    m = dict(cfg.model)
    m.update({k: v for k, v in overrides.items() if v is not None})
    ny = ny if ny is not None else m.get("ny")
    nu = nu if nu is not None else m.get("nu")
    if ny is None or nu is None:
        raise ConfigError(f"{cfg.path}: [model] ny and nu are required for a model with several channels")
    return MIMOGPNARX(ny=int(ny), nu=int(nu), kernel=m.get("kernel", "matern32+cubic"), mode=m.get("mode", "exact"),
                      n_inducing=int(m.get("inducing", 256)), max_train_points=m.get("max_train_points", 2000),
                      selection=m.get("selection", "stride"), n_restarts=int(m.get("restarts", 2)),
                      seed=int(m.get("seed", 0)), hyper=m.get("hyper", "subset"))


def mimo_lag_cell(cfg: DatasetConfig, train: list, lag_recs: list, ny: int, nu: int, settings: dict) -> dict:
    """One cell of the lag surface for a config with several channels (``training.lags.lag_cell_data`` hands it
    over): the MIMOGPNARX at (ny, nu) fitted on ``train``, the linearised free-run mean of every ``lags`` record
    scored per output channel (eq. 14); a record's fit is its worst channel's (``fits``), each channel's in
    ``channel_fits``; the cell's ``fit`` is their mean over the records, the single-output rule."""
    import time

    from gpnarx.model.metrics import fit_percent

    t0 = time.perf_counter()
    try:
        model = mimo_from_config(cfg, ny, nu, **settings).fit(train)
        fits, per = {}, {}
        for rec in lag_recs:
            run = model.simulate(rec.u, method="linear", y0=_start(rec, ny))
            ref = rec.meta.get("clean_y", rec.y) if settings.get("score_clean") else rec.y
            ref = ref[:, None] if np.ndim(ref) == 1 else ref
            f = [fit_percent(ref[:, o], run.mean[:, o]) for o in range(ref.shape[1])]
            per[rec.name] = {c.name: (float(v) if np.isfinite(v) else -1e3)
                             for c, v in zip(model.output_channels_, f)}
            fits[rec.name] = min(per[rec.name].values())
        fit, err = float(np.mean(list(fits.values()))), None
    except (ValueError, np.linalg.LinAlgError) as exc:
        fit, fits, per, err = float("nan"), {}, {}, str(exc)
    return {"ny": int(ny), "nu": int(nu), "fit": fit, "fits": fits, "channel_fits": per,
            "seconds": time.perf_counter() - t0, "error": err}


def calibrate_band_from_config(model: MIMOGPNARX, cfg: DatasetConfig, held: list, log=None) -> list:
    """Each output's band discrepancy term from the held-out 'lags' records with the config's band settings
    (``band_window`` [s], ``band_window_kind``, ``band_hold`` [s], ``band_gp_scale``), each record started by its
    own rule: ``pipeline.calibrate_band_from_config`` for several channels."""
    from gpnarx.model.discrepancy import GP_SCALE_GRID

    window = max(1, int(round(float(cfg.model.get("band_window", 0.25)) * cfg.fs)))
    hold = max(0, int(round(float(cfg.model.get("band_hold", 0.0)) * cfg.fs)))
    gp_scales = GP_SCALE_GRID if cfg.model.get("band_gp_scale", "fixed") == "calibrated" else (1.0,)
    starts = [(r.name, r.u, r.outputs_2d(), "measured" if r.meta.get("initial") == "measured" else "rest")
              for r in held]
    per = model.calibrate_band(starts, window, confidence=float(cfg.predict.get("confidence", 0.99)),
                               kind=str(cfg.model.get("band_window_kind", "centred")), hold=hold, gp_scales=gp_scales)
    for d in per:
        (log or (lambda m: None))(
            f"  band of {d['channel']}: propagated x {d['gp_scale']:.3g}, discrepancy scale {d['scale']:.4g}; worst "
            f"'lags' coverage {100 * min(d['coverage_before'].values()):.1f} % -> "
            f"{100 * min(d['coverage_after'].values()):.1f} %" + ("" if d["reached"] else " (target not reached)"))
    return per


def _start(rec: Record, ny: int):
    if rec.meta.get("initial") == "measured" and rec.y is not None:
        return rec.outputs_2d()[:ny]
    return None


def _score(rec: Record, mean, lower, upper, channels) -> dict:
    Y = rec.outputs_2d()
    out = {}
    for o, ch in enumerate(channels):
        out[ch.name] = summary(Y[:, o], mean[:, o], None if lower is None else lower[:, o],
                               None if upper is None else upper[:, o])
    return out


def train_mimo(config, registry, name: str | None = None, version: str | None = None, *, mc_paths: int | None = None,
               ny: int | None = None, nu: int | None = None, report: bool = True, log=None,
               max_seconds: float | None = None, report_method: str | None = None,
               model_overrides: dict | None = None) -> dict:
    """Train a model with several channels from a dataset config and write its bundle (see the module
    docstring). Returns name, version, path, the per-channel metrics and the fitted model. ``model_overrides``:
    [model] settings to override (``gpnarx train --mode/--train-points``)."""
    cfg = config if isinstance(config, DatasetConfig) else load_config(config)
    log = log or (lambda msg: None)
    t0 = time.perf_counter()
    method = report_method or cfg.predict.get("method", "mc")
    n_paths = int(mc_paths or cfg.predict.get("mc_paths", 1024))
    confidence = float(cfg.predict.get("confidence", 0.99))

    def records(role):
        recs = cfg.records_for(role)
        return [shorten(r, max_seconds) for r in recs] if max_seconds else recs

    train_recs = records("train")
    model = mimo_from_config(cfg, ny, nu, **(model_overrides or {}))
    log(f"training {cfg.name}: ny={model.ny} nu={model.nu}, {train_recs[0].n_inputs} input(s), "
        f"{train_recs[0].n_outputs} output(s), on {len(train_recs)} record(s)")
    model.fit(train_recs, progress=log,
              heldout=records("lags") if cfg.model.get("noise_calibration", "none") == "lags" else None)
    for ch, g in zip(model.output_channels_, model.outputs_):
        nc = getattr(g, "noise_calibration_", None)
        if nc is not None:
            log(f"  {ch.name}: sigma_y^2 {nc['noise_var_ml2']:.3g} (ML-II) -> {nc['noise_var']:.3g} (held-out, "
                f"standardised)")
    if cfg.model.get("band_calibration", "none") == "lags":
        calibrate_band_from_config(model, cfg, records("lags"), log)
    arx = MIMOLinearARX(model.ny, model.nu).fit(train_recs)
    # with one input, also each output channel's own linear ARX (u and that channel's lags: baselines.LinearARX)
    own = None
    if train_recs[0].n_inputs == 1:
        own = [LinearARX(model.ny, model.nu).fit([Record(r.u, r.outputs_2d()[:, o], r.fs) for r in train_recs])
               for o in range(train_recs[0].n_outputs)]
    chans = model.output_channels_
    scored, evals = {}, []
    todo = [(role, rec) for role in EVAL_ROLES for rec in records(role)]
    for k, (role, rec) in enumerate(todo):
        y0 = _start(rec, model.ny)
        run = model.simulate(rec.u, method=method, n_paths=n_paths, seed=k, confidence=confidence, y0=y0)
        entry = {"role": role, "method": run.method, "seconds": run.seconds, "diverged_paths": run.diverged_paths}
        if rec.y is not None:
            entry["channels"] = _score(rec, run.mean, run.lower, run.upper, chans)
            entry["baselines"] = {"linear ARX": _score(rec, arx.simulate(rec.u, y0), None, None, chans)}
            if own is not None:
                sims = np.column_stack([a.simulate(rec.u, None if y0 is None else y0[:, o]) for o, a in enumerate(own)])
                entry["baselines"]["linear ARX per channel"] = _score(rec, sims, None, None, chans)
            log(f"  {role:8s} {rec.name}: " + "; ".join(
                f"{c} fit {m['fit']:.1f} % (ARX {entry['baselines']['linear ARX'][c]['fit']:.1f} %) "
                f"cov {m['coverage']:.1f} %" for c, m in entry["channels"].items()))
        scored[rec.name] = entry
        evals.append((rec, run))
    metrics = {"fit_seconds": model.fit_seconds_, "n_rows": model.n_rows_,
               "n_train": [g.n_train_ for g in model.outputs_], "train_records": [r.name for r in train_recs],
               "records": scored, "mc_paths": n_paths, "method": method, "confidence": confidence,
               "channels": {"inputs": [c.to_dict() for c in model.input_channels_],
                            "outputs": [c.to_dict() for c in chans]}}
    units = {"u": _common([c.unit for c in model.input_channels_]), "y": _common([c.unit for c in chans])}
    with tempfile.TemporaryDirectory() as tmp:
        report_dir = None
        if report:
            report_dir = Path(tmp) / "report"
            write_figures(report_dir, cfg.name, evals, chans)
            (report_dir / "report.json").write_text(json.dumps(to_json_safe(metrics), indent=1, sort_keys=True))
        metrics["wall_seconds"] = time.perf_counter() - t0
        physics = dict(cfg.physics)
        physics.setdefault("output", cfg.system.get("output", "displacement"))
        path = save_bundle(model, registry, name or cfg.name, version, fs=cfg.fs, units=units, physics=physics,
                           novelty=None, training=to_json_safe(metrics), attach_dir=report_dir,
                           extra={"predict": {"method": cfg.predict.get("method", "mc"),
                                              "mc_paths": int(cfg.predict.get("mc_paths", 1024))}})
    log(f"bundle written to {path}")
    return {"name": name or cfg.name, "version": path.name, "path": str(path), "metrics": to_json_safe(metrics),
            "model": model}


def _common(units) -> str:
    return units[0] if len(set(units)) == 1 else ""


def write_figures(folder: Path, title: str, evals, channels) -> None:
    """One PNG per scored record: every output channel's measured and predicted output with the band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    for rec, run in evals:
        t = rec.t
        Y = rec.outputs_2d()
        fig, axes = plt.subplots(len(channels), 1, figsize=(10, 2.2 * len(channels)), sharex=True, squeeze=False)
        for o, (ax, ch) in enumerate(zip(axes[:, 0], channels)):
            ax.fill_between(t, run.lower[:, o], run.upper[:, o], color="tab:orange", alpha=0.3, lw=0,
                            label=f"{100 * run.confidence:g} % band")
            if Y is not None:
                ax.plot(t, Y[:, o], "k", lw=0.5, label="measured")
            ax.plot(t, run.mean[:, o], "r", lw=0.5, label=f"free run ({run.method})")
            ax.set_ylabel(f"{ch.name} [{ch.unit or '-'}]")
        axes[0, 0].legend(loc="upper right", fontsize=7, ncol=3)
        axes[-1, 0].set_xlabel("time [s]")
        fig.suptitle(f"{title}: {rec.name}")
        fig.tight_layout()
        fig.savefig(folder / f"{rec.name}.png", dpi=90)
        plt.close(fig)
