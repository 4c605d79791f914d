"""k-step-ahead prediction at k = 64 against the free run: the same record, model and process.

On the shipped ``bert-real`` bundle and a real record (default the 0.10 V noise run's first 16 s, held out), the
k-step-ahead prediction ``GPNARX.simulate(u, y=y, horizon=64)`` (the run restarted from the measured outputs every
64 samples; linearised: the segments as one batch, ``model.freerun.horizon``) against the free run from the
record's measured start ``simulate(u, y0=y[:ny])``, the work a user would otherwise run. Repetitions interleaved
(free, k-step, free, ...); the median of the per-repetition ratios.

- ``kstep_s``, ``baseline`` (the free run's seconds): the median wall seconds of each, linearised;
  ``ratio`` = kstep_s / baseline (lower: the k-step prediction is faster);
- ``mc_kstep_s``, ``mc_free_s``, ``mc_ratio``: the same by Monte Carlo (``--mc-paths`` paths, the first
  ``--mc-seconds`` s of the record, one repetition each);
- ``fit_k64``, ``fit_free``: the fits (eq. 14) of both, linearised.

    python bench/bench_kstep.py [--quick] [--registry R] [--record PATH] [--seconds S] [--reps N]
                                [--mc-paths P] [--mc-seconds S] [--threads N]

--quick: a small Bouc-Wen model, 3000 samples, 64 paths on 600 samples.
"""
from __future__ import annotations

import time

import _common as C
from gpnarx.model.metrics import fit_percent

K = 64


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def main() -> None:
    args = C.parse_args(__doc__, extra=lambda p: (p.add_argument("--registry"), p.add_argument("--record"),
                                                   p.add_argument("--seconds", type=float, default=16.0),
                                                   p.add_argument("--reps", type=int, default=3),
                                                   p.add_argument("--mc-paths", type=int, default=256),
                                                   p.add_argument("--mc-seconds", type=float, default=4.0)))
    if args.quick:
        from gpnarx.model.estimator import GPNARX

        pairs, _, r50 = C.protocol()
        model = GPNARX(ny=C.NY, nu=C.NU, mode="sparse", n_inducing=64, max_train_points=500).fit(
            pairs, theta=C.THETA_REF)
        u, y, fs = r50.u[:3000], r50.y[:3000], 750.0
        paths, mc_n, reps, what = 64, 600, 2, "quick_Bouc-Wen"
    else:
        import bench_realtime as R

        from gpnarx.storage.record_files import read_record
        from gpnarx.storage.registry import Registry

        reg, _ = R.bert_registry(args.registry)
        model = Registry(reg, lazy=True).scan(only="bert-real").get("bert-real").model
        rec = read_record(args.record or R.bert_data() / "Rand" / "Rand0p10")
        fs = rec.fs
        n = min(rec.n, int(round(args.seconds * fs)))
        u, y = rec.u[:n], rec.y[:n]
        paths, reps = int(args.mc_paths), int(args.reps)
        mc_n = min(n, int(round(args.mc_seconds * fs)))
        what = f"bert-real,_{rec.name}"
    ny = model.ny

    def free():
        return model.simulate(u, y0=y[:ny], method="linear")

    def kstep():
        return model.simulate(u, y=y, horizon=K, method="linear")

    free_s, kstep_s, ratios = [], [], []
    for _ in range(reps):
        tf, f = _timed(free)
        tk, k = _timed(kstep)
        free_s.append(tf)
        kstep_s.append(tk)
        ratios.append(tk / tf)
    mc_free_s, _ = _timed(lambda: model.simulate(u[:mc_n], y0=y[:ny], n_paths=paths, seed=0))
    mc_kstep_s, _ = _timed(lambda: model.simulate(u[:mc_n], y=y[:mc_n], horizon=K, n_paths=paths, seed=0))
    print(f"# {what}: {u.size / fs:.0f} s, k = {K}, linearised {reps} interleaved repetitions; Monte Carlo "
          f"{paths} paths on {mc_n / fs:.1f} s; {C.env_note()}")
    C.result(bench="kstep", model=what.replace(" ", "_"), k=K, seconds=u.size / fs, reps=reps,
             kstep_s=C.median(kstep_s), fit_k64=fit_percent(y, k.mean), fit_free=fit_percent(y, f.mean),
             mc_paths=paths, mc_seconds=mc_n / fs, mc_kstep_s=mc_kstep_s, mc_free_s=mc_free_s,
             mc_ratio=mc_kstep_s / mc_free_s, load=C.load(), blas_threads=C.blas_threads(),
             baseline=C.median(free_s), baseline_what="free_run_from_the_measured_start_same_record_model_process_s",
             ratio=C.median(ratios))


if __name__ == "__main__":
    main()
