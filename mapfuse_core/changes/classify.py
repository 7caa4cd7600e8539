"""Classify every known feature after a fused run: :func:`classify_changes`.

1. The logged observations are grouped by the estimator's landmark decisions and put
   in ``Wknown`` through the estimated trajectory and anchor
   (:mod:`mapfuse_core.changes.evidence`); a filter's poses from before
   its map match are first re-placed on the known map
   (:mod:`mapfuse_core.changes.relocalize`).  A landmark the estimator
   kept apart from the known map and saw only before the match is read through the
   estimator's final estimate of it when it gives one in ``Wknown`` (the anchor's
   uncertainty included jointly).
2. A known feature with an associated landmark is tested against that landmark's
   observation-only estimate: ``r = residual(known, evidence)``,
   ``S = cov(evidence) + J P_known Jᵀ``, moved when ``rᵀS⁻¹r > χ²_d(level)``.
3. A known feature without one, predicted in view at its surveyed place, or seen empty
   there (a tree: or seen occupied there), for at least
   :attr:`ChangeParams.link_min_scans` scans (a wall: whether or not,
   :attr:`ChangeParams.link_unviewed_lines`; a tree: with
   :attr:`ChangeParams.link_unviewed_circles`), is
   compared with the unassociated landmarks of its kind within
   ``max_move_m`` (and ``max_turn_rad``): the nearest, one to one, is the feature
   after a move beyond the association gate, and is tested the same way (a consistent
   one is a landmark the estimator did not merge: the feature is confirmed).  A
   landmark that an observed known feature already explains (a duplicate, see 5) may
   confirm the feature but is never taken for its move, and neither is a landmark out
   of reach of a tree whose surveyed place the raw scans found occupied for as many
   scans (the tree still stands there, unextracted).  A wall is confirmed (or
   explained) only by a landmark that overlaps the wall itself, its extent widened by
   three of the wall's and the landmark's position σ: one that fits the line beyond
   the wall's ends is another stretch of the line.  A wall moved keeps its length: a
   landmark longer than the wall by more than six of those σ in all is not its move.
4. Otherwise: missing when the known map predicts it in view for at least ``K``
   scans (:mod:`mapfuse_core.changes.visibility`), a circle at the smallest
   radius its map σ allows (:attr:`ChangeParams.missing_radius_sigmas`), or when the
   log's raw scans saw its surveyed place empty for at least ``K`` scans
   (:mod:`mapfuse_core.changes.freespace`; seen empty also counts as seen
   in step 3), else unobserved.
5. The other unassociated landmarks with at least ``min_obs`` observations are new,
   except duplicates: those consistent with an observed known feature, or within the
   move limits of one classified moved (another piece of it).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import numpy as np

from mapfuse_core.changes.evidence import (
    ObservationSet,
    fuse_against,
    observation_sets_in_known,
    poses_in_known,
)
from mapfuse_core.changes.freespace import read_surveyed_places
from mapfuse_core.changes.params import ChangeParams
from mapfuse_core.changes.relocalize import Relocalization, relocalize_before_match
from mapfuse_core.changes.report import (
    ChangeReport,
    ChangeStatus,
    FeatureChange,
    NewFeature,
)
from mapfuse_core.changes.residual import feature_residual, residual_dof
from mapfuse_core.changes.visibility import scans_in_view
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog

__all__ = ["classify_changes"]


def _test(
    obs: ObservationSet, known: FloatArray, known_cov: FloatArray, params: ChangeParams
) -> tuple[FloatArray, FloatArray, float, FloatArray, float]:
    """Residual, its covariance, the χ² statistic, the displacement (dx, dy, d3) and
    the evidence's spread factor."""
    ev = fuse_against(obs, known)
    _, Jk, _ = feature_residual(obs.kind, known, known)
    S = ev.cov + Jk @ known_cov @ Jk.T
    r = ev.residual
    stat = float(r @ np.linalg.solve(S, r))
    if obs.kind == FeatureKind.LINE:
        normal = np.array([-math.sin(known[2]), math.cos(known[2])])
        disp = np.array([*(r[0] * normal), r[1]])
    else:
        disp = r.copy()
    return r, S, stat, disp, ev.spread_factor


def _near(
    obs: ObservationSet,
    known: FloatArray,
    known_cov: FloatArray,
    extent: FloatArray | None,
    params: ChangeParams,
) -> float:
    """Size of the move that takes ``known`` onto ``obs`` (m), ``inf`` beyond the limits.

    The limits are ``max_move_m`` and ``max_turn_rad`` widened by three of the known
    feature's own σ (its position, or its angle for a line): the surveyed value itself
    is that far from where the feature stood, so a feature turned by the largest turn
    looked for, in a map whose angles have σθ = 0.05 rad, can appear turned by 0.15 rad
    more.  A line must also overlap the known wall along its length (its surveyed
    extent widened by ``max_move_m``; without one, within ``max_move_m`` of its
    reference point).
    """
    sig_xy = math.sqrt(max(0.0, 0.5 * float(known_cov[0, 0] + known_cov[1, 1])))
    max_move = params.max_move_m + 3.0 * sig_xy
    mean = obs.features.mean(axis=0)
    if obs.kind == FeatureKind.CIRCLE:
        d = float(np.hypot(*(mean[:2] - known[:2])))
        return d if d <= max_move else math.inf
    max_turn = params.max_turn_rad + 3.0 * math.sqrt(max(0.0, float(known_cov[2, 2])))
    r = np.array([feature_residual(obs.kind, known, f)[0] for f in obs.features]).mean(axis=0)
    if abs(r[1]) > max_turn or abs(r[0]) > max_move:
        return math.inf
    if not _overlaps(obs, known, extent, params.max_move_m):
        return math.inf
    return float(abs(r[0]))


def _along(obs: ObservationSet, known: FloatArray) -> list[float]:
    """Where the ends of ``obs``'s observed segments fall along the known line."""
    u_k = np.array([math.cos(known[2]), math.sin(known[2])])
    along = []
    for f, e in zip(obs.features, obs.extents, strict=True):
        u = np.array([math.cos(f[2]), math.sin(f[2])])
        ends = [0.0] if not np.all(np.isfinite(e)) else [float(e[0]), float(e[1])]
        along += [float((f[:2] + t * u - known[:2]) @ u_k) for t in ends]
    return along


def _overlaps(
    obs: ObservationSet, known: FloatArray, extent: FloatArray | None, margin: float
) -> bool:
    """Whether ``obs`` overlaps the known wall along its length, its surveyed extent
    widened by ``margin`` on each side (without an extent: within ``margin`` of its
    reference point)."""
    along = _along(obs, known)
    lo, hi = (0.0, 0.0) if extent is None or not np.all(np.isfinite(extent)) else extent
    return not (max(along) < lo - margin or min(along) > hi + margin)


def _same_piece(obs: ObservationSet, known: KnownMapArrays, r: int) -> bool:
    """Whether line landmark ``obs`` overlaps known wall ``r`` itself, not just its line:
    the surveyed extent widened by three of the wall's position σ and of the landmark's
    pose σ.  A wall consistent with another only as a line but beyond its ends is a
    collinear piece of another wall (the next stretch of a corridor past a door)."""
    return _overlaps(obs, known.params[r], _extent(known, r), 3.0 * _position_sigmas(obs, known, r))


def _position_sigmas(obs: ObservationSet, known: KnownMapArrays, r: int) -> float:
    """Known feature ``r``'s position σ plus the landmark's mean pose position σ (m)."""
    kc = known.covs[r]
    sig_k = math.sqrt(max(0.0, 0.5 * float(kc[0, 0] + kc[1, 1])))
    pc = obs.pose_covs
    sig_p = math.sqrt(max(0.0, 0.5 * float(np.mean(pc[:, 0, 0] + pc[:, 1, 1]))))
    return sig_k + sig_p


def _longer(obs: ObservationSet, known: KnownMapArrays, r: int) -> bool:
    """Whether line landmark ``obs`` spans more of the known wall's line than wall
    ``r`` is long, by more than six of the wall's and the landmark's position σ (the
    margin of three at each end that :func:`_same_piece` allows): a wall moved is
    still its own length, so a longer landmark is another wall (a plan wall that does
    not stand, near one the plan lacks)."""
    extent = _extent(known, r)
    if extent is None or not np.all(np.isfinite(extent)):
        return False
    along = _along(obs, known.params[r])
    excess = (max(along) - min(along)) - float(extent[1] - extent[0])
    return excess > 6.0 * _position_sigmas(obs, known, r)


def _extent(known: KnownMapArrays, r: int) -> FloatArray | None:
    return None if known.extents is None else np.asarray(known.extents[r], dtype=float)


def classify_changes(
    log: MeasurementLog,
    obs_landmark: np.ndarray,
    obs_known_id: np.ndarray,
    poses: FloatArray,
    pose_covs: FloatArray,
    x_Wknown_Wglobal: FloatArray,
    params: ChangeParams | None = None,
    *,
    anchor_cov: FloatArray | None = None,
    anchored_from_step: int = 0,
    landmark_estimates: Mapping[int, tuple[FloatArray, FloatArray]] | None = None,
) -> ChangeReport:
    """Classify the known map of ``log`` given a run's decisions, trajectory and anchor.

    ``poses``/``pose_covs``: the run's ``x^Wglobal_R`` per step and their covariances;
    ``x_Wknown_Wglobal``: its anchor.  ``anchor_cov``/``anchored_from_step``: a
    filtered track's anchor covariance and match step; the observations made before
    it carry the anchor's uncertainty too
    (:func:`~mapfuse_core.changes.evidence.poses_in_known`).
    ``landmark_estimates``: landmark id → the estimator's final estimate of a landmark
    it kept apart from the known map, in ``Wknown`` with its covariance; such a
    landmark seen only before ``anchored_from_step`` is tested through it instead of
    through its observations.  See the
    module docstring for the rules.
    """
    params = params or ChangeParams()
    anchor = np.asarray(x_Wknown_Wglobal, dtype=float)
    if anchor.shape != (3,) or not np.all(np.isfinite(anchor)):
        raise ValueError(f"the anchor must be a finite (3,) pose, got {anchor!r}")
    known = log.known_map
    poses_K, covs_K = poses_in_known(anchor, poses, pose_covs, anchor_cov, anchored_from_step)
    reloc = None
    filtered_K, filtered_covs_K = poses_K, covs_K
    if params.relocalize and anchored_from_step > 0:
        reloc = relocalize_before_match(
            log, obs_landmark, obs_known_id, poses_K, covs_K, anchored_from_step, params.level
        )
        poses_K, covs_K = reloc.poses, reloc.covs
    sets = observation_sets_in_known(log, obs_landmark, obs_known_id, poses_K, covs_K)
    if reloc is not None and reloc.tied_known:
        sets = [
            _own_ties_left_out(
                s,
                log,
                obs_landmark,
                obs_known_id,
                filtered_K,
                filtered_covs_K,
                anchored_from_step,
                reloc,
                params,
            )
            if s.known_id in reloc.tied_known and np.any(s.steps < anchored_from_step)
            else s
            for s in sets
        ]
    by_known: dict[int, ObservationSet] = {}
    free: list[ObservationSet] = []
    for s in sets:
        if s.known_id >= 0:
            best = by_known.get(s.known_id)
            if best is None or s.n_obs > best.n_obs:
                by_known[s.known_id] = s
        elif s.n_obs >= params.min_obs:
            own = None
            seen_before = int(s.steps.max()) < anchored_from_step
            if params.filter_estimates and landmark_estimates is not None and seen_before:
                # Seen only before the match: read through the estimator's final
                # estimate, not through the poses the filter had then.
                own = landmark_estimates.get(s.landmark)
            free.append(s if own is None else dataclasses.replace(s, estimate=own))
    occluders = _occluders(free, known)
    in_view = scans_in_view(known, poses_K, params, occluders)

    rows: dict[int, FeatureChange] = {}
    unassociated: list[int] = []
    for r in range(len(known)):
        kid = int(known.ids[r])
        if kid in by_known and by_known[kid].n_obs >= 1:
            rows[r] = _row(known, r, by_known[kid], True, in_view[kid], params)
        else:
            unassociated.append(r)
    empty = {int(known.ids[r]): 0 for r in unassociated}
    occupied: dict[int, tuple[int, float]] = {}
    if params.free_space and log.scan_bearings is not None and log.scan_ranges is not None:
        reading = read_surveyed_places(
            known, unassociated, poses_K, covs_K, log.scan_bearings, log.scan_ranges, params
        )
        empty, occupied = reading.empty, reading.occupied
    # Moves beyond the association gate: nearest unassociated landmark, one to one.  A
    # landmark consistent with a known feature already observed is another track of
    # that feature (a duplicate): it may confirm this one too (two plan walls a wall's
    # thickness apart), but it is not this one's move.
    explained = {i for i, s in enumerate(free) if _duplicate(s, known, rows, params)}
    pairs = []
    for r in unassociated:
        kind = FeatureKind(int(known.kinds[r]))
        kid = int(known.ids[r])
        need = min(params.link_min_scans or params.min_scans, params.min_scans)
        standing, reach = occupied.get(kid, (0, 0.0))
        # Seen occupied is seen too: the trunk that the beams hit at the surveyed place
        # (a tree moved by less than its reach, which hides its own surveyed place
        # from the view model) is linked to the landmark within that reach below.
        unviewed = in_view[kid] < need and empty[kid] < need and standing < need
        is_line = kind == FeatureKind.LINE
        linked = params.link_unviewed_lines if is_line else params.link_unviewed_circles
        if unviewed and not linked:
            # Not seen where the map has it, but never expected there either: nothing
            # says it moved, and a landmark near a tree is as likely a tree the map
            # lacks as this one moved (ChangeParams.link_unviewed_circles).
            continue
        for i, s in enumerate(free):
            if s.kind != kind:
                continue
            d = _near(s, known.params[r], known.covs[r], _extent(known, r), params)
            if not math.isfinite(d):
                continue
            if standing >= need and standing > empty[kid] and _beyond(s, known.params[r], reach):
                # The raw scans found a trunk standing at the surveyed place, and this
                # landmark is too far to be what they hit: another tree, not its move.
                continue
            consistent = _consistent(s, known, r, params)
            if consistent and kind == FeatureKind.LINE and not _same_piece(s, known, r):
                # The line fits but the landmark lies beyond the wall's ends: another
                # stretch of the line, not this wall seen again nor moved along itself.
                continue
            if i in explained and not consistent:
                continue
            if kind == FeatureKind.LINE and not consistent and _longer(s, known, r):
                continue
            pairs.append((d, r, i))
    used: set[int] = set()
    for _, r, i in sorted(pairs):
        if r in rows or i in used:
            continue
        used.add(i)
        kid = int(known.ids[r])
        row = _row(known, r, free[i], False, in_view[kid], params)
        rows[r] = dataclasses.replace(
            row, scans_seen_empty=empty[kid], scans_seen_occupied=occupied.get(kid, (0, 0.0))[0]
        )
    left = [r for r in unassociated if r not in rows]
    sure = dict(in_view)
    candidates = [
        r
        for r in left
        if in_view[int(known.ids[r])] >= params.min_scans
        and int(known.kinds[r]) == int(FeatureKind.CIRCLE)
    ]
    if candidates:
        # One more view, with only the would-be missing circles thinned: the others keep
        # hiding what they hide.
        thin = _thinned(known, candidates, params.radius_margin_sigmas())
        again = scans_in_view(thin, poses_K, params, occluders)
        for r in candidates:
            kid = int(known.ids[r])
            sure[kid] = min(in_view[kid], again[kid])
    for r in left:
        kid = int(known.ids[r])
        seen = sure[kid] >= params.min_scans or empty[kid] >= params.min_scans
        standing = occupied.get(kid, (0, 0.0))[0]
        if standing >= params.min_scans:
            # The raw scans found it where the map has it: not seen absent, however
            # many scans saw the place empty (from a pose further off than its σ).
            seen = False
        status = ChangeStatus.MISSING if seen else ChangeStatus.UNOBSERVED
        kind = FeatureKind(int(known.kinds[r]))
        rows[r] = FeatureChange(
            known_id=kid,
            kind=kind,
            status=status,
            displacement=np.full(3, np.nan),
            residual=np.zeros(0),
            residual_cov=np.zeros((0, 0)),
            statistic=math.nan,
            dof=residual_dof(kind),
            threshold=params.threshold(residual_dof(kind)),
            n_obs=0,
            scans_in_view=sure[kid],
            associated=False,
            landmark=-1,
            scans_seen_empty=empty[kid],
            scans_seen_occupied=occupied.get(kid, (0, 0.0))[0],
        )
    # New features: unassociated landmarks no known feature accounts for.
    new: list[NewFeature] = []
    duplicates = 0
    for i, s in enumerate(free):
        if i in used:
            continue
        if _duplicate(s, known, rows, params):
            duplicates += 1
            continue
        ref = s.features[0]
        ev = fuse_against(s, ref)
        est = _apply(s.kind, ref, ev.residual)
        # Lines: lateral and angle only; the along-line position is undetermined.
        cov3 = ev.cov if s.kind == FeatureKind.CIRCLE else _line_cov3(ref, ev.cov)
        new.append(
            NewFeature(
                landmark=s.landmark,
                kind=s.kind,
                params=est,
                cov=cov3,
                n_obs=s.n_obs,
                true_id=s.true_id,
            )
        )
    return ChangeReport(
        known=tuple(rows[r] for r in range(len(known))),
        new=tuple(new),
        duplicates=duplicates,
        level=params.level,
        x_Wknown_Wglobal=anchor,
        relocalized_steps=0 if reloc is None else reloc.relocalized,
        bridged_steps=0 if reloc is None else reloc.bridged,
        relocalize_refused=0 if reloc is None else reloc.refused,
    )


def _own_ties_left_out(
    s: ObservationSet,
    log: MeasurementLog,
    obs_landmark: np.ndarray,
    obs_known_id: np.ndarray,
    poses_K: FloatArray,
    covs_K: FloatArray,
    until: int,
    reloc: Relocalization,
    params: ChangeParams,
) -> ObservationSet:
    """``s`` read through poses re-placed without its own known feature's ties: the
    feature under test does not place the poses its evidence is read through.
    ``poses_K``/``covs_K``: the poses in ``Wknown`` before any re-placing, ``until``
    the first step from the match on; ``reloc``: the re-placing with every tie, whose
    placements are reused."""
    alt = relocalize_before_match(
        log,
        obs_landmark,
        obs_known_id,
        poses_K,
        covs_K,
        until,
        params.level,
        exclude_known=s.known_id,
        base=reloc,
    )
    only = np.where(np.asarray(obs_landmark) == s.landmark, obs_landmark, -1)
    again = observation_sets_in_known(log, only, obs_known_id, alt.poses, alt.covs)
    return again[0] if again else s


def _beyond(obs: ObservationSet, known: FloatArray, reach: float) -> bool:
    """Whether circle landmark ``obs`` stands too far from the known circle's centre for
    a beam it returns to have been read as a hit there: such a beam is aimed within the
    mapped radius of the centre (across the beam) and returns within ``reach`` of the
    centre's range (along it)."""
    centre = np.mean(obs.features[:, :2], axis=0)
    radius = max(float(np.median(obs.features[:, 2])), 0.0)
    window = math.hypot(reach, float(known[2]))
    return float(np.hypot(*(centre - known[:2]))) > window + radius


def _row(
    known: KnownMapArrays,
    r: int,
    obs: ObservationSet,
    associated: bool,
    in_view: int,
    params: ChangeParams,
) -> FeatureChange:
    kp = known.params[r]
    kc = known.covs[r]
    res, S, stat, disp, spread = _test(obs, kp, kc, params)
    dof = residual_dof(obs.kind)
    thr = params.threshold(dof)
    return FeatureChange(
        known_id=int(known.ids[r]),
        kind=obs.kind,
        status=ChangeStatus.MOVED if stat > thr else ChangeStatus.CONFIRMED,
        displacement=disp,
        residual=res,
        residual_cov=S,
        statistic=stat,
        dof=dof,
        threshold=thr,
        n_obs=obs.n_obs,
        scans_in_view=in_view,
        associated=associated,
        landmark=obs.landmark,
        spread_factor=spread,
    )


def _consistent(s: ObservationSet, known: KnownMapArrays, r: int, params: ChangeParams) -> bool:
    """Whether ``s`` passes the moved test of known feature ``r`` (is that feature)."""
    stat = _test(s, known.params[r], known.covs[r], params)[2]
    return stat <= params.threshold(residual_dof(s.kind))


def _duplicate(
    s: ObservationSet, known: KnownMapArrays, rows: dict[int, FeatureChange], params: ChangeParams
) -> bool:
    """Whether ``s`` is consistent with a known feature (of its kind) already observed."""
    for r, row in rows.items():
        if row.kind != s.kind or row.n_obs == 0:
            continue
        kp = known.params[r]
        if not math.isfinite(_near(s, kp, known.covs[r], _extent(known, r), params)):
            continue
        if row.status == ChangeStatus.MOVED:
            # A second landmark of a moved feature (a wall seen in pieces).
            return True
        if s.kind == FeatureKind.LINE and not _same_piece(s, known, r):
            continue
        if _consistent(s, known, r, params):
            return True
    return False


def _apply(kind: FeatureKind, ref: FloatArray, r: FloatArray) -> FloatArray:
    """The feature whose residual from ``ref`` is ``r`` (inverse of the residual map)."""
    if kind == FeatureKind.CIRCLE:
        return np.asarray(ref + r, dtype=float)
    n = np.array([-math.sin(ref[2]), math.cos(ref[2])])
    return np.array([*(ref[:2] + r[0] * n), ref[2] + r[1]])


def _line_cov3(ref: FloatArray, cov2: FloatArray) -> FloatArray:
    """(x, y, θ) covariance of a line from its (lateral, angle) covariance at ``ref``."""
    n = np.array([-math.sin(ref[2]), math.cos(ref[2])])
    J = np.zeros((3, 2))
    J[:2, 0] = n
    J[2, 1] = 1.0
    return J @ cov2 @ J.T


def _thinned(known: KnownMapArrays, rows: list[int], sigmas: float) -> KnownMapArrays:
    """``known`` with the circles of ``rows`` each ``sigmas`` of its own radius σ
    thinner (at least a millimetre): the thinnest trunk the map's error allows, for the
    view that decides "missing"."""
    params = known.params.copy()
    idx = np.asarray(rows, dtype=int)
    sig_r = np.sqrt(np.clip(known.covs[idx, 2, 2], 0.0, None))
    params[idx, 2] = np.maximum(params[idx, 2] - sigmas * sig_r, 1e-3)
    return dataclasses.replace(known, params=params)


def _occluders(free: list[ObservationSet], known: KnownMapArrays) -> KnownMapArrays:
    """The unassociated landmarks as map features (ids above the known ones): a line
    spans the union of its observed segments, a circle is its mean observation."""
    base = int(known.ids.max(initial=0)) + 1
    params, kinds, extents = [], [], []
    for s in free:
        ref = s.features[0].copy()
        if s.kind == FeatureKind.CIRCLE:
            params.append(s.features.mean(axis=0))
            extents.append([np.nan, np.nan])
        else:
            u = np.array([math.cos(ref[2]), math.sin(ref[2])])
            along = []
            for f, e in zip(s.features, s.extents, strict=True):
                if np.all(np.isfinite(e)):
                    uf = np.array([math.cos(f[2]), math.sin(f[2])])
                    along += [float((f[:2] + t * uf - ref[:2]) @ u) for t in e]
            if not along:
                continue
            params.append(ref)
            extents.append([min(along), max(along)])
        kinds.append(int(s.kind))
    n = len(params)
    return KnownMapArrays(
        ids=np.arange(base, base + n, dtype=np.int64),
        kinds=np.array(kinds, dtype=np.int8),
        params=np.array(params, dtype=float).reshape(n, 3),
        covs=np.zeros((n, 3, 3)),
        extents=np.array(extents, dtype=float).reshape(n, 2),
    )
