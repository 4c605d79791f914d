"""/metrics additions of service.telemetry: build info, process metrics, per-model latency, drift gauges."""
from __future__ import annotations

import platform
import re

import numpy as np
import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families
from test_service_support import FS, built_registry, multisine, noisy, simulate

from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings
from gpnarx.service.telemetry import Drift


def _samples(text: str) -> dict:
    """{(name, frozenset(labels)): value} of a Prometheus scrape."""
    out = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            out[(s.name, frozenset(s.labels.items()))] = s.value
    return out


def _get(samples: dict, name: str, **labels) -> float:
    return samples[(name, frozenset(labels.items()))]


def _nov(model, score, verdict="healthy", threshold=1.0, oor=()):
    return {"model": model, "score": score, "threshold": threshold, "verdict": verdict, "out_of_range": list(oor)}


def test_drift_window_quantiles_roll_and_skip_unjudged():
    d = Drift(window=10)
    for s in range(1, 11):  # scores 1..10
        d.observe("novelty", _nov("m", float(s)))
    snap = d.snapshot()["m"]
    assert snap["quantiles"][0.5] == pytest.approx(5.5) and snap["quantiles"][1.0] == 10.0
    assert snap["quantiles"][0.9] == pytest.approx(np.quantile(np.arange(1, 11), 0.9))
    for _ in range(10):  # the window rolls: the old scores leave it
        d.observe("novelty", _nov("m", 100.0, verdict="novel"))
    assert d.snapshot()["m"]["quantiles"][0.5] == 100.0
    d.observe("novelty", _nov("m", 0.0, verdict="unjudged", oor=["probe"]))  # not a comparable score
    snap = d.snapshot()["m"]
    assert snap["quantiles"][0.5] == 100.0 and snap["scores"] == 10 and snap["out_of_range_ratio"] == 0.1


def test_out_of_range_ratio_counts_every_operation_per_model():
    d = Drift(window=4)
    d.observe("predict", {"model": "a", "out_of_range": ["u"]})
    d.observe("loops", {"model": "a", "out_of_range": []})
    d.observe("predict", {"model": "b", "out_of_range": []})
    snap = d.snapshot()
    assert snap["a"]["out_of_range_ratio"] == 0.5 and snap["a"]["quantiles"] == {} and snap["a"]["answers"] == 2
    assert snap["b"]["out_of_range_ratio"] == 0.0


def test_a_scrape_shows_build_info_process_latency_and_drift():
    reg = built_registry().root
    app = create_app(reg, Settings(workers=1, queue_size=4, registry_poll=0, audit_log="off", drift_window=50))
    with TestClient(app) as c:
        scores = []
        for k in range(3):
            u = multisine(256, 60 + k)
            body = {"u": u.tolist(), "y": noisy(simulate(u), 60 + k).tolist(), "fs": FS, "mc_paths": 16}
            scores.append(c.post("/v1/models/boucwen/novelty", json=body).json()["score"])
        assert c.post("/v1/models/boucwen/predict", json={"u": (1e3 * u).tolist(), "fs": FS,
                                                          "mc_paths": 8}).status_code == 200
        text = c.get("/metrics").text
    s = _samples(text)
    info = [k for k in s if k[0] == "gpnarx_build_info"]
    assert len(info) == 1 and dict(info[0][1])["python"] == platform.python_version()
    assert re.match(r"\d+\.\d+", dict(info[0][1])["version"])
    assert _get(s, "process_resident_memory_bytes") > 1e6 and _get(s, "process_start_time_seconds") > 0
    assert _get(s, "gpnarx_answer_duration_seconds_count", model="boucwen", operation="novelty") == 3
    assert _get(s, "gpnarx_answer_duration_seconds_count", model="boucwen", operation="predict") == 1
    assert _get(s, "gpnarx_answer_duration_seconds_sum", model="boucwen", operation="novelty") > 0
    assert _get(s, "gpnarx_novelty_score_window", model="boucwen", quantile="0.5") == pytest.approx(np.median(scores))
    assert _get(s, "gpnarx_novelty_score_window", model="boucwen", quantile="1") == pytest.approx(max(scores))
    assert _get(s, "gpnarx_novelty_threshold", model="boucwen") > 0
    assert _get(s, "gpnarx_drift_window_answers", model="boucwen", kind="answers") == 4
    assert _get(s, "gpnarx_drift_window_answers", model="boucwen", kind="scores") == 3
    # the predict drove u 1000x outside the training range: 1 of the 4 answers is out of range
    assert _get(s, "gpnarx_out_of_range_window_ratio", model="boucwen") == pytest.approx(0.25)
    assert _get(s, "gpnarx_audit_lines_total", outcome="written") == 0  # audit off


def test_two_apps_in_one_process_keep_separate_metrics():
    a = create_app(None, Settings(workers=1, queue_size=0, registry_poll=0))
    b = create_app(None, Settings(workers=1, queue_size=0, registry_poll=0))
    for app in (a, b):
        text = TestClient(app).get("/metrics").text
        assert text.count("# TYPE gpnarx_build_info gauge") == 1 and "process_cpu_seconds_total" in text
