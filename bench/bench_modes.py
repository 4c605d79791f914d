"""Free-run throughput by mode: 1024 Monte Carlo paths on the Bouc-Wen 50 N sweep.

Product (``GPNARX(...).fit(records, theta=theta).simulate(u, ...)``, the shipped code path), same
hyperparameters (ML-II, one start, on a stride subset) for every mode:
  * exact, N=2000 training points (MC);
  * sparse, M=256 and M=512 inducing points (k-means) over all 4064 training rows (MC);
  * linearised (first-order propagation, one path) on the exact N=2000 model and on sparse M=512.

Equal-work comparisons (same model size, float64, same process, so the same BLAS threads and
malloc; repetitions interleaved A, B, A, B; the median of the per-repetition ratios):
  * ``ratio=`` (headline) and ``ratio_exact=``: exact MC against the per-step loop a user would
    write around scikit-learn's ``GaussianProcessRegressor.predict(X, return_std=True)`` at the
    SAME N (N=2000, same rows, kernel and hyperparameters; means checked equal), on the first steps
    of the record from rest (exact MC costs ~0.1-0.5 s per step);
  * ``ratio_sparse<M>=``: sparse MC against ``_common.NumpySparse``, a plain numpy/scipy evaluation
    of the same sparse posterior (same Z, w, G; scikit-learn has no sparse GP), same steps;
  * ``linear_vs_mc=``: linearised against the product's own exact MC on the same N=2000 model
    (MC time for the record extrapolated from its measured steps); ``linear_vs_mc_sparse=``: the
    same on sparse M=512, whose MC runs the whole record.
User comparison (NOT equal work; ``user_baseline=``): scikit-learn exact at N=4000 (about the
protocol's 4064 rows, what a user without a sparse mode would run), library defaults, a few steps
measured half before and half after the product's runs, extrapolated to the record:
``user_ratio=`` (sparse M=256 MC path-steps/s over it), ``user_ratio_sparse512=``,
``user_linear_speedup=`` (its extrapolated record time / the exact linearised run's wall time).

    python bench/bench_modes.py [--quick] [--threads N]
"""
from __future__ import annotations

import time
import warnings

import numpy as np

import _common as C
from gpnarx.model.estimator import GPNARX
from gpnarx.model.metrics import coverage, fit_percent

# equal work with the exact baselines: every Monte Carlo run here passes local=False, so the product evaluates
# eq. 8-9 at every path (its default checked local model is compared like for like in bench_mc_speed.py)


def main():
    args = C.parse_args(__doc__)
    q = args.quick
    P = 256 if q else 1024
    N_exact = 500 if q else 2000
    N_user = 1000 if q else 4000
    Ms = (32, 64) if q else (256, 512)
    seg = 8 if q else 20  # steps per interleaved repetition (exact and equal-work baselines)
    reps = 2 if q else 3
    user_steps = 2 if q else 6  # split half before, half after the product runs
    rec_len = 150 if q else None  # quick: first 150 samples of the 50 N sweep

    t0 = time.perf_counter()
    theta, _, hyp = C.hyperparameters(q)
    pairs, _, r50 = C.protocol()
    u50 = r50.u if rec_len is None else r50.u[:rec_len]
    y50 = r50.y if rec_len is None else r50.y[:rec_len]
    n = u50.size
    noise = float(np.exp(theta[-1]))
    y0 = np.zeros(C.NY)  # from rest, like the product's simulate() without y0
    uu = np.concatenate([np.zeros(C.NY), u50])  # the baseline loops start after ny known (zero) outputs
    quiet = warnings.catch_warnings

    def model(mode, **kw):
        m = GPNARX(ny=C.NY, nu=C.NU, mode=mode, max_train_points=N_exact, n_restarts=0, **kw)
        t = time.perf_counter()
        m.fit(pairs, theta=theta)
        return m, time.perf_counter() - t

    # user comparison: sklearn at N_user with the same hyperparameters and standardisation
    Xu, yu, xsc, ysc = C.training_set(N_user)
    gpr_user = C.sk_gpr(theta, Xu, yu)

    def user_run(steps, seed):
        with quiet():
            warnings.simplefilter("ignore")
            *_, s, ps, _ = C.sklearn_freerun(gpr_user, noise, xsc, ysc, uu[: C.NY + steps], y0, P, seed=seed)
        return s, ps

    user_run(1, 0)  # warm-up
    user = [user_run(user_steps // 2, 1)]

    # equal-work baseline of the exact mode: sklearn at the same N on the same rows
    exact, build_exact = model("exact")
    Xe, ye, _, _ = C.training_set(N_exact)
    same_rows = bool(np.allclose(Xe, exact.posterior_.points))
    gpr = C.sk_gpr(theta, Xe, ye)
    Xb = exact.posterior_.points[:P] + 0.05 * np.random.default_rng(0).standard_normal((min(P, N_exact), C.D))
    mean_diff_exact = float(np.max(np.abs(exact.posterior_.predict(Xb)[0] - gpr.predict(Xb))))
    u_seg = u50[:seg]

    def prod(m):
        def run():
            fr = m.simulate(u_seg, n_paths=P, seed=0, local=False)
            return fr.path_steps / fr.seconds
        return run

    def sk_exact():
        with quiet():
            warnings.simplefilter("ignore")
            *_, s, ps, _ = C.sklearn_freerun(gpr, noise, xsc, ysc, uu[: C.NY + seg], y0, P)
        return ps / s

    exact.simulate(u50[:2], n_paths=P, seed=0, local=False)  # warm-up
    sk_exact()
    ex = C.interleave({"product": prod(exact), "baseline": sk_exact}, reps)
    rows = {"exact": dict(N=N_exact, ps=C.median(ex["product"]), seg_ps=C.median(ex["product"]), build=build_exact,
                          run=None,
                          base_ps=C.median(ex["baseline"]), ratio=C.median_ratio(ex["product"], ex["baseline"]))}

    sparse = {}
    mean_diff_sparse = 0.0
    for M in Ms:
        m, build = model("sparse", n_inducing=M)
        sparse[M] = m
        ref = C.NumpySparse(m.posterior_)
        Xs_ = m.posterior_.points + 0.05 * np.random.default_rng(1).standard_normal(m.posterior_.points.shape)
        mean_diff_sparse = max(mean_diff_sparse, float(np.max(np.abs(m.posterior_.predict(Xs_)[0]
                                                                       - ref.predict(Xs_)[0]))))

        def np_sparse(ref=ref, m=m):
            *_, s, ps, _ = C.mc_freerun(ref.predict, noise, m.x_scaler_, m.y_scaler_, uu[: C.NY + seg], y0, P)
            return ps / s

        m.simulate(u50[:2], n_paths=P, seed=0, local=False)  # warm-up
        np_sparse()
        sp = C.interleave({"product": prod(m), "baseline": np_sparse}, reps)
        fr = m.simulate(u50, n_paths=P, seed=0, local=False)  # the whole record: fit, coverage, path-steps/s
        rows[f"sparse{M}"] = dict(N=M, ps=fr.path_steps / fr.seconds, seg_ps=C.median(sp["product"]), build=build,
                                  run=fr, base_ps=C.median(sp["baseline"]),
                                  ratio=C.median_ratio(sp["product"], sp["baseline"]))

    lin = {}
    for name, m in (("exact", exact), ("sparse", sparse[Ms[-1]])):
        m.simulate(u50[:5], method="linear")
        lin[name] = m.simulate(u50, method="linear")

    user.append(user_run(user_steps - user_steps // 2, 2))
    user_sec_per_step = sum(s for s, _ in user) / (sum(ps for _, ps in user) / P)
    user_ps = P / user_sec_per_step
    user_record_s = n * user_sec_per_step  # extrapolated MC time for the whole record
    exact_record_s = n * P / rows["exact"]["ps"]  # the product's exact MC, extrapolated from its measured steps
    sparse_mc_s = rows[f"sparse{Ms[-1]}"]["run"].seconds  # measured on the whole record

    print(f"bench_modes: Bouc-Wen 50 N sweep ({n} samples), {P} paths, D={C.D}; hyperparameters: {hyp}; "
          f"setup {time.perf_counter() - t0:.1f} s in all; {C.env_note()}")
    print(f"  equal work: {reps} interleaved repetitions of {seg} steps from rest, same model size on both sides, "
          f"median ratio; exact baseline = sklearn at N={N_exact} (same rows: {same_rows}, max |mean diff| "
          f"{mean_diff_exact:.1e}); sparse baseline = numpy reference of the same posterior (max |mean diff| "
          f"{mean_diff_sparse:.1e})")
    print(f"  {'mode':<12} {'N/M':>5} {'seg. path-steps/s':>17} {'baseline':>10} {'ratio':>6} {'record':>10} "
          f"{'fit %':>6} {'cov99 %':>7} {'build s':>7}   (path-steps/s; record: whole record, sparse only)")
    for name, r in rows.items():
        fitp = cov = float("nan")
        if r["run"] is not None:
            fitp = fit_percent(y50, r["run"].mean)
            cov = coverage(y50, r["run"].lower, r["run"].upper)
        rec = f"{r['ps']:10,.0f}" if r["run"] is not None else f"{'':>10}"
        print(f"  {name + ' MC':<12} {r['N']:>5} {r['seg_ps']:17,.0f} {r['base_ps']:10,.0f} {r['ratio']:6.2f} {rec} "
              f"{fitp:6.1f} {cov:7.1f} {r['build']:7.2f}")
    for name, fr in lin.items():
        print(f"  {'linear ' + name:<12} {'':>5} {n} steps in {fr.seconds:.2f} s; "
              f"fit {fit_percent(y50, fr.mean):.1f} %, cov99 {coverage(y50, fr.lower, fr.upper):.1f} %")
    print(f"  linearised vs the product's own MC on the same model: exact N={N_exact} "
          f"{exact_record_s / lin['exact'].seconds:.1f}x (MC extrapolated to the record), sparse M={Ms[-1]} "
          f"{sparse_mc_s / lin['sparse'].seconds:.1f}x (measured)")
    print(f"  user comparison (NOT equal work): sklearn exact N={N_user}, {user_sec_per_step:.3f} s/step on "
          f"{sum(ps for _, ps in user) // P} steps, {user_ps:,.0f} path-steps/s, record extrapolated to "
          f"{user_record_s:.0f} s: sparse M={Ms[0]} x{rows[f'sparse{Ms[0]}']['ps'] / user_ps:.1f}, "
          f"linearised exact x{user_record_s / lin['exact'].seconds:.0f}")
    C.result(exact=rows["exact"]["ps"], baseline=rows["exact"]["base_ps"], baseline_what=f"sklearn-exact-N{N_exact}",
             ratio=rows["exact"]["ratio"], ratio_exact=rows["exact"]["ratio"],
             **{f"sparse{M}": rows[f"sparse{M}"]["ps"] for M in Ms},
             **{f"ratio_sparse{M}": rows[f"sparse{M}"]["ratio"] for M in Ms},
             **{f"baseline_sparse{M}": rows[f"sparse{M}"]["base_ps"] for M in Ms},
             sparse_baseline_what="numpy-reference-same-posterior",
             linear_s=lin["exact"].seconds, linear_vs_mc=exact_record_s / lin["exact"].seconds,
             linear_vs_mc_sparse=sparse_mc_s / lin["sparse"].seconds,
             user_baseline=f"sklearn-exact-N{N_user}", user_baseline_ps=user_ps, user_record_s=user_record_s,
             user_ratio=rows[f"sparse{Ms[0]}"]["ps"] / user_ps,
             **{f"user_ratio_sparse{Ms[-1]}": rows[f"sparse{Ms[-1]}"]["ps"] / user_ps},
             user_linear_speedup=user_record_s / lin["exact"].seconds,
             max_mean_diff=max(mean_diff_exact, mean_diff_sparse), N=N_exact, reps=reps, steps=seg,
             paths=P, record=n, load=C.load(), blas_threads=C.blas_threads())


if __name__ == "__main__":
    main()
