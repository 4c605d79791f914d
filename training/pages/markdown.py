"""What every results page shares: numbers as the pages print them, Markdown table rows, stored RESULT lines and
run files, page blocks, and the command line that writes a page from a stored run."""
from __future__ import annotations

import json
import sys
from pathlib import Path


def pct(v, digits: int = 1) -> str:
    """A percentage (or fit %, or any fixed-point figure) as the pages print it: ``digits`` decimals, 'n/a' when
    missing."""
    return "n/a" if v is None else f"{float(v):.{digits}f}"


def sig(v, digits: int = 3) -> str:
    """``digits`` significant digits, 'n/a' when missing."""
    return "n/a" if v is None else f"{float(v):.{digits}g}"


def hz(v) -> str:
    """A frequency [Hz]: two decimals."""
    return pct(v, 2)


def grouped(v) -> str:
    """A large number rounded, with thin grouping (132 914)."""
    return f"{round(float(v)):,}".replace(",", " ")


def row(cells) -> str:
    """One Markdown table row."""
    return "| " + " | ".join(cells) + " |"


def rule(n: int) -> str:
    """The rule under a Markdown table header of ``n`` columns."""
    return "|" + "---|" * n


def table(head, rows) -> list[str]:
    """A Markdown table's lines: the header, its rule and the rows (each a sequence of cells)."""
    return [row(head), rule(len(head))] + [row(r) for r in rows]


def result_fields(line: str) -> dict:
    """The ``key=value`` fields of one ``RESULT`` line (what every bench prints)."""
    return dict(tok.split("=", 1) for tok in line[len("RESULT "):].split() if "=" in tok)


def result_lines(text: str) -> list[dict]:
    """The fields of every ``RESULT`` line of a stored run."""
    return [result_fields(ln) for ln in text.splitlines() if ln.startswith("RESULT ")]


def stored_run(text: str) -> tuple[str | None, list[tuple[str | None, dict]]]:
    """A stored run file of RESULT lines: its ``# run:`` description and its lines as (command, fields); a ``# ``
    line right before a RESULT line names that line's command."""
    about, rows, command = None, [], None
    for line in text.splitlines():
        if line.startswith("# run:"):
            about = line[len("# run:"):].strip()
        elif line.startswith("# "):
            command = line[2:].strip()
        elif line.startswith("RESULT "):
            rows.append((command, result_fields(line)))
            command = None
    return about, rows


def load_json(run_dir, name: str):
    """``RUN_DIR/NAME`` as JSON; None when the run has no such file."""
    p = Path(run_dir) / name
    return json.loads(p.read_text()) if p.is_file() else None


def replace_block(text: str, begin: str, end: str, block: str) -> str:
    """``text`` with the block from its ``begin`` marker line to its ``end`` marker replaced by ``block`` (which holds
    both markers)."""
    if begin not in text or end not in text:
        raise ValueError(f"no {begin!r} ... {end!r} block")
    head, rest = text.split(begin, 1)
    return head + block + rest.split(end, 1)[1]


def page_main(render, prog: str, argv=None) -> int:
    """``python -m PROG RUN_DIR OUT.md``: a results page rendered from a stored run folder."""
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2:
        print(f"usage: python -m {prog} RUN_DIR OUT.md", file=sys.stderr)
        return 2
    Path(argv[1]).write_text(render(argv[0]))
    return 0


def lines(rows: list[str]) -> str:
    """Lines as a block of text, each ended by a newline."""
    return "".join(r + "\n" for r in rows)
