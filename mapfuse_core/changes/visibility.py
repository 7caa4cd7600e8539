"""Where the known map says a feature should have been seen: :func:`scans_in_view`.

The known map itself is the occlusion model: its walls (from their surveyed extents)
and circles are ray cast from the estimated poses, so a feature hidden behind
another known feature is not expected.  A known line without a surveyed extent is
never predicted in view (its length is unknown), so it can be classified unobserved
but not missing.  Whether a feature the rays hit counts as in view in that scan:

* with the log's laser (:attr:`ChangeParams.laser`), when the extractor returns it
  from the noise-free scan the laser would record there, cut at
  :attr:`ChangeParams.max_range_m`.  Being hit by many beams is not enough: a
  trunk of 0.46 m radius at 8 m is hit by a dozen beams 0.5° apart and still fails
  the extractor's predicted signal-to-noise rule, and a feature predicted in view but
  beyond what the extractor can use would be called missing though it stands where
  the map says.  The extractor's rules depend on the geometry, not on the noise, so
  the noise-free scan is the one that decides.  The range cut is there because what
  the map does not hold occludes too: a tree too far to be extracted (hence never
  mapped) still splits a wall behind it into pieces too short to extract, so a far
  feature's absence from the scans is weak evidence;
* without it, when enough beams hit it (:attr:`ChangeParams.min_beams_line`,
  ``min_beams_circle``) within :attr:`ChangeParams.max_range_m` and, for a wall, at
  an incidence the extractor can use.
"""

from __future__ import annotations

import math

import numpy as np

from mapfuse_core.changes.params import ChangeParams
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.measlog import KnownMapArrays
from mapfuse_core.perception.extraction import ExtractionParams, extract_features
from mapfuse_core.sensor import Scan
from mapfuse_core.sim.laser import cast_rays
from mapfuse_core.sim.world import CircleObstacle, WallSegment, World

__all__ = ["map_world", "scans_in_view", "world_as_map"]


def map_world(features: KnownMapArrays) -> World | None:
    """The features as ray-castable walls and circles (``None`` if none can be)."""
    segs: list[WallSegment] = []
    circs: list[CircleObstacle] = []
    for r in range(len(features)):
        fid, p = int(features.ids[r]), features.params[r]
        if int(features.kinds[r]) == int(FeatureKind.CIRCLE):
            if p[2] > 0.0:
                circs.append(CircleObstacle(fid, (float(p[0]), float(p[1])), float(p[2])))
            continue
        if features.extents is None:
            continue
        e = features.extents[r]
        if not (np.all(np.isfinite(e)) and e[1] - e[0] > 1e-6):
            continue
        u = np.array([math.cos(p[2]), math.sin(p[2])])
        a, b = p[:2] + e[0] * u, p[:2] + e[1] * u
        segs.append(WallSegment(fid, (float(a[0]), float(a[1])), (float(b[0]), float(b[1]))))
    if not segs and not circs:
        return None
    return World(segments=tuple(segs), circles=tuple(circs))


def world_as_map(world: World) -> KnownMapArrays:
    """A world's walls and circles as map arrays (walls at their midpoints)."""
    ids, kinds, params, ext = [], [], [], []
    for s in world.segments:
        ids.append(s.id)
        kinds.append(int(FeatureKind.LINE))
        params.append(s.spmap())
        ext.append([-0.5 * s.length, 0.5 * s.length])
    for c in world.circles:
        ids.append(c.id)
        kinds.append(int(FeatureKind.CIRCLE))
        params.append(c.params())
        ext.append([math.nan, math.nan])
    n = len(ids)
    return KnownMapArrays(
        ids=np.array(ids, dtype=np.int64),
        kinds=np.array(kinds, dtype=np.int8),
        params=np.array(params, dtype=float).reshape(n, 3),
        covs=np.zeros((n, 3, 3)),
        extents=np.array(ext, dtype=float).reshape(n, 2),
    )


def scans_in_view(
    features: KnownMapArrays,
    poses: FloatArray,
    params: ChangeParams,
    occluders: KnownMapArrays | None = None,
) -> dict[int, int]:
    """Scans (of ``poses``, sensor poses in the map's frame) in which each feature of
    ``features`` is in view, counted at every ``view_stride``-th pose times the stride.

    ``occluders`` (ids distinct from the features') hide what lies behind them too:
    the mapped landmarks the known map does not hold.
    """
    counts = {int(i): 0 for i in features.ids}
    both = features
    if occluders is not None and len(occluders):
        ext = [
            np.full((len(m), 2), np.nan) if m.extents is None else m.extents
            for m in (features, occluders)
        ]
        both = KnownMapArrays(
            ids=np.concatenate([features.ids, occluders.ids]),
            kinds=np.concatenate([features.kinds, occluders.kinds]),
            params=np.vstack([features.params, occluders.params]),
            covs=np.vstack([features.covs, occluders.covs]),
            extents=np.vstack(ext),
        )
    world = map_world(both)
    if world is None:
        return counts
    P = np.asarray(poses, dtype=float)
    if params.laser is not None:
        _extractor_views(world, P, params, counts)
        return counts
    half = 0.5 * params.fov_rad
    bearings = np.linspace(-half, half, params.n_beams)
    seg_normal = {
        int(s.id): math.atan2(s.p2[1] - s.p1[1], s.p2[0] - s.p1[0]) + 0.5 * math.pi
        for s in world.segments
    }
    circle_ids = set(world.circ_ids.tolist())
    for k in range(0, P.shape[0], params.view_stride):
        x = P[k]
        if not np.all(np.isfinite(x)):
            continue
        ang = x[2] + bearings
        _, hit = cast_rays(world, x, ang, params.max_range_m)
        for fid in np.unique(hit[hit >= 0]).tolist():
            if fid not in counts:
                continue
            sel = hit == fid
            if fid in circle_ids:
                ok = int(sel.sum()) >= params.min_beams_circle
            else:
                inc = np.abs(np.cos(ang[sel] - seg_normal[fid]))
                good = int(np.sum(inc >= math.cos(params.max_incidence_rad)))
                ok = good >= params.min_beams_line
            if ok:
                counts[fid] += params.view_stride
    return counts


def _extractor_views(
    world: World, poses: FloatArray, params: ChangeParams, counts: dict[int, int]
) -> None:
    """Add to ``counts`` the scans in which the extractor returns each feature from the
    noise-free scan of ``world`` that ``params.laser`` records at the pose."""
    laser = params.laser
    assert laser is not None
    extraction = params.extraction if params.extraction is not None else ExtractionParams()
    bearings = laser.bearings()
    reach = min(laser.max_range_m, params.max_range_m)
    for k in range(0, poses.shape[0], params.view_stride):
        x = poses[k]
        if not np.all(np.isfinite(x)):
            continue
        ranges, hit = cast_rays(world, x, x[2] + bearings, reach)
        if not np.any(hit >= 0):
            continue
        found = extract_features(Scan(bearings, ranges, hit), laser, extraction).features
        for fid in {int(f.true_id) for f in found}:
            if fid in counts:
                counts[fid] += params.view_stride
