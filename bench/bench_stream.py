"""A record in chunks against the record whole: the stream state's fidelity, size and cost.

On the shipped ``bert-real`` bundle and a real 64 s record (default the 20 Hz sine, held out, from
rest), sent in 1 s chunks, each call continuing from the previous answer's state token
(``model.stream_token``: encoded after each chunk and decoded before the next, as the service does),
against the same record in one call:

- ``max_mean_diff``: largest |chunked - whole| mean, in the record's standard deviation;
- ``max_band_diff``: largest difference of a band edge, in the whole run's band half-width there, over
  the record, and ``max_band_diff_inner`` away from the last half-window of each chunk (the one place the
  model-discrepancy term's centred window cannot see the chunk to come; docs/api.md, Streams);
- ``token_bytes``: the state token's size; ``token_ms``: encode + decode per call;
- ``ratio``: wall seconds of the chunked run (tokens included) over the whole run's (the baseline, same
  process and threads).

Linearised over the whole record; Monte Carlo (1024 paths) over its first ``--mc-seconds`` (16 s).

    python bench/bench_stream.py [--quick] [--registry R] [--record PATH] [--mc-seconds S] [--threads N]

--quick: a small Bouc-Wen model with a discrepancy term, 64 paths, 600 samples in chunks of 100.
"""
from __future__ import annotations

import time

import numpy as np

import _common as C
from gpnarx.model.stream_token import decode_state, encode_state


def run_case(model, u, y, method, chunk, paths, hw_window):
    kw = {"n_paths": paths, "seed": 0} if method == "mc" else {}
    t0 = time.perf_counter()
    whole = model.simulate(u, method=method, **kw)
    t_whole = time.perf_counter() - t0
    parts, token, tok_s, size = [], None, 0.0, 0
    t0 = time.perf_counter()
    for c in range(0, u.size, chunk):
        t1 = time.perf_counter()
        state = None if token is None else decode_state(token, "m", "1")
        tok_s += time.perf_counter() - t1
        r = model.simulate(u[c:c + chunk], method=method, state=state, open_end=c + chunk < u.size, **kw)
        t1 = time.perf_counter()
        token = encode_state(r.state, "m", "1")
        tok_s += time.perf_counter() - t1
        size = max(size, len(token))
        parts.append(r)
    t_chunked = time.perf_counter() - t0
    cat = {k: np.concatenate([getattr(p, k) for p in parts]) for k in ("mean", "lower", "upper")}
    sd = float(np.std(y))
    half = np.maximum((whole.upper - whole.lower) / 2.0, 1e-300)
    band = np.maximum(np.abs(cat["lower"] - whole.lower), np.abs(cat["upper"] - whole.upper)) / half
    inner = np.ones(u.size, bool)
    for c in range(chunk, u.size, chunk):
        inner[max(0, c - hw_window // 2 - 1): c] = False
    calls = -(-u.size // chunk)
    return {"max_mean_diff": float(np.max(np.abs(cat["mean"] - whole.mean)) / sd),
            "max_band_diff": float(np.max(band)), "max_band_diff_inner": float(np.max(band[inner])),
            "token_bytes": size, "token_ms": 1e3 * tok_s / calls, "whole_s": t_whole, "chunked_s": t_chunked,
            "ratio": t_chunked / t_whole}


def main() -> None:
    args = C.parse_args(__doc__, extra=lambda p: (p.add_argument("--registry"), p.add_argument("--record"),
                                                   p.add_argument("--mc-seconds", type=float, default=16.0)))
    if args.quick:
        from gpnarx.model.estimator import GPNARX

        pairs, _, r50 = C.protocol()
        model = GPNARX(ny=C.NY, nu=C.NU, mode="sparse", n_inducing=64, max_train_points=500).fit(
            pairs, theta=C.THETA_REF)
        model.band_discrepancy_ = {"scale": 0.1, "window": 32}
        u, y, fs, chunk, paths, mc_n = r50.u[:600], r50.y[:600], 750.0, 100, 64, 600
        what = "quick Bouc-Wen"
    else:
        import bench_realtime as R

        from gpnarx.storage.record_files import read_record
        from gpnarx.storage.registry import Registry

        reg, _ = R.bert_registry(args.registry)
        model = Registry(reg, lazy=True).scan(only="bert-real").get("bert-real").model
        rec = read_record(args.record or R.bert_data() / "Sine" / "Sine_20Hz")
        u, y, fs = rec.u, rec.y, rec.fs
        chunk, paths, mc_n = int(round(fs)), 1024, int(round(args.mc_seconds * fs))
        what = f"bert-real, {rec.name}"
    disc = getattr(model, "band_discrepancy_", None) or {}
    w = int(disc.get("window", 0))
    lin = run_case(model, u, y, "linear", chunk, 0, w)
    mc = run_case(model, u[:mc_n], y[:mc_n], "mc", chunk, paths, w)
    print(f"# {what}: {u.size / fs:.0f} s linearised and {mc_n / fs:.0f} s Monte Carlo ({paths} paths) in chunks "
          f"of {chunk} samples; discrepancy window {w}")
    C.result(bench="stream", model=what.replace(" ", "_"), chunk=chunk,
             **{f"linear_{k}": v for k, v in lin.items()}, **{f"mc_{k}": v for k, v in mc.items()},
             baseline=lin["whole_s"], baseline_what="linearised_whole_record_in_one_call_s", ratio=lin["ratio"])


if __name__ == "__main__":
    main()
