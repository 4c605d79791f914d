"""Progress bars when tqdm is installed (extra ``train``); none otherwise, or plain lines where asked.

The core install serves and predicts without tqdm: every long-running loop asks :func:`progress_bar`
for a bar and runs the same with ``None``. A loop of few long units (``gpnarx lags``: minutes per
cell) asks for ``lines=True``: without tqdm it then gets one plain line on stderr per finished unit,
so a long run is never silent.
"""
from __future__ import annotations

import sys
import time


class LineProgress:
    """The part of tqdm's interface the package's loops use (``update``, ``n``, ``refresh``, ``close``), as one
    line per update on ``file`` (stderr): ``DESC: N/TOTAL UNITs (P %), S s``."""

    def __init__(self, total=None, initial: int = 0, desc: str = "", unit: str = "it", file=None, **_):
        self.total, self.n, self.desc, self.unit = total, int(initial), desc, unit
        self.file = file if file is not None else sys.stderr
        self.t0 = time.perf_counter()
        self._line("from a cache" if self.n else "started")

    def _line(self, note: str = "") -> None:
        share = f" ({100.0 * self.n / self.total:.0f} %)" if self.total else ""
        of = f"/{self.total}" if self.total else ""
        tail = f", {note}" if note else f", {time.perf_counter() - self.t0:.0f} s"
        print(f"{self.desc}: {self.n}{of} {self.unit}s{share}{tail}", file=self.file, flush=True)

    def update(self, k: int = 1) -> None:
        self.n += int(k)
        self._line()

    def refresh(self) -> None:
        self._line()

    def close(self) -> None:
        pass


def progress_bar(lines: bool = False, **kwargs):
    """A ``tqdm.tqdm(**kwargs)`` bar, or when tqdm is not installed a :class:`LineProgress` (``lines``) or None."""
    try:
        from tqdm import tqdm
    except ImportError:
        return LineProgress(**kwargs) if lines else None
    return tqdm(**kwargs)
