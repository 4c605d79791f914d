"""Does the Monte Carlo local model's check bound its error at every path? Measured on whole paths' sets.

``simulate_mc`` serves each step from a second-order model of eq. 8-9 around the paths' mean regressor
(``gp.LocalModel``) and checks it against eq. 8-9 at 12 paths only: the 6 farthest from the mean regressor
and 6 random ones (``freerun.LOCAL_CHECKS``). The claim behind it (docs/numerics.md section 6): the model's
error grows with the distance from the mean regressor, so the farthest paths bound it for all. This bench
tests the claim where it matters, on the shipped model and real records: at every step the check passes, the
model's mean and latent variance at EVERY path are compared with eq. 8-9 evaluated exactly at every path
(``posterior.predict``), as errors in units of the check's tolerances (mean: ``LOCAL_TOL_MEAN`` predictive
std; variance: ``LOCAL_TOL_VAR`` of the predictive variance; 1 = at the tolerance).

Product figure: ``max_err_all=``, the largest error at any path of any step the check passed, and
``exceed_steps=``, the steps where the check passed while some path was beyond the tolerance (the
check's misses; the claim says 0). Baseline, what the check itself sees: ``baseline=`` the largest error
at the 6 farthest paths over the same steps; ``ratio=`` = max_err_all / baseline (1: the farthest paths held
the worst error). Also ``argmax_far12=``: the share of steps [%] whose worst path is among the 12 farthest,
and per record class (``max_err_all_sine=``, ``exceed_steps_noise=``, ...).

Records (1024 paths, seed 0, from rest, the first ``--seconds`` of each, default 1 s): the 0.10 V sweep,
the 0.10 V and 0.25 V noise runs and the 20 Hz sine (near the first resonance), read from the shared
BERT folder. Exact evaluation at every path costs about 50 ms a step on 2 cores.

    python bench/bench_local_check.py [--quick] [--registry R] [--seconds S] [--threads N]

Without --registry a bundle is trained from configs/bert-real.toml into a cache (bench_realtime.py's).
--quick: bench_mc_speed's small Bouc-Wen sparse model on its 60-step segment (256 paths), for the smoke test.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

import _common as C
from gpnarx.model.freerun import mc as freerun

RECORDS = (("Chirp/Chirp0to40Hz/Chirp0p10", "sweep"), ("Rand/Rand0p10", "noise"), ("Rand/Rand0p25", "noise"),
           ("Sine/Sine_20Hz", "sine"))


def audited_run(model, u, n_paths: int, y0=None) -> np.ndarray:
    """``simulate_mc`` on u with every local step audited: rows (max error at any path, max error at the 6
    farthest paths, 1 when the worst path is among the 12 farthest), in tolerance units, for each step the
    check passed with the model serving every path."""
    post = model.posterior_
    rows = []
    served = freerun._LocalStep.__call__

    def audited(step, i, mu, var, n_exact=0):
        ok = served(step, i, mu, var, n_exact)
        if ok and not n_exact:
            st, ny = step.st, step.ny
            X = np.empty((st.P, st.Xs.shape[1]))
            np.subtract(st.ylag_raw, step.xm, out=X[:, :ny])
            X[:, :ny] /= step.xs
            X[:, ny:] = st.Ulag[i]
            m_ex, v_ex = post.predict(X)
            pv = v_ex + step.noise
            err = np.maximum(np.abs(mu - m_ex) / (freerun.LOCAL_TOL_MEAN * np.sqrt(pv)),
                             np.abs(var - v_ex) / (freerun.LOCAL_TOL_VAR * pv))
            order = np.argsort(np.einsum("ji,ji->i", step.d_t, step.d_t))
            rows.append((float(err.max()), float(err[order[-6:]].max()), float(np.argmax(err) in order[-12:])))
        return ok

    freerun._LocalStep.__call__ = audited
    try:
        freerun.simulate_mc(post, model.x_scaler_, model.y_scaler_, model.ny, model.nu, u, n_paths=n_paths, seed=0,
                            y0=y0, include_noise=model.include_noise)
    finally:
        freerun._LocalStep.__call__ = served
    return np.array(rows, dtype=float).reshape(-1, 3)


def main():
    def extra(ap):
        ap.add_argument("--registry", default=None, help="registry holding bert-real (default: train into a cache)")
        ap.add_argument("--seconds", type=float, default=1.0, help="seconds of each record from rest (default 1)")

    args = C.parse_args(__doc__, extra)
    if not args.seconds > 0:
        raise SystemExit("--seconds must be a positive number of seconds")
    if args.quick:
        import bench_mc_speed as S

        model, segs, note, _, _ = S.quick_model()
        runs = [(seg[0], seg[4], seg[1], seg[3]) for seg in segs]
        paths = 256
    else:
        import bench_realtime as R

        from gpnarx.storage.record_files import read_record
        from gpnarx.storage.registry import Registry

        reg, note = R.bert_registry(args.registry)
        bundle = Registry(reg).scan().get("bert-real")
        model, note = bundle.model, f"{note}; bert-real:{bundle.version}"
        runs = []
        for sub, cls in RECORDS:
            rec = read_record(str(R.bert_data() / sub), fs_default=bundle.fs)
            runs.append((f"{Path(sub).name} first {args.seconds:g} s from rest", cls,
                         rec.u[: int(round(args.seconds * rec.fs))], None))
        paths = 1024
    t0 = time.perf_counter()
    per_class: dict[str, list[np.ndarray]] = {}
    print(f"bench_local_check: {note}; {paths} paths; tolerances: mean {freerun.LOCAL_TOL_MEAN} predictive std, "
          f"latent variance {freerun.LOCAL_TOL_VAR} of the predictive variance; BLAS threads {C.blas_threads()}")
    print(f"  {'record':<40} {'steps':>6} {'audited':>7} {'max all':>8} {'max far6':>8} {'exceed':>6} "
          f"{'worst in far12':>14}")
    for name, cls, u, y0 in runs:
        a = audited_run(model, u, paths, y0)
        per_class.setdefault(cls, []).append(a)
        print(f"  {name:<40} {u.size:>6} {a.shape[0]:>7} {a[:, 0].max(initial=0.0):>8.3f} "
              f"{a[:, 1].max(initial=0.0):>8.3f} {int((a[:, 0] > 1.0).sum()):>6} {100 * a[:, 2].mean():>13.0f}%")
    every = np.vstack([a for v in per_class.values() for a in v])
    if every.shape[0] == 0:
        raise SystemExit("no step was served by the local model: nothing to audit")
    fields = {}
    for cls, arrs in per_class.items():
        a = np.vstack(arrs)
        fields[f"max_err_all_{cls}"] = a[:, 0].max(initial=0.0)
        fields[f"exceed_steps_{cls}"] = int((a[:, 0] > 1.0).sum())
    top, far = float(every[:, 0].max()), float(every[:, 1].max())
    C.result(max_err_all=top, baseline=far, baseline_what="max-error-at-the-6-farthest-paths-same-steps",
             ratio=top / far if far > 0 else float("nan"), exceed_steps=int((every[:, 0] > 1.0).sum()),
             audited_steps=every.shape[0], argmax_far12=100.0 * float(every[:, 2].mean()),
             median_err_all=float(np.median(every[:, 0])), paths=paths, seconds=time.perf_counter() - t0,
             **fields, load=C.load(), blas_threads=C.blas_threads())


if __name__ == "__main__":
    main()
