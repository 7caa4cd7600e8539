"""Range–bearing laser simulation by exact ray casting (``docs/method.md`` §3).

The sensor frame ``S`` has its x axis along the central beam; bearings are measured
counter-clockwise from it.  A :class:`Scan` holds the *nominal* bearing of every beam
and the measured range along it, which is what a real scanner reports.

Noise model (matches the σρ, σβ of the paper's Table 1):

* each beam is physically cast at ``nominal bearing + δβ``, ``δβ ~ N(0, σβ²)``;
* the true range along that perturbed ray gets ``+ δρ``, ``δρ ~ N(0, σρ²)``;
* the scan reports the nominal bearing and the noisy range.

A measured point ``ρ (cos β, sin β)`` therefore differs from the surface point that
was really hit by, to first order, ``δρ`` along the beam and ``ρ δβ`` across it:
covariance ``J diag(σρ², σβ²) Jᵀ`` with ``J = ∂(ρ cos β, ρ sin β)/∂(ρ, β)``, the model
the feature extraction uses.  Errors of different beams are independent.
"""

from __future__ import annotations

import math

import numpy as np

from mapfuse_core.geometry.se2 import FloatArray, as_pose
from mapfuse_core.sensor.laser import LaserParams, Scan
from mapfuse_core.sim.world import World

__all__ = ["cast_rays", "simulate_scan"]

# Rays (nearly) parallel to a segment never hit it: such a contact is a single point
# of measure zero, and dividing by the tiny cross product would only produce noise.
_PARALLEL_EPS = 1e-12


def cast_rays(
    world: World, x_W_S: FloatArray, angles_W: FloatArray, max_range: float
) -> tuple[FloatArray, np.ndarray]:
    """Exact ray casting from the sensor at ``x_W_S`` along world-frame ``angles_W``.

    Every ray is intersected with every segment and circle at once (beams × features
    arrays; features wholly beyond ``max_range`` are dropped first); the nearest
    positive hit wins, so nearer features occlude farther ones.
    A ray exactly tangent to a circle hits it at the tangent point; a ray parallel to
    a segment does not hit it.  From inside a circle a ray hits its far side.

    Returns ``(ranges, hit_ids)``: ``(n,)`` distances, ``np.inf`` where nothing lies
    within ``max_range``, and ``(n,)`` int64 ids of the hit features, −1 for a miss.
    """
    pose = as_pose(x_W_S, "x_W_S")
    ang = np.asarray(angles_W, dtype=np.float64)
    if ang.ndim != 1:
        raise ValueError(f"angles_W must be 1-D, got shape {ang.shape}")
    if not np.all(np.isfinite(ang)):
        raise ValueError("angles_W has a non-finite entry")
    if not (isinstance(max_range, int | float) and max_range > 0.0 and not math.isnan(max_range)):
        raise ValueError(f"max_range must be > 0, got {max_range!r}")

    o = pose[:2]
    d = np.column_stack((np.cos(ang), np.sin(ang)))  # (n, 2)
    n = ang.shape[0]
    best = np.full(n, np.inf)
    best_id = np.full(n, -1, dtype=np.int64)

    p1, p2, seg_ids = world.seg_p1, world.seg_p2, world.seg_ids
    if p1.shape[0] and math.isfinite(max_range):
        # Features wholly out of range cannot be hit: drop them before the n × S work.
        e = p2 - p1
        u0 = np.clip(np.sum((o - p1) * e, axis=1) / np.sum(e * e, axis=1), 0.0, 1.0)
        near = np.hypot(*(p1 + u0[:, None] * e - o).T) <= max_range
        p1, p2, seg_ids = p1[near], p2[near], seg_ids[near]
    if p1.shape[0]:
        # o + t d = p1 + u e  →  t = ((p1 − o) × e)/(d × e),  u = ((p1 − o) × d)/(d × e)
        e = p2 - p1  # (S, 2)
        w = p1 - o  # (S, 2)
        denom = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]  # (n, S)
        w_x_e = w[:, 0] * e[:, 1] - w[:, 1] * e[:, 0]  # (S,)
        w_x_d = w[None, :, 0] * d[:, None, 1] - w[None, :, 1] * d[:, None, 0]  # (n, S)
        ok = np.abs(denom) > _PARALLEL_EPS
        safe = np.where(ok, denom, 1.0)
        t = w_x_e[None, :] / safe
        u = w_x_d / safe
        hit = ok & (t > 0.0) & (u >= 0.0) & (u <= 1.0)
        t = np.where(hit, t, np.inf)
        j = np.argmin(t, axis=1)
        tj = t[np.arange(n), j]
        closer = tj < best
        best = np.where(closer, tj, best)
        best_id = np.where(closer, seg_ids[j], best_id)

    cc, cr, circ_ids = world.circ_c, world.circ_r, world.circ_ids
    if cc.shape[0] and math.isfinite(max_range):
        near = np.hypot(*(cc - o).T) - cr <= max_range
        cc, cr, circ_ids = cc[near], cr[near], circ_ids[near]
    if cc.shape[0]:
        w = cc - o  # (C, 2)
        b = d @ w.T  # (n, C): projection of the centre on the ray
        c0 = np.sum(w * w, axis=1) - cr**2  # (C,): < 0 when inside
        disc = b * b - c0[None, :]
        ok = disc >= 0.0
        sq = np.sqrt(np.where(ok, disc, 0.0))
        near = b - sq
        far = b + sq
        t = np.where(near > 0.0, near, far)
        t = np.where(ok & (t > 0.0), t, np.inf)
        j = np.argmin(t, axis=1)
        tj = t[np.arange(n), j]
        closer = tj < best
        best = np.where(closer, tj, best)
        best_id = np.where(closer, circ_ids[j], best_id)

    miss = best > max_range
    best = np.where(miss, np.inf, best)
    best_id = np.where(miss, -1, best_id).astype(np.int64)
    return best, best_id


def simulate_scan(
    world: World, x_W_S: FloatArray, params: LaserParams, rng: np.random.Generator
) -> Scan:
    """Simulate one scan from the sensor pose ``x_W_S`` (world frame).

    Noise model (see the module docstring): each beam is cast at its nominal bearing
    plus ``N(0, σβ²)``; the true range along that ray gets ``+ N(0, σρ²)``; the scan
    reports the nominal bearing and the noisy range.  A noisy range beyond
    ``max_range_m`` (or ≤ 0) is a no-return (``inf``, id −1).

    The bearing and range noise of *every* beam is drawn on every call, misses
    included, in that order, so the random stream consumed per scan (``2 n_beams``
    normals) does not depend on the geometry.  The sensor sits exactly at ``x_W_S``;
    simulations mount it at the vehicle reference point.
    """
    pose = as_pose(x_W_S, "x_W_S")
    if not isinstance(params, LaserParams):
        raise ValueError(f"params must be a LaserParams, got {type(params).__name__}")
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    bearings = params.bearings()
    n = bearings.shape[0]
    d_beta = rng.normal(0.0, 1.0, n) * params.sigma_bearing_rad
    d_rho = rng.normal(0.0, 1.0, n) * params.sigma_range_m
    # The limit applies to the *measured* range, so cast a little beyond it: a surface
    # more than 10 σρ farther cannot produce a return within range (p < 1e-23).
    cast_limit = params.max_range_m + 10.0 * params.sigma_range_m
    true_r, ids = cast_rays(world, pose, pose[2] + bearings + d_beta, cast_limit)
    with np.errstate(invalid="ignore"):
        r = true_r + d_rho
    valid = np.isfinite(r) & (r > 0.0) & (r <= params.max_range_m)
    ranges = np.where(valid, r, np.inf)
    hit_ids = np.where(valid, ids, -1).astype(np.int64)
    return Scan(bearings=bearings, ranges=ranges, hit_ids=hit_ids)
