"""Precision and recall of a moving-object mask against labels."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike


def precision_recall(predicted: ArrayLike, moving: ArrayLike) -> dict[str, float]:
    """Point-wise (or cell-wise) precision, recall and counts of `predicted` against the `moving` truth.
    Precision is NaN when nothing is predicted moving and recall NaN when nothing is moving: an undefined
    ratio, not a perfect one."""
    p = np.asarray(predicted, dtype=bool).ravel()
    m = np.asarray(moving, dtype=bool).ravel()
    if p.shape != m.shape:
        raise ValueError(f"predicted and moving differ in size: {p.size} and {m.size}")
    hits = int(np.count_nonzero(p & m))
    flagged, truth = int(np.count_nonzero(p)), int(np.count_nonzero(m))
    return {
        "precision": hits / flagged if flagged else float("nan"),
        "recall": hits / truth if truth else float("nan"),
        "predicted": flagged,
        "moving": truth,
        "points": int(p.size),
    }
