"""docs/results-accelerator.md from the stored GPU run in docs/runs/accelerator/, rendered by the results pages'
renderer (``gpnarx.training.pages.accelerator``, which says what the run folder holds):

    python -m studies.accelerator_page docs/runs/accelerator docs/results-accelerator.md
"""
from __future__ import annotations

import sys

from gpnarx.training.pages.accelerator import render
from gpnarx.training.pages.markdown import page_main

__all__ = ["main", "render"]


def main(argv=None) -> int:
    return page_main(render, "studies.accelerator_page", argv)


if __name__ == "__main__":
    sys.exit(main())
