"""The results of a stage's chunks: a chunk is a pure function of (stage, index, inputs), so its
results may come back in any order, from any worker (stages.py runs them)."""

from __future__ import annotations

import numpy as np


def placed(results, n: int, channels: int, dtype=np.float32) -> np.ndarray:
    """(n, channels) values from chunk results (first row, values) that come in any order."""
    out = np.zeros((n, channels), dtype)
    for first, values in results:
        out[int(first[0]) : int(first[0]) + len(values)] = values
    return out
