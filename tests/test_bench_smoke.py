"""Smoke test of the benchmarks: each bench/ script runs in --quick mode and prints the contract line.

Contract (design.md): one line starting ``RESULT `` with key=value pairs, among them the product's
figure, the baseline's and ``ratio=`` (a finite number). ``baseline_what=`` says what the
baseline is (``ratio=`` compares equal work, docs/benchmarks.md); a comparison with what a user
would otherwise run comes as ``user_ratio...=`` fields with a ``user_baseline=`` label. Runs with
``--threads 1`` so a machine oversubscribed by other processes does not make single small BLAS
calls wait for a second thread.
"""
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = ["bench_freerun.py", "bench_fit.py", "bench_modes.py", "bench_scaling.py", "bench_memory.py",
           "bench_kstep.py", "bench_bert_scale.py", "bench_predict_e2e.py", "bench_linear_band.py",
           "bench_sparse_accuracy.py", "bench_sparse_variance.py", "bench_mc_speed.py", "bench_realtime.py",
           "bench_gpu.py", "bench_gpu_steps.py", "bench_wire.py", "bench_stream.py", "bench_local_check.py",
           "bench_estimator_blas.py", "bench_update.py"]
# fields of some RESULT lines that must be finite positive numbers (besides ratio and baseline)
FINITE = {"bench_bert_scale.py": ("wall_s", "path_steps_per_s", "user_record_s_extrapolated", "user_ratio"),
          "bench_kstep.py": ("kstep_s", "fit_k64", "mc_kstep_s", "mc_ratio"),
          "bench_predict_e2e.py": ("wall_s", "baseline_wall_s", "path_steps_per_s", "simulate_s", "untuned_wall_s",
                                   "user_ratio"),
          "bench_modes.py": ("ratio_exact", "ratio_sparse32", "ratio_sparse64", "linear_vs_mc", "user_ratio"),
          "bench_fit.py": ("eval_s", "fit_ratio_plain", "user_ratio"),
          "bench_mc_speed.py": ("path_steps_per_s", "max_edge_diff_se"),
          "bench_realtime.py": ("rt_factor", "rt_factor_cpu", "wall_s", "cpu_s"),
          "bench_gpu.py": ("pss", "realtime", "pss_segment", "band_median_se", "numpy_seeds_band_median_se"),
          "bench_gpu_steps.py": ("product_us", "split_us_p64", "joint_us_p64", "product_us_p64"),
          "bench_wire.py": ("json_bytes", "gzip_bytes", "npz_bytes", "json_ms", "gzip_ms", "npz_ms"),
          "bench_stream.py": ("linear_token_bytes", "mc_token_bytes", "mc_token_ms", "ratio"),
          "bench_local_check.py": ("max_err_all", "baseline"),
          "bench_estimator_blas.py": ("product_s", "baseline"),
          "bench_update.py": ("update_s", "baseline", "rank_update_s", "rows_added")}
# the baselines' numerics agree with the product's (same model on both sides of ratio=)
MATCH = {"bench_freerun.py": "max_mean_diff", "bench_modes.py": "max_mean_diff",
         "bench_bert_scale.py": "ref_max_mean_diff", "bench_predict_e2e.py": "ref_max_mean_diff"}


def parse_result(stdout: str) -> dict:
    lines = [ln for ln in stdout.splitlines() if ln.startswith("RESULT ")]
    assert len(lines) == 1, f"expected exactly one RESULT line, got {len(lines)}:\n{stdout}"
    pairs = {}
    for tok in lines[0][len("RESULT "):].split():
        assert "=" in tok, f"token {tok!r} is not key=value"
        k, v = tok.split("=", 1)
        pairs[k] = v
    return pairs


# every other script here, the rest in tests/test_bench_smoke_more.py: two modules that pytest-xdist's
# loadscope gives to two workers
HERE = SCRIPTS[0::2]


@pytest.mark.parametrize("script", HERE)
def test_bench_quick(script):
    run_quick(script)


def run_quick(script: str) -> None:
    """Run bench/SCRIPT --quick and check its RESULT line (the contract and the script's own figures)."""
    path = ROOT / "bench" / script
    assert path.exists(), path
    proc = subprocess.run([sys.executable, str(path), "--quick", "--threads", "1"], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)  # a hang guard, not a speed limit
    assert proc.returncode == 0, f"{script} exited {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr}"
    kv = parse_result(proc.stdout)
    if "baseline_skipped" in kv:  # a baseline from git history (bench/baseline.py) this clone lacks: shallow
        pytest.skip(f"{script}: its baseline was skipped ({kv['baseline_skipped']}): {proc.stderr.strip()[-300:]}")
    check_contract(kv)
    for key in FINITE.get(script, ()):
        assert key in kv and math.isfinite(float(kv[key])) and float(kv[key]) > 0, (key, kv)
    if script == "bench_sparse_variance.py":  # the factored variance matches the QR reference
        assert float(kv["product_rel_err"]) < 1e-6 < float(kv["baseline_rel_err"]), kv
    if script == "bench_wire.py":  # the compact formats are smaller than JSON and answer the same numbers
        assert int(kv["gzip_bytes"]) < int(kv["json_bytes"]) and int(kv["npz_bytes"]) < int(kv["json_bytes"]), kv
        assert float(kv["max_mean_diff"]) == 0.0, kv
    if script == "bench_stream.py":  # chunks give the whole record's mean and, off the chunks' ends, its band
        assert float(kv["linear_max_mean_diff"]) == 0.0 and float(kv["mc_max_mean_diff"]) == 0.0, kv
        assert float(kv["linear_max_band_diff_inner"]) < 1e-9 and float(kv["mc_max_band_diff_inner"]) < 1e-9, kv
    if script in MATCH:
        assert float(kv[MATCH[script]]) < 1e-8, kv
    if script == "bench_local_check.py":  # steps were audited, and no path was beyond the check's tolerance
        assert int(kv["audited_steps"]) > 0 and int(kv["exceed_steps"]) == 0, kv
        assert float(kv["ratio"]) >= 1.0 and 0.0 <= float(kv["argmax_far12"]) <= 100.0, kv
    if script == "bench_mc_speed.py":  # same draws: the bands agree far inside their Monte Carlo error
        assert float(kv["max_edge_diff_se"]) < 0.5 and float(kv["cov_gap_points"]) <= 1.0, kv


def check_contract(kv: dict) -> None:
    """ratio= finite and positive, a numeric baseline= described by baseline_what=, user_ratio* labelled."""
    assert "ratio" in kv and "baseline" in kv, kv
    ratio = float(kv["ratio"])
    assert math.isfinite(ratio) and ratio > 0, kv
    assert math.isfinite(float(kv["baseline"])), kv
    assert kv.get("baseline_what"), f"no baseline_what= saying what the baseline is: {kv}"
    if any(k.startswith("user_ratio") for k in kv):
        assert kv.get("user_baseline"), f"user_ratio without a user_baseline= label: {kv}"


def test_parse_result_rejects_garbage():
    with pytest.raises(AssertionError):
        parse_result("no result here")
    assert parse_result("table\nRESULT a=1 ratio=2.5 baseline=3\n")["ratio"] == "2.5"


def test_contract_check_rejects_unlabelled_lines():
    check_contract(parse_result("RESULT a=1 ratio=2.5 baseline=3 baseline_what=x user_ratio=9 user_baseline=y"))
    for bad in ("RESULT a=1 ratio=2.5 baseline=3",  # no baseline_what
                "RESULT a=1 baseline=3 baseline_what=x",  # no ratio
                "RESULT a=1 ratio=2.5 baseline_what=x",  # no baseline
                "RESULT ratio=2.5 baseline=3 baseline_what=x user_ratio=9"):  # user_ratio without its label
        with pytest.raises(AssertionError):
            check_contract(parse_result(bad))


def test_bench_load_quick():
    """Loopback load test (bench/bench_load.py --quick): zero errors, shedding with Retry-After, live health."""
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "bench_load.py"), "--quick"], cwd=ROOT,
                          capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, f"exited {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr[-3000:]}"
    kv = parse_result(proc.stdout)
    check_contract(kv)
    assert int(kv["errors"]) == 0, kv
    assert float(kv["baseline"]) > 0, kv
    for t in ("predict", "novelty", "batch"):
        assert math.isfinite(float(kv[f"p95_{t}_ms"])), kv
    # overload: more simultaneous requests than workers + queue -> the surplus is shed with 503 + Retry-After
    assert int(kv["overload"]) > int(kv["capacity"]), kv
    assert int(kv["shed_503"]) > 0 and int(kv["retry_after_ok"]) == int(kv["shed_503"]), kv
    assert int(kv["shed_503"]) + int(kv["ok_200"]) == int(kv["overload"]), kv
    assert int(kv["other_5xx"]) == 0 and int(kv["health_errors"]) == 0, kv
    health = float(kv["health_p95_overload_ms"])
    assert math.isfinite(health) and 0 < health < 5000, kv  # the event loop is never blocked for seconds


def test_bench_streams_quick():
    """Streams per replica (bench/bench_streams.py --quick): streams with state tokens against a real `gpnarx serve`,
    every chunk answered; the figure is the largest count whose p99 stays under the chunk time."""
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "bench_streams.py"), "--quick"], cwd=ROOT,
                          capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, f"exited {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr[-3000:]}"
    kv = parse_result(proc.stdout)
    check_contract(kv)
    assert int(kv["baseline"]) >= 1 and math.isfinite(float(kv["single_p50_ms"])), kv
    assert int(kv["stream_s"]) >= 2 and kv["tried"], kv
    # a stream is followed only when every chunk got its 200 in time; 0 streams would mean not even the first count
    assert int(kv["streams"]) >= 1 and kv["limit"] in ("found", "lower-bound"), kv
