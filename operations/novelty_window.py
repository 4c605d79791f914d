"""A stream's rolling novelty window: the last samples of a stream scored together.

A novelty verdict on each chunk of a stream reacts fast but is noisy on short chunks; the verdict over the
last few seconds is steadier and sees a slow change sooner than a threshold crossing on one chunk. The
window holds the last ``max_samples`` samples of the stream: the input ``u`` [input units], the measured
output ``y`` and the free run's ``mean`` and ``std`` [output units], and each chunk's out-of-range flags
(a chunk's flags count while any of its samples is in the window). Its verdict is ``assess_novelty`` on
those samples, with the flags of its chunks together: the same score, threshold and rules as a record's.

``gpnarx stream`` keeps one in memory (``--window`` chunks); the HTTP novelty answer of a stream carries
it in the state token (``as_carry``/``from_carry``; ``HTTP_WINDOW_SECONDS`` of the stream), so any
replica continues it. Size: 4 x 8 x ``max_samples`` bytes of arrays (256 kB for 8 s at 1024 Hz) before
the token's compression.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

from gpnarx.checks import is_int
from gpnarx.model.novelty import assess_novelty

#: the HTTP stream's window [s]: the CLI's default of 8 chunks of 1 s
HTTP_WINDOW_SECONDS = 8.0
_ARRAYS = ("u", "y", "mean", "std")


@dataclass
class RollingWindow:
    """The last ``max_samples`` samples of a stream (see the module docstring). ``chunks``: per chunk still
    in the window, ``[samples, diverged_paths, out_of_range]`` (oldest first)."""

    max_samples: int
    u: np.ndarray = field(default_factory=lambda: np.zeros(0))
    y: np.ndarray = field(default_factory=lambda: np.zeros(0))
    mean: np.ndarray = field(default_factory=lambda: np.zeros(0))
    std: np.ndarray = field(default_factory=lambda: np.zeros(0))
    chunks: list = field(default_factory=list)

    def __post_init__(self):
        if not is_int(self.max_samples, 1):
            raise ValueError(f"novelty window max_samples must be a positive integer, got {self.max_samples!r}")
        self.max_samples = int(self.max_samples)

    def add(self, u, y, mean, std, flags: dict | None = None) -> "RollingWindow":
        """Append a chunk (its arrays and out-of-range ``flags``) and drop what falls out of the window."""
        new = {k: np.asarray(v, dtype=float).ravel() for k, v in zip(_ARRAYS, (u, y, mean, std))}
        if len({v.size for v in new.values()}) != 1:
            raise ValueError("novelty window: u, y, mean and std of a chunk must have the same length")
        flags = flags or {}
        for k, v in new.items():
            setattr(self, k, np.concatenate([getattr(self, k), v])[-self.max_samples:])
        self.chunks.append([int(new["u"].size), int(flags.get("diverged_paths", 0) or 0),
                            sorted(str(f) for f in flags.get("out_of_range", []))])
        held, keep = 0, []
        for c in reversed(self.chunks):  # the chunks with samples still in the window
            if held >= self.u.size:
                break
            keep.append(c)
            held += c[0]
        self.chunks = keep[::-1]
        return self

    def flags(self) -> dict:
        return {"diverged_paths": max((c[1] for c in self.chunks), default=0),
                "out_of_range": sorted({f for c in self.chunks for f in c[2]})}

    def assess(self, novelty: dict, fs: float) -> dict:
        """``{"chunks", "samples", "seconds", "score", "threshold", "verdict"}`` of the window (``assess_novelty``
        on its samples; the stream continues a run, so the probe is matched as a measured start)."""
        a = assess_novelty(novelty, self.u, self.y, fs, SimpleNamespace(mean=self.mean, std=self.std),
                           start="measured", flags=self.flags())
        return {"chunks": len(self.chunks), "samples": int(self.u.size), "seconds": self.u.size / float(fs),
                **{k: a[k] for k in ("score", "threshold", "verdict")}}

    def as_carry(self) -> dict:
        """The window as a state token's carry (``operations.stream_token``): arrays and JSON values."""
        return {"max_samples": self.max_samples, "chunks": self.chunks,
                **{k: getattr(self, k) for k in _ARRAYS}}

    @classmethod
    def from_carry(cls, d: dict | None, max_samples: int) -> "RollingWindow":
        """The window a token carried (a new one when ``d`` is None or its size differs from ``max_samples``)."""
        if not d or not is_int(d.get("max_samples")) or d.get("max_samples") != int(max_samples):
            return cls(max_samples)
        malformed = ValueError("state: its novelty window is malformed")
        try:  # a client may rebuild a token signed with the public key: every value is checked before use
            arrays = {k: np.asarray(d.get(k, np.zeros(0)), dtype=float).ravel() for k in _ARRAYS}
        except (TypeError, ValueError):
            raise malformed from None
        n = {v.size for v in arrays.values()}
        size = n.pop() if len(n) == 1 else -1
        finite = all(np.all(np.isfinite(arrays[k])) for k in ("u", "mean", "std"))  # y: NaN where none was measured
        chunks = d.get("chunks") or []
        if not 0 <= size <= max_samples or not finite or not isinstance(chunks, list) or len(chunks) > size + 1:
            raise malformed
        if not all(isinstance(c, list) and len(c) == 3 and all(is_int(v, 0) for v in c[:2])
                   and isinstance(c[2], list) and all(isinstance(f, str) for f in c[2]) for c in chunks):
            raise malformed
        return cls(int(max_samples), chunks=[[c[0], c[1], list(c[2])] for c in chunks], **arrays)


__all__ = ["HTTP_WINDOW_SECONDS", "RollingWindow"]
