"""The independent check of the model with several outputs against a known truth (issue 52).

A simulated chain of three masses with a Bouc-Wen joint between the first two and a displacement sensor on each
mass (``gpnarx.training.simulators.chain``), driven by a force on the last mass. A ``MIMOGPNARX`` (one input,
three outputs, one GP per output over the shared regressor) is trained on swept sines and band-limited noise at
two force levels, each record with 1 % measurement noise on every sensor, and its free run (every output fed back
together, linearised and Monte Carlo) is scored against the simulator on an independent swept sine at a level
between them and a noise run of another seed: fit % (eq. 14) and 99 % band coverage per channel, against the
measured outputs (predictive band) and the noise-free ones (latent band). Beside it, the baseline: one
single-output ``GPNARX`` per sensor (the input and that sensor's lags only, the same settings), linearised.

    python studies/mimo_chain.py [--quick] [--out docs/runs/mimo-chain]

writes ``results.json`` and one figure per check record (``chain-<record>.png``: each channel's measured and
predicted output with the band). ``--quick`` is the test's setting (tests/test_mimo_chain.py): shorter records,
fewer ML-II rows and paths.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from gpnarx.model.estimator import GPNARX
from gpnarx.model.metrics import summary
from gpnarx.model.mimo import MIMOGPNARX
from gpnarx.model.record import Record
from gpnarx.training.excitations import band_limited_noise, swept_sine
from gpnarx.training.simulators.chain import CHANNELS, Chain

FS = 200.0  # Hz: 22 samples per period of the first mode (9 Hz), 6 of the third (34 Hz)
NOISE_SHARE = 0.01  # measurement noise std on each sensor, as a share of its response's std


def _record(chain: Chain, u: np.ndarray, name: str, seed: int) -> Record:
    x = chain.simulate(u)["y"]
    rng = np.random.default_rng(seed)
    y = x + NOISE_SHARE * np.std(x, axis=0) * rng.normal(size=x.shape)
    return Record(u, y, FS, {"u": "N", "y": "m"}, name, {"clean_y": x},
                  channels={"u": [("F3", "N")], "y": [(c, "m") for c in CHANNELS]})


def records(quick: bool) -> tuple[list[Record], list[Record]]:
    """(training records, check records): swept sines 2-50 Hz at 3 and 8 N and 0-60 Hz noise at 1.5 and 4 N RMS
    for training; a 5.5 N sweep and a 2.5 N RMS noise run of another seed for the check (forces [N], outputs
    [m], every sensor with its measurement noise; ``meta["clean_y"]`` the simulator's output)."""
    chain = Chain(fs=FS)
    dur = 6.0 if quick else 12.0
    train = []
    for k, amp in enumerate((3.0, 8.0)):
        train.append(_record(chain, swept_sine(FS, amp, 2.0, 50.0, duration=dur), f"train-sweep-{amp:g}N", 10 + k))
        train.append(_record(chain, band_limited_noise(FS, dur / 2, 0.0, 60.0, amp / 2, seed=20 + k),
                             f"train-noise-{amp / 2:g}Nrms", 30 + k))
    check = [_record(chain, swept_sine(FS, 5.5, 2.0, 50.0, duration=dur), "check-sweep-5.5N", 40),
             _record(chain, band_limited_noise(FS, dur / 2, 0.0, 60.0, 2.5, seed=99), "check-noise-2.5Nrms", 41)]
    return train, check


def run(quick: bool = True, out: Path | None = None, log=print) -> dict:
    """Train on the chain, check the free runs; returns (and with ``out`` writes) the results."""
    t0 = time.perf_counter()
    train, check = records(quick)
    t_sim = time.perf_counter() - t0
    model = MIMOGPNARX(ny=8, nu=6, max_train_points=400 if quick else 800, n_restarts=0, seed=0)
    model.fit(train)
    log(f"fitted {model.n_outputs_} outputs on {model.n_rows_} rows in {model.fit_seconds_:.1f} s")
    methods = {"linear": {}, "mc": {"n_paths": 128 if quick else 256, "seed": 0}}
    results = {"quick": quick, "fs": FS, "noise_share": NOISE_SHARE, "ny": model.ny, "nu": model.nu,
               "train": [r.name for r in train], "simulate_seconds": t_sim, "fit_seconds": model.fit_seconds_,
               "channels": list(CHANNELS), "hyperparameters": [g.theta_.tolist() for g in model.outputs_],
               "checks": {}}
    runs = {}
    for rec in check:
        clean = rec.meta["clean_y"]
        for method, opts in methods.items():
            run_ = model.simulate(rec.u, method=method, **opts)
            runs[(rec.name, method)] = run_
            per = {}
            for o, ch in enumerate(CHANNELS):
                meas = summary(rec.y[:, o], run_.mean[:, o], run_.lower[:, o], run_.upper[:, o])
                lat = summary(clean[:, o], run_.mean[:, o], run_.latent_lower[:, o], run_.latent_upper[:, o])
                per[ch] = {"fit": meas["fit"], "rmse": meas["rmse"], "coverage": meas["coverage"],
                           "fit_clean": lat["fit"], "coverage_latent": lat["coverage"],
                           "band_width": meas.get("band_width")}
            results["checks"].setdefault(rec.name, {})[method] = {"seconds": run_.seconds,
                                                                   "n_paths": run_.n_paths, "channels": per}
            log(f"{rec.name} {method}: " + "; ".join(f"{ch} fit {v['fit']:.1f} % cov {v['coverage']:.1f} %"
                                                      for ch, v in per.items()))
    # the baseline: one single-output GPNARX per sensor (u and that sensor's lags only, the same settings)
    from threadpoolctl import threadpool_limits

    results["single_output"] = {}
    with threadpool_limits(limits=1, user_api="blas"):
        for o, ch in enumerate(CHANNELS):
            one = GPNARX(ny=model.ny, nu=model.nu, max_train_points=model.max_train_points, n_restarts=0, seed=0)
            one.fit([Record(r.u, r.y[:, o], r.fs) for r in train])
            for rec in check:
                run1 = one.simulate(rec.u, method="linear")
                m1 = summary(rec.y[:, o], run1.mean, run1.lower, run1.upper)
                one_fit = {"fit": m1["fit"], "coverage": m1["coverage"]}
                results["single_output"].setdefault(rec.name, {})[ch] = one_fit
    for rec in check:
        per = results["single_output"][rec.name]
        log(f"{rec.name} single-output GPNARX per sensor: "
            + "; ".join(f"{ch} fit {v['fit']:.1f} % cov {v['coverage']:.1f} %" for ch, v in per.items()))
    results["wall_seconds"] = time.perf_counter() - t0
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "results.json").write_text(json.dumps(results, indent=1, sort_keys=True) + "\n")
        for rec in check:
            _figure(out / f"chain-{rec.name}.png", rec, runs[(rec.name, "linear")], runs[(rec.name, "mc")])
    return results


def _figure(path: Path, rec: Record, lin, mc) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = rec.t
    fig, axes = plt.subplots(len(CHANNELS), 1, figsize=(10, 2.4 * len(CHANNELS)), sharex=True)
    for o, (ax, ch) in enumerate(zip(axes, CHANNELS)):
        ax.fill_between(t, mc.lower[:, o] * 1e3, mc.upper[:, o] * 1e3, color="tab:orange", alpha=0.25,
                        label="99 % band, Monte Carlo")
        ax.plot(t, lin.lower[:, o] * 1e3, "b:", lw=0.6, label="99 % band, linearised")
        ax.plot(t, lin.upper[:, o] * 1e3, "b:", lw=0.6)
        ax.plot(t, rec.y[:, o] * 1e3, "k", lw=0.6, label="simulator (1 % sensor noise)")
        ax.plot(t, lin.mean[:, o] * 1e3, "r", lw=0.5, label="free run mean, linearised")
        ax.set_ylabel(f"{ch} [mm]")
    axes[0].legend(loc="upper right", fontsize=7, ncol=2)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(f"MIMO GP-NARX free run on the three-mass Bouc-Wen chain: {rec.name}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    from PIL import Image  # a palette PNG, a quarter of the size

    Image.open(path).convert("RGB").quantize(colors=32).save(path, optimize=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    res = run(a.quick, a.out)
    print(f"RESULT wall_seconds={res['wall_seconds']:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
