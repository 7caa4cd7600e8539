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

Each decision is a named rule of :mod:`mapfuse_core.changes.rules`; this module
gathers the evidence the rules read and applies them in that order.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from mapfuse_core.changes.evidence import (
    ObservationSet,
    fuse_against,
    observation_sets_in_known,
    poses_in_known,
)
from mapfuse_core.changes.freespace import read_surveyed_places
from mapfuse_core.changes.params import ChangeParams
from mapfuse_core.changes.relations import move_size, move_test, surveyed_extent
from mapfuse_core.changes.relocalize import Relocalization, relocalize_before_match
from mapfuse_core.changes.report import (
    ChangeReport,
    FeatureChange,
    NewFeature,
)
from mapfuse_core.changes.residual import residual_dof
from mapfuse_core.changes.rules import (
    LinkCandidate,
    PlaceSight,
    is_duplicate,
    link_vetoed,
    looked_for_beyond_the_gate,
    nearest_one_to_one,
    needs_thinnest_view,
    status_by_move_test,
    status_without_landmark,
    strongest_associated_landmarks,
    unassociated_landmarks,
)
from mapfuse_core.changes.visibility import scans_in_view
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog

__all__ = ["classify_changes"]


@dataclass(frozen=True, eq=False)
class _Evidence:
    """What the run and the log say, in ``Wknown``, before any feature is classified."""

    poses: FloatArray
    """(N, 3) the run's poses in ``Wknown``, those before the match re-placed."""
    pose_covs: FloatArray
    """(N, 3, 3) their covariances."""
    relocalization: Relocalization | None
    """The re-placing of the poses before the match (``None`` when not done)."""
    tested: dict[int, ObservationSet]
    """Known id → the associated landmark its test reads
    (:func:`~mapfuse_core.changes.rules.strongest_associated_landmarks`)."""
    unassociated: list[ObservationSet]
    """The landmarks no known feature holds that count
    (:func:`~mapfuse_core.changes.rules.unassociated_landmarks`)."""
    occluders: KnownMapArrays
    """:attr:`unassociated` as map features, hiding what lies behind them in the view."""
    scans_in_view: dict[int, int]
    """Known id → scans the known map (and the occluders) predict it in view."""


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
    through its observations.  See the module docstring for the rules, and
    :mod:`mapfuse_core.changes.rules` for each.
    """
    params = params or ChangeParams()
    anchor = _finite_anchor(x_Wknown_Wglobal)
    known = log.known_map
    evidence = _gather_evidence(
        log,
        obs_landmark,
        obs_known_id,
        poses,
        pose_covs,
        anchor,
        params,
        anchor_cov=anchor_cov,
        anchored_from_step=anchored_from_step,
        landmark_estimates=landmark_estimates,
    )
    changes = _test_associated(known, evidence, params)
    without_landmark = [row for row in range(len(known)) if row not in changes]
    sights = _read_surveyed_places(log, without_landmark, evidence, params)
    links = _link_moves(known, without_landmark, evidence, sights, changes, params)
    changes.update(_linked_changes(known, links, evidence, sights, params))
    left_without_landmark = [row for row in without_landmark if row not in changes]
    changes.update(_missing_or_unobserved(known, left_without_landmark, evidence, sights, params))
    linked_landmarks = {index for _, index in links}
    new, duplicates = _new_features(known, evidence.unassociated, linked_landmarks, changes, params)
    relocalization = evidence.relocalization
    return ChangeReport(
        known=tuple(changes[row] for row in range(len(known))),
        new=tuple(new),
        duplicates=duplicates,
        level=params.level,
        x_Wknown_Wglobal=anchor,
        relocalized_steps=0 if relocalization is None else relocalization.relocalized,
        bridged_steps=0 if relocalization is None else relocalization.bridged,
        relocalize_refused=0 if relocalization is None else relocalization.refused,
    )


def _finite_anchor(x_Wknown_Wglobal: FloatArray) -> FloatArray:
    """The anchor as a finite (3,) pose; :class:`ValueError` otherwise."""
    anchor = np.asarray(x_Wknown_Wglobal, dtype=float)
    if anchor.shape != (3,) or not np.all(np.isfinite(anchor)):
        raise ValueError(f"the anchor must be a finite (3,) pose, got {anchor!r}")
    return anchor


def _gather_evidence(
    log: MeasurementLog,
    obs_landmark: np.ndarray,
    obs_known_id: np.ndarray,
    poses: FloatArray,
    pose_covs: FloatArray,
    anchor: FloatArray,
    params: ChangeParams,
    *,
    anchor_cov: FloatArray | None,
    anchored_from_step: int,
    landmark_estimates: Mapping[int, tuple[FloatArray, FloatArray]] | None,
) -> _Evidence:
    """Step 1: the poses in ``Wknown`` (re-placed before the match), the landmarks'
    observation sets read through them, and the predicted view (arguments as
    :func:`classify_changes`')."""
    run_poses, run_covs = poses_in_known(anchor, poses, pose_covs, anchor_cov, anchored_from_step)
    relocalization = None
    placed, placed_covs = run_poses, run_covs
    if params.relocalize and anchored_from_step > 0:
        relocalization = relocalize_before_match(
            log,
            obs_landmark,
            obs_known_id,
            run_poses,
            run_covs,
            anchored_from_step,
            params.level,
        )
        placed, placed_covs = relocalization.poses, relocalization.covs
    sets = observation_sets_in_known(log, obs_landmark, obs_known_id, placed, placed_covs)
    if relocalization is not None and relocalization.tied_known:
        sets = [
            _own_ties_left_out(
                s,
                log,
                obs_landmark,
                obs_known_id,
                run_poses,
                run_covs,
                anchored_from_step,
                relocalization,
                params,
            )
            if s.known_id in relocalization.tied_known and np.any(s.steps < anchored_from_step)
            else s
            for s in sets
        ]
    unassociated = unassociated_landmarks(sets, params, anchored_from_step, landmark_estimates)
    occluders = _landmarks_as_map(unassociated, log.known_map)
    return _Evidence(
        poses=placed,
        pose_covs=placed_covs,
        relocalization=relocalization,
        tested=strongest_associated_landmarks(sets),
        unassociated=unassociated,
        occluders=occluders,
        scans_in_view=scans_in_view(log.known_map, placed, params, occluders),
    )


def _own_ties_left_out(
    landmark: ObservationSet,
    log: MeasurementLog,
    obs_landmark: np.ndarray,
    obs_known_id: np.ndarray,
    run_poses: FloatArray,
    run_covs: FloatArray,
    until: int,
    relocalization: Relocalization,
    params: ChangeParams,
) -> ObservationSet:
    """``landmark`` read through poses re-placed without its own known feature's ties:
    the feature under test does not place the poses its evidence is read through.
    ``run_poses``/``run_covs``: the poses in ``Wknown`` before any re-placing,
    ``until`` the first step from the match on; ``relocalization``: the re-placing with
    every tie, whose placements are reused."""
    without_own_ties = relocalize_before_match(
        log,
        obs_landmark,
        obs_known_id,
        run_poses,
        run_covs,
        until,
        params.level,
        exclude_known=landmark.known_id,
        base=relocalization,
    )
    this_landmark_only = np.where(np.asarray(obs_landmark) == landmark.landmark, obs_landmark, -1)
    reread = observation_sets_in_known(
        log, this_landmark_only, obs_known_id, without_own_ties.poses, without_own_ties.covs
    )
    return reread[0] if reread else landmark


def _test_associated(
    known: KnownMapArrays, evidence: _Evidence, params: ChangeParams
) -> dict[int, FeatureChange]:
    """Step 2: row → the change of every known feature with an associated landmark
    that has observations, by its move test."""
    changes = {}
    for row in range(len(known)):
        kid = int(known.ids[row])
        landmark = evidence.tested.get(kid)
        if landmark is not None and landmark.n_obs >= 1:
            sight = PlaceSight(scans_in_view=evidence.scans_in_view[kid])
            changes[row] = _tested_change(known, row, landmark, sight, params, associated=True)
    return changes


def _tested_change(
    known: KnownMapArrays,
    row: int,
    landmark: ObservationSet,
    sight: PlaceSight,
    params: ChangeParams,
    *,
    associated: bool,
) -> FeatureChange:
    """Known feature ``row`` classified by the move test against ``landmark``
    (:func:`~mapfuse_core.changes.rules.status_by_move_test`)."""
    test = move_test(landmark, known.params[row], known.covs[row])
    dof = residual_dof(landmark.kind)
    threshold = params.threshold(dof)
    return FeatureChange(
        known_id=int(known.ids[row]),
        kind=landmark.kind,
        status=status_by_move_test(test.statistic, threshold),
        displacement=test.displacement,
        residual=test.residual,
        residual_cov=test.cov,
        statistic=test.statistic,
        dof=dof,
        threshold=threshold,
        n_obs=landmark.n_obs,
        scans_in_view=sight.scans_in_view,
        associated=associated,
        landmark=landmark.landmark,
        spread_factor=test.spread_factor,
        scans_seen_empty=sight.scans_seen_empty,
        scans_seen_occupied=sight.scans_seen_occupied,
    )


def _read_surveyed_places(
    log: MeasurementLog, rows: list[int], evidence: _Evidence, params: ChangeParams
) -> dict[int, PlaceSight]:
    """Known id → what was seen of the surveyed place of each known feature at ``rows``:
    the predicted view, and what the raw scans say when the log has them and
    :attr:`ChangeParams.free_space` is on."""
    known = log.known_map
    empty = {int(known.ids[row]): 0 for row in rows}
    occupied: dict[int, tuple[int, float]] = {}
    if params.free_space and log.scan_bearings is not None and log.scan_ranges is not None:
        reading = read_surveyed_places(
            known,
            rows,
            evidence.poses,
            evidence.pose_covs,
            log.scan_bearings,
            log.scan_ranges,
            params,
        )
        empty, occupied = reading.empty, reading.occupied
    sights = {}
    for row in rows:
        kid = int(known.ids[row])
        scans_occupied, reach = occupied.get(kid, (0, 0.0))
        sights[kid] = PlaceSight(
            scans_in_view=evidence.scans_in_view[kid],
            scans_seen_empty=empty[kid],
            scans_seen_occupied=scans_occupied,
            occupied_reach_m=reach,
        )
    return sights


def _link_moves(
    known: KnownMapArrays,
    rows: list[int],
    evidence: _Evidence,
    sights: Mapping[int, PlaceSight],
    tested: Mapping[int, FeatureChange],
    params: ChangeParams,
) -> list[tuple[int, int]]:
    """Step 3: ``(row, landmark index)`` links of the known features at ``rows`` to the
    unassociated landmarks taken for their moves beyond the association gate.
    ``tested``: the changes of the features with an associated landmark, which explain
    their duplicates."""
    explains_observed = [is_duplicate(s, known, tested, params) for s in evidence.unassociated]
    candidates = []
    for row in rows:
        kind = FeatureKind(int(known.kinds[row]))
        sight = sights[int(known.ids[row])]
        if not looked_for_beyond_the_gate(kind, sight, params):
            continue
        for index, landmark in enumerate(evidence.unassociated):
            if landmark.kind != kind:
                continue
            size = move_size(
                landmark, known.params[row], known.covs[row], surveyed_extent(known, row), params
            )
            if not math.isfinite(size):
                continue
            candidate = LinkCandidate(
                landmark=landmark,
                known=known,
                row=row,
                sight=sight,
                explains_an_observed_feature=explains_observed[index],
                params=params,
            )
            if not link_vetoed(candidate):
                candidates.append((size, row, index))
    return nearest_one_to_one(candidates)


def _linked_changes(
    known: KnownMapArrays,
    links: list[tuple[int, int]],
    evidence: _Evidence,
    sights: Mapping[int, PlaceSight],
    params: ChangeParams,
) -> dict[int, FeatureChange]:
    """Step 3, continued: row → the change of each linked known feature, by the move
    test against the unassociated landmark it is linked to."""
    changes = {}
    for row, index in links:
        sight = sights[int(known.ids[row])]
        landmark = evidence.unassociated[index]
        changes[row] = _tested_change(known, row, landmark, sight, params, associated=False)
    return changes


def _missing_or_unobserved(
    known: KnownMapArrays,
    rows: list[int],
    evidence: _Evidence,
    sights: Mapping[int, PlaceSight],
    params: ChangeParams,
) -> dict[int, FeatureChange]:
    """Step 4: row → the change of each known feature at ``rows`` (left without a
    landmark): missing or unobserved, the trees predicted in view at their thinnest."""
    scans_for_missing = _scans_in_view_at_thinnest(known, rows, evidence, params)
    changes = {}
    for row in rows:
        kid = int(known.ids[row])
        sight = dataclasses.replace(sights[kid], scans_in_view=scans_for_missing[kid])
        kind = FeatureKind(int(known.kinds[row]))
        dof = residual_dof(kind)
        changes[row] = FeatureChange(
            known_id=kid,
            kind=kind,
            status=status_without_landmark(sight, params),
            displacement=np.full(3, np.nan),
            residual=np.zeros(0),
            residual_cov=np.zeros((0, 0)),
            statistic=math.nan,
            dof=dof,
            threshold=params.threshold(dof),
            n_obs=0,
            scans_in_view=sight.scans_in_view,
            associated=False,
            landmark=-1,
            scans_seen_empty=sight.scans_seen_empty,
            scans_seen_occupied=sight.scans_seen_occupied,
        )
    return changes


def _scans_in_view_at_thinnest(
    known: KnownMapArrays, rows: list[int], evidence: _Evidence, params: ChangeParams
) -> dict[int, int]:
    """Known id → scans each feature at ``rows`` is predicted in view; for the trees
    :func:`~mapfuse_core.changes.rules.needs_thinnest_view` names, the fewer of those
    at the mapped radius and at the thinnest.  Only those trees are thinned: the others
    keep hiding what they hide."""
    in_view = evidence.scans_in_view
    scans = {int(known.ids[row]): in_view[int(known.ids[row])] for row in rows}
    thinnest = [
        row
        for row in rows
        if needs_thinnest_view(
            FeatureKind(int(known.kinds[row])), in_view[int(known.ids[row])], params
        )
    ]
    if not thinnest:
        return scans
    thinned_map = _thinned(known, thinnest, params.radius_margin_sigmas())
    thinned_view = scans_in_view(thinned_map, evidence.poses, params, evidence.occluders)
    for row in thinnest:
        kid = int(known.ids[row])
        scans[kid] = min(in_view[kid], thinned_view[kid])
    return scans


def _new_features(
    known: KnownMapArrays,
    unassociated: list[ObservationSet],
    linked: set[int],
    changes: Mapping[int, FeatureChange],
    params: ChangeParams,
) -> tuple[list[NewFeature], int]:
    """Step 5: the unassociated landmarks not ``linked`` to a known feature that no
    classified feature accounts for, as new features, and the number that one does
    (duplicates)."""
    new = []
    duplicates = 0
    for index, landmark in enumerate(unassociated):
        if index in linked:
            continue
        if is_duplicate(landmark, known, changes, params):
            duplicates += 1
            continue
        new.append(_new_feature(landmark))
    return new, duplicates


def _new_feature(landmark: ObservationSet) -> NewFeature:
    """``landmark`` as a new feature: its observation-only estimate in ``Wknown`` (a
    line's lateral offset and angle only; where along the line it lies is
    undetermined)."""
    reference = landmark.features[0]
    evidence = fuse_against(landmark, reference)
    estimate = _feature_at_residual(landmark.kind, reference, evidence.residual)
    cov = (
        evidence.cov
        if landmark.kind == FeatureKind.CIRCLE
        else _line_cov_xytheta(reference, evidence.cov)
    )
    return NewFeature(
        landmark=landmark.landmark,
        kind=landmark.kind,
        params=estimate,
        cov=cov,
        n_obs=landmark.n_obs,
        true_id=landmark.true_id,
    )


def _feature_at_residual(kind: FeatureKind, reference: FloatArray, r: FloatArray) -> FloatArray:
    """The feature whose residual from ``reference`` is ``r`` (inverse of the residual
    map)."""
    if kind == FeatureKind.CIRCLE:
        return np.asarray(reference + r, dtype=float)
    normal = np.array([-math.sin(reference[2]), math.cos(reference[2])])
    return np.array([*(reference[:2] + r[0] * normal), reference[2] + r[1]])


def _line_cov_xytheta(reference: FloatArray, cov_lateral_angle: FloatArray) -> FloatArray:
    """(x, y, θ) covariance of a line from its (lateral, angle) covariance at
    ``reference``."""
    normal = np.array([-math.sin(reference[2]), math.cos(reference[2])])
    J = np.zeros((3, 2))
    J[:2, 0] = normal
    J[2, 1] = 1.0
    return J @ cov_lateral_angle @ J.T


def _thinned(known: KnownMapArrays, rows: list[int], sigmas: float) -> KnownMapArrays:
    """``known`` with the circles of ``rows`` each ``sigmas`` of its own radius σ
    thinner (at least a millimetre): the thinnest trunk the map's error allows, for the
    view that decides "missing"."""
    params = known.params.copy()
    idx = np.asarray(rows, dtype=int)
    sigma_radius = np.sqrt(np.clip(known.covs[idx, 2, 2], 0.0, None))
    params[idx, 2] = np.maximum(params[idx, 2] - sigmas * sigma_radius, 1e-3)
    return dataclasses.replace(known, params=params)


def _landmarks_as_map(landmarks: list[ObservationSet], known: KnownMapArrays) -> KnownMapArrays:
    """The unassociated landmarks as map features (ids above the known ones), for the
    view to be hidden by: a line spans the union of its observed segments, a circle is
    its mean observation."""
    base = int(known.ids.max(initial=0)) + 1
    params, kinds, extents = [], [], []
    for landmark in landmarks:
        reference = landmark.features[0].copy()
        if landmark.kind == FeatureKind.CIRCLE:
            params.append(landmark.features.mean(axis=0))
            extents.append([np.nan, np.nan])
        else:
            u = np.array([math.cos(reference[2]), math.sin(reference[2])])
            along = []
            for f, e in zip(landmark.features, landmark.extents, strict=True):
                if np.all(np.isfinite(e)):
                    u_f = np.array([math.cos(f[2]), math.sin(f[2])])
                    along += [float((f[:2] + t * u_f - reference[:2]) @ u) for t in e]
            if not along:
                continue
            params.append(reference)
            extents.append([min(along), max(along)])
        kinds.append(int(landmark.kind))
    n = len(params)
    return KnownMapArrays(
        ids=np.arange(base, base + n, dtype=np.int64),
        kinds=np.array(kinds, dtype=np.int8),
        params=np.array(params, dtype=float).reshape(n, 3),
        covs=np.zeros((n, 3, 3)),
        extents=np.array(extents, dtype=float).reshape(n, 2),
    )
