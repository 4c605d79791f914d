"""Where the lab data lives: the one lookup of the real BERT records, for the code and the tests alike.

``$GPNARX_BERT_DATA`` when set; else the first existing of ``<source checkout>/../shared/data/bert-t5nm``,
``./shared/data/bert-t5nm`` and ``../shared/data/bert-t5nm`` from the working directory (the first
candidate when none exists, so a message can name where it looked).
"""
from __future__ import annotations

import os
from pathlib import Path

BERT_DATA_ENV = "GPNARX_BERT_DATA"
_TAIL = Path("shared") / "data" / "bert-t5nm"


def bert_data_dir() -> Path:
    """Folder of the real BERT records (see the module docstring)."""
    env = os.environ.get(BERT_DATA_ENV)
    if env:
        return Path(env).expanduser()
    candidates = [Path(__file__).resolve().parent.parent.parent / _TAIL, Path.cwd() / _TAIL, Path.cwd().parent / _TAIL]
    return next((c for c in candidates if c.is_dir()), candidates[0])
