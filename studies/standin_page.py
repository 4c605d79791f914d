"""docs/standin.md, the BERT stand-in's page: its calibration run (the stand-in against the real records) and its
render by the results pages' renderer (``gpnarx.training.pages.standin``).

    python -m studies.standin_page run docs/runs/standin        # recompute the table from the real records
    python -m studies.standin_page render docs/runs/standin docs/standin.md
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from gpnarx.training.pages.standin import render
from gpnarx.training.simulators.bert_standin import calibration_table

__all__ = ["main", "render", "run"]


def run(out_dir) -> dict:
    """The calibration table from the real records (``$GPNARX_BERT_DATA``), written to OUT/calibration.json."""
    res = {"command": "python -m studies.standin_page run docs/runs/standin", "rows": calibration_table()}
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "calibration.json").write_text(json.dumps(res, indent=1))
    return res


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["run"] and len(argv) == 2:
        run(argv[1])
        return 0
    if argv[:1] == ["render"] and len(argv) == 3:
        Path(argv[2]).write_text(render(json.loads((Path(argv[1]) / "calibration.json").read_text())))
        return 0
    print("usage: python -m studies.standin_page run RUN_DIR | render RUN_DIR OUT.md", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
