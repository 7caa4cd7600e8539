"""Helpers shared by the real-dataset tests: rigid fits, GPS lookup, pole residuals."""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares

from mapfuse_core.data.datasets import (
    dead_reckoning,
)
from mapfuse_core.geometry.se2 import wrap_scalar
from mapfuse_core.measlog import MeasurementLog


def rigid_fit(P: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation ``R`` and translation ``t`` minimising ``Σ‖R p + t − q‖²`` (Kabsch)."""
    mp, mq = P.mean(axis=0), Q.mean(axis=0)
    U, _, Vt = np.linalg.svd((P - mp).T @ (Q - mq))
    D = np.diag([1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, mq - R @ mp


def apply_rigid(R: np.ndarray, t: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Poses moved by the rigid transform ``(R, t)``."""
    out = poses.copy()
    out[:, :2] = poses[:, :2] @ R.T + t
    out[:, 2] = poses[:, 2] + math.atan2(R[1, 0], R[0, 0])
    return out


def gps_at(log: MeasurementLog, times: np.ndarray) -> np.ndarray:
    assert log.gps_times is not None
    assert log.gps_xy is not None
    return np.column_stack([np.interp(times, log.gps_times, log.gps_xy[:, i]) for i in range(2)])


def features_in_world(log: MeasurementLog, poses: np.ndarray) -> np.ndarray:
    """Centre of every feature in the frame of ``poses`` (one pose per step)."""
    x = poses[log.feat_step]
    c, s = np.cos(x[:, 2]), np.sin(x[:, 2])
    f = log.feat_params
    return np.column_stack(
        (x[:, 0] + c * f[:, 0] - s * f[:, 1], x[:, 1] + s * f[:, 0] + c * f[:, 1])
    )


def locally_aligned_poses(log: MeasurementLog, half_window_s: float) -> np.ndarray:
    """Dead reckoning re-aligned to GPS around every step (NaN where the car stands still).

    Removes the slow drift of dead reckoning so that what remains is the short-term
    odometry error, the GPS error and the sensor error.
    """
    dr = dead_reckoning(log.odometry)
    out = np.full_like(dr, np.nan)
    for k, t in enumerate(log.timestamps):
        m = np.abs(log.timestamps - t) <= half_window_s
        if np.ptp(dr[m, 0]) + np.ptp(dr[m, 1]) < 1.0:
            continue
        R, tr = rigid_fit(dr[m, :2], gps_at(log, log.timestamps[m]))
        out[k] = apply_rigid(R, tr, dr[k : k + 1])[0]
    return out


def pole_residuals(
    log: MeasurementLog, pose: np.ndarray, sl: slice, beacons: np.ndarray, gate_m: float
) -> list[tuple[int, int]]:
    """(feature index, beacon index) of the features of ``sl`` within ``gate_m`` of a beacon."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    f = log.feat_params[sl]
    centres = pose[:2] + f[:, :2] @ np.array([[c, s], [-s, c]])
    out = []
    for i, c in zip(range(sl.start, sl.stop), centres, strict=True):
        d = np.hypot(*(beacons - c).T)
        if d.min() < gate_m:
            out.append((int(i), int(np.argmin(d))))
    return out


def fit_pose(
    log: MeasurementLog, pairs: list[tuple[int, int]], beacons: np.ndarray, x0: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares laser pose from (feature, beacon) pairs; pose, covariance, residuals.

    Residuals are in range and bearing (m, rad); the weights include the survey σ.
    """
    known_var = float(log.known_map.covs[0, 0, 0])
    weights = [
        np.linalg.cholesky(np.linalg.inv(log.feat_cov[i][:2, :2] + known_var * np.eye(2))).T
        for i, _ in pairs
    ]

    def predicted(x: np.ndarray, j: int) -> np.ndarray:
        c, s = math.cos(x[2]), math.sin(x[2])
        d = beacons[j] - x[:2]
        return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])

    def fun(x: np.ndarray) -> np.ndarray:
        return np.concatenate(
            [
                W @ (predicted(x, j) - log.feat_params[i, :2])
                for (i, j), W in zip(pairs, weights, strict=True)
            ]
        )

    sol = least_squares(fun, x0)
    jac = np.asarray(sol.jac, dtype=np.float64)
    cov = np.linalg.inv(jac.T @ jac)
    res = []
    for i, j in pairs:
        p, f = predicted(sol.x, j), log.feat_params[i, :2]
        res.append(
            (
                math.hypot(*p) - math.hypot(*f),
                wrap_scalar(math.atan2(p[1], p[0]) - math.atan2(f[1], f[0])),
            )
        )
    return sol.x, cov, np.array(res)


def mad(v: np.ndarray) -> float:
    """Robust standard deviation (1.4826 × median absolute deviation)."""
    return float(1.4826 * np.median(np.abs(v - np.median(v))))
