"""Progress bars when tqdm is installed (extra ``train``); none otherwise.

The core install serves and predicts without tqdm: every long-running loop asks :func:`progress_bar`
for a bar and runs the same with ``None``.
"""
from __future__ import annotations


def progress_bar(**kwargs):
    """A ``tqdm.tqdm(**kwargs)`` bar, or None when tqdm is not installed."""
    try:
        from tqdm import tqdm
    except ImportError:
        return None
    return tqdm(**kwargs)
