#!/usr/bin/env bash
# The exact bert-real on one GPU: the JAX backend's Monte Carlo at 4096 paths over a 64 s real record, its bands
# against numpy's within Monte Carlo error, and its real-time factor (issue 54's GPU target: at least 50x on one
# H100 or H200). One prepared run, from the repository root of a checkout on the GPU machine:
#
#   bash bench/gpu_exact_mc.sh [BUNDLE_DIR] [RECORD]
#
# BUNDLE_DIR: the exact bert-real bundle (REGISTRY/bert-real/VERSION); without one, bert-real is trained from its
#   shipped config into a temporary registry (needs the lab records: ../shared/data/bert-t5nm or GPNARX_BERT_DATA).
# RECORD: default the 20 Hz sine of the lab data (64 s, 65,536 samples).
# GPNARX_WHEELS=DIR: install JAX's CUDA build and gpnarx's dependencies from wheels in DIR, offline (a GPU machine
#   that reaches no package index: fill DIR beforehand, on a machine that does and for the GPU machine's Python and
#   platform, with `pip download 'jax[cuda12]' -r requirements.lock -d DIR`); without it, from the package index.
#   GPNARX_JAX_EXTRA: the extra to install (default cuda12; cuda13 for a CUDA 13 driver).
# OUT=DIR: where the RESULT lines and the run's notes go (default docs/runs/accelerator/exact).
#
# Prints bench/bench_gpu.py's RESULT line (realtime= at 4096 paths, band_*_se= against numpy in Monte Carlo
# standard errors) and a verdict line: bands equal numpy's within Monte Carlo error when the median difference of
# the band edges is at most 1.5 standard errors and the largest at most 1.5 times what two numpy runs at seeds 0
# and 1 differ by; real time against 50x.
set -euo pipefail
cd "$(dirname "$0")/.."
BUNDLE="${1:-}"
RECORD="${2:-}"
OUT="${OUT:-docs/runs/accelerator/exact}"
EXTRA="${GPNARX_JAX_EXTRA:-cuda12}"
mkdir -p "$OUT"

nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/device.txt"

if [ -n "${GPNARX_WHEELS:-}" ]; then
  python -m pip install --no-index --find-links "$GPNARX_WHEELS" "jax[$EXTRA]" -e .
else
  python -m pip install -U "jax[$EXTRA]" -e .
fi
python - <<'PY'
import jax
devs = jax.devices()
print("jax", jax.__version__, devs)
if not any(d.platform == "gpu" for d in devs):
    raise SystemExit("JAX sees no GPU: the CUDA build did not install or does not match the driver")
PY

DATA="${GPNARX_BERT_DATA:-../shared/data/bert-t5nm}"
if [ -z "$RECORD" ]; then
  RECORD="$DATA/Sine/Sine_20Hz"
fi
if [ -z "$BUNDLE" ]; then
  REG="$(mktemp -d)/registry"
  python -m gpnarx train bert-real --registry "$REG" --no-report
  BUNDLE="$(ls -d "$REG"/bert-real/* | sort | tail -1)"
fi
python - "$BUNDLE" <<'PY'
import json, sys
m = json.load(open(sys.argv[1] + "/manifest.json"))
print("bundle", m["name"], m["version"], "mode", m["mode"], "lags", m["lags"])
if m["mode"] != "exact":
    raise SystemExit("the target is the exact bert-real: this bundle is " + m["mode"])
PY

git rev-parse --short=12 HEAD > "$OUT/code.txt" 2>/dev/null || true
python bench/bench_gpu.py --bundle "$BUNDLE" --record "$RECORD" --paths 4096 --seconds 64 --baseline-seconds 2 \
  2>&1 | tee "$OUT/bench_gpu.log"
grep '^RESULT ' "$OUT/bench_gpu.log" > "$OUT/bench_gpu.txt"

python - "$OUT/bench_gpu.txt" <<'PY'
import sys
line = [ln for ln in open(sys.argv[1]) if ln.startswith("RESULT ")][-1]
kv = dict(tok.split("=", 1) for tok in line.split()[1:] if "=" in tok)
rt = float(kv["realtime"])
med, mx = float(kv["band_median_se"]), float(kv["band_max_se"])
seeds_max = float(kv["numpy_seeds_band_max_se"])
bands_ok = med <= 1.5 and mx <= 1.5 * max(seeds_max, 1.0)
print(f"VERDICT device={kv.get('device')} paths={kv['paths']} realtime={rt:.1f}x (target 50x: "
      f"{'met' if rt >= 50 else 'missed'}) bands vs numpy: median {med:.2f} / max {mx:.2f} standard errors "
      f"(two numpy seeds: max {seeds_max:.2f}): {'equal within Monte Carlo error' if bands_ok else 'NOT equal'}")
PY
