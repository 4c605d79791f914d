"""Monte Carlo free-run throughput on the real-BERT model: path-steps per second at 1024 paths,
``simulate_mc`` (checked local model per step) against the previous product code, and the bands'
agreement.

Each record class on its own (``pss_sine=``, ``pss_sweep=``, ``pss_noise=``, their ``ratio_*``,
``realtime_*``: record seconds per wall second at 1024 paths, and ``cpu_ms_step_*`` /
``cpu_ms_step_prev_*``: process CPU time per step of the product and of the baseline, the figure that
depends least on the machine's load): on spread paths (start-ups, sweeps, noise) the local model falls
back to exact evaluation, so the speed depends on the record.

The line also names the timed bundle's posterior and its lowest held-out fit % (``posterior=``,
``heldout_fit_min=``, ``heldout_fit_min_record=``: ``_common.bundle_fidelity``), so that a speed is quoted with the
fidelity it comes with.

Model: the ``bert-real`` bundle as its shipped config trains it (``configs/bert-real.toml``: the exact
posterior on its training rows, or a sparse one where the config says so), on three
segments of 1024 steps of a 64 s real record (default the 20 Hz sine, the held-out record nearest
the first resonance): from rest at 0 s (the start-up towards resonance), from the measured outputs
at 20 s (steady state) and at 51 s (the drive stops and the structure decays: the latent variance
falls below the noise there while the paths are still spread, the hardest case for the local model);
then (unless ``--sine-only``) the held-out 0.10 V sweep from rest at 0 s and from measured outputs at
3 s (crossing the resonance), and the 0.10 V noise run at 0 s and 5 s. ``--whole``: instead, the whole
0.10 V sweep and the 0.10 V and 0.25 V noise runs from rest (16 s each); ``--seconds S`` with it: their
first S seconds (from rest), for a bundle whose whole records take too long (the exact posterior).

Product: ``model.freerun.simulate_mc`` (default ``local=True``): each step a second-order model of
eq. 8-9 around the paths' mean regressor in the output-lag coordinates (``gp.LocalModel``), checked
against eq. 8-9 at 12 paths (the farthest and random ones), with exact evaluation of the farthest 1/16
or 1/4 or of all paths when the check fails. Baseline (``ratio=``): the previous product code, the
``simulate_mc`` of git commit ``baseline.MC_BASELINE`` (``--baseline-ref``), imported from the git history
beside the product (``bench/baseline.py``: the same algorithm and checks; one call per kernel part for k, J
and each Hessian, a (P x ny) lag shift per step), on the same posterior (``baseline.fitted_copy``), paths,
seed, segments, BLAS threads, in this process. Repetitions interleave product and baseline; ratio = median
over repetitions of (baseline seconds / product seconds), all segments together; ``ratio_exact=`` is the
same against ``freerun_reference.simulate_mc_reference`` (eq. 8-9 at every path), timed once. In a clone
without that commit (a shallow clone) the baseline is skipped: ``baseline=nan ratio=nan
baseline_skipped=CODE``, the reason on stderr.

Accuracy, same seed and paths (the draws are the same random numbers, so paths differ only by the
local model's error): the largest difference of the mean and of the 0.5 % / 99.5 % band edges against
the exact reference, in units of the band's Monte Carlo standard error, estimated as the median
difference between the reference's bands at seeds 0 and 1 divided by sqrt(2); the coverage of the
measured output by each band (points); and ``prev_max_diff_se=``, the largest difference of mean and
band edges against the previous code (round-off), in the same units. ``--whole`` leaves the exact
reference out (about 10 minutes a record) and takes the standard error from the previous code at
seeds 0 and 1.

    python bench/bench_mc_speed.py [--quick] [--whole [--seconds S]] [--registry R] [--record PATH] [--reps N]
                                   [--threads N] [--baseline-ref REF]

Without --registry a bundle is trained from configs/bert-real.toml into a cache (about 10 minutes;
bench_realtime.py shares the cache). --quick: a small Bouc-Wen sparse model (M=64, fixed
hyperparameters), 256 paths, 60 steps; for the smoke test only.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import baseline as BL
import numpy as np

import _common as C
from gpnarx.model.freerun import simulate_mc
from gpnarx.model.freerun.reference import simulate_mc_reference


def quick_model():
    from gpnarx.model.estimator import GPNARX

    pairs, _, r50 = C.protocol()
    m = GPNARX(ny=C.NY, nu=C.NU, mode="sparse", n_inducing=64, max_train_points=500).fit(pairs, theta=C.THETA_REF)
    seg = ("50 N sweep from measured", r50.u[900:960], r50.y[900:960], r50.y[900: 900 + C.NY], "sweep")
    return m, [seg], "quick", 750.0, {}


WHOLE = (("Chirp/Chirp0to40Hz/Chirp0p10", "sweep"), ("Rand/Rand0p10", "noise"), ("Rand/Rand0p25", "noise"))


def bert_model(registry, record, classes=True, whole=False, seconds=None):
    import bench_realtime as R

    from gpnarx.storage.record_files import read_record
    from gpnarx.storage.registry import Registry

    reg, note = R.bert_registry(registry)
    b = Registry(reg).scan().get("bert-real")
    ny = b.model.ny
    if whole:  # whole records from rest
        segs = []
        for sub, cls in WHOLE:
            rec = read_record(str(R.bert_data() / sub), fs_default=b.fs)
            n = rec.u.size if seconds is None else int(round(seconds * rec.fs))
            what = "whole" if n >= rec.u.size else f"first {n / rec.fs:g} s"
            segs.append((f"{Path(sub).name} {what} from rest", rec.u[:n], rec.y[:n], None, cls))
        return b.model, segs, f"{note}; {b.name}:{b.version}", rec.fs, C.bundle_fidelity(b)
    path = Path(record) if record else R.bert_data() / "Sine" / "Sine_20Hz"
    rec = read_record(str(path), fs_default=b.fs)
    fs = rec.fs
    segs = segments(rec, path.name, "sine", (20.0, 51.0), ny)
    if classes:  # a sweep through the resonance and a noise run too: the speed a user sees depends on the record
        data = R.bert_data()
        for sub, cls, starts in (("Chirp/Chirp0to40Hz/Chirp0p10", "sweep", (3.0,)),
                                 ("Rand/Rand0p10", "noise", (5.0,))):
            other = read_record(str(data / sub), fs_default=b.fs)
            segs += segments(other, Path(sub).name, cls, starts, ny)
    return b.model, segs, f"{note}; {b.name}:{b.version}", fs, C.bundle_fidelity(b)


def segments(rec, name, cls, starts, ny, steps=1024):
    """1024-step segments of a record: from rest at 0 s, and from its measured outputs at each start [s]."""
    segs = [(f"{name} 0 s from rest", rec.u[:steps], rec.y[:steps], None, cls)]
    for t0 in starts:
        s1 = int(round(t0 * rec.fs))
        segs.append((f"{name} {t0:.0f} s from measured", rec.u[s1: s1 + steps + ny], rec.y[s1: s1 + steps + ny],
                     rec.y[s1: s1 + ny], cls))
    return segs


def coverage(y, run) -> float:
    return 100.0 * float(np.mean((y >= run.lower) & (y <= run.upper)))


def main():
    def extra(ap):
        ap.add_argument("--registry", default=None, help="registry holding bert-real (default: train into a cache)")
        ap.add_argument("--record", default=None, help="64 s record (default: BERT Sine_20Hz)")
        ap.add_argument("--reps", type=int, default=None, help="interleaved repetitions (default 3; 2 with --quick)")
        ap.add_argument("--sine-only", action="store_true",
                        help="only the sine record's segments (default: also a sweep and a noise run)")
        ap.add_argument("--whole", action="store_true",
                        help="the whole 0.10 V sweep and 0.10 / 0.25 V noise runs instead of segments")
        ap.add_argument("--seconds", type=float, default=None,
                        help="with --whole: only the first SECONDS of each record (from rest)")
        ap.add_argument("--baseline-ref", default=BL.MC_BASELINE,
                        help="git ref of the baseline's product code (default: the commit before the fused local "
                             "model, bench/baseline.py MC_BASELINE)")

    args = C.parse_args(__doc__, extra)
    q = args.quick
    P = 256 if q else 1024
    reps = args.reps or (2 if q else 3)
    if args.seconds is not None and not (args.whole and args.seconds > 0):
        raise SystemExit("--seconds needs --whole and a positive number of seconds")
    model, segs, note, fs, fidelity = quick_model() if q else bert_model(args.registry, args.record, not args.sine_only,
                                                                args.whole, args.seconds)
    try:
        prev = previous_code(args.baseline_ref, model)
        skipped = None
    except BL.BaselineUnavailable as exc:
        print(f"bench_mc_speed: baseline skipped ({exc.code}): {exc}", file=sys.stderr)
        prev, skipped = None, exc.code
    nan = float("nan")

    def run(fn, seg, seed=0, m=model):
        _, u, _, y0 = seg[:4]
        c0 = time.process_time()
        r = fn(m.posterior_, m.x_scaler_, m.y_scaler_, m.ny, m.nu, u, n_paths=P, seed=seed, y0=y0,
               include_noise=m.include_noise)
        r.cpu = time.process_time() - c0
        return r

    def run_prev(seg, seed=0):
        return run(prev[0], seg, seed, prev[1])

    for seg in segs:  # warm-up
        short = (seg[0], seg[1][:40], None, seg[3], seg[4])
        run(simulate_mc, short)
        if prev:
            run_prev(short)
        if not args.whole:
            run(simulate_mc_reference, short)
    load0 = C.load()
    t_new = [[0.0] * len(segs) for _ in range(reps)]
    t_old = [[nan] * len(segs) for _ in range(reps)]
    c_new = [[0.0] * len(segs) for _ in range(reps)]
    c_old = [[nan] * len(segs) for _ in range(reps)]
    loads = []
    last_new, last_old, local = {}, {}, {}
    steps = [0] * len(segs)
    for r in range(reps):
        for j, seg in enumerate(segs):
            a = run(simulate_mc, seg)
            t_new[r][j], c_new[r][j] = a.seconds, a.cpu
            last_new[j] = a
            if prev:
                b = run_prev(seg)
                t_old[r][j], c_old[r][j] = b.seconds, b.cpu
                last_old[j] = b
            local[j] = a.local_steps
            steps[j] = a.path_steps // P
            loads.append(C.load())
    load1 = C.load()
    ratios = [sum(t_old[r]) / sum(t_new[r]) for r in range(reps)]
    ps_new = P * sum(steps) / C.median([sum(t) for t in t_new])
    ps_old = P * sum(steps) / C.median([sum(t) for t in t_old])

    print(f"bench_mc_speed: {note}; {P} paths; {reps} interleaved reps; load {load0:.1f} -> {load1:.1f} "
          f"(median {C.median(loads):.1f}); BLAS threads {C.blas_threads()}; baseline "
          + (f"simulate_mc of git {prev[2]}" if prev else f"skipped ({skipped})"))
    print(f"  {'segment':<34} {'steps':>5} {'local':>5} {'new ps/s':>10} {'prev ps/s':>10} {'ratio':>6} "
          f"{'new cpu ms/step':>15} {'prev cpu ms/step':>16}")
    for j, seg in enumerate(segs):
        tn = C.median([t[j] for t in t_new])
        to = C.median([t[j] for t in t_old])
        print(f"  {seg[0]:<34} {steps[j]:>5} {local[j]:>5} {P * steps[j] / tn:>10,.0f} {P * steps[j] / to:>10,.0f} "
              f"{C.median_ratio([t[j] for t in t_old], [t[j] for t in t_new]):>6.2f} "
              f"{1e3 * C.median([c[j] for c in c_new]) / steps[j]:>15.3f} "
              f"{1e3 * C.median([c[j] for c in c_old]) / steps[j]:>16.3f}")

    # accuracy: same seed (same draws); MC error from the exact reference (or, --whole, the previous code)
    # at seeds 0 and 1
    worst = {"mean": 0.0, "edge": 0.0, "prev": 0.0 if prev else nan}
    cov_gap = 0.0
    rows = []
    t_ref = 0.0
    for j, seg in enumerate(segs):
        a, o = last_new[j], last_old.get(j)
        if args.whole:  # the previous code's bands at seeds 0 and 1 (without it: the product's own, no diff)
            b, b1 = (o, run_prev(seg, seed=1)) if prev else (a, run(simulate_mc, seg, seed=1))
        else:
            b = run(simulate_mc_reference, seg)
            t_ref += b.seconds
            b1 = run(simulate_mc_reference, seg, seed=1)
        k0 = 0 if seg[3] is None else model.ny
        sl = slice(k0 + 1, None)
        se = np.median(np.concatenate([np.abs(b.lower[sl] - b1.lower[sl]), np.abs(b.upper[sl] - b1.upper[sl])])) \
            / np.sqrt(2.0)
        se_mean = np.median(np.abs(b.mean[sl] - b1.mean[sl])) / np.sqrt(2.0)
        d_edge = max(np.max(np.abs(a.lower[sl] - b.lower[sl])), np.max(np.abs(a.upper[sl] - b.upper[sl]))) / se
        d_mean = np.max(np.abs(a.mean[sl] - b.mean[sl])) / se_mean
        if b is a:
            d_edge = d_mean = nan
        d_prev = nan if o is None else max(
            np.max(np.abs(a.mean[sl] - o.mean[sl])) / se_mean, np.max(np.abs(a.lower[sl] - o.lower[sl])) / se,
            np.max(np.abs(a.upper[sl] - o.upper[sl])) / se)
        worst["edge"] = max(worst["edge"], d_edge)
        worst["mean"] = max(worst["mean"], d_mean)
        worst["prev"] = max(worst["prev"], d_prev)
        y = seg[2]
        c_a, c_b, c_b1 = coverage(y, a), coverage(y, b), coverage(y, b1)
        cov_gap = max(cov_gap, abs(c_a - c_b))
        rows.append((seg[0], d_mean, d_edge, d_prev, c_a, c_b, c_b1))
    if args.whole and not prev:  # nothing to compare with
        worst["mean"] = worst["edge"] = cov_gap = nan
    what = ("previous code" if prev else "product") if args.whole else "exact reference"
    print(f"  same seed, product vs {what} (MC standard error from the {what} at seeds 0 and 1):")
    for name, dm, de, dp, ca, cb, cb1 in rows:
        print(f"    {name:<34} max |mean diff| {dm:.2g} MC s.e.; max |band-edge diff| {de:.2g} MC s.e.; "
              f"vs previous code {dp:.2g} MC s.e.; coverage of measured y: product {ca:.2f} %, {what} {cb:.2f} % "
              f"(seed 1: {cb1:.2f} %)")
    per_class = {}
    for cls in dict.fromkeys(seg[4] for seg in segs):  # each record class on its own: its segments' total
        js = [j for j, seg in enumerate(segs) if seg[4] == cls]
        tn = C.median([sum(t[j] for j in js) for t in t_new])
        to = C.median([sum(t[j] for j in js) for t in t_old])
        n_cls = sum(steps[j] for j in js)
        per_class[f"pss_{cls}"] = P * n_cls / tn
        per_class[f"ratio_{cls}"] = to / tn
        per_class[f"realtime_{cls}"] = n_cls / fs / tn
        per_class[f"cpu_ms_step_{cls}"] = 1e3 * C.median([sum(c[j] for j in js) for c in c_new]) / n_cls
        per_class[f"cpu_ms_step_prev_{cls}"] = 1e3 * C.median([sum(c[j] for j in js) for c in c_old]) / n_cls
    extra = {} if args.whole else {"ratio_exact": t_ref / C.median([sum(t) for t in t_new])}
    if skipped:
        extra["baseline_skipped"] = skipped
    commit = prev[2] if prev else args.baseline_ref[:12]
    C.result(path_steps_per_s=ps_new, baseline=ps_old,
             baseline_what=f"simulate_mc-of-git-{commit}-same-posterior-paths-seed",
             ratio=C.median(ratios), paths=P, steps=sum(steps), local_steps=sum(local.values()),
             max_mean_diff_se=worst["mean"], max_edge_diff_se=worst["edge"], prev_max_diff_se=worst["prev"],
             cov_gap_points=cov_gap, load=C.median(loads), blas_threads=C.blas_threads(), **extra, **per_class,
             **fidelity)


def previous_code(ref: str, model):
    """The baseline's ``simulate_mc`` (git ``ref``'s, ``bench/baseline.py``), the product's fitted ``model`` as the
    baseline's own estimator, and the baseline's commit (12 digits)."""
    pkg = BL.load_model(ref)
    commit = BL.resolve(ref)
    return BL.submodule(pkg, "freerun").simulate_mc, BL.fitted_copy(pkg, model), commit[:12]


if __name__ == "__main__":
    main()
