"""docs/results-monitoring.md from the stored runs of the cycle, torque and real-monitor studies
(docs/runs/monitoring/), rendered by the results pages' renderer (``gpnarx.training.pages.monitoring``):

    python -m studies.monitoring_page docs/runs/monitoring docs/results-monitoring.md
"""
from __future__ import annotations

import sys

from gpnarx.training.pages.markdown import page_main
from gpnarx.training.pages.monitoring import CYCLE_RUNS, bundle_facts, render

__all__ = ["CYCLE_RUNS", "bundle_facts", "main", "render"]


def main(argv=None) -> int:
    return page_main(render, "studies.monitoring_page", argv)


if __name__ == "__main__":
    sys.exit(main())
