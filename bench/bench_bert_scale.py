"""The paper-scale BERT run: 4096 Monte Carlo paths x 16384 samples, sparse mode, on 2 cores.

Section 4 of the paper propagates 4096 Monte Carlo paths through 16384-sample (16 s at 1024 Hz)
free-run predictions of the BERT rig. Product: ``GPNARX`` built from the settings of
``configs/bert-standin.toml`` (ny=24, nu=10, eq. 12 kernel, sparse mode, M=256 k-means inducing
points over all training rows, ML-II on 1000 stride-selected rows, no restarts), trained on that
config's four train sweeps of the BERT STAND-IN (a calibrated simulator, never the rig), then
``simulate(u, n_paths=4096)`` on its 0.15 V validation sweep (16384 samples): the whole record,
timed as one call (wall time printed; target < 10 minutes on 2 cores).

Baseline, equal work (``ratio=``): ``_common.NumpySparse``, a plain numpy/scipy evaluation of the
product's own sparse posterior (same M=256 inducing inputs, weights and variance factor; float64;
scikit-learn has no sparse GP) inside the same per-step Monte Carlo loop a user would write, 4096
paths, in this process (same BLAS threads and malloc). Product and baseline run the same first
steps of the record from rest, interleaved (A, B, A, B, ...); ratio = median over repetitions of
baseline time / product time.

User comparison (NOT equal work; ``user_ratio=``, ``user_baseline=``): the per-step loop around
scikit-learn's ``GaussianProcessRegressor.predict(X, return_std=True)``, exact GP on the product's
1000 ML-II rows and hyperparameters, D=34, 4096 paths. It runs only a few steps (half before, half
after the product) and its time for the record is EXTRAPOLATED: record steps x measured seconds per
step. user_ratio = its extrapolated seconds / product's measured seconds for the whole record.
The product's fit % and 99 % coverage on the record are printed (stand-in numbers).

    python bench/bench_bert_scale.py [--quick] [--threads N] [--samples N]

--quick: 256 paths x 600 samples, M=64, 300 ML-II rows, a 3000-sample piece of each train sweep.
--samples: a shorter record than the paper's 16384 samples (the model and paths stay the paper's).
"""
from __future__ import annotations

import time
import warnings

import numpy as np

import _common as C
from gpnarx.model.metrics import coverage, fit_percent
from gpnarx.model.record import Record

# equal work with the exact baselines: every Monte Carlo run here passes local=False, so the product evaluates
# eq. 8-9 at every path (its default checked local model is compared like for like in bench_mc_speed.py)

CONFIG = C.ROOT / "configs" / "bert-standin.toml"


def lagged(u: np.ndarray, nu: int) -> np.ndarray:
    upad = np.concatenate([np.zeros(nu - 1), u])
    return np.stack([upad[nu - 1 - j: nu - 1 - j + u.size] for j in range(nu)], axis=1)


def sklearn_steps(gpr, noise, model, u, n_paths, steps, seed=0):
    """(seconds, steps) of the scikit-learn per-step Monte Carlo loop from rest on u[:steps]."""
    ny, nu = model.ny, model.nu
    P = int(n_paths)
    rng = np.random.default_rng(seed)
    xsc, ysc = model.x_scaler_, model.y_scaler_
    ym, ys = float(ysc.mean_[0]), float(ysc.scale_[0])
    Ulag = lagged(u[:steps], nu)
    ylag = np.zeros((P, ny))
    t0 = time.perf_counter()
    for i in range(steps):
        Xs = xsc.transform(np.hstack([ylag, np.tile(Ulag[i], (P, 1))]))
        mu, sd = gpr.predict(Xs, return_std=True)
        ysamp = (mu + np.sqrt(sd ** 2 + noise) * rng.standard_normal(P)) * ys + ym
        np.quantile(ysamp, [0.005, 0.995])
        ylag = np.hstack([ysamp[:, None], ylag[:, :-1]])
    return time.perf_counter() - t0, steps


def main():
    args = C.parse_args(__doc__, lambda ap: ap.add_argument(
        "--samples", type=int, default=None, help="record length (default 16384; 600 with --quick)"))
    q = args.quick
    P = 256 if q else 4096
    n_rec = args.samples or (600 if q else 16384)
    seg = 8 if q else 20  # steps per interleaved repetition of the equal-work comparison
    reps = 2 if q else 3
    M = 64 if q else None  # None: the config's
    max_train = 300 if q else None
    base_steps = 2 if q else 4  # half before, half after the product

    from gpnarx.training.config import load_config
    from gpnarx.training.prepare import model_from_config

    t0 = time.perf_counter()
    cfg = load_config(CONFIG)
    train = cfg.records_for("train")
    if q:  # a piece of each sweep through the resonance (about 3.5 s at 1024 Hz)
        train = [Record(r.u[2000:5000], r.y[2000:5000], r.fs, name=r.name) for r in train]
    val = cfg.record("sweep-0.15V")
    u, y = val.u[:n_rec], val.y[:n_rec]
    rec_s = time.perf_counter() - t0
    overrides = {}
    if M:
        overrides["inducing"] = M
    if max_train:
        overrides["max_train_points"] = max_train
    model = model_from_config(cfg, **overrides)
    t0 = time.perf_counter()
    model.fit(train)
    fit_s = time.perf_counter() - t0

    # baseline: exact sklearn GP on the product's ML-II rows and hyperparameters
    from gpnarx.model.regressors import stack_regressors
    from gpnarx.model.selection import select_rows

    pairs = [(r.u, r.y) for r in train]
    X, Y, idx = stack_regressors(pairs, model.ny, model.nu)
    Xs = model.x_scaler_.transform(X)
    Ys = (Y - model.y_scaler_.mean_[0]) / model.y_scaler_.scale_[0]
    rows = select_rows(Ys, idx, model.max_train_points, model.selection, model.seed)
    gpr = C.sk_gpr(model.theta_, np.ascontiguousarray(Xs[rows]), Ys[rows])
    noise = float(np.exp(model.theta_[-1]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sklearn_steps(gpr, noise, model, u, P, 1)  # warm-up
        b1 = sklearn_steps(gpr, noise, model, u, P, base_steps // 2, seed=1)
    model.simulate(u[:8], n_paths=P, seed=0, local=False)  # warm-up
    t0 = time.perf_counter()
    run = model.simulate(u, n_paths=P, seed=0, local=False)
    wall = time.perf_counter() - t0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        b2 = sklearn_steps(gpr, noise, model, u, P, base_steps - base_steps // 2, seed=2)
    base_step_s = (b1[0] + b2[0]) / (b1[1] + b2[1])
    base_record_s = base_step_s * n_rec  # EXTRAPOLATED
    ps = run.path_steps / wall
    user_ps = P / base_step_s

    # equal work: the same posterior evaluated by plain numpy, same steps, interleaved
    ref = C.NumpySparse(model.posterior_)
    Zp = model.posterior_.points
    Xchk = Zp + 0.05 * np.random.default_rng(0).standard_normal(Zp.shape)
    ref_mean_diff = float(np.max(np.abs(model.posterior_.predict(Xchk)[0] - ref.predict(Xchk)[0])))
    uu = np.concatenate([np.zeros(model.ny), u[:seg]])

    def product():
        fr = model.simulate(u[:seg], n_paths=P, seed=0, local=False)
        return fr.path_steps / fr.seconds

    def baseline():
        *_, s, pst, _ = C.mc_freerun(ref.predict, noise, model.x_scaler_, model.y_scaler_, uu, np.zeros(model.ny), P,
                                     ny=model.ny, nu=model.nu)
        return pst / s

    baseline()  # warm-up
    eq = C.interleave({"product": product, "baseline": baseline}, reps)
    ratio = C.median_ratio(eq["product"], eq["baseline"])
    base_ps = C.median(eq["baseline"])
    fitp = fit_percent(y, run.mean)
    cov = coverage(y, run.lower, run.upper)
    M_used = model.posterior_.n_points
    print(f"bench_bert_scale: BERT stand-in 0.15 V sweep, {P} paths x {n_rec} samples, sparse M={M_used}, "
          f"ny={model.ny} nu={model.nu} (D={model.ny + model.nu}); records {rec_s:.1f} s, training {fit_s:.1f} s "
          f"(ML-II on {model.n_train_} rows, posterior over {model.n_rows_} rows); {C.env_note()}")
    print(f"  product: simulate() wall time {wall:.1f} s ({wall / 60:.2f} min; target < 10 min), "
          f"{ps:,.0f} path-steps/s; fit {fitp:.1f} %, 99 % coverage {cov:.1f} % (stand-in numbers)")
    print(f"  equal work: {reps} interleaved repetitions of the first {seg} steps, product "
          f"{C.median(eq['product']):,.0f} vs numpy reference of the same posterior {base_ps:,.0f} path-steps/s "
          f"(max |mean diff| {ref_mean_diff:.1e}): ratio {ratio:.2f}")
    print(f"  user comparison (NOT equal work): sklearn exact predict loop, N={model.n_train_}: {base_step_s:.3f} "
          f"s/step measured on {b1[1] + b2[1]} steps (half before, half after); EXTRAPOLATED to the record: "
          f"{base_record_s:.0f} s ({base_record_s / 3600:.2f} h); {user_ps:,.0f} path-steps/s; user_ratio "
          f"(extrapolated / product measured) {base_record_s / wall:.1f}")
    C.result(wall_s=wall, wall_min=wall / 60.0, path_steps_per_s=ps, baseline=base_ps,
             baseline_what=f"numpy-reference-same-posterior-M{M_used}", ratio=ratio,
             segment_path_steps_per_s=C.median(eq["product"]), ref_max_mean_diff=ref_mean_diff,
             user_baseline=f"sklearn-exact-N{model.n_train_}-extrapolated", user_baseline_ps=user_ps,
             user_record_s_extrapolated=base_record_s, user_ratio=base_record_s / wall, target_met=int(wall < 600),
             paths=P, samples=n_rec, M=M_used, reps=reps, steps=seg, fit=fitp, coverage=cov, train_s=fit_s,
             load=C.load(), blas_threads=C.blas_threads())


if __name__ == "__main__":
    main()
