"""Prometheus metrics of one app (its own ``CollectorRegistry``, so several apps can coexist).

- ``gpnarx_http_requests_total{method,route,status}`` and ``gpnarx_http_errors_total{method,route,status}``
  (status >= 400), labelled by the route template (``/v1/models/{name}/predict``), never the raw path;
- ``gpnarx_http_request_duration_seconds{method,route}`` latency histogram;
- ``gpnarx_mc_path_steps_total`` Monte Carlo path-steps served;
- ``gpnarx_requests_shed_total`` requests refused with 503 because the work queue was full;
- ``gpnarx_requests_timed_out_total{stage}`` requests past GPNARX_REQUEST_TIMEOUT (stage ``queued``:
  503, the job never started; ``running``: 504, the job was cancelled at its next checkpoint);
- ``gpnarx_requests_abandoned_total`` requests whose client disconnected before the answer (job cancelled);
- ``gpnarx_answers_total{model,operation}`` answered predict/loops/novelty calls (single or batch slot),
  ``gpnarx_out_of_range_total{model,field}`` answers flagged out of the model's range (field ``u``, ``y``,
  ``prediction``, ``probe``), ``gpnarx_diverged_answers_total{model}`` answers with ``diverged_paths`` > 0,
  ``gpnarx_novelty_verdicts_total{model,verdict}``: the per-model counts alerting is built on. Model
  labels come from the registry's names, so the label set is bounded by the registry;
- ``gpnarx_bundles_loaded`` / ``gpnarx_bundles_refused`` gauges, ``gpnarx_work_pending`` (running + waiting jobs);
- ``gpnarx_registry_scans_total{trigger,outcome}`` registry scans (trigger ``poll`` or ``reload``; outcome
  ``changed``, ``unchanged``, ``held``: a scan that dropped too many versions was not served, ``error``: the store
  could not be read), ``gpnarx_registry_held`` (1 while such a scan is held back),
  ``gpnarx_registry_held_accepted_total`` (held listings served after confirmation or an admin action),
  ``gpnarx_registry_versions_added_total`` / ``gpnarx_registry_versions_removed_total``,
  ``gpnarx_registry_leftovers_removed_total`` (what killed writes left, removed: local temporary
  folders, unpublished versions on an object store).
"""
from __future__ import annotations

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
)

BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0)


class ServiceMetrics:
    def __init__(self, state):
        self.state = state
        self.registry = CollectorRegistry(auto_describe=True)
        r = self.registry
        self.requests = Counter("gpnarx_http_requests", "HTTP requests by route and status",
                                ["method", "route", "status"], registry=r)
        self.errors = Counter("gpnarx_http_errors", "HTTP error answers (status >= 400) by route and status",
                              ["method", "route", "status"], registry=r)
        self.latency = Histogram("gpnarx_http_request_duration_seconds", "HTTP request latency",
                                 ["method", "route"], buckets=BUCKETS, registry=r)
        self.path_steps = Counter("gpnarx_mc_path_steps", "Monte Carlo path-steps served", registry=r)
        self.shed = Counter("gpnarx_requests_shed", "Requests refused with 503 because the work queue was full",
                            registry=r)
        self.timed_out = Counter("gpnarx_requests_timed_out", "Requests past their time limit, by the stage "
                                 "their job was in (queued -> 503, running -> 504, predicted: a 504 at once)",
                                 ["stage"], registry=r)
        self.abandoned = Counter("gpnarx_requests_abandoned", "Requests whose client disconnected before the "
                                 "answer (their job was cancelled)", registry=r)
        self.answers = Counter("gpnarx_answers", "Answered predict, loops and novelty calls by model and operation",
                               ["model", "operation"], registry=r)
        self.out_of_range = Counter("gpnarx_out_of_range", "Answers flagged outside the model's range, by model and "
                                    "field (u, y, prediction, probe)", ["model", "field"], registry=r)
        self.diverged = Counter("gpnarx_diverged_answers", "Answers whose free run diverged (diverged_paths > 0), "
                                "by model", ["model"], registry=r)
        self.verdicts = Counter("gpnarx_novelty_verdicts", "Novelty verdicts by model and verdict",
                                ["model", "verdict"], registry=r)
        self.loaded = Gauge("gpnarx_bundles_loaded", "Model bundles loaded (verified and served)", registry=r)
        self.built = Gauge("gpnarx_bundles_in_memory", "Models built in memory (at most GPNARX_MAX_LOADED)",
                           registry=r)
        self.built.set_function(lambda: self.state.registry.loaded_count())
        self.refused = Gauge("gpnarx_bundles_refused", "Model bundles refused (corrupt or invalid)", registry=r)
        self.scans = Counter("gpnarx_registry_scans", "Registry scans by trigger (poll, reload) and outcome "
                             "(changed, unchanged, held, error)", ["trigger", "outcome"], registry=r)
        self.held = Gauge("gpnarx_registry_held", "1 while a registry scan that dropped too many versions is held "
                          "back (the last good registry serves)", registry=r)
        self.held.set_function(lambda: 1.0 if self.state.held else 0.0)
        self.scans_accepted = Counter("gpnarx_registry_held_accepted", "Held registry listings served after "
                                      "confirmation on consecutive scans or an admin reload with accept_removal",
                                      registry=r)
        self.leftovers = Counter("gpnarx_registry_leftovers_removed", "What killed writes left, removed at start or "
                                 "by a scan: local temporary folders, unpublished object-store versions", registry=r)
        self.leftovers.inc(getattr(state, "leftovers_removed", 0))
        self.versions_added = Counter("gpnarx_registry_versions_added", "Versions a registry scan added",
                                      registry=r)
        self.versions_removed = Counter("gpnarx_registry_versions_removed", "Versions a registry scan removed",
                                        registry=r)
        self.pending = Gauge("gpnarx_work_pending", "Jobs running or waiting on the worker pool", registry=r)
        self.pending.set_function(lambda: self.state.executor.pending)

    def observe(self, method: str, route: str, status: int, seconds: float) -> None:
        self.requests.labels(method, route, str(status)).inc()
        if status >= 400:
            self.errors.labels(method, route, str(status)).inc()
        self.latency.labels(method, route).observe(seconds)

    def answered(self, operation: str, out: dict) -> None:
        """Count one answered operation by model: flags and (for novelty) the verdict."""
        model = str(out.get("model", ""))
        self.answers.labels(model, operation).inc()
        for f in out.get("out_of_range") or ():
            self.out_of_range.labels(model, str(f)).inc()
        if int(out.get("diverged_paths") or 0) > 0:
            self.diverged.labels(model).inc()
        if operation == "novelty" and out.get("verdict") in ("healthy", "novel", "unjudged"):
            self.verdicts.labels(model, out["verdict"]).inc()

    def update_bundles(self) -> None:
        reg = self.state.registry
        self.loaded.set(sum(len(v) for v in reg.bundles.values()))
        self.refused.set(len(reg.refused))

    def render(self) -> tuple[bytes, str]:
        return generate_latest(self.registry), CONTENT_TYPE_LATEST
