"""docs/api.md's wire table ("Wire formats": one 64 s predict answer as JSON, gzip JSON and NPZ), a block of that
page rendered from the stored run of bench/bench_wire.py (docs/runs/bench/wire.txt):
``python bench/bench_wire.py --render docs/api.md``."""
from __future__ import annotations

from pathlib import Path

from gpnarx.training.pages.markdown import replace_block, stored_run, table

BEGIN = "<!-- wire-table: rendered by bench/bench_wire.py --render from docs/runs/bench/wire.txt -->"
END = "<!-- /wire-table -->"
KINDS = ("json", "gzip", "npz")


def last_result(path) -> tuple[str, str, dict]:
    """A stored run file's ``# run:`` description, and its last RESULT line's command and fields."""
    about, rows = stored_run(Path(path).read_text())
    if not rows:
        raise ValueError(f"{path}: no RESULT line")
    command, kv = rows[-1]
    return about or "", command or "", kv


def render(about: str, command: str, kv: dict) -> str:
    """The wire table of docs/api.md from a stored run."""
    mb = {k: int(kv[f"{k}_bytes"]) / 1e6 for k in KINDS}
    wire = {k: float(kv[f"{k}_wire_ms"]) for k in KINDS}
    total = {k: float(kv[f"{k}_ms"]) for k in KINDS}
    gz = wire["gzip"] / wire["json"]
    gz_note = ": compression costs CPU on loopback, it pays on a slow link" if gz > 1 else ""
    rows = [
        ("JSON (the only format before)", f"{mb['json']:.2f} MB", f"{wire['json']:.0f} ms"),
        ("JSON, answer gzip-compressed", f"{mb['gzip']:.2f} MB ({float(kv['gzip_size_ratio']):.1f}x smaller)",
         f"{wire['gzip']:.0f} ms ({gz:.1f}x JSON's{gz_note})"),
        ("NPZ both ways", f"{mb['npz']:.2f} MB ({float(kv['npz_size_ratio']):.1f}x smaller)",
         f"{wire['npz']:.0f} ms ({float(kv['ratio']):.1f}x less)"),
    ]
    return "\n".join([BEGIN, "", f"Stored run `docs/runs/bench/wire.txt` (`{command}`). {about} \"Wire\" is the "
                      "end-to-end time of the call minus the prediction itself (from `Server-Timing`): encoding, "
                      "transfer, validation, rendering and decoding into numpy arrays on both sides; sizes are the "
                      "answer's bytes on the wire.", ""]
                     + table(["body and answer", "answer size", "wire time", "end to end, prediction included"],
                             [[label, size, w, f"{total[k] / 1e3:.1f} s"] for (label, size, w), k in zip(rows, KINDS)])
                     + ["", END])


def render_page(page, run) -> None:
    """Re-render ``page``'s wire table from the stored run file ``run``."""
    page = Path(page)
    page.write_text(replace_block(page.read_text(), BEGIN, END, render(*last_result(run))))
