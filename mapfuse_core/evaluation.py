"""Evaluation shared by every backend: errors, NEES, the ``metrics.json`` schema, TUM files.

All backends report the vehicle pose ``x^Wglobal_R`` (``Wglobal`` = the vehicle at
step 0) with a covariance of the absolute ``(x, y, θ)`` perturbation, so one
function computes every metric from the same truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import chi2

from mapfuse_core.features import FeatureKind, express_in, pairing_residual, transform_feature
from mapfuse_core.se2 import (
    FloatArray,
    compose,
    compose_jacobians,
    inverse,
    transform_point,
    wrap_angle,
)

__all__ = [
    "CHI2_3_95",
    "MapDrawOffset",
    "NeesMeanDistribution",
    "PoseErrors",
    "anchor_metrics",
    "anchor_truth",
    "consistent_error_draws",
    "consistent_nees_draws",
    "gps_error_series",
    "gps_position_metrics",
    "integrated_autocorrelation_time",
    "interpolate_positions",
    "joint_nees",
    "known_map_draw_offset",
    "nees_mean_distribution",
    "nees_mean_interval",
    "nees_series",
    "path_length",
    "pooled_nees_mean_distribution",
    "pose_errors",
    "pose_metrics",
    "rigid_alignment",
    "runtime_metrics",
    "summary_stats",
    "truth_in_global",
    "write_tum",
]

CHI2_3_95 = float(chi2.ppf(0.95, 3))


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


def nees_series(dx: FloatArray, covs: FloatArray) -> FloatArray:
    """NEES ``eᵀ P⁻¹ e`` per step; NaN where the covariance is singular (e.g. step 0)."""
    out = np.full(dx.shape[0], np.nan)
    for k in range(dx.shape[0]):
        P = covs[k]
        if not np.all(np.isfinite(P)):
            continue
        w = np.linalg.eigvalsh(P)
        if w.min() <= 1e-14 * max(w.max(), 1e-300):
            continue
        out[k] = float(dx[k] @ np.linalg.solve(P, dx[k]))
    return out


def summary_stats(x: FloatArray) -> dict[str, float]:
    """rmse, mean, median, max and final of a non-negative series."""
    return {
        "rmse": float(np.sqrt(np.mean(np.square(x)))),
        "mean": float(np.mean(x)),
        "median": float(np.median(x)),
        "max": float(np.max(x)),
        "final": float(x[-1]),
    }


def integrated_autocorrelation_time(x: FloatArray, window_factor: float = 5.0) -> float:
    """Integrated autocorrelation time ``τ = 1 + 2 Σ_k ρ(k)`` of a series, in samples.

    Sokal's automatic window: the sum stops at the first lag ``M ≥ window_factor·τ(M)``,
    which keeps the noise of the far lags out.  ``N / τ`` samples of the series carry
    as much information about its mean as that many independent ones.  ``1.0`` for a
    series too short or constant.
    """
    v = np.asarray(x, dtype=float)
    v = v[np.isfinite(v)]
    n = v.size
    if n < 4:
        return 1.0
    d = v - v.mean()
    var = float(d @ d)
    if var <= 0.0:
        return 1.0
    f = np.fft.rfft(d, 2 * n)
    acf = np.fft.irfft(f * np.conj(f))[:n] / var
    tau = 1.0
    for m in range(1, n):
        tau += 2.0 * float(acf[m])
        if m >= window_factor * tau:
            break
    return max(tau, 1.0)


def nees_mean_interval(nees: FloatArray, dof: int = 3, p: float = 0.95) -> dict[str, float]:
    """Two-sided ``p`` interval of the mean NEES of a consistent estimator, honestly.

    Consecutive NEES values of a smoother (or a slowly mixing filter) are strongly
    correlated: on loop600 the whitened smoothed errors have τ of 300–470 steps, so a
    2,400-step run holds only a handful of independent samples and the textbook
    interval ``χ²(N·dof)/N`` is far too narrow.  Here ``N`` is replaced by the effective
    number of samples ``N/τ`` (τ of the NEES series itself).  Still approximate: a run
    only ~20τ long underestimates τ (the sample mean absorbs part of the slow error),
    and the interval then misses about 14 % of consistent runs instead of 5 %.

    It is far too narrow when part of the error lasts the whole run, which a series
    cannot show.  On loop600 with fusion, the anchor's and the known map's errors are
    such a part: the batch smoother's own joint covariance puts the standard deviation
    of a run's mean NEES at 1.4 (seeds 0–4), its 40-seed spread is 1.3, and this
    interval is ±0.4 wide on seed 4.  When the joint covariance of the errors is known
    (a smoother's), :func:`nees_mean_distribution` gives the exact moments instead.
    """
    v = np.asarray(nees, dtype=float)
    v = v[np.isfinite(v)]
    tau = integrated_autocorrelation_time(v)
    n_eff = max(v.size / tau, 1.0)
    lo = float(chi2.ppf(0.5 * (1.0 - p), dof * n_eff) / n_eff)
    hi = float(chi2.ppf(0.5 * (1.0 + p), dof * n_eff) / n_eff)
    return {"autocorrelation_steps": tau, "effective_samples": n_eff, "interval_95": [lo, hi]}


@dataclass(frozen=True)
class NeesMeanDistribution:
    """Distribution of a run's mean NEES for an estimator whose joint error covariance
    is known: what a consistent estimator's mean NEES would scatter over."""

    steps: int
    """Poses the mean is taken over."""
    dof: int
    """Dimension of each pose's error."""
    mean: float
    """Expected mean NEES (``dof``: the blocks are the poses' marginals)."""
    sd: float
    """Its standard deviation, exact for Gaussian errors."""
    equivalent_poses: float
    """Independent poses carrying the same information about the mean:
    ``2·mean² / (dof·sd²)``.  Much fewer than :attr:`steps` when errors persist."""
    interval: tuple[float, float]
    """Two-sided interval of :attr:`p` of the moment-matched scaled χ² (Satterthwaite)."""
    p: float
    """Probability of :attr:`interval`."""


def _satterthwaite(steps: int, dof: int, mean: float, var: float, p: float) -> NeesMeanDistribution:
    # a·χ²(ν) with the same mean and variance: a = var / (2 mean), ν = 2 mean² / var.
    a, nu = var / (2.0 * mean), 2.0 * mean * mean / var
    lo = float(chi2.ppf(0.5 * (1.0 - p), nu))
    hi = float(chi2.ppf(0.5 * (1.0 + p), nu))
    return NeesMeanDistribution(
        steps=steps,
        dof=dof,
        mean=mean,
        sd=math.sqrt(var),
        equivalent_poses=nu / dof,
        interval=(float(a * lo), float(a * hi)),
        p=p,
    )


def _block_inverse_factors(joint_cov: FloatArray, dof: int) -> tuple[FloatArray, FloatArray]:
    """The checked ``joint_cov`` and the inverse Cholesky factors (T, dof, dof) of its
    diagonal blocks: ``L_t⁻¹ e_t`` whitens pose ``t``'s error by its own marginal."""
    S = np.asarray(joint_cov, dtype=float)
    if S.ndim != 2 or S.shape[0] != S.shape[1] or S.shape[0] % dof or S.shape[0] == 0:
        raise ValueError(
            f"joint_cov must be square with a side that is a positive multiple of {dof}, "
            f"got shape {S.shape}"
        )
    if not np.all(np.isfinite(S)):
        raise ValueError("joint_cov has non-finite entries")
    n = S.shape[0] // dof
    blocks = S.reshape(n, dof, n, dof)[np.arange(n), :, np.arange(n), :]
    try:
        L = np.linalg.cholesky(0.5 * (blocks + blocks.transpose(0, 2, 1)))
    except np.linalg.LinAlgError as exc:
        raise ValueError("a diagonal block of joint_cov is not positive definite") from exc
    Li: FloatArray = np.linalg.inv(L)
    return S, Li


def _whitened_joint(joint_cov: FloatArray, dof: int) -> FloatArray:
    """``D^{-1/2} Σ D^{-T/2}`` with ``D`` the diagonal blocks of ``Σ`` (Cholesky factors)."""
    S, Li = _block_inverse_factors(joint_cov, dof)
    n = Li.shape[0]
    W = np.einsum("sab,sbtc,tdc->satd", Li, S.reshape(n, dof, n, dof), Li)
    W = W.reshape(n * dof, n * dof)
    out: FloatArray = 0.5 * (W + W.T)
    return out


def nees_mean_distribution(
    joint_cov: FloatArray, dof: int = 3, p: float = 0.95
) -> NeesMeanDistribution:
    """Exact mean and standard deviation of the mean NEES over ``T`` poses whose errors
    are jointly Gaussian with covariance ``joint_cov`` ((T·dof)², pose by pose), and an
    interval of probability ``p``.

    Each pose's NEES uses its own marginal, the diagonal block.  With ``W`` the joint
    covariance whitened by those blocks, the mean NEES is ``‖z‖² / T`` for
    ``z ~ N(0, W)``: mean ``tr W / T = dof`` and variance ``2 ‖W‖_F² / T²``.  The
    interval is that of the scaled χ² with these moments (Satterthwaite), which is
    close when the run is worth a few independent poses or more (checked against
    draws in the tests).

    Unlike :func:`nees_mean_interval` this sees errors that last the whole run: use it
    where a smoother gives the joint covariance of its poses.
    """
    W = _whitened_joint(joint_cov, dof)
    n = W.shape[0] // dof
    mean = float(np.trace(W)) / n
    var = 2.0 * float(np.sum(W * W)) / (n * n)
    return _satterthwaite(n, dof, mean, var, p)


def pooled_nees_mean_distribution(
    parts: list[NeesMeanDistribution], p: float = 0.95
) -> NeesMeanDistribution:
    """The distribution of the mean NEES over several independent runs' poses taken
    together (each run weighted by its number of poses)."""
    if not parts:
        raise ValueError("pooled_nees_mean_distribution needs at least one run")
    dofs = {d.dof for d in parts}
    if len(dofs) != 1:
        raise ValueError(f"runs of different dof cannot be pooled: {sorted(dofs)}")
    total = sum(d.steps for d in parts)
    mean = sum(d.steps * d.mean for d in parts) / total
    var = sum((d.steps * d.sd) ** 2 for d in parts) / total**2
    return _satterthwaite(total, parts[0].dof, mean, var, p)


def consistent_error_draws(
    joint_cov: FloatArray, n_draws: int, rng: np.random.Generator, dof: int = 3
) -> FloatArray:
    """Errors (n_draws, T, dof) drawn from ``joint_cov``: those of a consistent estimator
    with this joint covariance (for the maximum error over a run, for one)."""
    if n_draws < 1:
        raise ValueError(f"n_draws must be >= 1, got {n_draws}")
    S, _ = _block_inverse_factors(joint_cov, dof)
    w, V = np.linalg.eigh(0.5 * (S + S.T))
    root = V * np.sqrt(np.clip(w, 0.0, None))
    out: FloatArray = (rng.standard_normal((n_draws, S.shape[0])) @ root.T).reshape(
        n_draws, -1, dof
    )
    return out


def joint_nees(errors: FloatArray, joint_cov: FloatArray, dof: int = 3) -> FloatArray:
    """NEES (…, T) of errors (…, T, dof), each pose's against its own diagonal block of
    ``joint_cov`` (the pose's marginal), e.g. of :func:`consistent_error_draws`."""
    _, Li = _block_inverse_factors(joint_cov, dof)
    e = np.asarray(errors, dtype=float)
    if e.shape[-2:] != (Li.shape[0], dof):
        raise ValueError(
            f"errors must end in ({Li.shape[0]}, {dof}) to match joint_cov, got {e.shape}"
        )
    z = np.einsum("tab,...tb->...ta", Li, e)
    out: FloatArray = np.sum(z * z, axis=-1)
    return out


def consistent_nees_draws(
    joint_cov: FloatArray, n_draws: int, rng: np.random.Generator, dof: int = 3
) -> FloatArray:
    """NEES series (n_draws, T) of errors drawn from ``joint_cov`` itself: what a
    consistent estimator with this joint covariance would show, for statistics without
    a closed form (the fraction of steps within a χ² bound, for one)."""
    return joint_nees(consistent_error_draws(joint_cov, n_draws, rng, dof), joint_cov, dof)


def pose_metrics(est: FloatArray, covs: FloatArray, truth: FloatArray) -> dict[str, Any]:
    """The pose part of ``metrics.json``: position/heading errors and NEES.

    ``nees.mean_interval`` is the 95 % interval of the mean NEES corrected for the
    autocorrelation of the series (:func:`nees_mean_interval`): the mean is consistent
    when inside it.
    """
    err = pose_errors(est, truth)
    nees = nees_series(err.dx, covs)
    valid = nees[np.isfinite(nees)]
    return {
        "position_error_m": summary_stats(err.position),
        "heading_error_rad": {
            "rmse": float(np.sqrt(np.mean(np.square(err.heading)))),
            "max": float(np.max(err.heading)),
        },
        "nees": {
            "mean": float(np.mean(valid)) if valid.size else math.nan,
            "fraction_within_chi2_95": float(np.mean(valid <= CHI2_3_95))
            if valid.size
            else math.nan,
            "bound": CHI2_3_95,
            "steps": int(valid.size),
            "mean_interval": nees_mean_interval(valid) if valid.size else None,
        },
    }


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
) -> dict[str, Any] | None:
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
    if x_ref_Wglobal is None:
        T, alignment = rigid_alignment(est, ref), "best_fit"
    else:
        T, alignment = np.asarray(x_ref_Wglobal, dtype=float), "anchor"
    out: dict[str, Any] = summary_stats(np.hypot(*(transform_point(T, est) - ref).T))
    out.update(
        {
            "reference": "gps",
            "alignment": alignment,
            "fixes": int(est.shape[0]),
            "x_gps_Wglobal": [float(v) for v in T],
        }
    )
    return out


def runtime_metrics(step_time_s: FloatArray) -> dict[str, float]:
    """The ``runtime_s`` block: total and per-step percentiles."""
    return {
        "total": float(np.sum(step_time_s)),
        "per_step_p50": float(np.percentile(step_time_s, 50)),
        "per_step_p99": float(np.percentile(step_time_s, 99)),
    }


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
) -> dict[str, Any]:
    """The ``anchor`` block: estimate of ``x^Wknown_Wglobal`` against truth."""
    out: dict[str, Any] = {
        "estimate": [float(v) for v in estimate],
        "truth": None if truth is None else [float(v) for v in truth],
        "position_error_m": None,
        "heading_error_rad": None,
        "accepted_at_step": int(accepted_at_step),
        "pairings": len(pairings),
        "correct_pairings": sum(1 for t, k in pairings if t == k and t >= 0),
    }
    if truth is not None:
        out["position_error_m"] = float(math.hypot(*(estimate[:2] - truth[:2])))
        out["heading_error_rad"] = float(abs(wrap_angle(estimate[2] - truth[2])))
    return out


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
