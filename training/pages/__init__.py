"""The results pages of ``docs/``: one renderer, each page a render of its stored run and nothing else.

``markdown`` holds what every page shares (number formats, table rows, stored RESULT lines and run files, the
command line); one module a page family: ``protocol`` (``gpnarx reproduce``'s results-bouc-wen.md,
results-bert-standin.md and results-bert-real-paper.md), ``benchmarks`` (benchmarks.md, from the benches' stored
RESULT lines), ``accelerator`` (results-accelerator.md), ``monitoring`` (results-monitoring.md) and ``standin``
(standin.md); and two blocks of reference pages: ``wire`` (docs/api.md's wire table, bench/bench_wire.py's run)
and ``install_sizes`` (docs/deploy.md's install tiers, tools/install_sizes.py's run). results-bert-real.md is
``training.reproduce.real_page``'s, around the tables of a checkout's studies.

    python -m gpnarx.training.pages NAME RUN_DIR OUT.md
"""
