"""Sparse against exact accuracy on the Bouc-Wen validation records.

Both models are ``GPNARX`` fits of the same training sweeps (``_common.protocol``: 10/80 N with the
paper's noise, ny=20, nu=17) with the same hyperparameters (ML-II, one start, stride subset):

* baseline: exact posterior on N=2000 stride-selected rows;
* product: sparse, M inducing points (k-means, default 256) over all training rows.

Scored on every validation record of ``configs/bouc-wen.toml`` (35.59 Hz sine and random-phase
multisine at 10/50/80 N) against the noise-free output: fit % (eq. 14) of the free-run mean and
coverage of the 99% band. Both use the linearised propagation (``method="linear"``), whose band
``bench_linear_band.py`` measures within 1.5 % of 1024-path Monte Carlo; exact Monte Carlo on all
six records would take most of an hour on 2 cores. Also printed: the per-record wall time of
each (exact / sparse = the sparse speed-up). Target: coverage and fit within 1 point of exact.

Baseline (no scikit-learn equivalent): the product's exact posterior on the ML-II rows, same
hyperparameters, propagation, records and process. ``ratio=`` = the sparse model's lowest coverage
over the records / the exact model's (an accuracy ratio; the sizes differ by design: the exact
posterior holds N=2000 rows, the sparse one M inducing points over all 4064 rows).

    python bench/bench_sparse_accuracy.py [--quick] [--inducing M]
"""
from __future__ import annotations

import numpy as np

import _common as C
from gpnarx.model.estimator import GPNARX
from gpnarx.model.metrics import coverage, fit_percent


def main():
    args = C.parse_args(__doc__, lambda ap: ap.add_argument("--inducing", type=int, default=None,
                                                             help="inducing points of the sparse model (default 256)"))
    q = args.quick
    from gpnarx.training.config import load_config

    theta, _, hyp = C.hyperparameters(q)
    pairs, _, _ = C.protocol()
    n_exact = 300 if q else 2000
    M = args.inducing or (32 if q else 256)
    exact = GPNARX(ny=C.NY, nu=C.NU, mode="exact", max_train_points=n_exact, n_restarts=0).fit(pairs, theta=theta)
    sparse = GPNARX(ny=C.NY, nu=C.NU, mode="sparse", n_inducing=M, max_train_points=n_exact,
                    n_restarts=0).fit(pairs, theta=theta)
    cfg = load_config(C.ROOT / "configs" / "bouc-wen.toml")
    records = cfg.records_for("validate")
    if q:
        records = records[:2]
    print(f"bench_sparse_accuracy: Bouc-Wen validation records, exact N={n_exact} vs sparse M={M}, linearised "
          f"99% bands; hyperparameters: {hyp}; {C.env_note()}")
    print(f"  {'record':<15} {'n':>5} {'fit exact':>9} {'fit sparse':>10} {'cov exact':>9} {'cov sparse':>10} "
          f"{'exact s':>8} {'sparse s':>8}")
    d_fit, d_cov, cov_e, cov_s, t_e, t_s = [], [], [], [], 0.0, 0.0
    for r in records:
        u = r.u[:150] if q else r.u
        clean = np.asarray(r.meta.get("clean_y", r.y))[: u.size]
        y0 = clean[: C.NY] if r.meta.get("initial") == "measured" else None
        fe = exact.simulate(u, method="linear", y0=y0)
        fs_ = sparse.simulate(u, method="linear", y0=y0)
        row = (fit_percent(clean, fe.mean), fit_percent(clean, fs_.mean),
               coverage(clean, fe.lower, fe.upper), coverage(clean, fs_.lower, fs_.upper))
        d_fit.append(row[1] - row[0])
        d_cov.append(row[3] - row[2])
        cov_e.append(row[2])
        cov_s.append(row[3])
        t_e += fe.seconds
        t_s += fs_.seconds
        print(f"  {r.name:<15} {u.size:>5} {row[0]:9.2f} {row[1]:10.2f} {row[2]:9.2f} {row[3]:10.2f} "
              f"{fe.seconds:8.2f} {fs_.seconds:8.2f}", flush=True)
    worst_fit = max(d_fit, key=abs)
    worst_cov = max(d_cov, key=abs)
    print(f"  largest difference sparse - exact: fit {worst_fit:+.2f} points, coverage {worst_cov:+.2f} points; "
          f"wall {t_e:.1f} s exact vs {t_s:.1f} s sparse")
    C.result(min_coverage=min(cov_s), baseline=min(cov_e), baseline_what=f"product-exact-N{n_exact}-linear",
             ratio=min(cov_s) / min(cov_e),
             worst_fit_diff=worst_fit, worst_coverage_diff=worst_cov, speedup=t_e / t_s, M=M, N=n_exact,
             load=C.load(), blas_threads=C.blas_threads())


if __name__ == "__main__":
    main()
