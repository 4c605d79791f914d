"""Monte Carlo free run on the JAX backend (a GPU where JAX has one) against the numpy backend, same bundle.

Product: ``GPNARX.simulate(..., backend="jax")`` (``model.freerun_jax``): eq. 8-9 exact at every path,
every step, float64, one compiled scan per block of steps, on the device JAX sees (``device=``). It
runs the whole record (default 64 s, 65,536 steps) with ``--paths`` paths (default 4096, the paper's
section 4.3). Path-steps per second (``pss=``) and the real-time factor (``realtime=``: record seconds
per wall second, compile excluded: a first call of the block length compiles, ``compile_s=``).

Baseline (``baseline=``, ``ratio=``): the numpy backend, the product's default (``freerun.simulate_mc``
with its checked local model), same bundle, paths and seed, on this machine's cores, timed on the
first ``--baseline-seconds`` of the record (the whole record at 4096 paths takes minutes there); both
backends are also timed on that same segment, interleaved (``ratio_segment=``, equal work).

Bands (``band_*``): on that segment, the largest and the median difference between the two backends'
0.5 % / 99.5 % band edges and means, in units of the band's Monte Carlo standard error (estimated as
the median |difference| of the JAX backend's bands at seeds 0 and 1 over 0.6745 sqrt(2), as for two
independent normal errors; two independent runs of one backend then differ by a median of 0.95); and each
band's coverage of the measured output (points). Also the linearised method on both backends over the
whole record (``linear_realtime_*``).

    python bench/bench_gpu.py --bundle DIR --record REC [--paths 4096] [--seconds 64] [--quick]

DIR: a bundle folder (e.g. REGISTRY/bert-real/1); REC: a record gpnarx reads (an LMS folder, .npz, .csv).
--quick: a small Bouc-Wen sparse model, 256 paths, 2 s; for the smoke test only.
"""
from __future__ import annotations

import time

import numpy as np

import _common as C


def _args(ap):
    ap.add_argument("--bundle", help="bundle folder (registry/NAME/VERSION)")
    ap.add_argument("--record", help="record file or LMS folder")
    ap.add_argument("--paths", type=int, default=4096)
    ap.add_argument("--seconds", type=float, default=64.0, help="record length run on the JAX backend [s]")
    ap.add_argument("--baseline-seconds", type=float, default=4.0, help="segment both backends run [s]")
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--unroll", type=int, default=None,
                    help="steps per compiled loop iteration (default: the module's)")


def quick_setup():
    from gpnarx.model.estimator import GPNARX

    pairs, _, r50 = C.protocol()
    m = GPNARX(ny=C.NY, nu=C.NU, mode="sparse", n_inducing=64, max_train_points=500).fit(pairs, theta=C.THETA_REF)
    return m, r50.u, r50.y, 750.0, "bouc-wen-quick-M64"


def main() -> None:
    args = C.parse_args(__doc__, _args)
    from gpnarx.model.backend import jax_device
    from gpnarx.model.freerun import jax_backend as freerun_jax

    if args.unroll:
        freerun_jax.SCAN_UNROLL = int(args.unroll)

    if args.quick:
        model, u, y, fs, what = quick_setup()
        args.paths, args.seconds, args.baseline_seconds, args.reps = 256, 2.0, 0.5, 1
    else:
        from gpnarx.storage.bundle import load_bundle
        from gpnarx.storage.record_files import read_record

        b = load_bundle(args.bundle)
        rec = read_record(args.record, fs_default=b.fs)
        model, u, y, fs, what = b.model, rec.u, rec.y, rec.fs, f"{b.name}:{b.version}"
    n = min(u.size, int(round(args.seconds * fs)))
    nb = min(n, int(round(args.baseline_seconds * fs)))
    P = int(args.paths)
    device = jax_device()
    print(f"model {what}, device {device}, {P} paths, {n} steps ({n / fs:.1f} s), baseline segment {nb} steps",
          flush=True)

    # compile the block programs of the whole run and of the segment (their block lengths can differ)
    t = time.perf_counter()
    model.simulate(u[: min(n, freerun_jax.MAX_BLOCK_STEPS)], n_paths=P, seed=0, backend="jax")
    compile_s = time.perf_counter() - t
    model.simulate(u[:nb], n_paths=P, seed=0, backend="jax")
    # equal work on the segment, interleaved
    def timed(backend):
        t0 = time.perf_counter()
        model.simulate(u[:nb], n_paths=P, seed=0, backend=backend)
        return time.perf_counter() - t0

    seg = C.interleave({"jax": lambda: timed("jax"), "numpy": lambda: timed("numpy")}, args.reps)
    runs = {k: model.simulate(u[:nb], n_paths=P, seed=s, backend=k) for k, s in (("jax", 0), ("numpy", 0))}
    other = model.simulate(u[:nb], n_paths=P, seed=1, backend="jax")
    other_np = model.simulate(u[:nb], n_paths=P, seed=1, backend="numpy")
    t = time.perf_counter()
    whole = model.simulate(u[:n], n_paths=P, seed=0, backend="jax")
    jax_s = time.perf_counter() - t
    ja, nu_ = runs["jax"], runs["numpy"]
    # two independent runs differ by N(0, 2 se^2): median |difference| = 0.6745 sqrt(2) se
    se = {k: float(np.median(np.abs(getattr(ja, k) - getattr(other, k)))) / (0.6745 * np.sqrt(2.0))
          for k in ("lower", "upper")}
    se_all = max(min(se.values()), 1e-300)
    diffs = {k: np.abs(getattr(ja, k) - getattr(nu_, k)) / se_all for k in ("lower", "upper", "mean")}
    ref = {k: np.abs(getattr(nu_, k) - getattr(other_np, k)) / se_all for k in ("lower", "upper", "mean")}
    cov = {k: 100.0 * float(np.mean((y[:nb] >= r.lower) & (y[:nb] <= r.upper))) for k, r in runs.items()}
    lin = {}
    for k in ("numpy", "jax"):
        model.simulate(u[: min(n, 256)], method="linear", backend=k)
        t = time.perf_counter()
        model.simulate(u[:n], method="linear", backend=k)
        lin[k] = (n / fs) / (time.perf_counter() - t)
    pss_jax = n * P / jax_s
    pss_np_seg = nb * P / C.median(seg["numpy"])
    pss_jax_seg = nb * P / C.median(seg["jax"])
    whole_cov = 100.0 * float(np.mean((y[:n] >= whole.lower) & (y[:n] <= whole.upper)))
    C.result(bench="gpu", device=device.replace(" ", "_"), model=what, paths=P, steps=n, pss=pss_jax,
             realtime=(n / fs) / jax_s, seconds=jax_s, compile_s=compile_s, coverage_whole=whole_cov,
             diverged=whole.diverged_paths, baseline=pss_np_seg, baseline_what="numpy_backend_local_model_same_cores",
             ratio=pss_jax / pss_np_seg, ratio_segment=C.median_ratio(seg["numpy"], seg["jax"]),
             pss_segment=pss_jax_seg,
             band_max_se=max(float(diffs["lower"].max()), float(diffs["upper"].max())),
             band_median_se=float(np.median(np.concatenate([diffs["lower"], diffs["upper"]]))),
             mean_max_se=float(diffs["mean"].max()),
             numpy_seeds_band_max_se=max(float(ref["lower"].max()), float(ref["upper"].max())),
             numpy_seeds_band_median_se=float(np.median(np.concatenate([ref["lower"], ref["upper"]]))),
             numpy_seeds_mean_max_se=float(ref["mean"].max()), unroll=freerun_jax.SCAN_UNROLL,
             coverage_jax=cov["jax"], coverage_numpy=cov["numpy"],
             linear_realtime_jax=lin["jax"], linear_realtime_numpy=lin["numpy"])


if __name__ == "__main__":
    main()
