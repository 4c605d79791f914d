"""Real-time factor of ``gpnarx predict`` with 99 % bands on a whole real record, and the bands'
accuracy against a 1024-path Monte Carlo reference.

Product: the whole ``python -m gpnarx predict --registry R --model bert-real REC --method linear
--out OUT.npz`` process (interpreter start, imports, bundle load with checksums, reading the LMS
Test.Lab record, the linearised free run from rest over the whole record, the envelope checks and
metrics, writing OUT.npz), on a 64 s real BERT record (65,536 samples at 1024 Hz; default the 20 Hz
sine, the held-out record nearest the first resonance). Real-time factor = record duration / wall.
Where the product's time goes: ``free_run_s=`` is the free run itself (the ``seconds:`` line the command
prints), ``outside_s=`` the rest of the process's wall time (interpreter, imports, reading, checks, output).
Each pass of the free run timed alone on one thread in this process (``pass1_s=``, ``pass2_s=`` with the
triangular products of eq. 9 inside it, ``trmm_s=`` at ``trmm_gflops=``, ``pass3_s=``): half their sum plus
``outside_s=`` is the least wall time two cores can give the whole process (``two_core_floor_s=``,
``rt_factor_floor=``), however the passes overlap.
The timed bundle's fidelity goes with its speed (``_common.bundle_fidelity``): ``posterior=`` (exact or sparse)
and the lowest fit % of its training report over the held-out records, ``heldout_fit_min=`` (which record:
``heldout_fit_min_record=``); ``--registry`` may hold a bert-real trained otherwise (``gpnarx train bert-real
--mode sparse``) to compare the two.
``--method linear`` is what the shipped bert-real config names for whole records
(``[predict] method``); the CLI's own default is Monte Carlo (see the notes printed below).

Baseline, equal work (``ratio=``): the same command in a process that first replaces
``model.freerun.simulate_linear`` with ``freerun_reference.simulate_linear_reference`` (the code path before this
change: one ``posterior.mean_grad`` call per step), then runs the same CLI entry point with the same
arguments: same bundle, record, tuning and output. Product and baseline processes alternate
(A, B, A, B, ...); ratio = median over repetitions of baseline wall / product wall.

``--baseline-ref REF``: the baseline is instead the same command run by the whole package as it stood at git
commit REF (``bench/baseline.py`` ``export_package``: that commit's ``gpnarx`` first on the path, started outside
the checkout), the previous product code end to end; ``baseline_what=`` names the commit. ``compiled=`` says
whether the product ran the compiled pass 1 (numba importable, ``model/freerun/linear_compiled.py``).

Also timed in the same alternation (``serial_ratio=``): the product's code with pass 2 (eq. 9 and the
mean gradient) on the calling thread only (``simulate_linear(workers=0)``), to show what its worker
thread beside the mean recursion buys on the cores this process gets.

Accuracy (in this process, same bundle): on 4 s windows (``--window``) of the record (from rest at 0 s, and from
the measured outputs at 20 s) the linearised band against the 1024-path Monte Carlo band
(``freerun_reference.simulate_mc_reference``: eq. 8-9 exactly at every path, seed 0; seed 1 shows its own Monte Carlo
spread): coverage of the measured output by each band (points), and the mean width ratio linear /
MC. Also a faster Monte Carlo as a candidate default: 128 paths on the same
windows (coverage, width) and its real-time factor extrapolated from the window's simulate time
(the MC step cost does not depend on the position in the record).

    python bench/bench_realtime.py [--quick] [--registry R] [--record PATH] [--reps N] [--window S] [--threads N]
                                   [--baseline-ref REF]

Without --registry a bundle is trained from configs/bert-real.toml into a cache (about 10 minutes).
--quick: a tiny Bouc-Wen model and a 2031-sample simulated sweep (bench_predict_e2e's quick
config), 2 repetitions, 256-path reference; for the smoke test only.
"""
from __future__ import annotations

import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import _common as C

BASELINE_CODE = (
    "import sys; import gpnarx.model.freerun as F; "
    "from gpnarx.model.freerun.linear_stepwise import run_linear_stepwise; "
    "F.RUNNERS[('linear', 'numpy')] = run_linear_stepwise; "
    "from gpnarx.cli.main import main; sys.argv = ['gpnarx'] + sys.argv[1:]; sys.exit(main())"
)
# the product's code with pass 2 on the calling thread only (no worker thread beside the mean recursion)
SERIAL_CODE = (
    "import sys, dataclasses; import gpnarx.model.freerun as F; lin = F.RUNNERS[('linear', 'numpy')]; "
    "F.RUNNERS[('linear', 'numpy')] = lambda p, u, s: lin(p, u, dataclasses.replace(s, workers=0)); "
    "from gpnarx.cli.main import main; sys.argv = ['gpnarx'] + sys.argv[1:]; sys.exit(main())"
)


def bert_data() -> Path:
    from gpnarx.training.datapaths import bert_data_dir  # the package's one lookup of the lab data

    return bert_data_dir()


def _env(first: Path | None = None):
    e = dict(os.environ)
    paths = ([str(first)] if first else []) + [str(C.ROOT)] + ([e["PYTHONPATH"]] if e.get("PYTHONPATH") else [])
    e["PYTHONPATH"] = os.pathsep.join(paths)
    e.pop("GPNARX_REGISTRY", None)
    return e


def timed(cmd: list, cpu: list | None = None, free_run: list | None = None, package: Path | None = None) -> float:
    """Wall seconds of a subprocess; its CPU seconds (user + system) appended to ``cpu``, and the free run's own
    seconds (the ``seconds:`` line ``gpnarx predict`` prints) to ``free_run``. ``package``: a folder that holds
    another ``gpnarx`` (``baseline.export_package``), first on the path, the process started in it (so the
    checkout's own ``gpnarx/`` is not found first)."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=package or C.ROOT, env=_env(package), capture_output=True, text=True,
                          timeout=3600)
    dt = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(map(str, cmd[:4]))} ... failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    if cpu is not None:
        cpu.append((r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime))
    if free_run is not None:
        found = [ln.split(":", 1)[1] for ln in proc.stdout.splitlines() if ln.startswith("seconds:")]
        if not found:
            raise SystemExit(f"{' '.join(map(str, cmd[:4]))} ... printed no 'seconds:' line")
        free_run.append(float(found[0]))
    return dt


def bert_registry(arg: str | None) -> tuple[Path, str]:
    if arg:
        return Path(arg), f"registry {arg}"
    import hashlib

    text = (C.ROOT / "configs" / "bert-real.toml").read_text()
    key = hashlib.sha256(text.encode()).hexdigest()[:12]
    reg = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "gpnarx" / "bench-realtime" / key
    if not (reg / "bert-real").is_dir():
        t = timed([sys.executable, "-m", "gpnarx", "train", "bert-real", "--registry", str(reg), "--no-report"])
        return reg, f"trained into {reg} in {t:.0f} s (cached)"
    return reg, f"cached registry {reg}"


def quick_setup(tmp: Path) -> tuple[Path, str, Path, str]:
    import bench_predict_e2e as E

    reg, note = E.cached_registry(True, False)
    rec = tmp / "sweep50.npz"
    timed([sys.executable, "-m", "gpnarx", "simulate", "bouc-wen", "--excitation", "sweep", "--amplitude", "50",
           "--rate", "53.55", "--out", str(rec)])
    return reg, "bouc-wen", rec, note


def band_stats(y, run) -> tuple[float, float]:
    """(coverage of y by the band [%], mean band width)."""
    inside = (y >= run.lower) & (y <= run.upper)
    return 100.0 * float(np.mean(inside)), float(np.mean(run.upper - run.lower))


def open_run(registry: Path, name: str, record: Path):
    """(model, record, fidelity) of the in-process measurements, after the CLI's tuning for free runs; fidelity:
    ``_common.bundle_fidelity`` of the bundle."""
    from gpnarx.runtime import tune_for_free_run
    from gpnarx.storage.record_files import read_record
    from gpnarx.storage.registry import Registry

    tune_for_free_run(None)
    bundle = Registry(registry).scan().get(name)
    return bundle.model, read_record(str(record), fs_default=bundle.fs), C.bundle_fidelity(bundle)


def accuracy(model, rec, quick: bool, window: float = 4.0) -> dict:
    """Linearised and few-path MC bands against the reference MC on 4 s windows (quick: 300 samples)."""
    from gpnarx.model.discrepancy import widen
    from gpnarx.model.freerun.reference import simulate_mc_reference

    args = (model.posterior_, model.x_scaler_, model.y_scaler_, model.ny, model.nu)
    disc = getattr(model, "band_discrepancy_", None)
    P_ref = 256 if quick else 1024
    P_few = 64 if quick else 128
    win = int(round(window * rec.fs)) if not quick else 300
    starts = [0] if quick else [0, int(round(20.0 * rec.fs))]
    out = {"windows": [], "discrepancy": bool(disc)}
    for s0 in starts:
        u, y = rec.u[s0: s0 + win], rec.y[s0: s0 + win]
        y0 = None if s0 == 0 else y[: model.ny]
        ref = simulate_mc_reference(*args, u, n_paths=P_ref, seed=0, y0=y0, include_noise=model.include_noise)
        ref1 = simulate_mc_reference(*args, u, n_paths=P_ref, seed=1, y0=y0, include_noise=model.include_noise)
        if disc:  # model.simulate widens the product's bands by the calibrated discrepancy term: the same here
            ref, ref1 = (widen(r, float(disc["scale"]), int(disc["window"])) for r in (ref, ref1))
        lin = model.simulate(u, y0=y0, method="linear")
        few = model.simulate(u, n_paths=P_few, seed=0, y0=y0, method="mc")
        c_ref, w_ref = band_stats(y, ref)
        c_ref1, w_ref1 = band_stats(y, ref1)
        c_lin, w_lin = band_stats(y, lin)
        c_few, w_few = band_stats(y, few)
        out["windows"].append({
            "t0": s0 / rec.fs, "n": int(u.size), "start": "rest" if s0 == 0 else "measured", "mc_paths": P_ref,
            "cov_mc": c_ref, "cov_mc_seed1": c_ref1, "width_mc_seed_ratio": w_ref1 / w_ref,
            "cov_lin": c_lin, "cov_few": c_few, "width_mc": w_ref,
            "width_ratio_lin": w_lin / w_ref, "width_ratio_few": w_few / w_ref,
            "few_paths": P_few, "few_steps_per_s": (u.size - (0 if y0 is None else model.ny)) / few.seconds,
            "mc_path_steps_per_s": ref.path_steps / ref.seconds})
    return out


def pass_profile(model, rec) -> dict:
    """Each pass of the linearised free run timed on its own, in this process, on the whole record with pass 2 on
    the calling thread (``simulate_linear(workers=0)``: one thread, so each pass's wall time is its CPU time):
    pass 1 (the mean recursion), pass 2 (eq. 9 and the mean gradient at every step) and, inside it, the
    triangular products |Linv k|^2 (rows x N^2 flops, the exact posterior; 0 for another posterior), and pass 3
    (the covariance recursion). Their sum over two cores is the least wall time two cores can give the free run
    (perfect overlap), whatever the scheduling."""
    from gpnarx.model import linalg as gpmod
    from gpnarx.model.freerun import linear as freerun

    post = model.posterior_
    spent = {"pass1": 0.0, "nested": 0.0, "trmm": 0.0, "pass3": 0.0}
    trmm_flops = [0.0]

    def timed_call(key, fn, flops=None):
        def wrapper(*a, **kw):
            t0 = time.perf_counter()
            try:
                return fn(*a, **kw)
            finally:
                spent[key] += time.perf_counter() - t0
                if flops is not None:
                    trmm_flops[0] += flops(*a)
        return wrapper

    # without workers, pass 1 hands each chunk to _Workers.submit, which runs pass 2 and pass 3 on it at once
    from gpnarx.model.freerun.linear_compiled import CompiledMean

    saved = (freerun._MeanRecursion.run, freerun._Workers.submit, freerun._CovarianceRecursion.advance,
             gpmod._dtrmm_rows, CompiledMean.run)
    freerun._MeanRecursion.run = timed_call("pass1", saved[0])
    CompiledMean.run = timed_call("pass1", saved[4])  # the compiled pass 1, where numba is
    freerun._Workers.submit = timed_call("nested", saved[1])
    freerun._CovarianceRecursion.advance = timed_call("pass3", saved[2])
    gpmod._dtrmm_rows = timed_call("trmm", saved[3], lambda L, B, *_: float(B.shape[0]) * L.shape[0] ** 2)
    try:
        args = (post, model.x_scaler_, model.y_scaler_, model.ny, model.nu, rec.u)
        freerun.simulate_linear(*args[:5], rec.u[:2048], workers=0)  # warm-up
        for k in spent:
            spent[k] = 0.0
        trmm_flops[0] = 0.0
        t0 = time.perf_counter()
        freerun.simulate_linear(*args, workers=0)
        total = time.perf_counter() - t0
    finally:
        (freerun._MeanRecursion.run, freerun._Workers.submit, freerun._CovarianceRecursion.advance,
         gpmod._dtrmm_rows, CompiledMean.run) = saved
    return {"serial_s": total, "pass1": spent["pass1"] - spent["nested"], "pass2": spent["nested"] - spent["pass3"],
            "pass3": spent["pass3"], "trmm": spent["trmm"],
            "trmm_gflops": trmm_flops[0] / spent["trmm"] / 1e9 if spent["trmm"] else 0.0}


def main():
    def extra(ap):
        ap.add_argument("--registry", default=None, help="registry holding bert-real (default: train into a cache)")
        ap.add_argument("--record", default=None, help="64 s record (default: BERT Sine_20Hz)")
        ap.add_argument("--reps", type=int, default=None, help="interleaved repetitions (default 3; 2 with --quick)")
        ap.add_argument("--baseline-ref", default=None,
                        help="baseline: the whole gpnarx process of this git ref (bench/baseline.py export_package) "
                             "instead of the reference linearised loop")
        ap.add_argument("--window", type=float, default=4.0,
                        help="seconds of each accuracy window (default 4; the exact posterior's 1024-path "
                             "reference takes about a minute per second of record)")

    args = C.parse_args(__doc__, extra)
    q = args.quick
    if not args.window > 0:
        raise SystemExit("--window must be a positive number of seconds")
    reps = args.reps or (2 if q else 3)
    with tempfile.TemporaryDirectory(prefix="gpnarx-rt-") as tmp:
        tmp = Path(tmp)
        if q:
            reg, name, record, note = quick_setup(tmp)
        else:
            reg, note = bert_registry(args.registry)
            name = "bert-real"
            record = Path(args.record) if args.record else bert_data() / "Sine" / "Sine_20Hz"
        from gpnarx.storage.record_files import read_record

        rec = read_record(str(record), fs_default=None if q else 1024.0)
        duration = rec.n / rec.fs
        out = tmp / "pred.npz"
        argv = ["predict", "--registry", str(reg), "--model", name, str(record), "--method", "linear",
                "--out", str(out)]
        product = [sys.executable, "-m", "gpnarx", *argv]
        package, base_what, skipped = None, "same-cli-process-reference-linear-loop", None
        baseline = [sys.executable, "-c", BASELINE_CODE, *argv]
        if args.baseline_ref:
            import baseline as BL

            try:
                package = BL.export_package(args.baseline_ref)
                baseline = [sys.executable, "-m", "gpnarx", *argv]
                base_what = f"gpnarx-predict-process-of-git-{BL.resolve(args.baseline_ref)[:12]}"
            except BL.BaselineUnavailable as exc:
                print(f"bench_realtime: baseline skipped ({exc.code}): {exc}", file=sys.stderr)
                baseline, skipped = None, exc.code
        serial = [sys.executable, "-c", SERIAL_CODE, *argv]
        timed(product)  # warm the page cache (record, bundle, libraries) for both sides
        if baseline:
            timed(baseline, package=package)
        load0 = C.load()
        walls = {"product": [], "baseline": [], "serial": []}
        cpus = {"product": [], "baseline": [], "serial": []}
        free_runs = []  # the product's free run alone (the recursion), from its own output
        nan = float("nan")
        for _ in range(reps):
            walls["product"].append(timed(product, cpus["product"], free_runs))
            if baseline:
                walls["baseline"].append(timed(baseline, cpus["baseline"], package=package))
            else:
                walls["baseline"].append(nan)
                cpus["baseline"].append(nan)
            walls["serial"].append(timed(serial, cpus["serial"]))
        load1 = C.load()
        model, rec_in, fidelity = open_run(reg, name, record)
        prof = pass_profile(model, rec_in)
        acc = accuracy(model, rec_in, q, args.window)

    ratio = C.median_ratio(walls["baseline"], walls["product"])
    wall = C.median(walls["product"])
    base_wall = C.median(walls["baseline"])
    rt = duration / wall
    print(f"bench_realtime: {name}, {Path(record).name}: {rec.n} samples = {duration:.1f} s; {note}; "
          f"{reps} interleaved reps; load {load0:.1f} -> {load1:.1f}")
    print(f"  {'rep':>3} {'product s':>10} {'baseline s':>11} {'ratio':>6} {'serial s':>9} {'product cpu s':>13} "
          f"{'baseline cpu s':>14} {'serial cpu s':>12}")
    for r in range(reps):
        p, b, sr = walls["product"][r], walls["baseline"][r], walls["serial"][r]
        print(f"  {r:>3} {p:10.2f} {b:11.2f} {b / p:6.2f} {sr:9.2f} {cpus['product'][r]:13.2f} "
              f"{cpus['baseline'][r]:14.2f} {cpus['serial'][r]:12.2f}")
    cpu = C.median(cpus["product"])
    free_run = C.median(free_runs)
    print(f"  product's time: the free run itself {free_run:.2f} s ({duration / free_run:.1f}x real time), "
          f"everything else (interpreter, imports, reading the bundle and the record, the envelope check, "
          f"writing the answer) {wall - free_run:.2f} s")
    work = prof["pass1"] + prof["pass2"] + prof["pass3"]
    floor = work / 2.0 + (wall - free_run)
    print(f"  each pass alone (one thread, in this process): pass 1 {prof['pass1']:.2f} s, "
          f"pass 2 {prof['pass2']:.2f} s "
          f"(of which the triangular products {prof['trmm']:.2f} s at {prof['trmm_gflops']:.1f} GFLOPS), pass 3 "
          f"{prof['pass3']:.2f} s; over two cores at best {work / 2:.2f} s, so the whole process at best "
          f"{floor:.2f} s = {duration / floor:.1f}x real time")
    print(f"  real-time factor (whole process, --method linear): product {rt:.1f}x, "
          f"baseline {duration / base_wall:.1f}x, pass 2 serial {duration / C.median(walls['serial']):.1f}x "
          f"(wall, at the load above); on CPU time (what one free core "
          f"gives): product {duration / cpu:.1f}x, baseline {duration / C.median(cpus['baseline']):.1f}x")
    for w in acc["windows"]:
        print(f"  window at {w['t0']:.0f} s ({w['n']} samples) from {w['start']}: coverage of measured y: "
              f"MC{w['mc_paths']} "
              f"{w['cov_mc']:.1f} % (seed 1: {w['cov_mc_seed1']:.1f} %, width x{w['width_mc_seed_ratio']:.3f}), "
              f"linear {w['cov_lin']:.1f} %, MC{w['few_paths']} {w['cov_few']:.1f} %; "
              f"mean width ratio to MC{w['mc_paths']}: linear {w['width_ratio_lin']:.3f}, MC{w['few_paths']} "
              f"{w['width_ratio_few']:.3f}; MC{w['few_paths']} runs {w['few_steps_per_s']:.0f} steps/s = "
              f"{w['few_steps_per_s'] / rec.fs:.1f}x real time before process overhead")
    if acc["discrepancy"]:
        print("  (the bundle's model-discrepancy term widens every band above, the reference's too)")
    ws = acc["windows"]
    cov_gap = max(abs(w["cov_lin"] - w["cov_mc"]) for w in ws)
    width_dev = max(abs(w["width_ratio_lin"] - 1.0) for w in ws)
    few_rt = min(w["few_steps_per_s"] for w in ws) / rec.fs
    extra = {"baseline_skipped": skipped} if skipped else {}
    C.result(rt_factor=rt, baseline=duration / base_wall, baseline_what=base_what,
             ratio=ratio, wall_s=wall, baseline_wall_s=base_wall, record_s=duration, cpu_s=cpu,
             free_run_s=free_run, outside_s=wall - free_run, rt_factor_free_run=duration / free_run,
             pass1_s=prof["pass1"], pass2_s=prof["pass2"], trmm_s=prof["trmm"], trmm_gflops=prof["trmm_gflops"],
             pass3_s=prof["pass3"], two_core_floor_s=floor, rt_factor_floor=duration / floor,
             serial_wall_s=C.median(walls["serial"]), serial_ratio=C.median_ratio(walls["serial"], walls["product"]),
             serial_cpu_s=C.median(cpus["serial"]), window_s=ws[0]["n"] / rec.fs,
             rt_factor_cpu=duration / cpu, baseline_cpu_s=C.median(cpus["baseline"]),
             cov_mc_seed_gap=max(abs(w["cov_mc_seed1"] - w["cov_mc"]) for w in ws),
             cov_gap_points=cov_gap, width_ratio_min=min(w["width_ratio_lin"] for w in ws),
             width_ratio_max=max(w["width_ratio_lin"] for w in ws), width_dev=width_dev,
             cov_mc=ws[0]["cov_mc"], cov_lin=ws[0]["cov_lin"], few_paths=ws[0]["few_paths"],
             few_mc_rt_simulate_only=few_rt, few_width_ratio_min=min(w["width_ratio_few"] for w in ws),
             load=C.load(), blas_threads=C.blas_threads(), compiled=int(_compiled()), **extra, **fidelity)


def _compiled() -> bool:
    """Whether the product's linearised run takes the compiled pass 1 here (numba importable, not turned off)."""
    from gpnarx.model.freerun.linear_compiled import enabled

    return enabled()


if __name__ == "__main__":
    main()
