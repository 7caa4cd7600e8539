"""Each rule of the change classification (:mod:`mapfuse_core.changes.rules`) on the
least evidence that triggers it, and on evidence just short of it.

Observations here are exact copies of one feature with a measurement σ of 5 cm (3
mrad for a line's angle) and no pose uncertainty, so a landmark passes or fails a
known feature's χ² test by construction: the known features carry a σ of 0.1 m
(0.05 rad), and a landmark 2 m off is 20 σ away.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mapfuse_core.changes import ChangeParams, ChangeStatus, FeatureChange
from mapfuse_core.changes.evidence import ObservationSet
from mapfuse_core.changes.rules import (
    LINK_VETOES,
    LinkCandidate,
    PlaceSight,
    another_stretch_of_the_line,
    another_track_of_an_observed_feature,
    duplicate_of,
    duplicate_of_an_observed_feature,
    enough_observations,
    estimate_to_read_through,
    is_duplicate,
    link_scans_needed,
    link_vetoed,
    longer_than_this_wall,
    looked_for_beyond_the_gate,
    nearest_one_to_one,
    needs_thinnest_view,
    piece_of_a_moved_feature,
    seen_absent,
    status_by_move_test,
    status_without_landmark,
    strongest_associated_landmarks,
    trunk_stands_where_surveyed,
    unassociated_landmarks,
)
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.measlog import KnownMapArrays

PARAMS = ChangeParams()
LINE, CIRCLE = FeatureKind.LINE, FeatureKind.CIRCLE
#: A known wall along x from 0 to 4 m, and a known tree of radius 0.5 m at (0, 10).
WALL, TREE = 0, 1


def _known(wall_extent: tuple[float, float] = (0.0, 4.0)) -> KnownMapArrays:
    return KnownMapArrays(
        ids=np.array([10, 11], dtype=np.int64),
        kinds=np.array([int(LINE), int(CIRCLE)], dtype=np.int8),
        params=np.array([[0.0, 0.0, 0.0], [0.0, 10.0, 0.5]]),
        covs=np.array([np.diag([0.01, 0.01, 0.0025]), np.diag([0.01, 0.01, 0.0001])]),
        extents=np.array([wall_extent, (np.nan, np.nan)]),
    )


def _landmark(
    kind: FeatureKind,
    feature: tuple[float, float, float],
    *,
    n: int = 5,
    extent: tuple[float, float] = (np.nan, np.nan),
    known_id: int = -1,
    landmark: int = 7,
    steps: np.ndarray | None = None,
) -> ObservationSet:
    """``n`` exact observations of ``feature`` (a line's with ``extent`` along it)."""
    sigma = [0.05, 0.05, 0.003] if kind == LINE else [0.05, 0.05, 0.05]
    return ObservationSet(
        landmark=landmark,
        known_id=known_id,
        kind=kind,
        features=np.tile(np.asarray(feature, dtype=float), (n, 1)),
        meas_covs=np.tile(np.diag(np.square(sigma)), (n, 1, 1)),
        pose_covs=np.zeros((n, 3, 3)),
        extents=np.tile(np.asarray(extent, dtype=float), (n, 1)),
        steps=np.arange(n) if steps is None else steps,
        true_id=-1,
    )


def _candidate(
    landmark: ObservationSet,
    row: int,
    sight: PlaceSight | None = None,
    *,
    explains: bool = False,
    known: KnownMapArrays | None = None,
) -> LinkCandidate:
    return LinkCandidate(
        landmark=landmark,
        known=_known() if known is None else known,
        row=row,
        sight=PlaceSight(scans_in_view=30) if sight is None else sight,
        explains_an_observed_feature=explains,
        params=PARAMS,
    )


def _change(kind: FeatureKind, status: ChangeStatus, n_obs: int = 5) -> FeatureChange:
    return FeatureChange(
        known_id=10,
        kind=kind,
        status=status,
        displacement=np.zeros(3),
        residual=np.zeros(2),
        residual_cov=np.eye(2),
        statistic=0.0,
        dof=2,
        threshold=13.8,
        n_obs=n_obs,
        scans_in_view=30,
        associated=True,
        landmark=1,
    )


# --- Evidence ---


def test_strongest_associated_landmark_is_the_one_with_most_observations():
    short = _landmark(CIRCLE, (0.0, 10.0, 0.5), n=3, known_id=11, landmark=1)
    long = _landmark(CIRCLE, (0.0, 10.0, 0.5), n=6, known_id=11, landmark=2)
    equal = _landmark(CIRCLE, (0.0, 10.0, 0.5), n=6, known_id=11, landmark=3)
    free = _landmark(CIRCLE, (5.0, 10.0, 0.5), n=9, known_id=-1, landmark=4)
    tested = strongest_associated_landmarks([short, long, equal, free])
    assert set(tested) == {11}
    # The first of equals stays; an unassociated landmark is never tested this way.
    assert tested[11].landmark == 2
    assert strongest_associated_landmarks([free]) == {}


def test_a_landmark_counts_from_min_obs_observations():
    assert enough_observations(_landmark(CIRCLE, (0, 0, 1), n=PARAMS.min_obs), PARAMS)
    assert not enough_observations(_landmark(CIRCLE, (0, 0, 1), n=PARAMS.min_obs - 1), PARAMS)


def test_a_landmark_seen_only_before_the_match_is_read_through_the_estimate():
    estimate = (np.array([1.0, 2.0, 0.5]), np.eye(3) * 0.01)
    estimates = {7: estimate}
    before = _landmark(CIRCLE, (1, 2, 0.5), steps=np.array([3, 5, 9]))
    assert estimate_to_read_through(before, PARAMS, 10, estimates) is estimate
    # Seen at the match step or later: its observations decide.
    also_after = _landmark(CIRCLE, (1, 2, 0.5), steps=np.array([3, 5, 10]))
    assert estimate_to_read_through(also_after, PARAMS, 10, estimates) is None
    off = dataclasses.replace(PARAMS, filter_estimates=False)
    assert estimate_to_read_through(before, off, 10, estimates) is None
    assert estimate_to_read_through(before, PARAMS, 10, None) is None
    assert estimate_to_read_through(before, PARAMS, 10, {8: estimate}) is None


def test_unassociated_landmarks_keep_the_counted_free_ones_in_order():
    estimate = (np.array([1.0, 2.0, 0.5]), np.eye(3) * 0.01)
    # Known id 0 is a known feature like any other.
    merged = _landmark(CIRCLE, (0, 10, 0.5), known_id=0, landmark=1)
    few = _landmark(CIRCLE, (4, 4, 0.5), n=2, landmark=2)
    early = _landmark(CIRCLE, (1, 2, 0.5), landmark=3, steps=np.arange(5))
    late = _landmark(CIRCLE, (6, 2, 0.5), landmark=4, steps=np.arange(20, 25))
    out = unassociated_landmarks([merged, few, early, late], PARAMS, 10, {3: estimate, 4: estimate})
    assert [s.landmark for s in out] == [3, 4]
    assert out[0].estimate is estimate
    assert out[1] is late


# --- A known feature with an associated landmark ---


def test_move_test_status_is_moved_above_the_threshold_only():
    assert status_by_move_test(13.9, 13.8) == ChangeStatus.MOVED
    assert status_by_move_test(13.8, 13.8) == ChangeStatus.CONFIRMED


# --- A move beyond the association gate ---


def test_link_scans_needed_is_link_min_scans_at_most_min_scans():
    assert link_scans_needed(PARAMS) == 8
    assert link_scans_needed(dataclasses.replace(PARAMS, link_min_scans=None)) == 20
    assert link_scans_needed(dataclasses.replace(PARAMS, link_min_scans=30)) == 20


@pytest.mark.parametrize(
    ("sight", "line", "circle"),
    [
        (PlaceSight(scans_in_view=8), True, True),
        (PlaceSight(scans_in_view=0, scans_seen_empty=8), True, True),
        (PlaceSight(scans_in_view=0, scans_seen_occupied=8), True, True),
        # Seen 7 scans each way: not enough; a wall is looked for anyway.
        (PlaceSight(scans_in_view=7, scans_seen_empty=7, scans_seen_occupied=7), True, False),
    ],
)
def test_a_feature_is_looked_for_beyond_the_gate_when_its_place_was_seen(sight, line, circle):
    assert looked_for_beyond_the_gate(LINE, sight, PARAMS) is line
    assert looked_for_beyond_the_gate(CIRCLE, sight, PARAMS) is circle


def test_unviewed_features_are_looked_for_as_their_kinds_setting_says():
    unseen = PlaceSight(scans_in_view=0)
    flipped = dataclasses.replace(PARAMS, link_unviewed_lines=False, link_unviewed_circles=True)
    assert not looked_for_beyond_the_gate(LINE, unseen, flipped)
    assert looked_for_beyond_the_gate(CIRCLE, unseen, flipped)


def test_a_trunk_standing_at_the_surveyed_place_vetoes_a_far_landmark():
    standing = PlaceSight(scans_in_view=0, scans_seen_occupied=10, occupied_reach_m=0.3)
    far = _landmark(CIRCLE, (3.0, 10.0, 0.5))
    near = _landmark(CIRCLE, (0.4, 10.0, 0.5))
    assert trunk_stands_where_surveyed(_candidate(far, TREE, standing))
    # Within the reach of the beams that hit (hypot(0.3, 0.5) + 0.5 m): the tree itself.
    assert not trunk_stands_where_surveyed(_candidate(near, TREE, standing))
    # Seen empty in more scans than standing, or standing in too few: no veto.
    emptier = dataclasses.replace(standing, scans_seen_empty=11)
    assert not trunk_stands_where_surveyed(_candidate(far, TREE, emptier))
    briefly = dataclasses.replace(standing, scans_seen_occupied=7)
    assert not trunk_stands_where_surveyed(_candidate(far, TREE, briefly))


def test_a_line_landmark_beyond_the_walls_ends_is_another_stretch_of_its_line():
    beyond = _landmark(LINE, (8.0, 0.0, 0.0), extent=(0.0, 2.0))
    on_it = _landmark(LINE, (1.0, 0.0, 0.0), extent=(0.0, 2.0))
    beside = _landmark(LINE, (8.0, 2.0, 0.0), extent=(0.0, 2.0))
    assert another_stretch_of_the_line(_candidate(beyond, WALL))
    assert not another_stretch_of_the_line(_candidate(on_it, WALL))
    # Off the line by 20 σ it fails the test: a move, not a stretch of this line.
    assert not another_stretch_of_the_line(_candidate(beside, WALL))


def test_a_duplicate_of_an_observed_feature_is_no_move_unless_it_fits_this_one():
    moved = _landmark(CIRCLE, (2.0, 10.0, 0.5))
    fits = _landmark(CIRCLE, (0.0, 10.0, 0.5))
    assert duplicate_of_an_observed_feature(_candidate(moved, TREE, explains=True))
    assert not duplicate_of_an_observed_feature(_candidate(fits, TREE, explains=True))
    assert not duplicate_of_an_observed_feature(_candidate(moved, TREE, explains=False))


def test_a_line_landmark_longer_than_the_wall_is_not_its_move():
    # The wall is 4 m long; a landmark 2 m beside it spanning 8 m is another wall.
    long = _landmark(LINE, (-2.0, 2.0, 0.0), extent=(0.0, 8.0))
    same_length = _landmark(LINE, (0.0, 2.0, 0.0), extent=(0.0, 4.0))
    long_on_it = _landmark(LINE, (-2.0, 0.0, 0.0), extent=(0.0, 8.0))
    assert longer_than_this_wall(_candidate(long, WALL))
    assert not longer_than_this_wall(_candidate(same_length, WALL))
    # One that passes the wall's test is the wall seen longer, not another wall.
    assert not longer_than_this_wall(_candidate(long_on_it, WALL))
    no_extent = _known((np.nan, np.nan))
    assert not longer_than_this_wall(_candidate(long, WALL, known=no_extent))


def test_a_link_is_vetoed_when_any_veto_holds():
    assert (
        trunk_stands_where_surveyed,
        another_stretch_of_the_line,
        duplicate_of_an_observed_feature,
        longer_than_this_wall,
    ) == LINK_VETOES
    moved = _landmark(CIRCLE, (2.0, 10.0, 0.5))
    assert not link_vetoed(_candidate(moved, TREE))
    assert link_vetoed(_candidate(moved, TREE, explains=True))


def test_links_pair_the_smallest_moves_first_one_to_one():
    # Row 0 is nearest landmark 1; row 1 then gets landmark 0, though farther.
    candidates = [(2.0, 0, 0), (1.0, 0, 1), (1.5, 1, 1), (3.0, 1, 0)]
    assert nearest_one_to_one(candidates) == [(0, 1), (1, 0)]
    # Equal moves: the lower row first, then the lower landmark.
    assert nearest_one_to_one([(1.0, 2, 0), (1.0, 1, 0), (1.0, 1, 1)]) == [(1, 0)]
    assert nearest_one_to_one([]) == []


# --- A known feature left without a landmark ---


def test_only_trees_predicted_in_view_long_enough_are_viewed_at_their_thinnest():
    assert needs_thinnest_view(CIRCLE, PARAMS.min_scans, PARAMS)
    assert not needs_thinnest_view(CIRCLE, PARAMS.min_scans - 1, PARAMS)
    assert not needs_thinnest_view(LINE, 10 * PARAMS.min_scans, PARAMS)


@pytest.mark.parametrize(
    ("sight", "status"),
    [
        (PlaceSight(scans_in_view=20), ChangeStatus.MISSING),
        (PlaceSight(scans_in_view=0, scans_seen_empty=20), ChangeStatus.MISSING),
        (PlaceSight(scans_in_view=19, scans_seen_empty=19), ChangeStatus.UNOBSERVED),
        # Seen standing in K scans: not absent, however often seen empty.
        (
            PlaceSight(scans_in_view=40, scans_seen_empty=40, scans_seen_occupied=20),
            ChangeStatus.UNOBSERVED,
        ),
        (PlaceSight(scans_in_view=40, scans_seen_occupied=19), ChangeStatus.MISSING),
    ],
)
def test_a_feature_without_landmark_is_missing_when_seen_absent(sight, status):
    assert seen_absent(sight, PARAMS) is (status == ChangeStatus.MISSING)
    assert status_without_landmark(sight, PARAMS) == status


# --- The landmarks left ---


def test_a_piece_of_a_moved_feature_is_a_landmark_near_one_classified_moved():
    assert piece_of_a_moved_feature(_change(LINE, ChangeStatus.MOVED))
    for status in (ChangeStatus.CONFIRMED, ChangeStatus.MISSING, ChangeStatus.UNOBSERVED):
        assert not piece_of_a_moved_feature(_change(LINE, status))


def test_another_track_passes_the_features_test_and_lies_on_the_wall_itself():
    known = _known()
    assert another_track_of_an_observed_feature(
        _landmark(CIRCLE, (0.0, 10.0, 0.5)), known, TREE, PARAMS
    )
    assert not another_track_of_an_observed_feature(
        _landmark(CIRCLE, (1.0, 10.0, 0.5)), known, TREE, PARAMS
    )
    assert another_track_of_an_observed_feature(
        _landmark(LINE, (1.0, 0.0, 0.0), extent=(0.0, 2.0)), known, WALL, PARAMS
    )
    # On the wall's line but past its end: another wall.
    assert not another_track_of_an_observed_feature(
        _landmark(LINE, (8.0, 0.0, 0.0), extent=(0.0, 2.0)), known, WALL, PARAMS
    )


def test_a_duplicate_lies_within_the_move_limits_of_an_observed_feature_of_its_kind():
    known = _known()
    moved = _change(CIRCLE, ChangeStatus.MOVED)
    near = _landmark(CIRCLE, (3.0, 10.0, 0.5))
    assert duplicate_of(near, known, TREE, moved, PARAMS)
    # Beyond max_move_m (6 m plus three of the tree's 0.1 m σ).
    far = _landmark(CIRCLE, (6.5, 10.0, 0.5))
    assert not duplicate_of(far, known, TREE, moved, PARAMS)
    # Not observed, or of another kind: accounts for nothing.
    assert not duplicate_of(near, known, TREE, _change(CIRCLE, ChangeStatus.MOVED, 0), PARAMS)
    assert not duplicate_of(near, known, TREE, _change(LINE, ChangeStatus.MOVED), PARAMS)
    # Near a confirmed feature, only another track of it is its duplicate.
    confirmed = _change(CIRCLE, ChangeStatus.CONFIRMED)
    assert not duplicate_of(near, known, TREE, confirmed, PARAMS)
    assert duplicate_of(_landmark(CIRCLE, (0, 10, 0.5)), known, TREE, confirmed, PARAMS)


def test_a_landmark_is_a_duplicate_when_any_classified_feature_accounts_for_it():
    known = _known()
    near = _landmark(CIRCLE, (3.0, 10.0, 0.5))
    changes = {WALL: _change(LINE, ChangeStatus.MOVED), TREE: _change(CIRCLE, ChangeStatus.MOVED)}
    assert is_duplicate(near, known, changes, PARAMS)
    assert not is_duplicate(near, known, {WALL: changes[WALL]}, PARAMS)
    assert not is_duplicate(near, known, {}, PARAMS)
