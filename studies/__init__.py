"""Studies: one-off investigations whose figures are published in docs/ (a results page renders each from
its stored run under docs/runs/). They use the product as a user would (``gpnarx`` imports or the CLI in a
child process) and live in the repository, not in the wheel: run one from a checkout with
``gpnarx reproduce STUDY -- ARGS`` (``gpnarx.training.checkout`` finds this folder) or
``python -m studies.MODULE ARGS`` from the repository root.
"""
