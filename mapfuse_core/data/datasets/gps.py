"""GPS-based reference labels: which surveyed beacon each detected pole is.

Not ground truth: a label for checking data association on real data.
"""

from __future__ import annotations

import numpy as np

from mapfuse_core.data.datasets.odometry import dead_reckoning
from mapfuse_core.evaluation import rigid_alignment
from mapfuse_core.geometry.se2 import FloatArray, compose, transform_point


def gps_reference_labels(
    timestamps: FloatArray,
    odometry: FloatArray,
    feat_step: np.ndarray,
    feat_xy: FloatArray,
    gps_times: FloatArray,
    gps_xy: FloatArray,
    beacons: FloatArray,
    *,
    half_window_s: float = 2.0,
    gate_m: float = 0.5,
) -> np.ndarray:
    """Reference beacon id of every detected pole (−1 when unsure), from GPS.

    Not ground truth: a label for checking data association on real data.  Around every
    step the dead reckoning is fitted rigidly to GPS over ``±half_window_s`` (which
    removes its slow drift; steps where the car moves less than 1 m in the window take
    the fit of the nearest step that has one), the pole ``feat_xy`` (laser frame) is
    mapped through it, and it is labelled with the nearest beacon if that is within
    ``gate_m`` and no other beacon is within ``2·gate_m`` (beacons are metres apart;
    ``docs/real-data.md`` gives how close the poles land).
    """
    dr = dead_reckoning(odometry)
    gps = np.column_stack([np.interp(timestamps, gps_times, gps_xy[:, i]) for i in range(2)])
    n = timestamps.shape[0]
    fits = np.full((n, 3), np.nan)
    for k in range(n):
        m = np.abs(timestamps - timestamps[k]) <= half_window_s
        if np.ptp(dr[m, 0]) + np.ptp(dr[m, 1]) < 1.0:
            continue
        fits[k] = rigid_alignment(dr[m, :2], gps[m])
    have = np.flatnonzero(np.isfinite(fits[:, 0]))
    labels = np.full(feat_step.shape[0], -1, dtype=np.int64)
    if have.size == 0:
        return labels
    for i, (k, f) in enumerate(zip(feat_step.tolist(), feat_xy, strict=True)):
        T = fits[have[np.argmin(np.abs(have - k))]]
        w = transform_point(compose(T, dr[k]), f)
        d = np.hypot(beacons[:, 0] - w[0], beacons[:, 1] - w[1])
        order = np.argsort(d)
        if d[order[0]] < gate_m and (d.size == 1 or d[order[1]] >= 2.0 * gate_m):
            labels[i] = int(order[0])
    return labels
