"""Segmentation of a scan into clusters, and the occluded ends of a cluster.

A missing return, or a gap between neighbouring points larger than
``jump_abs_m + jump_beams · ρ · Δβ`` (an occlusion edge), starts a new cluster.  A
cluster end next to a nearer return may hide a corner, so line fits leave out the
returns near it (:func:`_outside_occluded_ends`).
"""

from __future__ import annotations

import numpy as np

from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.perception.extraction.params import ExtractionParams
from mapfuse_core.sensor import LaserParams, Scan


def _segment(scan: Scan, laser: LaserParams, params: ExtractionParams) -> list[np.ndarray]:
    """Clusters of beam indices: consecutive returns without an occlusion-size gap."""
    idx = np.flatnonzero(scan.valid())
    if idx.size == 0:
        return []
    r = scan.ranges[idx]
    b = scan.bearings[idx]
    P = np.column_stack((r * np.cos(b), r * np.sin(b)))
    gap = np.hypot(*(P[1:] - P[:-1]).T)
    tol = params.jump_abs_m + params.jump_beams * np.minimum(r[1:], r[:-1]) * (
        laser.beam_spacing_rad
    )
    breaks = (np.diff(idx) > 1) | (gap > tol)
    return np.split(idx, np.flatnonzero(breaks) + 1)


def _outside_occluded_ends(
    scan: Scan, b: FloatArray, ends: list[tuple[int, int]], margin: float
) -> np.ndarray:
    """Mask of the returns at bearings ``b`` farther than ``margin`` in bearing from
    every occluded cluster end.

    ``ends`` pairs the beam index of each outermost return of the cluster (before
    ``end_trim``) with that of the beam just beyond it; the end is occluded when that
    beam's return is nearer.
    """
    keep = np.ones(b.size, dtype=bool)
    for end, beyond in ends:
        if scan.ranges[beyond] < scan.ranges[end]:
            keep &= np.abs(b - scan.bearings[end]) > margin
    return keep
