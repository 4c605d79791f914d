"""docs/results-accelerator.md, rendered from the stored GPU run in docs/runs/accelerator/ (nothing hand-typed).

The run folder holds ``run.json`` (device, code, commands), ``bench_gpu.txt`` (the RESULT lines of
bench/bench_gpu.py), ``steps_xla.txt`` and ``steps_precision.txt`` (per-step timings of the JAX Monte
Carlo block) and ``rows_study.json`` (studies/rows_study.py): the first run, on an H100. Its ``h200/``
folder holds the latest code's run on an H200: ``run.json``, ``bench_gpu.txt`` and
``bench_gpu_steps.txt`` (bench/bench_gpu_steps.py, per step by variant). Re-render with
``python -m studies.accelerator_page docs/runs/accelerator docs/results-accelerator.md``.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

from gpnarx.training.pages.markdown import load_json, pct, result_lines, row, rule, sig, table

_STEP = re.compile(r"(?P<tag>.*?) P (?P<paths>\d+): .*?(?P<us>[0-9.]+) us/step")


def _steps(text: str) -> list[tuple[str, int, float]]:
    out = []
    for ln in text.splitlines():
        m = _STEP.match(ln.strip())
        if m:
            out.append((m["tag"].strip(), int(m["paths"]), float(m["us"])))
    return out


_VARIANTS = {"joint": "one product K [F^T, w] (the previous code)", "split": "K F^T and K w apart (the product)",
             "split_reduce": "K w as a row reduction", "tri": "F as the triangle R of its QR",
             "f32": "split, float32", "nostats": "split, no band statistics",
             "product": "the product's simulate (host loop and draws included)"}


def _bench_table(bench: list[dict]) -> list[str]:
    return table(["paths", "steps", "unroll", "path-steps/s", "real time", "numpy path-steps/s", "ratio",
                  "band vs numpy (median / max)", "numpy seed 0 vs 1", "coverage (JAX, whole record)",
                  "linearised on JAX"],
                 [[r["paths"], r["steps"], r["unroll"], sig(r["pss"]), f"**{float(r['realtime']):.1f}x**",
                   sig(r["baseline"]), pct(r["ratio"]),
                   f"{pct(r['band_median_se'], 2)} / {pct(r['band_max_se'])}",
                   f"{pct(r['numpy_seeds_band_median_se'], 2)} / {pct(r['numpy_seeds_band_max_se'])}",
                   pct(r["coverage_whole"]), f"{float(r['linear_realtime_jax']):.1f}x"] for r in bench])


def _latest(run_dir: Path) -> list[str]:
    """The latest code's run (``h200/``): bench_gpu at each path count, and the step by variant."""
    meta = json.loads((run_dir / "run.json").read_text())
    bench = result_lines((run_dir / "bench_gpu.txt").read_text())
    steps = result_lines((run_dir / "bench_gpu_steps.txt").read_text())[0]
    paths = sorted({int(k.rsplit("_p", 1)[1]) for k in steps if k.startswith("split_us_p")}, reverse=True)
    top, low = paths[0], paths[-1]
    out = ["## The latest code (`bench/bench_gpu.py`, `bench/bench_gpu_steps.py`)\n",
           f"Device: {meta['device']}; JAX {meta['jax']}; code {meta['code']}; model: {meta['bundle']}; record: "
           f"{meta['record']}, whole, from rest (commands: `{run_dir.name}/run.json`). Columns as in the first "
           "run's table below.\n"]
    out += _bench_table(bench)
    out += ["\nTime per step of the compiled block by variant (`bench_gpu_steps.py`: the second call of each "
            "variant's program on the same arrays; `joint`, the previous code, is the same-run baseline):\n"]
    out += table(["variant"] + [f"{p} paths" for p in paths],
                 [[f"{v}: {what}"] + [f"{pct(steps[f'{v}_us_p{p}'])} us" for p in paths]
                  for v, what in _VARIANTS.items()])
    best = max((r for r in bench if int(r["paths"]) == top), key=lambda r: float(r["realtime"]))
    goal_us = 1e6 / (1024.0 * 50.0)  # one step of a 1024 Hz record at 50x real time
    split_top, split_low = float(steps[f"split_us_p{top}"]), float(steps[f"split_us_p{low}"])
    out.append(f"\nThe split products made a step {float(steps['ratio']):.2f}x faster at {top} paths "
               f"({float(steps[f'joint_us_p{top}']):.1f} -> {split_top:.1f} us). The whole 64 s record at {top} paths "
               f"runs at **{float(best['realtime']):.1f}x real time**: the goal of 50x (at most {goal_us:.1f} us "
               f"per step) is missed. {low} paths still take {split_low:.1f} us per step, and float32 saves "
               f"{split_top - float(steps[f'f32_us_p{top}']):.1f} us at {top}: the chain of small kernels a step "
               "launches (two products, the kernel block, the draw), each waiting for the one before, sets a floor "
               "above the goal's whole budget. 50x needs the step fused into one kernel that loops over a block's "
               "steps for its own paths (the paths are independent), not faster arithmetic.\n")
    return out


def _exact(run_dir: Path) -> list[str]:
    """The exact bert-real at 4096 paths (``bench/gpu_exact_mc.sh``): its RESULT line where it ran, else what is
    prepared and why it did not run (``pending.json``)."""
    pending = load_json(run_dir, "pending.json")
    if (run_dir / "bench_gpu.txt").is_file():
        device = (run_dir / "device.txt").read_text().strip() if (run_dir / "device.txt").is_file() else "?"
        out = ["## The exact bert-real at 4096 paths (`bench/gpu_exact_mc.sh`)\n",
               f"Device: {device}; commands and notes in `exact/`.\n"]
        return out + _bench_table(result_lines((run_dir / "bench_gpu.txt").read_text())) + [""]
    if not pending:
        return []
    return ["## The exact bert-real at 4096 paths: prepared, not run\n",
            f"{pending['what']}: **{pending['status']}**, {pending['reason']}. The run is one prepared script, "
            f"`{pending['script']}`: `{pending['command']}` on the GPU machine, from the repository root; offline: "
            f"{pending['offline']}. It writes {pending['writes']}; this page then renders its table here.\n",
            f"What to expect: {pending['expected']}.\n"]


def render(run_dir) -> str:
    run_dir = Path(run_dir)
    meta = json.loads((run_dir / "run.json").read_text())
    bench = result_lines((run_dir / "bench_gpu.txt").read_text())
    xla = _steps((run_dir / "steps_xla.txt").read_text())
    prec = _steps((run_dir / "steps_precision.txt").read_text())
    rows = json.loads((run_dir / "rows_study.json").read_text())
    out = ["# Results: the JAX backend on a GPU\n",
           "Rendered by `python -m studies.accelerator_page docs/runs/accelerator docs/results-accelerator.md` "
           "from the stored run in `docs/runs/accelerator/` (its `run.json` holds the commands). How to install and "
           "select the backend: [accelerator.md](accelerator.md).\n"]
    out += _exact(run_dir / "exact")
    if (run_dir / "h200").is_dir():
        out += _latest(run_dir / "h200")
    out += ["## The first run: Monte Carlo at the paper's scale (`bench/bench_gpu.py`)\n",
           f"Device: {meta['device']}; JAX {meta['jax']}; code {meta['code']}; model: {meta['bundle']}.\n",
           f"Record: {meta['record'].split(' for ')[0]}, whole, from rest. The numpy backend (the product's default, "
           "with its checked local model) ran on the 16 CPU cores beside the GPU, on the record's first 2 s "
           "(`baseline`); `band vs numpy` is the median and largest difference of the two backends' 99 % band "
           "edges on those 2 s, in Monte Carlo standard errors, next to the same figures between two numpy runs "
           "at seeds 0 and 1 (what Monte Carlo error alone gives).\n"]
    out += _bench_table(bench)
    best = max(bench, key=lambda r: float(r["realtime"])) if bench else None
    if best is not None:
        out.append(f"\nThe goal was 50x real time at 4096 paths on one H100: this run reaches "
                   f"{float(best['realtime']):.1f}x ({sig(float(best['pss']))} path-steps/s), a miss. "
                   "The per-step timings below say why.\n")
    out += ["## The first run, per step\n",
            "Time per step of the compiled block (the second call; the sweep of the `steps_*` commands in "
            "`run.json`). A step is one kernel block K(x_paths, Z), one product with [F^T | w] and the draws.\n",
            row(["variant", "4096 paths", "1024 paths"]), rule(3)]
    for tag_rows in (xla, prec):
        for tag in dict.fromkeys(t for t, _, _ in tag_rows):
            us = {p: u for t, p, u in tag_rows if t == tag}
            out.append(row([tag] + [f"{pct(us.get(p, float('nan')))} us" for p in (4096, 1024)]))
    if prec:
        f64 = [u for t, p, u in prec if t.endswith("False") and p == 4096]
        f32 = [u for t, p, u in prec if t.endswith("True") and p == 4096]
        if f64 and f32:
            out.append(f"\nAt 4096 paths a step takes {f64[0]:.1f} us in float64 and {f32[0]:.1f} us in float32, and "
                       "1024 paths take half the time of 4096, not a quarter: the step is bound by the latency of "
                       "its kernels, not by arithmetic, so float32 (which the real rig's variance cannot afford, "
                       "`model/freerun_jax.py`) buys nothing and float64 stays the default.\n")
    out += ["## Do more training rows improve the real rig's free run? (`studies/rows_study.py`)\n",
            "The shipped `bert-real` settings in exact mode at N training rows (the config's stride selection, "
            "ML-II and the solves on the GPU, the config's noise calibration), the linearised free run of every "
            "held-out record, whole and from rest; fit (eq. 14, %). `fit s`: ML-II, solves and calibration on "
            "the GPU.\n"]
    names = rows["validate"]
    short = [n.replace("heldout-", "") for n in names]
    out += [row(["model", "fit s"] + short + ["worst", "mean"]), rule(len(names) + 4)]
    ref = rows.get("reference")
    if ref:
        fits = [ref["records"][n]["fit"] for n in names]
        out.append(row([ref["what"], "-"] + [pct(f) for f in fits] + [pct(min(fits)), pct(sum(fits) / len(fits))]))
    for r in rows["rows"]:
        out.append(row([f"exact, N = {r['n_train']}", pct(r["fit_seconds"], 0)]
                       + [pct(r["records"][n]["fit"]) for n in names] + [pct(r["worst_fit"]), pct(r["mean_fit"])]))
    if ref and rows["rows"]:
        best = max(rows["rows"], key=lambda r: r["mean_fit"])
        wins = " / ".join(str(sum(r["records"][n]["fit"] > ref["records"][n]["fit"] for n in names))
                          for r in rows["rows"])
        sizes = " / ".join(str(r["n_train"]) for r in rows["rows"])
        ref_mean = sum(ref["records"][n]["fit"] for n in names) / len(names)
        out.append(f"\nExact at N = {sizes} beats the shipped sparse model on {wins} of the {len(names)} held-out "
                   f"records; the mean fit peaks at N = {best['n_train']} "
                   f"({pct(best['mean_fit'])} against {pct(ref_mean)}) "
                   "and does not keep rising with N: more rows of the same records do not by themselves make the "
                   "free run more faithful.\n")
    return "\n".join(out) + "\n"
