"""What each answer leaves behind: its audit line, the drift gauges and the per-model latency.

``Telemetry(state)`` hangs off ``ServiceState`` (``state.telemetry``) and adds to the app's
Prometheus registry (``service.metrics``):

- ``gpnarx_build_info{version,python}`` (always 1);
- the standard ``process_*`` metrics (CPU seconds, resident memory, open file descriptors, start
  time; Linux) and ``python_gc_*`` / ``python_info`` from prometheus_client;
- ``gpnarx_answer_duration_seconds{model,operation}``: queue wait + compute of each answered
  predict, loops or novelty call (a batch slot: its compute), a histogram labelled by model;
- drift, per model, over its last ``GPNARX_DRIFT_WINDOW`` answers:
  ``gpnarx_novelty_score_window{model,quantile}`` (quantile 0.5, 0.9 and 1 of the novelty scores
  judged in the window: ``healthy`` or ``novel``, not ``unjudged``), ``gpnarx_novelty_threshold{model}``
  (the threshold of the last verdict), ``gpnarx_out_of_range_window_ratio{model}`` (share of the
  window's answers, every operation, with a non-empty ``out_of_range``) and
  ``gpnarx_drift_window_answers{model,kind}`` (answers and scores the window holds now);
- the audit trail (``service.audit``): ``gpnarx_audit_lines_total{outcome}`` (written, failed,
  dropped), ``gpnarx_audit_lines_lost_total``, ``gpnarx_audit_write_failures_total``,
  ``gpnarx_audit_reopens_total{reason}``, ``gpnarx_audit_torn_lines_total`` and ``gpnarx_audit_queue_lines``.

A rising ``gpnarx_novelty_score_window{quantile="0.5"}`` against ``gpnarx_novelty_threshold`` shows
a slowly loosening bolt before single verdicts turn ``novel``; a rising out-of-range ratio shows a
changed operating regime (docs/deploy.md has an alert rule). Model labels come from the registry's
names, so the label set is bounded by the registry.

Nothing here may lose an answer: ``answered`` catches and logs its own failures.
"""
from __future__ import annotations

import asyncio
import logging
import math
import platform
import threading
from collections import deque

import numpy as np
from prometheus_client import GC_COLLECTOR, PLATFORM_COLLECTOR, Histogram, Info, ProcessCollector
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

from .audit import AuditTrail, client_id
from .deps import API_KEY_HEADER
from .metrics import BUCKETS
from .observability import REQUEST_ID

log = logging.getLogger("gpnarx.service")

#: quantiles of the novelty scores in the drift window (1 = the window's largest score)
QUANTILES = (0.5, 0.9, 1.0)


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("gpnarx")
    except Exception:  # pragma: no cover - not installed as a distribution
        return "unknown"


def _on_event_loop() -> bool:
    """Whether this thread runs an event loop (then the record is hashed on the audit trail's thread)."""
    try:
        asyncio.get_running_loop()
    except RuntimeError:
        return False
    return True


class Drift:
    """Per-model rolling windows of novelty scores and out-of-range flags (thread-safe)."""

    def __init__(self, window: int):
        self.window = int(window)
        self._lock = threading.Lock()
        self._scores: dict[str, deque] = {}
        self._flags: dict[str, deque] = {}
        self._threshold: dict[str, float] = {}

    def observe(self, operation: str, out: dict) -> None:
        model = str(out.get("model", ""))
        with self._lock:
            self._flags.setdefault(model, deque(maxlen=self.window)).append(1 if out.get("out_of_range") else 0)
            if operation != "novelty" or out.get("verdict") not in ("healthy", "novel"):
                return
            try:
                score, threshold = float(out.get("score")), float(out.get("threshold"))
            except (TypeError, ValueError):
                return
            if math.isfinite(score):
                self._scores.setdefault(model, deque(maxlen=self.window)).append(score)
            if math.isfinite(threshold):
                self._threshold[model] = threshold

    def snapshot(self) -> dict:
        """Per model: ``quantiles`` ({q: score} or {}), ``threshold``, ``out_of_range_ratio``,
        ``answers`` and ``scores`` in the window."""
        with self._lock:
            models = sorted(set(self._flags) | set(self._scores))
            data = {m: (list(self._scores.get(m, ())), list(self._flags.get(m, ())), self._threshold.get(m))
                    for m in models}
        out = {}
        for m, (scores, flags, threshold) in data.items():
            qs = np.quantile(np.asarray(scores), QUANTILES).tolist() if scores else []
            out[m] = {"quantiles": dict(zip(QUANTILES, qs)), "threshold": threshold,
                      "out_of_range_ratio": (sum(flags) / len(flags)) if flags else None,
                      "answers": len(flags), "scores": len(scores)}
        return out


class _Collector:
    """Drift gauges and audit counters, computed at scrape time."""

    def __init__(self, drift: Drift, audit: AuditTrail):
        self.drift = drift
        self.audit = audit

    def describe(self):
        return []

    def collect(self):
        q = GaugeMetricFamily("gpnarx_novelty_score_window", "Quantiles of the novelty scores judged (healthy or "
                              "novel) in the model's last GPNARX_DRIFT_WINDOW answers", labels=["model", "quantile"])
        thr = GaugeMetricFamily("gpnarx_novelty_threshold", "Novelty threshold of the model's last verdict",
                                labels=["model"])
        oor = GaugeMetricFamily("gpnarx_out_of_range_window_ratio", "Share of the model's last GPNARX_DRIFT_WINDOW "
                                "answers with a non-empty out_of_range", labels=["model"])
        n = GaugeMetricFamily("gpnarx_drift_window_answers", "Answers (kind=answers) and judged novelty scores "
                              "(kind=scores) in the model's drift window", labels=["model", "kind"])
        for model, s in self.drift.snapshot().items():
            for qv, v in s["quantiles"].items():
                q.add_metric([model, f"{qv:g}"], v)
            if s["threshold"] is not None:
                thr.add_metric([model], s["threshold"])
            if s["out_of_range_ratio"] is not None:
                oor.add_metric([model], s["out_of_range_ratio"])
            n.add_metric([model, "answers"], s["answers"])
            n.add_metric([model, "scores"], s["scores"])
        yield from (q, thr, oor, n)
        a = self.audit.status()
        lines = CounterMetricFamily("gpnarx_audit_lines", "Audit lines by outcome: written, failed (the write "
                                    "failed), dropped (the queue was full)", labels=["outcome"])
        for outcome in ("written", "failed", "dropped"):
            lines.add_metric([outcome], a[outcome])
        yield lines
        yield CounterMetricFamily("gpnarx_audit_write_failures", "Failed writes to the audit target (each loses "
                                  "the lines it held)", value=self.audit.failures)
        yield CounterMetricFamily("gpnarx_audit_lines_lost", "Audit lines accepted but not in the trail: failed "
                                  "writes and full-queue drops", value=a["lost"])
        reopens = CounterMetricFamily("gpnarx_audit_reopens", "Reopens of the audit trail's file: deleted or "
                                      "rotated (renamed) under the server, on a signal (SIGHUP), after a failed "
                                      "write", labels=["reason"])
        for reason, n in a["reopens"].items():
            reopens.add_metric([reason], n)
        yield reopens
        yield CounterMetricFamily("gpnarx_audit_torn_lines", "Fragments of failed audit writes that could not be "
                                  "cut off (each ended by a newline, alone on its line)", value=a["torn"])
        yield GaugeMetricFamily("gpnarx_audit_queue_lines", "Audit lines waiting to be written", value=a["queued"])


class Telemetry:
    """Audit trail, drift windows and per-model latency of one app (``state.telemetry``)."""

    def __init__(self, state):
        settings = state.settings
        self.audit = AuditTrail.from_settings(settings)
        self.drift = Drift(settings.drift_window)
        r = state.metrics.registry
        Info("gpnarx_build", "Version of the gpnarx package and of Python", registry=r).info(
            {"version": _version(), "python": platform.python_version()})
        ProcessCollector(registry=r)
        for c in (GC_COLLECTOR, PLATFORM_COLLECTOR):  # the default registry's instances, shared
            r.register(c)
        self.latency = Histogram("gpnarx_answer_duration_seconds", "Queue wait and compute of each answered "
                                 "predict, loops or novelty call by model (a batch slot: its compute)",
                                 ["model", "operation"], buckets=BUCKETS, registry=r)
        r.register(_Collector(self.drift, self.audit))

    def answered(self, request, operation: str, out: dict, req, seconds: float | None = None,
                 slot: int | None = None) -> None:
        """Record one answered call: drift window, latency, audit line. Never raises."""
        try:
            model = str(out.get("model", ""))
            self.drift.observe(operation, out)
            if seconds is not None:
                self.latency.labels(model, operation).observe(seconds)
            if self.audit.wants(operation):
                key = request.headers.get(API_KEY_HEADER) if request is not None else None
                rid = REQUEST_ID.get()
                if rid is None and request is not None:
                    rid = request.scope.get("state", {}).get("request_id")
                self.audit.record(operation, out, req, rid, client_id(key), slot=slot, offload=_on_event_loop())
        except Exception:  # telemetry never loses an answer
            log.exception("telemetry of a %s answer failed", operation)

    def ready(self) -> dict:
        """``audit`` of /health/ready."""
        return self.audit.status()

    def close(self) -> None:
        self.audit.close()
