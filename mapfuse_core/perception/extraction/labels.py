"""The world id a feature is labelled with, from the laser's ``hit_ids`` of its points.

Labels never steer the extraction: they are attached to a feature after it is
accepted, for evaluation and for tests.
"""

from __future__ import annotations

import numpy as np


def _label(hit_ids: np.ndarray, majority: float) -> int:
    """World id of at least ``majority`` of the points, else −1."""
    if hit_ids.size == 0:
        return -1
    # Nearly always a single id; np.unique costs as much as a line fit.
    first = int(hit_ids[0])
    if (hit_ids == first).all():
        return first if first >= 0 else -1
    ids, counts = np.unique(hit_ids, return_counts=True)
    k = int(np.argmax(counts))
    if ids[k] >= 0 and counts[k] >= majority * hit_ids.size:
        return int(ids[k])
    return -1
