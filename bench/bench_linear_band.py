"""Linearised propagation against Monte Carlo on the verification sweeps.

Product: one sparse GP-NARX (M=256 inducing points over all training rows, the shipped Bouc-Wen
mode; hyperparameters by ML-II, one start, on a stride subset) on the Bouc-Wen protocol
(``_common.protocol``: 10/80 N training sweeps with the paper's noise). For each verification
sweep (10, 50, 80 N) it runs the free run twice:

* Monte Carlo, 1024 paths (the baseline here: the band the paper's method defines), and
* the first-order (linearised) mean/variance propagation of ``model.freerun.simulate_linear``.

Printed per sweep: the mean 99% band width of each [m] and their ratio (linear / MC, target
within 0.8-1.2), the share of samples where the two widths differ by more than 20 % and the
time of the largest relative difference (where they differ), the fit % of both means against
the noise-free response, and the wall times (MC / linear = speed-up of the linearised mode).

Baseline (no scikit-learn equivalent): the product's own 1024-path Monte Carlo band on the same
model, record and process. ``ratio=`` = linear / MC mean band width on the sweep where they differ
most (an accuracy ratio: same model, M, float64, BLAS threads).

    python bench/bench_linear_band.py [--quick]
"""
from __future__ import annotations

import numpy as np

import _common as C
from gpnarx.model.estimator import GPNARX
from gpnarx.model.metrics import fit_percent

AMPLITUDES = (10.0, 50.0, 80.0)  # N


def main():
    args = C.parse_args(__doc__)
    q = args.quick
    paths = 128 if q else 1024
    rec_len = 200 if q else None
    theta, _, hyp = C.hyperparameters(q)
    pairs, _, _ = C.protocol()
    m = GPNARX(ny=C.NY, nu=C.NU, mode="sparse", n_inducing=64 if q else 256,
               max_train_points=500 if q else 2000, n_restarts=0).fit(pairs, theta=theta)
    print(f"bench_linear_band: Bouc-Wen verification sweeps, sparse M={m.n_inducing}, {paths} MC paths vs "
          f"linearised; hyperparameters: {hyp}; {C.env_note()}")
    print(f"  {'sweep':>6} {'MC width m':>11} {'lin width m':>11} {'ratio':>6} {'>20% diff':>9} "
          f"{'worst at s':>10} {'fit MC':>7} {'fit lin':>7} {'MC s':>7} {'lin s':>6} {'speed-up':>8}")
    kv = {}
    rows = []
    for a in AMPLITUDES:
        r = C.record(a)
        u = r.u if rec_len is None else r.u[:rec_len]
        y = r.y if rec_len is None else r.y[:rec_len]
        mc = m.simulate(u, n_paths=paths, seed=0)
        lin = m.simulate(u, method="linear")
        w_mc = mc.upper - mc.lower
        w_lin = lin.upper - lin.lower
        ratio = float(np.mean(w_lin) / np.mean(w_mc))
        rel = np.abs(w_lin - w_mc) / np.maximum(w_mc, 1e-300)
        worst = int(np.argmax(rel))
        share = float(np.mean(rel > 0.2) * 100)
        rows.append((ratio, float(np.mean(w_lin)), float(np.mean(w_mc)), a))
        print(f"  {a:>5.0f}N {np.mean(w_mc):11.3e} {np.mean(w_lin):11.3e} {ratio:6.3f} {share:8.1f}% "
              f"{worst / r.fs:10.3f} {fit_percent(y, mc.mean):7.1f} {fit_percent(y, lin.mean):7.1f} "
              f"{mc.seconds:7.2f} {lin.seconds:6.2f} {mc.seconds / lin.seconds:8.1f}", flush=True)
        kv[f"ratio_{a:.0f}N"] = ratio
        kv[f"speedup_{a:.0f}N"] = mc.seconds / lin.seconds
        kv[f"share_over20_{a:.0f}N"] = share
    ratio, w_lin, w_mc, a = max(rows, key=lambda r: abs(r[0] - 1.0))  # the sweep where they differ most
    kv.update(worst_sweep_N=a, width=w_lin, baseline=w_mc, baseline_what=f"product-MC-{paths}-paths-same-model",
              ratio=ratio)
    kv["paths"] = paths
    kv["load"] = C.load()
    kv["blas_threads"] = C.blas_threads()
    C.result(**kv)


if __name__ == "__main__":
    main()
