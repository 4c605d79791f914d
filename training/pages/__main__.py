"""``python -m gpnarx.training.pages NAME RUN_DIR OUT.md``: a results page rendered from its stored run folder."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from gpnarx.training.pages import accelerator, benchmarks, monitoring, protocol, standin
from gpnarx.training.pages.markdown import load_json, page_main


def _protocol(system: str):
    def render(run_dir) -> str:
        return protocol.PAGES[system](json.loads((Path(run_dir) / "summary.json").read_text()),
                                      load_json(run_dir, "lag_surface.json"))
    return render


# NAME: how it renders from RUN_DIR (the folder the page's own header names)
PAGES = {"benchmarks": benchmarks.render,  # docs/runs
         "accelerator": accelerator.render,  # docs/runs/accelerator
         "monitoring": monitoring.render,  # docs/runs/monitoring
         "standin": lambda run_dir: standin.render(load_json(run_dir, "calibration.json")),  # docs/runs/standin
         **{system: _protocol(system) for system in protocol.PAGES}}  # docs/runs/SYSTEM


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] not in PAGES:
        print(f"usage: python -m gpnarx.training.pages NAME RUN_DIR OUT.md; NAME: {', '.join(PAGES)}",
              file=sys.stderr)
        return 2
    return page_main(PAGES[argv[0]], f"gpnarx.training.pages {argv[0]}", argv[1:])


if __name__ == "__main__":
    sys.exit(main())
