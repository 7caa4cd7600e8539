"""The rules of :func:`~mapfuse_core.changes.classify.classify_changes`, one decision each.

:func:`~mapfuse_core.changes.classify.classify_changes` applies them in this order
(``docs/change-detection.md``):

Evidence
  1. :func:`strongest_associated_landmarks`: a known feature is tested against the
     associated landmark with the most observations.
  2. :func:`unassociated_landmarks`: a landmark no known feature holds counts with
     ``min_obs`` observations (:func:`enough_observations`); seen only before the
     map match it is read through the estimator's own estimate
     (:func:`estimate_to_read_through`).

A known feature with an associated landmark
  3. :func:`status_by_move_test`: moved when the landmark's evidence fails the χ²
     test against it, else confirmed.

A known feature without one: a move beyond the association gate
  4. :func:`looked_for_beyond_the_gate`: only a feature whose surveyed place was seen
     (in view, seen empty or seen standing) is looked for, unless its kind's
     ``link_unviewed_*`` setting says otherwise.
  5. A landmark of its kind within the move limits
     (:func:`~mapfuse_core.changes.relations.move_size`) is a candidate
     (:class:`LinkCandidate`) unless one of :data:`LINK_VETOES` holds:
     :func:`trunk_stands_where_surveyed`, :func:`another_stretch_of_the_line`,
     :func:`duplicate_of_an_observed_feature`, :func:`longer_than_this_wall`.
  6. :func:`nearest_one_to_one`: the candidates are paired nearest first, each feature
     and each landmark once; a pair is tested as in 3.

A known feature left without a landmark
  7. :func:`needs_thinnest_view`: a tree predicted in view long enough to be missing is
     viewed again at the thinnest radius its map σ allows.
  8. :func:`status_without_landmark`: missing when seen absent
     (:func:`seen_absent`), else unobserved.

The landmarks left
  9. :func:`duplicate_of`: a landmark within the move limits of an observed known
     feature is no new feature when that feature is moved
     (:func:`piece_of_a_moved_feature`) or the landmark is another track of it
     (:func:`another_track_of_an_observed_feature`); the others are new.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from functools import cached_property

from mapfuse_core.changes.evidence import ObservationSet
from mapfuse_core.changes.params import ChangeParams
from mapfuse_core.changes.relations import (
    beyond_reach,
    longer_than_the_wall,
    move_size,
    on_the_wall_itself,
    passes_move_test,
    surveyed_extent,
)
from mapfuse_core.changes.report import ChangeStatus, FeatureChange
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.measlog import KnownMapArrays

__all__ = [
    "LINK_VETOES",
    "LinkCandidate",
    "PlaceSight",
    "another_stretch_of_the_line",
    "another_track_of_an_observed_feature",
    "duplicate_of",
    "duplicate_of_an_observed_feature",
    "enough_observations",
    "estimate_to_read_through",
    "is_duplicate",
    "link_scans_needed",
    "link_vetoed",
    "longer_than_this_wall",
    "looked_for_beyond_the_gate",
    "nearest_one_to_one",
    "needs_thinnest_view",
    "piece_of_a_moved_feature",
    "seen_absent",
    "status_by_move_test",
    "status_without_landmark",
    "strongest_associated_landmarks",
    "trunk_stands_where_surveyed",
    "unassociated_landmarks",
]


@dataclass(frozen=True)
class PlaceSight:
    """How often a known feature's surveyed place was seen, by each reading."""

    scans_in_view: int
    """Scans in which the known map predicts the feature in view
    (:func:`~mapfuse_core.changes.visibility.scans_in_view`)."""
    scans_seen_empty: int = 0
    """Scans whose raw beams went through the surveyed place
    (:mod:`mapfuse_core.changes.freespace`)."""
    scans_seen_occupied: int = 0
    """Scans whose raw beams found a trunk standing at the surveyed place (circles)."""
    occupied_reach_m: float = 0.0
    """The largest reach (m) in front of the mapped centre a hit of those scans was
    counted within."""


# --- Evidence -------------------------------------------------------------------


def strongest_associated_landmarks(sets: Iterable[ObservationSet]) -> dict[int, ObservationSet]:
    """Known id → the landmark tested against that known feature: of the landmarks the
    estimator merged with it, the one with the most observations (the first of equals).
    An estimator that keeps a second, shorter track of a feature has not merged it
    fully; the longer track is the feature's evidence."""
    tested: dict[int, ObservationSet] = {}
    for landmark in sets:
        if landmark.known_id < 0:
            continue
        strongest = tested.get(landmark.known_id)
        if strongest is None or landmark.n_obs > strongest.n_obs:
            tested[landmark.known_id] = landmark
    return tested


def enough_observations(landmark: ObservationSet, params: ChangeParams) -> bool:
    """Whether a landmark has the ``min_obs`` observations it needs to count as observed,
    as a move of a known feature or as new: fewer are as likely a spurious
    extraction."""
    return landmark.n_obs >= params.min_obs


def estimate_to_read_through(
    landmark: ObservationSet,
    params: ChangeParams,
    anchored_from_step: int,
    landmark_estimates: Mapping[int, tuple[FloatArray, FloatArray]] | None,
) -> tuple[FloatArray, FloatArray] | None:
    """The estimator's final estimate (``Wknown``, covariance) to read an unassociated
    landmark through, or ``None`` to read it through its observations.  A landmark seen
    only before the map match (every step before ``anchored_from_step``) was observed
    through poses the filter had before it knew the map; its final estimate was
    corrected by everything after (:attr:`ChangeParams.filter_estimates`)."""
    if not params.filter_estimates or landmark_estimates is None:
        return None
    seen_only_before_match = int(landmark.steps.max()) < anchored_from_step
    return landmark_estimates.get(landmark.landmark) if seen_only_before_match else None


def unassociated_landmarks(
    sets: Iterable[ObservationSet],
    params: ChangeParams,
    anchored_from_step: int,
    landmark_estimates: Mapping[int, tuple[FloatArray, FloatArray]] | None,
) -> list[ObservationSet]:
    """The landmarks no known feature holds that count (:func:`enough_observations`),
    in order, each with the estimate it is read through
    (:func:`estimate_to_read_through`)."""
    out = []
    for landmark in sets:
        if landmark.known_id >= 0 or not enough_observations(landmark, params):
            continue
        estimate = estimate_to_read_through(
            landmark, params, anchored_from_step, landmark_estimates
        )
        out.append(
            landmark if estimate is None else dataclasses.replace(landmark, estimate=estimate)
        )
    return out


# --- A known feature with an associated landmark --------------------------------


def status_by_move_test(statistic: float, threshold: float) -> ChangeStatus:
    """Moved when the landmark's evidence fails the χ² test against the known feature
    (``statistic > threshold``), else confirmed: at the test's level a feature where
    the map has it is called moved with probability ``1 − level``."""
    return ChangeStatus.MOVED if statistic > threshold else ChangeStatus.CONFIRMED


# --- A known feature without one: a move beyond the association gate ------------


def link_scans_needed(params: ChangeParams) -> int:
    """Scans a surveyed place must be seen before a landmark near it is taken for the
    feature's move: :attr:`ChangeParams.link_min_scans`, at most ``min_scans`` (so that
    a feature seen long enough to be called missing is always looked for)."""
    return min(params.link_min_scans or params.min_scans, params.min_scans)


def looked_for_beyond_the_gate(kind: FeatureKind, sight: PlaceSight, params: ChangeParams) -> bool:
    """Whether a known feature without an associated landmark is looked for among the
    unassociated landmarks.  Yes when its surveyed place was predicted in view, seen
    empty or seen standing for :func:`link_scans_needed` scans (a trunk the beams hit at
    the surveyed place may be the tree moved by less than its reach, hiding its own
    surveyed place from the view model).  Otherwise only when its kind's
    ``link_unviewed_*`` setting is on: a feature not seen where the map has it, but
    never expected there either, has nothing saying it moved, and a landmark near a
    tree is as likely a tree the map lacks."""
    need = link_scans_needed(params)
    seen = (
        sight.scans_in_view >= need
        or sight.scans_seen_empty >= need
        or sight.scans_seen_occupied >= need
    )
    if seen:
        return True
    return params.link_unviewed_lines if kind == FeatureKind.LINE else params.link_unviewed_circles


@dataclass(frozen=True, eq=False)
class LinkCandidate:
    """An unassociated landmark within the move limits of a known feature without an
    associated landmark: perhaps that feature after a move beyond the association gate."""

    landmark: ObservationSet
    """The unassociated landmark."""
    known: KnownMapArrays
    """The known map."""
    row: int
    """The known feature's row in :attr:`known`."""
    sight: PlaceSight
    """What was seen of the known feature's surveyed place."""
    explains_an_observed_feature: bool
    """Whether the landmark is a duplicate of a known feature with an associated
    landmark (:func:`is_duplicate` against the tested features)."""
    params: ChangeParams
    """The settings."""

    @cached_property
    def passes_move_test(self) -> bool:
        """Whether the landmark passes the known feature's move test (is that feature,
        unmoved): computed once, when a veto asks."""
        return passes_move_test(self.landmark, self.known, self.row, self.params)

    @property
    def is_line(self) -> bool:
        """Whether the pair is of lines."""
        return self.landmark.kind == FeatureKind.LINE


def trunk_stands_where_surveyed(candidate: LinkCandidate) -> bool:
    """Veto: the raw scans found a trunk standing at the surveyed place (in
    :func:`link_scans_needed` scans, and more than saw it empty), and the landmark is
    beyond the reach of what those beams hit: the trunk is the tree itself, and the
    landmark another tree, not its move."""
    sight = candidate.sight
    standing = sight.scans_seen_occupied
    if not (standing >= link_scans_needed(candidate.params) and standing > sight.scans_seen_empty):
        return False
    return beyond_reach(
        candidate.landmark, candidate.known.params[candidate.row], sight.occupied_reach_m
    )


def another_stretch_of_the_line(candidate: LinkCandidate) -> bool:
    """Veto: a line landmark that fits the wall's line but lies beyond the wall's ends
    (:func:`~mapfuse_core.changes.relations.on_the_wall_itself`) is another stretch of
    the line, not this wall seen again nor moved along itself."""
    return (
        candidate.passes_move_test
        and candidate.is_line
        and not on_the_wall_itself(candidate.landmark, candidate.known, candidate.row)
    )


def duplicate_of_an_observed_feature(candidate: LinkCandidate) -> bool:
    """Veto: a landmark that an observed known feature already explains (another track
    of it) may confirm this feature too (two plan walls a wall's thickness apart), but
    is not its move."""
    return candidate.explains_an_observed_feature and not candidate.passes_move_test


def longer_than_this_wall(candidate: LinkCandidate) -> bool:
    """Veto: a wall moved keeps its length, so a line landmark that fails the wall's
    test and is longer than it
    (:func:`~mapfuse_core.changes.relations.longer_than_the_wall`) is another wall (a
    plan wall that does not stand, near one the plan lacks)."""
    return (
        candidate.is_line
        and not candidate.passes_move_test
        and longer_than_the_wall(candidate.landmark, candidate.known, candidate.row)
    )


#: The vetoes of a link, in the order they are asked; the move test they share is computed
#: once, by the first veto that needs it.
LINK_VETOES: tuple[Callable[[LinkCandidate], bool], ...] = (
    trunk_stands_where_surveyed,
    another_stretch_of_the_line,
    duplicate_of_an_observed_feature,
    longer_than_this_wall,
)


def link_vetoed(candidate: LinkCandidate) -> bool:
    """Whether any of :data:`LINK_VETOES` holds for ``candidate``."""
    return any(veto(candidate) for veto in LINK_VETOES)


def nearest_one_to_one(candidates: Iterable[tuple[float, int, int]]) -> list[tuple[int, int]]:
    """``(row, landmark)`` links from ``(move size, row, landmark)`` candidates: the
    smallest move first (equal moves by row, then landmark), each known row and each
    landmark in one link at most.  The smallest move is the likeliest explanation, and
    one landmark cannot be two features' moves."""
    linked_rows: set[int] = set()
    linked_landmarks: set[int] = set()
    links = []
    for _, row, landmark in sorted(candidates):
        if row in linked_rows or landmark in linked_landmarks:
            continue
        linked_rows.add(row)
        linked_landmarks.add(landmark)
        links.append((row, landmark))
    return links


# --- A known feature left without a landmark ------------------------------------


def needs_thinnest_view(kind: FeatureKind, scans_in_view: int, params: ChangeParams) -> bool:
    """Whether a known feature left without a landmark is viewed again at the thinnest
    radius its map σ allows (:attr:`ChangeParams.missing_radius_sigmas`): a tree
    predicted in view for ``min_scans`` scans.  A map that draws a trunk too thick
    predicts it extractable where the real, thinner trunk is not; missing asks the view
    to hold for any radius the map's error allows."""
    return kind == FeatureKind.CIRCLE and scans_in_view >= params.min_scans


def seen_absent(sight: PlaceSight, params: ChangeParams) -> bool:
    """Whether a known feature without a landmark was seen absent: predicted in view
    (a tree: at its thinnest) or seen empty for ``min_scans`` scans, and not seen
    standing for as many (the raw scans found it where the map has it, however many
    scans from poses further off than their σ saw the place empty)."""
    seen = sight.scans_in_view >= params.min_scans or sight.scans_seen_empty >= params.min_scans
    return seen and sight.scans_seen_occupied < params.min_scans


def status_without_landmark(sight: PlaceSight, params: ChangeParams) -> ChangeStatus:
    """Missing when :func:`seen_absent`, else unobserved."""
    return ChangeStatus.MISSING if seen_absent(sight, params) else ChangeStatus.UNOBSERVED


# --- The landmarks left ---------------------------------------------------------


def piece_of_a_moved_feature(change: FeatureChange) -> bool:
    """Whether a landmark within the move limits of known feature ``change`` is another
    piece of it because the feature is classified moved (a wall seen in pieces)."""
    return change.status == ChangeStatus.MOVED


def another_track_of_an_observed_feature(
    landmark: ObservationSet, known: KnownMapArrays, row: int, params: ChangeParams
) -> bool:
    """Whether ``landmark`` is another track of known feature ``row``, one the estimator
    did not merge: it passes the feature's move test and, a line, lies on the wall
    itself (:func:`~mapfuse_core.changes.relations.on_the_wall_itself`)."""
    if landmark.kind == FeatureKind.LINE and not on_the_wall_itself(landmark, known, row):
        return False
    return passes_move_test(landmark, known, row, params)


def duplicate_of(
    landmark: ObservationSet,
    known: KnownMapArrays,
    row: int,
    change: FeatureChange,
    params: ChangeParams,
) -> bool:
    """Whether ``landmark`` is accounted for by known feature ``row`` (classified
    ``change``): an observed feature of its kind within whose move limits it lies, and
    :func:`piece_of_a_moved_feature` or :func:`another_track_of_an_observed_feature`."""
    if change.kind != landmark.kind or change.n_obs == 0:
        return False
    size = move_size(
        landmark, known.params[row], known.covs[row], surveyed_extent(known, row), params
    )
    if not math.isfinite(size):
        return False
    return piece_of_a_moved_feature(change) or another_track_of_an_observed_feature(
        landmark, known, row, params
    )


def is_duplicate(
    landmark: ObservationSet,
    known: KnownMapArrays,
    changes: Mapping[int, FeatureChange],
    params: ChangeParams,
) -> bool:
    """Whether any classified known feature (row → change) accounts for ``landmark``
    (:func:`duplicate_of`): it is then neither new nor a change."""
    return any(
        duplicate_of(landmark, known, row, change, params) for row, change in changes.items()
    )
