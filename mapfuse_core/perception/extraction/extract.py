"""The extraction of one scan: clusters, then a circle or lines from each.

The method and its rejection rules are described in the package docstring of
:mod:`mapfuse_core.perception.extraction`.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from mapfuse_core.perception.extraction.circles import _circle_from_cluster
from mapfuse_core.perception.extraction.lines import _lines_from_cluster
from mapfuse_core.perception.extraction.noise import _Noise
from mapfuse_core.perception.extraction.params import (
    ExtractedFeature,
    ExtractionParams,
    ExtractionResult,
)
from mapfuse_core.perception.extraction.segment import _outside_occluded_ends, _segment
from mapfuse_core.sensor import LaserParams, Scan

__all__ = ["extract_features"]

_DEFAULT_PARAMS = ExtractionParams()


def extract_features(
    scan: Scan, laser: LaserParams, params: ExtractionParams = _DEFAULT_PARAMS
) -> ExtractionResult:
    """Extract lines and circles from ``scan`` (sensor frame) with their covariances.

    ``laser`` supplies the noise model (σρ, σβ) and the beam spacing; it must be the
    laser the scan came from.  An empty scan, or one without returns, gives no
    features.  The method and the rejection rules are described in the package docstring
    of :mod:`mapfuse_core.perception.extraction`.
    """
    if not isinstance(scan, Scan):
        raise ValueError(f"scan must be a Scan, got {type(scan).__name__}")
    if not isinstance(laser, LaserParams):
        raise ValueError(f"laser must be a LaserParams, got {type(laser).__name__}")
    if not isinstance(params, ExtractionParams):
        raise ValueError(f"params must be an ExtractionParams, got {type(params).__name__}")
    if scan.bearings.size not in (0, laser.n_beams):
        raise ValueError(
            f"scan has {scan.bearings.size} beams but the laser has n_beams={laser.n_beams}"
        )
    if scan.bearings.size > 1 and np.any(np.diff(scan.bearings) <= 0.0):
        raise ValueError("scan.bearings must be strictly increasing")

    noise = _Noise(
        var_r=laser.sigma_range_m**2 + params.wall_roughness_m**2,
        var_b=laser.sigma_bearing_rad**2,
        floor2=params.sigma_floor_m**2,
    )
    rejected: Counter[str] = Counter()
    features: list[ExtractedFeature] = []
    min_pts = min(params.min_line_points, params.min_circle_points)
    # Round-off in the bearings must not decide whether a beam is inside the margin.
    end_margin = params.corner_margin_sigma * laser.sigma_bearing_rad * (1.0 + 1e-9)
    n_beams = scan.bearings.size
    for cl in _segment(scan, laser, params):
        # Most clusters are a few returns (far trunks, wall slivers): reject them first.
        if cl.size - 2 * params.end_trim < min_pts:
            rejected["too_few_points"] += 1
            continue
        span_b = (float(scan.bearings[cl[0]]), float(scan.bearings[cl[-1]]))
        end_r = (float(scan.ranges[cl[0]]), float(scan.ranges[cl[-1]]))
        at_fov_edge = bool(cl[0] == 0 or cl[-1] == n_beams - 1)
        ends = [(e, j) for e, j in ((cl[0], cl[0] - 1), (cl[-1], cl[-1] + 1)) if 0 <= j < n_beams]
        beside = np.array([j for _, j in ends], dtype=int)
        outside = (scan.ranges[beside], scan.bearings[beside])
        if params.end_trim:
            cl = cl[params.end_trim : cl.size - params.end_trim]
        r = scan.ranges[cl]
        b = scan.bearings[cl]
        ids = scan.hit_ids[cl]
        P = np.column_stack((r * np.cos(b), r * np.sin(b)))
        chord = float(np.hypot(*(P[-1] - P[0])))
        # A cluster cut by the edge of the field of view has no silhouette on that side:
        # its span says nothing about a radius, and an arc there cannot be checked.
        if (
            not at_fov_edge
            and cl.size >= params.min_circle_points
            and chord <= 2.2 * params.circle_radius_max_m
        ):
            circ = _circle_from_cluster(P, r, b, ids, span_b, outside, end_r, noise, params)
            if isinstance(circ, ExtractedFeature):
                features.append(circ)
                continue
            if isinstance(circ, str):
                rejected[circ] += 1
                continue
        # Cheap exits for the many small clusters (far trunks, wall slivers); no segment
        # of a cluster can be longer than the diagonal of its bounding box.
        if cl.size < params.min_line_points:
            rejected["too_few_points"] += 1
            continue
        if float(np.hypot(*np.ptp(P, axis=0))) < params.min_line_length_m:
            rejected["too_short"] += 1
            continue
        if params.occluded_end_margin:
            keep = _outside_occluded_ends(scan, b, ends, end_margin)
            if not keep.all():
                P, r, b, ids = P[keep], r[keep], b[keep], ids[keep]
        features.extend(_lines_from_cluster(P, r, b, ids, noise, laser, params, rejected))
    return ExtractionResult(features=tuple(features), rejected=dict(sorted(rejected.items())))
