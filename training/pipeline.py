"""Offline training pipeline: config -> ML-II -> verification/validation -> novelty -> bundle + report.

``train(config, registry)`` runs five steps: ``fit`` (the GP-NARX with the config's lags and settings,
ML-II on the ``train`` records, and the config's noise and band calibrations), ``evaluate`` (Monte
Carlo or linearised free run of every ``lags``, ``verify``, ``validate``, ``healthy`` and ``damaged``
record, scored: fit % eq. 14, RMSE, 99% coverage, band width; the baselines beside them),
``calibrate_novelty`` (the threshold on the ``healthy`` records when present), ``write_report`` (PSD
peaks, loop areas, figures) and ``save`` (a versioned bundle with its report folder, atomically, into
``REGISTRY/NAME/VERSION``).
"""
from __future__ import annotations

import json
import tempfile
import time
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

from gpnarx._progress import progress_bar
from gpnarx.model.discrepancy import GP_SCALE_GRID
from gpnarx.model.estimator import GPNARX
from gpnarx.model.metrics import summary
from gpnarx.model.novelty import (
    RMS_METHOD,
    calibrate_threshold,
    judge,
    novelty_score,
    novelty_start,
    record_envelope,
)
from gpnarx.model.probe import probe_contract
from gpnarx.model.record import Record
from gpnarx.storage.bundle import save_bundle
from gpnarx.storage.jsonsafe import to_json_safe
from gpnarx.training.baselines import fit_baselines, score_baselines
from gpnarx.training.config import DatasetConfig, load_config
from gpnarx.training.distributed import TaskRunner
from gpnarx.training.hyper_refine import DEFAULT_TOLERANCE as REFINE_TOLERANCE
from gpnarx.training.hyper_refine import refine_lengthscales
from gpnarx.training.mimo_pipeline import train_mimo
from gpnarx.training.prepare import model_from_config, shorten

__all__ = ["EVAL_ROLES", "as_config", "basic_metrics", "calibrate_novelty", "evaluate", "evaluate_record", "fit",
           "model_from_config", "save", "score_records", "train", "training_metrics", "write_report"]

EVAL_ROLES = ("lags", "verify", "validate", "healthy", "damaged")


def as_config(config) -> DatasetConfig:
    return config if isinstance(config, DatasetConfig) else load_config(config)


def evaluate_record(model: GPNARX, rec: Record, role: str, n_paths: int, seed: int = 0, confidence: float = 0.99,
                    method: str = "mc", progress=None) -> dict:
    """Free-run prediction of one record and everything the report needs (arrays + metrics)."""
    # records measured in steady state (sines, periodic multisines) start from their first ny
    # measured outputs (meta initial = "measured"), and so do novelty records (healthy/damaged,
    # the rule of model.novelty.novelty_start); the others start from rest
    if role in ("healthy", "damaged") and rec.y is not None:
        y0 = novelty_start(rec.y, model.ny)
    else:
        y0 = rec.y[: model.ny] if rec.meta.get("initial") == "measured" and rec.y is not None else None
    run = model.simulate(rec.u, n_paths=n_paths, seed=seed, confidence=confidence, method=method, y0=y0,
                         progress=progress)
    out = {
        "name": rec.name, "role": role, "fs": rec.fs, "u": rec.u, "y": rec.y,
        "y_clean": rec.meta.get("clean_y"), "mean": run.mean, "lower": run.lower, "upper": run.upper,
        "std": run.std, "units": dict(rec.units), "seconds": run.seconds, "n_paths": run.n_paths,
        "method": run.method, "roles": rec.meta.get("roles"),
        # the latent band (no noise term): what the noise-free y_clean is scored against
        "latent_lower": run.latent_lower, "latent_upper": run.latent_upper,
    }
    sim = rec.meta.get("simulate") or {}
    if sim.get("excitation") == "sine" and sim.get("freq"):
        out["drive_freq"] = float(sim["freq"])
    elif rec.meta.get("drive_freq"):
        out["drive_freq"] = float(rec.meta["drive_freq"])
    return out


def basic_metrics(ev: dict) -> dict:
    res = {}
    if ev["y"] is not None:
        res.update(summary(ev["y"], ev["mean"], ev["lower"], ev["upper"]))
    if ev.get("y_clean") is not None:  # the noise-free output against the latent band (no sigma_y^2)
        clean = summary(ev["y_clean"], ev["mean"], ev.get("latent_lower"), ev.get("latent_upper"))
        res["fit_clean"] = clean["fit"]
        if "coverage" in clean:
            res["coverage_latent"] = clean["coverage"]
    return res


def score_records(evals: list[dict], method: str = RMS_METHOD) -> list[float]:
    """Novelty scores (model.novelty, by ``method``) of evaluated records (evaluate_record output)."""
    return [novelty_score(ev["y"], ev["mean"], ev["std"], method)["score"] for ev in evals]


def calibrate_band_from_config(model: GPNARX, cfg: DatasetConfig, held: list, log=None) -> dict:
    """The band's model-discrepancy term (model.discrepancy) from the held-out 'lags' records, each
    predicted (linearised) with its own start rule, as the report predicts it."""
    window = max(1, int(round(float(cfg.model.get("band_window", 0.25)) * cfg.fs)))
    starts = [(r.name, r.u, r.y, "measured" if r.meta.get("initial") == "measured" else "rest") for r in held]
    hold = max(0, int(round(float(cfg.model.get("band_hold", 0.0)) * cfg.fs)))
    gp_scales = GP_SCALE_GRID if cfg.model.get("band_gp_scale", "fixed") == "calibrated" else (1.0,)
    d = model.calibrate_band(starts, window, confidence=float(cfg.predict.get("confidence", 0.99)),
                             kind=str(cfg.model.get("band_window_kind", "centred")), hold=hold, gp_scales=gp_scales)
    worst = min(d["coverage_before"].values()), min(d["coverage_after"].values())
    log = log or (lambda msg: None)
    log(f"band calibrated on {len(held)} held-out 'lags' record(s): "
        + (f"propagated band x {d['gp_scale']:.3g}, " if len(gp_scales) > 1 else "")
        + f"discrepancy scale {d['scale']:.4g} of the "
        f"local amplitude ({window} samples, {d['window_kind']}"
        f"{f', held {hold} samples' if hold else ''}); worst coverage {100 * worst[0]:.1f} % -> "
        f"{100 * worst[1]:.1f} %"
        + ("" if d["reached"] else f" (target {100 * d['target']:.0f} % not reached)"))
    return d


class _Progress:
    """tqdm bar over Monte Carlo steps of several records (stderr; silent when disabled)."""

    def __init__(self, enabled: bool, total: int, desc: str):
        self.bar = None
        if enabled:
            self.bar = progress_bar(total=total, desc=desc, unit="step", leave=False, mininterval=0.5)
        self.base = 0

    def callback(self, n_total: int):
        def cb(done, n):
            if self.bar is not None:
                self.bar.n = self.base + done
                self.bar.refresh()
        return cb

    def advance(self, n):
        self.base += n

    def close(self):
        if self.bar is not None:
            self.bar.close()


def train(config, registry, name: str | None = None, version: str | None = None, *, progress: bool = False,
          mc_paths: int | None = None, ny: int | None = None, nu: int | None = None, report: bool = True,
          lag_surface: dict | None = None, baselines: dict | None = None, paper: dict | None = None,
          model_overrides: dict | None = None, log=None, max_seconds: float | None = None,
          extra_evals: list | None = None, report_method: str | None = None, scheduler=None) -> dict:
    """Train from a dataset config and write a bundle; returns name, version, path and metrics.

    The steps, in order: ``fit`` (ML-II and the config's noise and band calibrations), ``evaluate``
    (a free run of every scored record, its metrics and the baselines), ``calibrate_novelty`` (the
    threshold on the ``healthy`` records), ``write_report`` and ``save``.

    ``report_method`` ('mc' or 'linear') overrides the config's ``predict.method`` for the report's free
    runs only (the model written, and the bundle's default propagation, are the same); ``mc_paths``
    likewise overrides ``predict.mc_paths``. ``max_seconds`` [s] cuts every record to its first seconds.
    ``scheduler`` (a Dask scheduler address or ``distributed.Client``): the verification/validation
    free runs and the report's per-record metrics and figures run as tasks on that cluster, with
    the fitted model and the record arrays sent to the workers; the seeds, and so the bundle's
    metrics, are those of the local run. ML-II, the baselines and the novelty calibration stay here.

    A config with several input or output channels (``[system] inputs`` / ``outputs``) trains a model with
    several channels instead (``training.mimo_pipeline.train_mimo``).
    """
    cfg = as_config(config)
    if cfg.several_channels:
        given = (("lag_surface", lag_surface), ("baselines", baselines), ("paper", paper),
                 ("extra_evals", extra_evals), ("scheduler", scheduler))
        unbuilt = [k for k, v in given if v not in (None, "", {}, [])]
        if unbuilt:
            raise ValueError(f"{', '.join(unbuilt)}: not built yet for a config with several channels")
        return train_mimo(cfg, registry, name, version, mc_paths=mc_paths, ny=ny, nu=nu, report=report, log=log,
                          max_seconds=max_seconds, report_method=report_method, model_overrides=model_overrides)
    log = log or (lambda msg: None)
    t0 = time.perf_counter()
    with ExitStack() as stack:
        runner = None
        if scheduler not in (None, ""):
            runner = stack.enter_context(TaskRunner(scheduler))
            log(f"tasks on {runner.where}")
        plan = _Plan.of(cfg, mc_paths, report_method, max_seconds)
        train_recs = plan.records("train")
        model = fit(cfg, train_recs, plan.records, ny=ny, nu=nu, model_overrides=model_overrides, log=log)
        todo = [(role, rec) for role in EVAL_ROLES for rec in plan.records(role)]
        evals = evaluate(model, todo, plan, runner=runner, progress=progress, log=log)
        if baselines is None:
            baselines = score_against_baselines(train_recs, [rec for _, rec in todo], model.ny, model.nu, log)
        novelty = calibrate_novelty(cfg, evals, plan.n_paths)
        metrics = training_metrics(model, train_recs, evals, plan, baselines)
        physics = physics_of(cfg)
        with tempfile.TemporaryDirectory() as tmp:
            report_dir = None
            if report:
                report_dir = Path(tmp) / "report"
                write_report(report_dir, cfg, model, plan, evals + list(extra_evals or []), metrics, novelty,
                             physics=physics, lag_surface=lag_surface, baselines=baselines, paper=paper,
                             runner=runner)
            metrics["wall_seconds"] = time.perf_counter() - t0
            path = save(model, cfg, registry, name, version, physics=physics, novelty=novelty, metrics=metrics,
                        report_dir=report_dir)
    log(f"bundle written to {path}")
    return {"name": name or cfg.name, "version": path.name, "path": str(path),
            "metrics": to_json_safe(metrics), "evals": evals, "model": model,
            "novelty": to_json_safe(novelty)}


@dataclass(frozen=True)
class _Plan:
    """What a training run evaluates with: Monte Carlo paths, confidence, the report's propagation
    ('mc' or 'linear') and the record cut [s] (None: whole records)."""

    cfg: DatasetConfig
    n_paths: int
    confidence: float
    propagation: str
    max_seconds: float | None

    @classmethod
    def of(cls, cfg: DatasetConfig, mc_paths: int | None, report_method: str | None,
           max_seconds: float | None) -> _Plan:
        propagation = report_method or cfg.predict.get("method", "mc")
        if propagation not in ("mc", "linear"):
            raise ValueError(f"method must be 'mc' or 'linear', got {propagation!r}")
        return cls(cfg, int(mc_paths or cfg.predict.get("mc_paths", 1024)),
                   float(cfg.predict.get("confidence", 0.99)), propagation, max_seconds)

    def records(self, role: str) -> list[Record]:
        """The config's records of ``role``, each cut to its first ``max_seconds`` when set."""
        recs = self.cfg.records_for(role)
        return [shorten(r, self.max_seconds) for r in recs] if self.max_seconds else recs


def fit(cfg: DatasetConfig, train_recs: list[Record], records, *, ny: int | None = None, nu: int | None = None,
        model_overrides: dict | None = None, log=None) -> GPNARX:
    """The GP-NARX of the config (lags ``ny``/``nu`` [samples] override the config's) fitted by ML-II on
    ``train_recs``; with the config's ``noise_calibration = "lags"`` the noise variance and with
    ``band_calibration = "lags"`` the band's discrepancy scale are calibrated on ``records("lags")``."""
    log = log or (lambda msg: None)
    model = model_from_config(cfg, ny, nu, **(model_overrides or {}))
    log(f"training {cfg.name}: ny={model.ny} nu={model.nu} mode={model.mode} on {len(train_recs)} record(s)")
    calibrate_noise = cfg.model.get("noise_calibration", "none") == "lags"
    model.fit(train_recs, heldout=records("lags") if calibrate_noise else None)
    log(f"ML-II done in {model.fit_seconds_:.1f} s (N={model.n_train_}, NLML={model.nlml_:.1f})")
    if model.noise_calibration_ is not None:
        nc = model.noise_calibration_
        log(f"noise calibrated on {nc['n_records']} held-out 'lags' record(s), {nc['n_residuals']} one-step "
            f"residuals: sigma_y^2 {nc['noise_var_ml2']:.3g} (ML-II) -> {nc['noise_var']:.3g} (standardised)")
    if cfg.model.get("lengthscale_refine", "none") == "lags":
        refine_lengthscales(model, records("lags"), log=log,
                            tolerance=float(cfg.model.get("lengthscale_refine_tolerance", REFINE_TOLERANCE)))
        if model.noise_calibration_ is not None and model.hyper_refinement_.get("factor", 1.0) != 1.0:
            nc = model.recalibrate_noise(records("lags"))  # the held-out rule again, at the lengthscales kept
            log(f"noise recalibrated at the refined lengthscales: sigma_y^2 {nc['noise_var']:.3g} (standardised)")
    if cfg.model.get("band_calibration", "none") == "lags":
        calibrate_band_from_config(model, cfg, records("lags"), log)
    return model


def _run_key(role: str, rec: Record) -> tuple:
    """A record with several roles (e.g. lags and verify) is simulated once; each further role reuses that
    prediction unless the start rule differs (novelty roles start from measured outputs, see evaluate_record)."""
    return rec.name, role in ("healthy", "damaged")


def evaluate(model: GPNARX, todo: list, plan: _Plan, *, runner: TaskRunner | None = None, progress: bool = False,
             log=None) -> list[dict]:
    """The free run (``plan.propagation``, ``plan.n_paths`` paths, seed = the record's position in ``todo``)
    and basic metrics (fit %, RMSE, coverage %, band width) of every (role, record) of ``todo``, in order."""
    log = log or (lambda msg: None)
    done = {}
    if runner is not None:  # the free runs as tasks on the cluster, then reported in the same order
        done = _evaluate_remote(runner, model, todo, _run_key, plan.n_paths, plan.confidence, plan.propagation,
                                progress, log)
    bar = _Progress(progress and runner is None, sum(r.n for _, r in {_run_key(*t): t for t in todo}.values()),
                    "free-run")
    evals = []
    for k, (role, rec) in enumerate(todo):
        key = _run_key(role, rec)
        if key in done:
            ev = {**done[key], "role": role}
        else:
            ev = evaluate_record(model, rec, role, plan.n_paths, seed=k, confidence=plan.confidence,
                                 method=plan.propagation, progress=bar.callback(rec.n))
            bar.advance(rec.n)
            done[key] = ev
        ev["metrics"] = basic_metrics(ev)
        evals.append(ev)
        log(f"  {role:8s} {rec.name}: " + ", ".join(f"{k}={v:.4g}" for k, v in ev["metrics"].items()))
    bar.close()
    return evals


def score_against_baselines(train_recs: list[Record], scored: list[Record], ny: int, nu: int, log=None) -> dict:
    """The baseline models (training.baselines) fitted on ``train_recs`` with the model's lags [samples] and
    scored on ``scored``: {record name: {baseline: metrics}}."""
    return score_baselines(fit_baselines(train_recs, ny, nu, log=log), scored)


def calibrate_novelty(cfg: DatasetConfig, evals: list[dict], n_paths: int) -> dict | None:
    """The novelty threshold at the config's false-alarm rate from the scores of the ``healthy`` records
    (None with fewer than two), by the config's ``[novelty] method`` score, with the envelope and probe
    contract it holds for; each healthy or damaged record's metrics gain its score and verdict."""
    healthy = [ev for ev in evals if ev["role"] == "healthy"]
    if len(healthy) < 2:
        return None
    far = float(cfg.novelty.get("false_alarm_rate", 0.01))
    score_method = cfg.novelty.get("method", RMS_METHOD)
    scored = [ev for ev in evals if ev["role"] in ("healthy", "damaged")]
    for ev, score in zip(scored, score_records(scored, score_method)):
        ev["metrics"]["novelty_score"] = score
    novelty = calibrate_threshold([ev["metrics"]["novelty_score"] for ev in healthy], far)
    novelty["method"] = score_method
    novelty["mc_paths"] = n_paths
    novelty["envelope"] = record_envelope([(ev["u"], ev["y"]) for ev in healthy])
    # the probe contract: the excitation (and start rule) the threshold holds for (model.probe)
    novelty["probe"] = probe_contract([ev["u"] for ev in healthy], cfg.fs, start="measured")
    for ev in scored:
        # the records the probe contract is derived from: judged on score and envelope only
        ev["metrics"]["verdict"] = judge(novelty, ev["metrics"]["novelty_score"], ev["u"], ev["y"], cfg.fs,
                                         check_probe=False)["verdict"]
    return novelty


def training_metrics(model: GPNARX, train_recs: list[Record], evals: list[dict], plan: _Plan,
                     baselines: dict) -> dict:
    """The manifest's ``training`` block: ML-II time [s], rows, NLML, each scored record's metrics, the
    report's propagation and baselines (``wall_seconds`` [s] is filled in just before saving)."""
    return {
        "fit_seconds": model.fit_seconds_, "n_train": model.n_train_, "n_rows": model.n_rows_,
        "nlml": model.nlml_, "train_records": [r.name for r in train_recs],
        "records": {ev["name"]: {"role": ev["role"], **{k: v for k, v in ev["metrics"].items()}} for ev in evals},
        "mc_paths": plan.n_paths, "method": plan.propagation, "confidence": plan.confidence, "wall_seconds": None,
        "baselines": baselines,
    }


def physics_of(cfg: DatasetConfig) -> dict:
    """The config's physical constants (mass [kg], ...) with the output kind (default: displacement)."""
    physics = dict(cfg.physics)
    physics.setdefault("output", cfg.system.get("output", "displacement"))
    return physics


def write_report(report_dir: Path, cfg: DatasetConfig, model: GPNARX, plan: _Plan, evals: list[dict],
                 metrics: dict, novelty: dict | None, *, physics: dict, lag_surface=None, baselines=None,
                 paper=None, runner=None) -> None:
    """The training report (HTML, figures, report.json) into ``report_dir``; its richer per-record metrics
    (PSD peaks [Hz], loop areas [J]) are merged into ``metrics["records"]``."""
    # the report module imports matplotlib and selects its Agg backend: imported only when a
    # report is written, so importing the pipeline leaves a caller's plotting set-up alone
    from gpnarx.training.report import write_report as write_html_report
    from gpnarx.training.report_residuals import attach_residual_tests

    attach_residual_tests(model, evals)  # the verify/validate records' one-step residual tests
    full = write_html_report(report_dir, f"GP-NARX {cfg.name}", {
        "config": str(cfg.path), "ny": model.ny, "nu": model.nu, "mode": model.mode,
        "kernel": repr(model.kernel_), "noise_var": model.noise_var_,
        "noise_calibration": model.noise_calibration_, "n_train": model.n_train_,
        "fit_seconds": model.fit_seconds_, "mc_paths": plan.n_paths, "method": plan.propagation,
        "novelty": novelty,
    }, evals, physics=physics, lag_surface=lag_surface, baselines=baselines, paper=paper, runner=runner)
    rj = json.loads((report_dir / "report.json").read_text())
    for rm in rj.get("records", []):
        nm = rm.get("name")
        if nm in metrics["records"]:
            metrics["records"][nm].update({k: v for k, v in rm.get("metrics", {}).items()
                                           if not isinstance(v, (list, dict)) or k.startswith("psd")})
    del full


def save(model: GPNARX, cfg: DatasetConfig, registry, name: str | None, version: str | None, *, physics: dict,
         novelty: dict | None, metrics: dict, report_dir: Path | None) -> Path:
    """The bundle, written atomically into ``REGISTRY/NAME/VERSION`` with the report folder attached; the
    answers' default propagation is the config's ``[predict]``, not a lighter report's override."""
    return save_bundle(model, registry, name or cfg.name, version, fs=cfg.fs, units=cfg.units,
                       physics=physics, novelty=novelty, training=to_json_safe(metrics), attach_dir=report_dir,
                       extra={"predict": {"method": cfg.predict.get("method", "mc"),
                                          "mc_paths": int(cfg.predict.get("mc_paths", 1024))}})


def _evaluate_remote(runner: TaskRunner, model: GPNARX, todo: list, run_key, n_paths: int, conf: float, method: str,
                     progress: bool, log) -> dict:
    """The distinct free runs of ``todo`` on ``runner``: {run key: evaluate_record output}, each with the
    seed the local loop gives it (its first position in ``todo``)."""
    firsts = {}
    for k, (role, rec) in enumerate(todo):
        firsts.setdefault(run_key(role, rec), (k, role, rec))
    shared = runner.share(model)
    bar = progress_bar(total=len(firsts), desc="free-run", unit="record", leave=False) if progress else None
    t0 = time.perf_counter()
    try:
        results = runner.run(evaluate_record, [(shared, runner.send(rec), role, n_paths, k, conf, method)
                                               for k, role, rec in firsts.values()],
                             on_done=None if bar is None else (lambda i: bar.update(1)))
    finally:
        if bar is not None:
            bar.close()
    log(f"{len(firsts)} free run(s) on {runner.where} in {time.perf_counter() - t0:.1f} s")
    return dict(zip(firsts, results))
