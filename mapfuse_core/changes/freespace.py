"""Where the laser saw through a mapped circle or wall, or found a mapped circle
standing: :func:`read_surveyed_places`.

:func:`~mapfuse_core.changes.visibility.scans_in_view` asks whether the
extractor *would* have returned a feature; that is indirect evidence of absence, and
near the extractor's limits (a thin trunk, a far one) the answer turns on a few
centimetres of the map's radius.  The raw scan gives direct evidence: a trunk that
stands where the map has it stops every beam aimed through its middle, so a beam aimed
there that returns from beyond the trunk's far side, or returns nothing, saw the place
empty.  This needs no extractor and no radius threshold, only the scan.

Which beams count.  The trunk may stand off its mapped centre by the map's position
error, the pose's position error, and the heading error and the beam's own bearing
error (the laser's) times the range, together a lateral σ; its radius may be smaller
than mapped by the map's radius σ.  A beam whose perpendicular distance from the
mapped centre is below ``r − q·σ`` (``σ`` the two combined, ``q`` the one-sided
normal quantile of the test level) would hit the trunk wherever those errors put it.
Only such *core* beams are read:

* a return beyond ``d + r + q·σ`` (``d`` the range to the mapped centre, range noise
  included in ``σ``), or no return: the beam went through; it *passes*;
* a return within ``r + q·σ`` of the centre's range: something stands there; it *hits*;
* a shorter return: something in front hides the place; the beam says nothing.

A scan sees the place empty when at least one core beam passes and none hits.

A trunk thinner than its position's reach (``r ≤ q·σ``) has no core beam, but its
absence can still be read from the beams *swept* across the places it could stand:
its centre lies within ``q·σ`` of the mapped one (position errors only), and it is at
least ``r − q·σ_r`` thick (``σ_r`` the radius σ).  Wherever in that disc it stands, it
stops the beams passing within that thickness of its centre; if the passing beams
leave no gap it fits in, and no beam that could meet it there returns near the
centre's range, nothing of that thickness stands anywhere in the disc.  A beam may
have gone ``q`` bearing σ off its recorded bearing, so that much is taken off what it
covers.  A beam returning shorter leaves a gap, so a place hidden in part says
nothing.

Both readings rest on the poses' σ: a pose further off than its σ can read a standing
trunk's place empty.  Such a trunk is also read standing in the scans from better
poses, and a trunk read standing in ``K`` scans is never called missing, whatever the
count of empty scans.

The same beams say the converse (:func:`circles_seen_occupied`): a trunk that still
stands where the map has it returns the beams aimed at its mapped disc (within the
mapped radius of the centre, core or not) from its near face: within reach in front
of the centre's range, and no further behind it than the position and range errors
allow.
A scan sees the place occupied when at least ``min_beams_present`` of those beams do.
This reads a trunk the extractor missed (hidden in part by another, or thinner than
mapped), which the view rules cannot tell from an absent one.

Walls (known lines with extents) are read the same way along each beam. A beam meets
the mapped wall's line at range ``t``; it is a core beam when it meets it inside the
wall's extent by more than ``q·σ_s`` at both ends, ``σ_s`` the first-order error of
where it crosses (map and pose position, heading and bearing errors times ``t``, the
wall's lateral error times the tangent of the incidence). It passes beyond
``t + q·σ_t`` (``σ_t`` the lateral error over the cosine of the incidence, the heading and
bearing errors' effect on ``t`` and the range noise), hits within ``q·σ_t`` of ``t``,
and says nothing when shorter. A wall's place is seen empty when no core beam hits and
at least ``min_beams_line`` pass: the support the extractor needs to see a wall, so
that a doorway, or the one stretch of a wall left unhidden by people, is not an empty
wall. Beams beyond ``max_incidence_rad`` from the wall's normal are not read. A wall
without extents gives no evidence.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.stats import norm

from mapfuse_core.changes.params import ChangeParams
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.measlog import KnownMapArrays

__all__ = ["PlaceReading", "circles_seen_occupied", "read_surveyed_places", "scans_seen_empty"]


@dataclass(frozen=True)
class PlaceReading:
    """What the raw scans say of the surveyed places of some known features."""

    empty: dict[int, int]
    """Known id → scans in which its place was seen empty (circles and walls)."""
    occupied: dict[int, tuple[int, float]]
    """Known id of a circle → scans in which it was seen standing there, and the
    largest reach (m) in front of the mapped centre a hit was counted within."""


def read_surveyed_places(
    features: KnownMapArrays,
    rows: list[int],
    poses: FloatArray,
    pose_covs: FloatArray,
    bearings: FloatArray,
    ranges: FloatArray,
    params: ChangeParams,
) -> PlaceReading:
    """Read the raw scans at the surveyed places of ``features`` at ``rows`` (see the
    module docstring): the scans that saw each place empty and, for circles, those
    that saw it occupied, counted at every ``view_stride``-th step times the stride.

    ``poses``/``pose_covs``: the sensor pose of every step in the map's frame and its
    covariance (only its largest position variance and its heading variance are used,
    so the frame it is expressed in does not matter); ``bearings``/``ranges``: the raw
    scans, (B,) and (N, B).
    """
    empty = {int(features.ids[r]): 0 for r in rows}
    P = np.asarray(poses, dtype=float)
    C = np.asarray(pose_covs, dtype=float)
    b = np.asarray(bearings, dtype=float)
    q = float(norm.ppf(params.level))
    sig_range = 0.0 if params.laser is None else float(params.laser.sigma_range_m)
    # A beam's own bearing error: each beam's, where the heading error is every beam's.
    sig_bearing = 0.0 if params.laser is None else float(params.laser.sigma_bearing_rad)
    noise = (sig_range, sig_bearing)
    walls = [
        r
        for r in rows
        if int(features.kinds[r]) == int(FeatureKind.LINE)
        and features.extents is not None
        and np.all(np.isfinite(features.extents[r]))
    ]
    if walls:
        _walls_seen_empty(features, walls, P, C, b, ranges, q, noise, params, empty)
    circles = [r for r in rows if int(features.kinds[r]) == int(FeatureKind.CIRCLE)]
    occupied = {int(features.ids[r]): (0, 0.0) for r in circles}
    if circles:
        _read_circles(features, circles, P, C, b, ranges, q, noise, params, empty, occupied)
    return PlaceReading(empty=empty, occupied=occupied)


def scans_seen_empty(
    features: KnownMapArrays,
    rows: list[int],
    poses: FloatArray,
    pose_covs: FloatArray,
    bearings: FloatArray,
    ranges: FloatArray,
    params: ChangeParams,
) -> dict[int, int]:
    """Scans in which the circles and walls of ``features`` at ``rows`` were seen empty
    (:func:`read_surveyed_places`'s ``empty``)."""
    reading = read_surveyed_places(features, rows, poses, pose_covs, bearings, ranges, params)
    return reading.empty


def circles_seen_occupied(
    features: KnownMapArrays,
    rows: list[int],
    poses: FloatArray,
    pose_covs: FloatArray,
    bearings: FloatArray,
    ranges: FloatArray,
    params: ChangeParams,
) -> dict[int, tuple[int, float]]:
    """Per circle of ``features`` at ``rows``: the scans in which its surveyed place was
    seen occupied, and the largest reach of a hit (:func:`read_surveyed_places`'s
    ``occupied``)."""
    circles = [r for r in rows if int(features.kinds[r]) == int(FeatureKind.CIRCLE)]
    reading = read_surveyed_places(features, circles, poses, pose_covs, bearings, ranges, params)
    return reading.occupied


def _read_circles(
    features: KnownMapArrays,
    circles: list[int],
    P: FloatArray,
    C: FloatArray,
    b: FloatArray,
    ranges: FloatArray,
    q: float,
    noise: tuple[float, float],
    params: ChangeParams,
    empty: dict[int, int],
    occupied: dict[int, tuple[int, float]],
) -> None:
    """Both readings of the circles at ``circles``, in one pass over the scans, added
    into ``empty`` and ``occupied``.  ``noise``: the laser's range and bearing σ."""
    sig_range, sig_bearing = noise
    centres = features.params[circles, :2]
    radii = features.params[circles, 2]
    map_var = np.array([_largest_position_variance(features.covs[r]) for r in circles])
    radius_var = np.clip(features.covs[circles, 2, 2], 0.0, None)
    n_empty = np.zeros(len(circles), dtype=np.int64)
    n_occupied = np.zeros(len(circles), dtype=np.int64)
    reach_max = np.zeros(len(circles))
    for k in range(0, P.shape[0], params.view_stride):
        x = P[k]
        if not np.all(np.isfinite(x)) or not np.all(np.isfinite(C[k])):
            continue
        pos_var = _largest_position_variance(C[k])
        head_var = max(float(C[k][2, 2]), 0.0)
        rho = np.asarray(ranges[k], dtype=float)
        for j in range(len(circles)):
            v = centres[j] - x[:2]
            d = math.hypot(float(v[0]), float(v[1]))
            if d > params.max_range_m or d <= radii[j]:
                continue
            common = map_var[j] + pos_var + d * d * head_var
            lateral = common + d * d * sig_bearing**2
            reach = radii[j] + q * math.sqrt(lateral + radius_var[j] + sig_range**2)
            rel = np.angle(np.exp(1j * (b - (math.atan2(v[1], v[0]) - x[2]))))
            across = np.abs(d * np.sin(rel))
            ahead = np.cos(rel) > 0.0
            # Empty: core beams (sure to hit the trunk wherever its errors put it) pass.
            core = radii[j] - q * math.sqrt(lateral + radius_var[j])
            through = False
            if core > 0.0:
                seen = rho[(across < core) & ahead]
                if seen.size:
                    passes = seen > d + reach
                    hits = (seen >= d - reach) & ~passes
                    through = bool(np.any(passes) and not np.any(hits))
            if not through:
                # Empty too: the passing beams sweep every place the trunk could stand.
                thin = radii[j] - q * math.sqrt(radius_var[j])
                spread = q * math.sqrt(common)
                jitter = q * sig_bearing
                through = _swept(rel, rho, d, spread, thin, radii[j], reach, jitter)
            if through:
                n_empty[j] += params.view_stride
            # Occupied: beams on the mapped disc return from a near face.  A standing
            # trunk never returns from beyond its centre by more than the position and
            # range errors allow.
            seen = rho[(across < radii[j]) & ahead]
            if seen.size >= params.min_beams_present:
                behind = q * math.sqrt(lateral + sig_range**2)
                hits_n = np.count_nonzero((seen >= d - reach) & (seen <= d + behind))
                if hits_n >= params.min_beams_present:
                    n_occupied[j] += params.view_stride
                    reach_max[j] = max(reach_max[j], reach)
    for j, r in enumerate(circles):
        kid = int(features.ids[r])
        empty[kid] += int(n_empty[j])
        occupied[kid] = (int(n_occupied[j]), float(reach_max[j]))


def _swept(
    rel: FloatArray,
    rho: FloatArray,
    d: float,
    spread: float,
    thin: float,
    radius: float,
    reach: float,
    jitter: float = 0.0,
) -> bool:
    """Whether one scan's beams went through every place where a trunk at least
    ``thin`` in radius could stand within ``spread`` of a mapped centre ``d`` ahead.

    ``rel``: each beam's bearing from the direction of the mapped centre; ``rho``: its
    range.  A trunk of radius ``thin`` whose centre lies in that disc stops every beam
    passing within ``thin`` of its centre, an angle of at least ``asin(thin / (d +
    spread))`` either side of it; the disc spans ``asin(spread / d)`` either side of
    the mapped centre.  The place is seen through when the beams that pass (return
    beyond ``d + reach``, or nothing) leave no gap a trunk fits in, and no beam that
    could meet a trunk of the mapped ``radius`` anywhere in the disc returns within
    ``reach`` of ``d`` (a hit).  A beam that returns shorter hides the place from
    itself and leaves a gap.  ``jitter``: how far a beam may have gone off its recorded
    bearing (rad), taken off what each beam covers and added to the hit band.
    """
    if not (thin > 0.0 and spread < d and d - spread > radius and jitter >= 0.0):
        return False
    half = math.asin(spread / d)
    cover = math.asin(min(1.0, thin / (d + spread))) - jitter
    if not cover > 0.0:
        return False
    wide = math.asin(min(1.0, (spread + radius) / d)) + jitter
    band = np.abs(rel) < wide
    seen = rho[band]
    passes = seen > d + reach
    if np.any((seen >= d - reach) & ~passes):
        return False
    a = np.sort(rel[band][passes])
    if a.size == 0 or a[0] - cover >= -half or a[-1] + cover <= half:
        return False
    return bool(a.size == 1 or np.max(np.diff(a)) < 2.0 * cover)


def _walls_seen_empty(
    features: KnownMapArrays,
    walls: list[int],
    P: FloatArray,
    C: FloatArray,
    b: FloatArray,
    ranges: FloatArray,
    q: float,
    noise: tuple[float, float],
    params: ChangeParams,
    out: dict[int, int],
) -> None:
    """Add to ``out`` the scans that saw the walls at ``walls`` empty.  ``noise``: the
    laser's range and bearing σ."""
    sig_range, sig_bearing = noise
    assert features.extents is not None
    min_cos = math.cos(params.max_incidence_rad)
    for r in walls:
        line = features.params[r]
        th = float(line[2])
        u = np.array([math.cos(th), math.sin(th)])
        n = np.array([-math.sin(th), math.cos(th)])
        e0, e1 = sorted(float(e) for e in features.extents[r])
        cov = features.covs[r]
        var_nn = float(n @ cov[:2, :2] @ n)
        var_uu = float(u @ cov[:2, :2] @ u)
        cov_nt = float(n @ cov[:2, 2])
        var_th = max(float(cov[2, 2]), 0.0)
        for k in range(0, P.shape[0], params.view_stride):
            x = P[k]
            if not np.all(np.isfinite(x)) or not np.all(np.isfinite(C[k])):
                continue
            pos_var = _largest_position_variance(C[k])
            # A beam's bearing error moves it as the heading error does.
            head_var = max(float(C[k][2, 2]), 0.0) + sig_bearing**2
            phi = x[2] + b
            w = np.column_stack((np.cos(phi), np.sin(phi)))
            nw = w @ n
            c = float(n @ (line[:2] - x[:2]))
            ok = np.abs(nw) >= max(min_cos, 1e-9)
            nw_safe = np.where(ok, nw, 1.0)
            t = np.where(ok, c / nw_safe, 0.0)
            ok &= (t > 0.0) & (t <= params.max_range_m)
            if not np.any(ok):
                continue
            s_along = (x[:2] - line[:2]) @ u + t * (w @ u)
            cos_inc = np.abs(nw)
            tan2 = (1.0 - cos_inc**2) / np.maximum(cos_inc**2, 1e-18)
            var_perp = np.clip(var_nn + 2.0 * s_along * cov_nt + s_along**2 * var_th, 0.0, None)
            var_perp = var_perp + pos_var
            wp_n = np.cos(phi) * n[1] - np.sin(phi) * n[0]  # n · dw/dphi
            var_t = (
                var_perp / np.maximum(cos_inc**2, 1e-18)
                + (t * wp_n / nw_safe) ** 2 * head_var
                + sig_range**2
            )
            var_s = pos_var + var_uu + t**2 * head_var / np.maximum(cos_inc**2, 1e-18)
            var_s = var_s + var_perp * tan2
            margin = q * np.sqrt(np.where(ok, var_s, 0.0))
            core = ok & (s_along > e0 + margin) & (s_along < e1 - margin)
            if np.count_nonzero(core) < params.min_beams_line:
                continue
            seen = np.asarray(ranges[k], dtype=float)[core]
            reach = q * np.sqrt(var_t[core])
            passes = seen > t[core] + reach
            hits = (seen >= t[core] - reach) & ~passes
            if not np.any(hits) and np.count_nonzero(passes) >= params.min_beams_line:
                out[int(features.ids[r])] += params.view_stride


def _largest_position_variance(cov: FloatArray) -> float:
    """Largest eigenvalue of the position block of a 3×3 covariance (≥ 0)."""
    a, bb, c = float(cov[0, 0]), float(cov[0, 1]), float(cov[1, 1])
    return max(0.5 * (a + c) + math.sqrt(0.25 * (a - c) ** 2 + bb * bb), 0.0)
