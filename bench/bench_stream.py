"""A record in chunks against the record whole: the stream state's fidelity, size and cost.

On the shipped ``bert-real`` bundle and a real 64 s record (default the 20 Hz sine, held out, from
rest), sent in 1 s chunks, each call continuing from the previous answer's state token
(``operations.stream_token``: encoded after each chunk and decoded before the next, as the service does),
against the same record in one call, linearised and by Monte Carlo over the whole record:

- ``max_mean_diff``: largest |chunked - whole| mean, in the record's standard deviation;
- ``max_band_diff``: largest difference of a band edge, in the whole run's band half-width there, over
  the record, and ``max_band_diff_inner`` away from the last half-window of each chunk (where a centred
  discrepancy window cannot see the chunk to come; docs/api.md, Streams); for the bundle's window kind
  (``linear_``/``mc_``, centred on ``bert-real`` as shipped) and the same scale with the trailing window
  (``linear_trailing_``/``mc_trailing_``), which sees only the past;
- ``token_bytes``: the state token's size; ``token_ms``: encode + decode per call;
- ``ratio``: wall seconds of the chunked run (tokens included) over the whole run's (the baseline, same
  process and threads).

The Monte Carlo free run is computed once in chunks and once whole; the discrepancy term of each window
kind is then added as ``GPNARX.simulate`` adds it (``discrepancy.widen_chunk``, chunk by chunk with the
carried tail), so both kinds are measured on the same paths.

    python bench/bench_stream.py [--quick] [--registry R] [--record PATH] [--mc-paths P] [--mc-seconds S]
                                 [--threads N]

--quick: a small Bouc-Wen model with a discrepancy term, 64 paths, 600 samples in chunks of 100.
"""
from __future__ import annotations

import time

import numpy as np

import _common as C
from gpnarx.model.discrepancy import widen_chunk
from gpnarx.operations.stream_token import decode_state, encode_state


def _chunks(model, u, method, chunk, kw, disc):
    """The chunk runs of ``u``, each continuing the previous one's decoded token, which carries the mean tail
    of the discrepancy ``disc`` as the model's does; (runs, token s, max bytes)."""
    parts, token, tok_s, size = [], None, 0.0, 0
    for c in range(0, u.size, chunk):
        t1 = time.perf_counter()
        state = None if token is None else decode_state(token, "m", "1")
        tok_s += time.perf_counter() - t1
        r = model.simulate(u[c:c + chunk], method=method, state=state, open_end=c + chunk < u.size, **kw)
        r.state.amp_tail = widen_chunk(r, disc, None if state is None else state.amp_tail)[1]
        t1 = time.perf_counter()
        token = encode_state(r.state, "m", "1")
        tok_s += time.perf_counter() - t1
        size = max(size, len(token))
        parts.append(r)
    return parts, tok_s, size


def _diffs(whole, parts, y, chunk, hw_window) -> dict:
    cat = {k: np.concatenate([getattr(p, k) for p in parts]) for k in ("mean", "lower", "upper")}
    half = np.maximum((whole.upper - whole.lower) / 2.0, 1e-300)
    band = np.maximum(np.abs(cat["lower"] - whole.lower), np.abs(cat["upper"] - whole.upper)) / half
    inner = np.ones(whole.mean.size, bool)
    for c in range(chunk, whole.mean.size, chunk):
        inner[max(0, c - hw_window // 2 - 1): c] = False
    return {"max_mean_diff": float(np.max(np.abs(cat["mean"] - whole.mean)) / float(np.std(y))),
            "max_band_diff": float(np.max(band)), "max_band_diff_inner": float(np.max(band[inner]))}


def run_case(model, u, y, method, chunk, paths, kinds):
    """Whole and chunked runs of ``u``; the band's discrepancy of each of ``kinds`` (name -> stored
    ``band_discrepancy``) added to both as the model adds it. Returns {name: figures}."""
    kw = {"n_paths": paths, "seed": 0} if method == "mc" else {}
    t0 = time.perf_counter()
    whole = model.simulate(u, method=method, **kw)
    t_whole = time.perf_counter() - t0
    t0 = time.perf_counter()
    parts, tok_s, size = _chunks(model, u, method, chunk, kw, next(iter(kinds.values())))
    t_chunked = time.perf_counter() - t0
    calls = len(parts)
    out = {}
    for name, disc in kinds.items():
        w, tail, held, widened = widen_chunk(whole, disc)[0], None, None, []
        for k, p in enumerate(parts):
            r, tail, held = widen_chunk(p, disc, tail, open_end=k < calls - 1, hold_start=held)
            widened.append(r)
        out[name] = _diffs(w, widened, y, chunk, int(disc["window"]))
    out["timing"] = {"token_bytes": size, "token_ms": 1e3 * tok_s / calls, "whole_s": t_whole,
                     "chunked_s": t_chunked, "ratio": t_chunked / t_whole}
    return out


def main() -> None:
    args = C.parse_args(__doc__, extra=lambda p: (p.add_argument("--registry"), p.add_argument("--record"),
                                                   p.add_argument("--mc-paths", type=int, default=1024),
                                                   p.add_argument("--mc-seconds", type=float, default=None)))
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
        chunk, paths = int(round(fs)), int(args.mc_paths)
        mc_n = u.size if args.mc_seconds is None else min(u.size, int(round(args.mc_seconds * fs)))
        what = f"bert-real, {rec.name}"
    disc = dict(getattr(model, "band_discrepancy_", None) or {})
    kinds = {"": disc, "trailing_": {**disc, "window_kind": "trailing"}}
    model.band_discrepancy_ = None  # added per kind by run_case, as simulate adds it
    lin = run_case(model, u, y, "linear", chunk, 0, kinds)
    mc = run_case(model, u[:mc_n], y[:mc_n], "mc", chunk, paths, kinds)
    print(f"# {what}: {u.size / fs:.0f} s linearised and {mc_n / fs:.0f} s Monte Carlo ({paths} paths) in chunks "
          f"of {chunk} samples; discrepancy scale {disc.get('scale')} window {disc.get('window')} "
          f"(shipped kind {disc.get('window_kind', 'centred')})")
    fields = {}
    for prefix, res in (("linear_", lin), ("mc_", mc)):
        for kind in kinds:
            fields.update({f"{prefix}{kind}{k}": v for k, v in res[kind].items()})
        fields.update({f"{prefix}{k}": v for k, v in res["timing"].items()})
    C.result(bench="stream", model=what.replace(" ", "_"), chunk=chunk, mc_paths=paths, mc_seconds=mc_n / fs,
             **fields, baseline=lin["timing"]["whole_s"], baseline_what="linearised_whole_record_in_one_call_s",
             ratio=lin["timing"]["ratio"])


if __name__ == "__main__":
    main()
