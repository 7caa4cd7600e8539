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
from dataclasses import dataclass

import numpy as np

from mapfuse_core.geometry.se2 import FloatArray, as_pose
from mapfuse_core.sim.limits import MAX_ANGLE_SIGMA, MAX_BEAMS
from mapfuse_core.sim.world import World

__all__ = ["LaserParams", "Scan", "cast_rays", "simulate_scan"]

# Rays (nearly) parallel to a segment never hit it: such a contact is a single point
# of measure zero, and dividing by the tiny cross product would only produce noise.
_PARALLEL_EPS = 1e-12


@dataclass(frozen=True)
class LaserParams:
    """Geometry and noise of a planar range–bearing laser scanner."""

    fov_rad: float = math.pi
    """Field of view (rad), centred on the sensor x axis; in ``(0, 2π]``."""
    max_range_m: float = 80.0
    """Maximum range (m); farther surfaces give no return."""
    n_beams: int = 361
    """Number of beams, evenly spaced over the field of view (361 → 0.5° spacing);
    2 … :data:`~mapfuse_core.sim.limits.MAX_BEAMS`."""
    sigma_range_m: float = 0.05
    """Standard deviation σρ of the range noise (m), ≥ 0."""
    sigma_bearing_rad: float = math.pi / 720
    """Standard deviation σβ of the bearing (pointing) noise (rad), in ``[0, π]``."""

    def __post_init__(self) -> None:
        for name in ("fov_rad", "max_range_m", "sigma_range_m", "sigma_bearing_rad"):
            value = getattr(self, name)
            if not isinstance(value, int | float) or not math.isfinite(value):
                raise ValueError(f"LaserParams.{name} must be a finite number, got {value!r}")
        if not 0.0 < self.fov_rad <= 2.0 * math.pi:
            raise ValueError(f"LaserParams.fov_rad must be in (0, 2π], got {self.fov_rad}")
        if self.max_range_m <= 0.0:
            raise ValueError(f"LaserParams.max_range_m must be > 0, got {self.max_range_m}")
        if isinstance(self.n_beams, bool) or not isinstance(self.n_beams, int | np.integer):
            raise ValueError(f"LaserParams.n_beams must be an integer, got {self.n_beams!r}")
        if self.n_beams < 2:
            raise ValueError(f"LaserParams.n_beams must be >= 2, got {self.n_beams}")
        if self.n_beams > MAX_BEAMS:
            raise ValueError(
                f"LaserParams.n_beams must be <= {MAX_BEAMS:,} (the documented maximum), "
                f"got {self.n_beams}"
            )
        if self.sigma_range_m < 0.0:
            raise ValueError(f"LaserParams.sigma_range_m must be >= 0, got {self.sigma_range_m}")
        if self.sigma_bearing_rad < 0.0:
            raise ValueError(
                f"LaserParams.sigma_bearing_rad must be >= 0, got {self.sigma_bearing_rad}"
            )
        if self.sigma_bearing_rad > MAX_ANGLE_SIGMA:
            raise ValueError(
                f"LaserParams.sigma_bearing_rad must be <= π, got {self.sigma_bearing_rad}"
            )

    @property
    def beam_spacing_rad(self) -> float:
        """Angle between consecutive beams (rad)."""
        return self.fov_rad / (self.n_beams - 1)

    def bearings(self) -> FloatArray:
        """(n_beams,) nominal bearings from ``−fov/2`` to ``+fov/2`` inclusive.

        With ``fov = 2π`` the first and last beams point the same way.
        """
        half = 0.5 * self.fov_rad
        return np.linspace(-half, half, int(self.n_beams), dtype=np.float64)


@dataclass(frozen=True)
class Scan:
    """One laser scan in the sensor frame."""

    bearings: FloatArray
    """(n,) nominal beam bearings in the sensor frame (rad), increasing."""
    ranges: FloatArray
    """(n,) measured ranges (m); ``np.inf`` where there is no return."""
    hit_ids: np.ndarray
    """(n,) int64 id of the world feature each beam hit, −1 for none (simulation truth)."""

    def __post_init__(self) -> None:
        b = np.asarray(self.bearings, dtype=np.float64)
        r = np.asarray(self.ranges, dtype=np.float64)
        h = np.asarray(self.hit_ids)
        if b.ndim != 1:
            raise ValueError(f"Scan.bearings must be 1-D, got shape {b.shape}")
        if r.shape != b.shape or h.shape != b.shape:
            raise ValueError(
                "Scan.bearings, ranges and hit_ids must have the same shape, got "
                f"{b.shape}, {r.shape}, {h.shape}"
            )
        if not np.all(np.isfinite(b)):
            raise ValueError("Scan.bearings has a non-finite entry")
        if np.any(np.isnan(r)):
            raise ValueError("Scan.ranges has a NaN entry (use np.inf for no return)")
        if np.any(r <= 0.0):
            raise ValueError("Scan.ranges must be > 0 (use np.inf for no return)")
        if h.size and not np.issubdtype(h.dtype, np.integer):
            raise ValueError(f"Scan.hit_ids must be integers, got dtype {h.dtype}")
        object.__setattr__(self, "bearings", b)
        object.__setattr__(self, "ranges", r)
        object.__setattr__(self, "hit_ids", h.astype(np.int64))

    def valid(self) -> np.ndarray:
        """(n,) bool mask of beams with a return."""
        return np.asarray(np.isfinite(self.ranges))

    def points(self) -> FloatArray:
        """(k, 2) sensor-frame ``(x, y)`` of the valid returns, in beam order."""
        m = self.valid()
        r, b = self.ranges[m], self.bearings[m]
        return np.column_stack((r * np.cos(b), r * np.sin(b)))


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
