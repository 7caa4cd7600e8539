"""Metrics shared by every backend: pose errors, GPS errors, the anchor, run times
(the parts of :class:`~mapfuse_core.estimate.metrics.RunMetrics`) and TUM trajectory
files."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from mapfuse_core.estimate.metrics import (
    AnchorMetrics,
    HeadingError,
    NeesSummary,
    PositionError,
    RuntimeMetrics,
)
from mapfuse_core.evaluation.nees import CHI2_3_95, nees_mean_interval, nees_series
from mapfuse_core.geometry.features import FeatureKind, express_in, transform_feature
from mapfuse_core.geometry.se2 import (
    FloatArray,
    compose,
    compose_jacobians,
    inverse,
    transform_point,
    wrap_angle,
)
from mapfuse_core.models import pairing_residual

__all__ = [
    "MapDrawOffset",
    "PoseErrors",
    "anchor_metrics",
    "anchor_truth",
    "gps_error_series",
    "gps_position_metrics",
    "interpolate_positions",
    "known_map_draw_offset",
    "nees_summary",
    "path_length",
    "pose_errors",
    "pose_metrics",
    "rigid_alignment",
    "runtime_metrics",
    "summary_stats",
    "truth_in_global",
    "write_tum",
]


def path_length(poses: FloatArray) -> float:
    """Length in metres of the polyline through the positions of ``poses`` (N, 3)."""
    if poses.shape[0] < 2:
        return 0.0
    d = np.diff(poses[:, :2], axis=0)
    return float(np.sum(np.hypot(d[:, 0], d[:, 1])))


def truth_in_global(true_poses: FloatArray) -> FloatArray:
    """True poses re-expressed in ``Wglobal``: ``⊖x_W_R0 ⊕ x_W_Rk``."""
    inv0 = inverse(true_poses[0])
    return np.array([compose(inv0, p) for p in true_poses])


def anchor_truth(true_poses: FloatArray, known_frame: FloatArray | None = None) -> FloatArray:
    """True ``x^Wknown_Wglobal = ⊖x^W_Wknown ⊕ x^W_R0`` (``Wglobal`` is the vehicle at
    step 0).  ``known_frame`` is ``x^W_Wknown`` (``MeasurementLog.known_frame``);
    ``None`` means the known map's frame is the world's."""
    x0 = np.asarray(true_poses[0], dtype=float).copy()
    if known_frame is None:
        return x0
    frame = np.asarray(known_frame, dtype=float)
    if frame.shape != (3,) or not np.all(np.isfinite(frame)):
        raise ValueError(f"known_frame must be a finite (3,) pose, got {frame!r}")
    return compose(inverse(frame), x0)


@dataclass(frozen=True)
class PoseErrors:
    """Per-step errors of estimated poses against truth."""

    dx: FloatArray
    """(N, 3) estimate − truth, angle wrapped."""
    position: FloatArray
    """(N,) Euclidean position error (m)."""
    heading: FloatArray
    """(N,) absolute heading error (rad)."""


def pose_errors(est: FloatArray, truth: FloatArray) -> PoseErrors:
    """Errors of ``est`` against ``truth`` (both (N, 3) in one frame)."""
    if est.shape != truth.shape:
        raise ValueError(f"estimate shape {est.shape} differs from truth shape {truth.shape}")
    d = est - truth
    d[:, 2] = wrap_angle(d[:, 2])
    return PoseErrors(dx=d, position=np.hypot(d[:, 0], d[:, 1]), heading=np.abs(d[:, 2]))


def summary_stats(x: FloatArray) -> PositionError:
    """rmse, mean, median, max and final of a non-negative series of distances (m)."""
    return PositionError(
        rmse=float(np.sqrt(np.mean(np.square(x)))),
        mean=float(np.mean(x)),
        median=float(np.median(x)),
        max=float(np.max(x)),
        final=float(x[-1]),
    )


def nees_summary(nees: FloatArray) -> NeesSummary:
    """Mean, fraction within χ²(3, 0.95) and the mean's acceptance region of a 3-dof
    NEES series (its finite values)."""
    valid = nees[np.isfinite(nees)]
    return NeesSummary(
        mean=float(np.mean(valid)) if valid.size else math.nan,
        fraction_within_chi2_95=float(np.mean(valid <= CHI2_3_95)) if valid.size else math.nan,
        bound=CHI2_3_95,
        steps=int(valid.size),
        mean_interval=nees_mean_interval(valid) if valid.size else None,
    )


def pose_metrics(
    est: FloatArray, covs: FloatArray, truth: FloatArray
) -> tuple[PositionError, HeadingError, NeesSummary]:
    """Position and heading errors and the NEES of ``est`` (covariances ``covs``)
    against ``truth``, all (N, 3) in one frame.

    The NEES summary's ``mean_interval`` is the 95 % acceptance region of the mean
    NEES corrected for the autocorrelation of the series (:func:`nees_mean_interval`):
    the mean is consistent when inside it.
    """
    err = pose_errors(est, truth)
    heading = HeadingError(
        rmse=float(np.sqrt(np.mean(np.square(err.heading)))), max=float(np.max(err.heading))
    )
    return summary_stats(err.position), heading, nees_summary(nees_series(err.dx, covs))


def interpolate_positions(
    timestamps: FloatArray, poses: FloatArray, query_times: FloatArray
) -> tuple[FloatArray, np.ndarray]:
    """Positions of ``poses`` (N, 3) at ``query_times``, linearly interpolated in time.

    Returns the (M, 2) positions and the (M,) mask of the query times inside
    ``[timestamps[0], timestamps[-1]]``: nothing is extrapolated, so the rows outside the
    run are NaN.  ``timestamps`` must be non-decreasing.
    """
    t = np.asarray(timestamps, dtype=float)
    q = np.asarray(query_times, dtype=float)
    if t.ndim != 1 or t.shape[0] != poses.shape[0] or t.shape[0] == 0:
        raise ValueError(f"need one timestamp per pose, got {t.shape} for poses {poses.shape}")
    if np.any(np.diff(t) < 0.0):
        raise ValueError("timestamps must be non-decreasing")
    inside = (q >= t[0]) & (q <= t[-1]) & np.isfinite(q)
    out = np.full((q.shape[0], 2), np.nan)
    out[inside, 0] = np.interp(q[inside], t, poses[:, 0])
    out[inside, 1] = np.interp(q[inside], t, poses[:, 1])
    return out, inside


def rigid_alignment(src: FloatArray, dst: FloatArray) -> FloatArray:
    """The pose ``T = (x, y, θ)`` minimising ``Σ‖T ⊕ src_i − dst_i‖²`` over 2-D points.

    Least-squares rotation and translation without scale (the 2-D Kabsch solution,
    closed form through ``atan2``).  Needs at least two distinct points.
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 2:
        raise ValueError(f"need two (M, 2) point sets of one shape, got {src.shape}, {dst.shape}")
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - ms, dst - md
    if src.shape[0] < 2 or float(np.sum(a * a)) < 1e-12:
        raise ValueError("alignment needs at least two distinct points")
    # Cross-covariance terms give the optimal angle directly in 2-D.
    theta = math.atan2(
        float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])),
        float(np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])),
    )
    c, s = math.cos(theta), math.sin(theta)
    t = md - np.array([c * ms[0] - s * ms[1], s * ms[0] + c * ms[1]])
    return np.array([t[0], t[1], theta])


def _gps_pairs(
    timestamps: FloatArray, poses: FloatArray, gps_times: FloatArray, gps_xy: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(times, estimated positions, GPS positions)`` at the finite fixes inside the run."""
    xy, inside = interpolate_positions(timestamps, poses, gps_times)
    ref = np.asarray(gps_xy, dtype=float)[inside]
    keep = np.all(np.isfinite(ref), axis=1)
    return np.asarray(gps_times, dtype=float)[inside][keep], xy[inside][keep], ref[keep]


def gps_error_series(
    timestamps: FloatArray,
    poses: FloatArray,
    gps_times: FloatArray,
    gps_xy: FloatArray,
    x_gps_Wglobal: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """``(times, position errors)`` at the GPS fixes inside the run, the estimate put in
    the GPS frame through ``x_gps_Wglobal`` (e.g. the ``x_gps_Wglobal`` of the metrics)."""
    t, est, ref = _gps_pairs(timestamps, poses, gps_times, gps_xy)
    T = np.asarray(x_gps_Wglobal, dtype=float)
    return t, np.hypot(*(transform_point(T, est) - ref).T)


def gps_position_metrics(
    timestamps: FloatArray,
    poses: FloatArray,
    gps_times: FloatArray,
    gps_xy: FloatArray,
    x_ref_Wglobal: FloatArray | None = None,
) -> PositionError | None:
    """Position error against GPS fixes, the ``position_error_m`` block of real data.

    The estimate (poses in ``Wglobal``) is interpolated at the GPS times inside the run,
    then expressed in the GPS frame: through ``x_ref_Wglobal`` (the anchor
    ``x^Wknown_Wglobal`` when the known map shares the GPS frame, as the car park's
    surveyed beacons do) or, when it is ``None``, through the rigid transform that best
    fits the estimate to GPS (which hides a rigid error of the whole trajectory; the
    block says which one was used).  ``None`` when fewer than two fixes fall inside the
    run.
    """
    _, est, ref = _gps_pairs(timestamps, poses, gps_times, gps_xy)
    if est.shape[0] < 2:
        return None
    alignment: Literal["anchor", "best_fit"]
    if x_ref_Wglobal is None:
        T, alignment = rigid_alignment(est, ref), "best_fit"
    else:
        T, alignment = np.asarray(x_ref_Wglobal, dtype=float), "anchor"
    stats = summary_stats(np.hypot(*(transform_point(T, est) - ref).T))
    return dataclasses.replace(
        stats,
        reference="gps",
        alignment=alignment,
        fixes=int(est.shape[0]),
        x_gps_Wglobal=tuple(float(v) for v in T),
    )


def runtime_metrics(step_time_s: FloatArray) -> RuntimeMetrics:
    """Total and per-step percentiles of the step times."""
    return RuntimeMetrics(
        total=float(np.sum(step_time_s)),
        per_step_p50=float(np.percentile(step_time_s, 50)),
        per_step_p99=float(np.percentile(step_time_s, 99)),
    )


def write_tum(
    path: str | Path, timestamps: FloatArray, poses: FloatArray, comment: str | None = None
) -> Path:
    """TUM trajectory (``t x y z qx qy qz qw``), readable by evo; z = 0, yaw about z.

    ``comment`` (one line) goes first in the ``#`` header, e.g. what the poses are and
    in which frame.
    """
    path = Path(path)
    header = "timestamp tx ty tz qx qy qz qw"
    if comment:
        if "\n" in comment:
            raise ValueError("a TUM header comment must be a single line")
        header = f"{comment}\n{header}"
    half = 0.5 * poses[:, 2]
    rows = np.column_stack(
        [
            timestamps,
            poses[:, 0],
            poses[:, 1],
            np.zeros(len(poses)),
            np.zeros(len(poses)),
            np.zeros(len(poses)),
            np.sin(half),
            np.cos(half),
        ]
    )
    np.savetxt(path, rows, fmt="%.9f", header=header)
    return path


def anchor_metrics(
    estimate: FloatArray,
    truth: FloatArray | None,
    accepted_at_step: int,
    pairings: list[tuple[int, int]] | tuple[tuple[int, int], ...],
    cov: FloatArray | None = None,
) -> AnchorMetrics:
    """The anchor's estimate of ``x^Wknown_Wglobal`` against truth (its NEES under
    ``cov`` when given)."""
    nees = None
    if truth is not None and cov is not None:
        d = pose_errors(np.asarray(estimate, dtype=float)[None], np.asarray(truth)[None])
        nees = float(nees_series(d.dx, np.asarray(cov, dtype=float)[None])[0])
    return AnchorMetrics(
        estimate=tuple(float(v) for v in estimate),
        truth=None if truth is None else tuple(float(v) for v in truth),
        position_error_m=None if truth is None else float(math.hypot(*(estimate[:2] - truth[:2]))),
        heading_error_rad=None if truth is None else float(abs(wrap_angle(estimate[2] - truth[2]))),
        accepted_at_step=int(accepted_at_step),
        pairings=len(pairings),
        correct_pairings=sum(1 for t, k in pairings if t == k and t >= 0),
        nees=nees,
    )


@dataclass(frozen=True, eq=False)
class MapDrawOffset:
    """How far a noisy known map is, as a whole, from the true map it was drawn around.

    A known map whose features are each off by independent noise is also off as a
    whole: its features are close to ``offset ⊕`` the true ones, for some rigid
    ``offset``.  An estimator that matched the map perfectly would put any true pose
    ``x`` of ``Wknown`` at ``offset ⊕ x`` (the anchor included), so ``offset ⊕
    x_true`` is where an ideal anchor estimate is expected: the reference to hold an
    anchor's error against when the map's own draw is unlucky.  It is an expectation,
    not a strict bound (an estimate can land nearer the truth by chance).  Simulation
    only: it needs the true map.
    """

    offset: FloatArray
    """(3,) ``(x, y, θ)`` (m, m, rad) in the map frame, rotation about its origin: the
    rigid motion that puts the true features best onto the noisy ones (weighted least
    squares with the map's covariances, linearised at the solution).  Read-only."""
    cov: FloatArray
    """(3, 3) covariance of :attr:`offset` under the map's stated noise; far from the
    origin its θ and (x, y) are strongly correlated.  Read-only."""
    nees: float
    """Normalised squared size of the offset, computed about the features' centroid
    (where it does not depend on the map frame's origin): χ²(3) if the noise is as
    stated."""


def _check_draw_inputs(
    kinds: np.ndarray, params: FloatArray, covs: FloatArray, true_params: FloatArray
) -> None:
    m = kinds.shape[0] if kinds.ndim == 1 else -1
    if m < 1 or params.shape != (m, 3) or true_params.shape != (m, 3) or covs.shape != (m, 3, 3):
        raise ValueError(
            "known_map_draw_offset needs kinds (M,), params and true_params (M, 3) and "
            f"covs (M, 3, 3) with M ≥ 1; got {kinds.shape}, {params.shape}, "
            f"{true_params.shape}, {covs.shape}"
        )
    valid = {int(k) for k in FeatureKind}
    if not np.issubdtype(kinds.dtype, np.integer) or not set(kinds.tolist()) <= valid:
        raise ValueError(
            f"known_map_draw_offset: kinds must be integer FeatureKind codes {sorted(valid)}, "
            f"got {np.unique(kinds).tolist()}"
        )
    for name, a in (("params", params), ("covs", covs), ("true_params", true_params)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"known_map_draw_offset: {name} holds NaN or inf")
    asym = np.abs(covs - covs.transpose(0, 2, 1)).max(axis=(1, 2))
    bad = np.nonzero(asym > 1e-9 * (1.0 + np.abs(covs).max(axis=(1, 2))))[0]
    if bad.size:
        raise ValueError(f"known_map_draw_offset: covs[{int(bad[0])}] is not symmetric")


def known_map_draw_offset(
    kinds: np.ndarray,
    params: FloatArray,
    covs: FloatArray,
    true_params: FloatArray,
    max_iterations: int = 20,
) -> MapDrawOffset:
    """The rigid offset of a known-map draw (``params``) from its truth (``true_params``).

    Features (``kinds`` codes, ``(x, y, θ)`` SPmap lines or ``(x, y, r)`` circles, all
    in the map frame) are compared by their pairing residuals, so a line's position
    along itself does not count.  Solved by Gauss–Newton about the features' centroid
    (well conditioned wherever the map frame's origin is), then expressed about the
    origin.  Raises :class:`ValueError` on bad shapes, kinds or covariances, non-finite
    values, a map that does not fix a rigid frame (e.g. only parallel lines), or no
    convergence within ``max_iterations``.
    """
    kinds = np.asarray(kinds)
    params = np.asarray(params, dtype=np.float64)
    covs = np.asarray(covs, dtype=np.float64)
    true_params = np.asarray(true_params, dtype=np.float64)
    _check_draw_inputs(kinds, params, covs, true_params)
    if (
        isinstance(max_iterations, bool)
        or not isinstance(max_iterations, int)
        or max_iterations < 1
    ):
        raise ValueError(f"max_iterations must be an int ≥ 1, got {max_iterations!r}")
    feature_kinds = [FeatureKind(int(k)) for k in kinds]
    # Work in a frame at the centroid: about a far origin the rotation column of the
    # normal matrix grows with the lever arm and hides a degenerate map (or fakes one).
    centre = np.array([*true_params[:, :2].mean(axis=0), 0.0])
    lever = max(float(np.sqrt(np.mean(np.sum((true_params[:, :2] - centre[:2]) ** 2, 1)))), 1.0)
    z_c, C_c, f_c = [], [], []
    for kind, z, C, f in zip(feature_kinds, params, covs, true_params, strict=True):
        zc, _, Jz = express_in(kind, centre, z)
        z_c.append(zc)
        C_c.append(Jz @ C @ Jz.T)
        f_c.append(express_in(kind, centre, f)[0])
    S = np.zeros(3)
    H = np.zeros((3, 3))
    for _ in range(max_iterations):
        H = np.zeros((3, 3))
        g = np.zeros(3)
        for i, kind in enumerate(feature_kinds):
            moved, J_S, _ = transform_feature(kind, S, f_c[i])
            r, J_z, J_moved = pairing_residual(kind, z_c[i], moved)
            try:
                L = np.linalg.cholesky(J_z @ C_c[i] @ J_z.T)
            except np.linalg.LinAlgError:
                raise ValueError(
                    f"known_map_draw_offset: covs[{i}] is not positive definite in the "
                    "components the features are compared on"
                ) from None
            J = np.linalg.solve(L, J_moved @ J_S)
            H += J.T @ J
            g += J.T @ np.linalg.solve(L, r)
        scale = np.array([1.0, 1.0, lever])
        if np.linalg.cond(H / np.outer(scale, scale)) > 1e10:
            raise ValueError(
                "known_map_draw_offset: the features do not fix a rigid frame "
                "(e.g. only parallel lines, or a single circle)"
            )
        step = np.linalg.solve(H, g)
        S = S - step
        if np.max(np.abs(step * scale)) < 1e-10:
            break
    else:
        raise ValueError(f"known_map_draw_offset: no convergence in {max_iterations} iterations")
    # offset = centre ⊕ S ⊕ ⊖centre: the same rigid motion, about the map origin.
    inv_c = inverse(centre)
    right, J_S_right, _ = compose_jacobians(S, inv_c)
    offset, _, J_right = compose_jacobians(centre, right)
    J = J_right @ J_S_right
    cov_S = np.linalg.inv(H)
    cov = J @ (0.5 * (cov_S + cov_S.T)) @ J.T
    offset.setflags(write=False)
    cov.setflags(write=False)
    return MapDrawOffset(offset=offset, cov=cov, nees=float(S @ H @ S))
