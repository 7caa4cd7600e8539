"""Known-map change classification on small synthetic logs with the true decisions
and trajectory, so that each class is checked apart from any estimator."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapfuse_core.changes import (
    ChangeParams,
    ChangeStatus,
    classify_changes,
    feature_residual,
)
from mapfuse_core.geometry.features import FeatureKind, transform_feature
from mapfuse_core.geometry.se2 import compose, inverse, relative
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog
from mapfuse_core.sim.map_changes import with_changes
from mapfuse_core.sim.scenario import load_scenario
from tests.synthetic import synthetic_log

PARAMS = ChangeParams(max_range_m=25.0)


def _log() -> MeasurementLog:
    return synthetic_log(steps=300, seed=3, known_fraction=0.7)


def _classify(
    log: MeasurementLog,
    params: ChangeParams = PARAMS,
    anchor_offset=None,
    unassociated: int | None = None,
):
    """Classify with the true decisions and the true trajectory (tiny pose covariance).

    ``unassociated``: a known id the estimator never associated, so that its
    observations form an unlinked landmark."""
    lm, kn = _true_decisions(log, unassociated)
    start, poses, covs = _true_trajectory(log)
    anchor = start if anchor_offset is None else compose(anchor_offset, start)
    return classify_changes(log, lm, kn, poses, covs, anchor, params)


def _true_decisions(log: MeasurementLog, unassociated: int | None = None):
    """The true decisions: every observation its world feature's landmark, merged with
    the known feature of that id unless it is ``unassociated``."""
    known = set(log.known_map.ids.tolist()) - {unassociated}
    lm = log.feat_true_id.copy()
    kn = np.array([i if i in known else -1 for i in lm.tolist()], dtype=np.int64)
    return lm, kn


def _true_trajectory(log: MeasurementLog):
    """The true start pose, the true poses relative to it, and a tiny covariance."""
    start = log.true_poses[0]
    poses = np.array([relative(start, p)[0] for p in log.true_poses])
    covs = np.tile(np.eye(3) * 1e-6, (poses.shape[0], 1, 1))
    return start, poses, covs


def _replace_known(log: MeasurementLog, **fields) -> MeasurementLog:
    k = log.known_map
    new = KnownMapArrays(
        ids=fields.get("ids", k.ids),
        kinds=fields.get("kinds", k.kinds),
        params=fields.get("params", k.params),
        covs=fields.get("covs", k.covs),
        extents=fields.get("extents", k.extents),
    )
    return dataclasses.replace(log, known_map=new)


def test_unchanged_map_is_confirmed_where_observed():
    rep = _classify(_log())
    counts = rep.counts()
    # At level 0.999 a consistent feature fails with probability 1e-3; none of ~20 here.
    assert counts["moved"] == 0
    assert counts["missing"] == 0
    assert counts["confirmed"] >= 15
    # Every world feature the map lacks is seen, so it is new.
    log = _log()
    absent = set(log.world.ids.tolist()) - set(log.known_map.ids.tolist())
    assert {n.true_id for n in rep.new} == absent


def test_moved_circle_and_turned_line_are_moved_with_their_displacement():
    log = _log()
    p = log.known_map.params.copy()
    circ = int(np.nonzero(log.known_map.kinds == FeatureKind.CIRCLE)[0][0])
    line = int(np.nonzero(log.known_map.kinds == FeatureKind.LINE)[0][0])
    p[circ, :2] += (0.6, -0.3)
    p[line, 2] += 0.3
    rep = _classify(_replace_known(log, params=p))
    c = rep.known[circ]
    assert c.status == ChangeStatus.MOVED
    # The map holds the feature 0.6, -0.3 off: the evidence puts it back (map σ 0.1 m).
    assert c.displacement[:2] == pytest.approx([-0.6, 0.3], abs=0.3)
    assert c.statistic > c.threshold
    ln = rep.known[line]
    assert ln.status == ChangeStatus.MOVED
    assert ln.displacement[2] == pytest.approx(-0.3, abs=0.1)
    others = [k for i, k in enumerate(rep.known) if i not in (circ, line)]
    assert all(k.status != ChangeStatus.MOVED for k in others)


def _most_in_view(log: MeasurementLog, kind: FeatureKind) -> int:
    """Index of the known feature of ``kind`` predicted in view the most scans."""
    rep = _classify(log)
    rows = [i for i, c in enumerate(rep.known) if c.kind == kind]
    return max(rows, key=lambda i: rep.known[i].scans_in_view)


def _most_viewed_tree_surveyed_3m_off() -> tuple[MeasurementLog, int, int]:
    """The test log with the known tree most in view surveyed 3 m off along x: the log,
    the tree's row and its id."""
    log = _log()
    circ = _most_in_view(log, FeatureKind.CIRCLE)
    p = log.known_map.params.copy()
    p[circ, :2] += (3.0, 0.0)
    return _replace_known(log, params=p), circ, int(log.known_map.ids[circ])


def test_move_beyond_the_gate_links_the_unassociated_landmark():
    moved, circ, kid = _most_viewed_tree_surveyed_3m_off()
    # The estimator did not associate it: its observations stay unlinked.
    rep = _classify(moved, unassociated=kid)
    c = rep.known[circ]
    # Predicted in view where the map has it, not seen there: the landmark is its move.
    assert c.scans_in_view >= PARAMS.min_scans
    assert c.status == ChangeStatus.MOVED
    assert not c.associated
    assert c.displacement[0] == pytest.approx(-3.0, abs=0.3)
    assert kid not in {n.true_id for n in rep.new}


def _with_phantom(
    log: MeasurementLog, like: int, params: np.ndarray, extent: tuple[float, float]
) -> tuple[MeasurementLog, int]:
    """``log`` whose known map also has a feature of known feature ``like``'s kind and σ
    at ``params`` (with ``extent``) that the world lacks, and that feature's id."""
    k = log.known_map
    a_id = int(max(k.ids.max(), log.world.ids.max())) + 1
    out = _replace_known(
        log,
        ids=np.append(k.ids, a_id),
        kinds=np.append(k.kinds, k.kinds[like]),
        params=np.vstack((k.params, params)),
        covs=np.concatenate((k.covs, k.covs[like][None]), axis=0),
        extents=None if k.extents is None else np.vstack((k.extents, extent)),
    )
    return out, a_id


def _with_phantom_circle(log: MeasurementLog, near: int, offset: tuple[float, float]):
    """``log`` whose known map also has a circle ``offset`` from known circle ``near``
    that the world lacks, and that circle's id."""
    at = log.known_map.params[near] + np.array([*offset, 0.0])
    return _with_phantom(log, near, at, (np.nan, np.nan))


def _classify_with_a_second_track(
    log: MeasurementLog, known_ids: set[int], split: int, params: ChangeParams
):
    """Classify with the true decisions and trajectory, but with the second half of
    known feature ``split``'s observations a separate landmark that the estimator
    never associated; only ``known_ids`` are associated."""
    lm = log.feat_true_id.copy()
    kn = np.array([i if i in known_ids else -1 for i in lm.tolist()], dtype=np.int64)
    of = np.flatnonzero(lm == split)
    second = of[of.size // 2 :]
    lm[second] = 10**6
    kn[second] = -1
    start, poses, covs = _true_trajectory(log)
    return classify_changes(log, lm, kn, poses, covs, start, params)


def test_a_second_track_of_an_observed_tree_is_not_the_move_of_a_missing_one():
    """The estimator splits an observed tree B into two landmarks, the second never
    associated; the map also has a tree A, 4 m from B (within ``max_move_m``), that the
    world lacks.  The second track is B's (consistent with it), so it is neither A's
    move nor a new tree: A, predicted in view and never seen, is missing."""
    log = _log()
    # This short drive sees each tree in few of the scans the view rule samples.
    params = dataclasses.replace(PARAMS, min_scans=8)
    b = _most_in_view(log, FeatureKind.CIRCLE)
    b_id = int(log.known_map.ids[b])
    # The side of B from which the drive sees the phantom longest.
    offsets = [(4.0, 0.0), (-4.0, 0.0), (0.0, 4.0), (0.0, -4.0)]
    views = []
    for off in offsets:
        ph, a_id = _with_phantom_circle(log, b, off)
        rep = _classify(ph, params)
        views.append(next(c for c in rep.known if c.known_id == a_id).scans_in_view)
    phantom, a_id = _with_phantom_circle(log, b, offsets[int(np.argmax(views))])
    rep = _classify_with_a_second_track(phantom, set(log.known_map.ids.tolist()), b_id, params)
    a = next(c for c in rep.known if c.known_id == a_id)
    assert a.scans_in_view >= params.min_scans
    assert a.status == ChangeStatus.MISSING
    assert next(c for c in rep.known if c.known_id == b_id).status == ChangeStatus.CONFIRMED
    assert b_id not in {n.true_id for n in rep.new}
    assert rep.duplicates >= 1


def test_a_wall_further_along_the_line_of_an_observed_one_is_not_confirmed_by_it():
    """The map has a wall A on the line of an observed wall B but 3 m past B's end, and
    the world lacks A; the estimator splits B into two landmarks, the second never
    associated.  The second track fits A's line but lies beyond A's ends: it is B's
    duplicate, and A, never seen itself, is not confirmed."""
    log = _log()
    b = _most_in_view(log, FeatureKind.LINE)
    k = log.known_map
    assert k.extents is not None
    b_id = int(k.ids[b])
    lo, hi = (float(v) for v in k.extents[b])
    th = float(k.params[b, 2])
    u = np.array([math.cos(th), math.sin(th)])
    a_params = np.array([*(k.params[b, :2] + (hi + 4.0) * u), th])
    phantom, a_id = _with_phantom(log, b, a_params, (-1.0, 1.0))
    rep = _classify_with_a_second_track(phantom, set(k.ids.tolist()), b_id, PARAMS)
    a = next(c for c in rep.known if c.known_id == a_id)
    assert hi - lo > 0.0
    assert a.status != ChangeStatus.CONFIRMED
    assert a.landmark != 10**6
    assert next(c for c in rep.known if c.known_id == b_id).status == ChangeStatus.CONFIRMED
    assert rep.duplicates >= 1
    assert b_id not in {n.true_id for n in rep.new}


def _least_viewed_tree_surveyed_3m_off() -> tuple[MeasurementLog, int, int]:
    """The test log with its least-viewed known tree (in view under ``min_scans``)
    surveyed 3 m off along x: the log, the tree's row and its id."""
    log = _log()
    rep0 = _classify(log)
    circ = min(
        (i for i, c in enumerate(rep0.known) if c.kind == FeatureKind.CIRCLE),
        key=lambda i: rep0.known[i].scans_in_view,
    )
    assert rep0.known[circ].scans_in_view < PARAMS.min_scans
    p = log.known_map.params.copy()
    p[circ, :2] += (3.0, 0.0)
    return _replace_known(log, params=p), circ, int(log.known_map.ids[circ])


def test_landmark_near_a_known_feature_never_in_view_is_new_not_its_move():
    """A known tree never predicted in view, and an unassociated tree 3 m from it: the
    landmark may be a tree the map lacks, so it is new and the known one unobserved."""
    moved, circ, kid = _least_viewed_tree_surveyed_3m_off()
    rep = _classify(moved, unassociated=kid)
    assert rep.known[circ].status == ChangeStatus.UNOBSERVED
    assert kid in {n.true_id for n in rep.new}


def test_link_unviewed_circles_takes_the_nearest_landmark_for_the_trees_move():
    """The tree of the test above, never in view where the map has it, with
    ``link_unviewed_circles``: its landmark 3 m away is its move, not a new tree."""
    moved, circ, kid = _least_viewed_tree_surveyed_3m_off()
    linked = _classify(
        moved, dataclasses.replace(PARAMS, link_unviewed_circles=True), unassociated=kid
    )
    c = linked.known[circ]
    assert c.status == ChangeStatus.MOVED
    assert not c.associated
    # The map holds it 3 m off along x; the landmark puts it back (map σ 0.1 m).
    assert c.displacement[:2] == pytest.approx([-3.0, 0.0], abs=0.3)
    assert kid not in {n.true_id for n in linked.new}


def test_link_min_scans_above_k_links_whatever_is_seen_long_enough_to_be_missing():
    """``link_min_scans`` larger than ``min_scans`` acts as ``min_scans``: a tree in
    view long enough to be called missing is always looked for, so its landmark 3 m
    away is its move."""
    moved, circ, kid = _most_viewed_tree_surveyed_3m_off()
    rep = _classify(moved, dataclasses.replace(PARAMS, link_min_scans=10**6), unassociated=kid)
    c = rep.known[circ]
    assert c.scans_in_view >= PARAMS.min_scans
    assert c.status == ChangeStatus.MOVED
    assert kid not in {n.true_id for n in rep.new}


def test_link_needs_only_link_min_scans_in_view_not_the_missing_rules_k():
    """A tree in view for fewer scans than ``K`` (here ``K`` is out of reach) and
    never associated: with ``link_min_scans`` of 1 its landmark 3 m away is its move,
    with ``link_min_scans=None`` (``K``) the tree is unobserved and the landmark new."""
    blind = dataclasses.replace(PARAMS, min_scans=10**6)
    moved, circ, kid = _most_viewed_tree_surveyed_3m_off()
    short = _classify(moved, dataclasses.replace(blind, link_min_scans=1), unassociated=kid)
    c = short.known[circ]
    assert 1 <= c.scans_in_view < blind.min_scans
    assert c.status == ChangeStatus.MOVED
    assert c.displacement[:2] == pytest.approx([-3.0, 0.0], abs=0.3)
    assert kid not in {n.true_id for n in short.new}
    strict = _classify(moved, dataclasses.replace(blind, link_min_scans=None), unassociated=kid)
    assert strict.known[circ].status == ChangeStatus.UNOBSERVED
    assert kid in {n.true_id for n in strict.new}


def test_wall_never_predicted_in_view_is_linked_to_its_unassociated_landmark():
    """No feature reaches ``min_scans`` here; a wall surveyed 2 m beside where it stands,
    never associated, is that wall moved (a landmark parallel to it and overlapping it
    along its length), and with the linking off it is unobserved and its landmark new."""
    log = _log()
    blind = dataclasses.replace(PARAMS, min_scans=10**6, link_min_scans=None)
    line = _most_in_view(log, FeatureKind.LINE)
    kid = int(log.known_map.ids[line])
    p = log.known_map.params.copy()
    th = float(p[line, 2])
    p[line, :2] += 2.0 * np.array([-math.sin(th), math.cos(th)])
    moved = _replace_known(log, params=p)
    rep = _classify(moved, blind, unassociated=kid)
    c = rep.known[line]
    # In view long enough for the view rule at the default K: only min_scans (and with
    # it link_min_scans) keeps that rule from linking it, so the link comes from
    # link_unviewed_lines.
    assert c.scans_in_view >= PARAMS.min_scans
    assert c.status == ChangeStatus.MOVED
    assert not c.associated
    assert math.hypot(*c.displacement[:2]) == pytest.approx(2.0, abs=0.3)
    assert kid not in {n.true_id for n in rep.new}
    off = _classify(moved, dataclasses.replace(blind, link_unviewed_lines=False), unassociated=kid)
    assert off.known[line].status == ChangeStatus.UNOBSERVED
    assert kid in {n.true_id for n in off.new}


def test_short_wall_is_not_moved_onto_a_longer_unmapped_wall():
    """The map has a wall of 1 m (its σ 0.1 m) 2 m beside a longer wall it lacks, never
    associated: a wall moved keeps its length, so the longer landmark is not its move.
    The short wall is missing or unobserved and the long one new; the same long wall
    surveyed 2 m off at its own length is that wall, moved."""
    log = _log()
    line = _most_in_view(log, FeatureKind.LINE)
    kid = int(log.known_map.ids[line])
    assert log.known_map.extents is not None
    lo, hi = (float(v) for v in log.known_map.extents[line])
    assert hi - lo > 1.0 + 6.0 * 0.1 + 0.5
    p = log.known_map.params.copy()
    th = float(p[line, 2])
    p[line, :2] += 2.0 * np.array([-math.sin(th), math.cos(th)])
    ext = log.known_map.extents.copy()
    mid = 0.5 * (lo + hi)
    ext[line] = (mid - 0.5, mid + 0.5)
    short = _classify(_replace_known(log, params=p, extents=ext), unassociated=kid)
    c = short.known[line]
    assert c.status in (ChangeStatus.MISSING, ChangeStatus.UNOBSERVED)
    assert kid in {n.true_id for n in short.new}
    full = _classify(_replace_known(log, params=p), unassociated=kid)
    assert full.known[line].status == ChangeStatus.MOVED
    assert kid not in {n.true_id for n in full.new}
    # Surveyed 0.4 m short (within six of the map's σ of 0.1 m in all, the pose σ
    # being tiny here), the wall is still linked: the margin allows for the survey.
    ext_short = log.known_map.extents.copy()
    ext_short[line] = (lo + 0.2, hi - 0.2)
    near = _classify(_replace_known(log, params=p, extents=ext_short), unassociated=kid)
    assert near.known[line].status == ChangeStatus.MOVED


def test_turn_beyond_max_turn_but_within_the_maps_own_angle_sigma_links_the_landmark():
    """A line surveyed 0.42 rad off (max_turn_rad 0.35 plus under 3 of the map's
    σθ = 0.05 rad) and not associated by the estimator is that line, moved."""
    log = _log()
    line = _most_in_view(log, FeatureKind.LINE)
    kid = int(log.known_map.ids[line])
    assert math.sqrt(log.known_map.covs[line, 2, 2]) == pytest.approx(0.05)
    p = log.known_map.params.copy()
    p[line, 2] += 0.42
    moved = _replace_known(log, params=p)
    rep = _classify(moved, unassociated=kid)
    c = rep.known[line]
    assert c.status == ChangeStatus.MOVED
    assert not c.associated
    assert c.displacement[2] == pytest.approx(-0.42, abs=0.05)
    assert kid not in {n.true_id for n in rep.new}
    # Without the widening (a map that claims exact angles) the search gives up.
    exact = moved.known_map.covs.copy()
    exact[line, 2, 2] = 1e-12
    rep2 = _classify(_replace_known(moved, covs=exact), unassociated=kid)
    assert rep2.known[line].status in (ChangeStatus.MISSING, ChangeStatus.UNOBSERVED)
    assert kid in {n.true_id for n in rep2.new}


def _with_absent_trees(radius: float, sigma_r: float) -> MeasurementLog:
    """The test log with two trees of ``radius`` (σ 0.1 m, radius σ ``sigma_r``) in its
    known map and not in its world: 8 m inside the driven circle (in view for many
    scans) and 200 m away."""
    log = _log()
    k = log.known_map
    start = log.true_poses[0]
    near = compose(start, np.array([8.0, 0.0, 0.0]))
    trees = np.array([[near[0], near[1], radius], [start[0] + 200.0, start[1], radius]])
    return _replace_known(
        log,
        ids=np.concatenate([k.ids, [9001, 9002]]),
        kinds=np.concatenate([k.kinds, [1, 1]]).astype(np.int8),
        params=np.vstack([k.params, trees]),
        covs=np.vstack([k.covs, np.tile(np.diag([0.01, 0.01, sigma_r**2]), (2, 1, 1))]),
        extents=np.vstack([k.extents, np.full((2, 2), np.nan)]),
    )


def test_removed_feature_in_view_is_missing_and_one_out_of_view_unobserved():
    rep = _classify(_with_absent_trees(0.8, 0.01))
    assert rep.status_of(9001) == ChangeStatus.MISSING
    assert rep.known[-2].scans_in_view >= PARAMS.min_scans
    assert rep.status_of(9002) == ChangeStatus.UNOBSERVED


def test_a_tree_the_map_may_draw_too_thick_to_be_seen_is_not_called_missing():
    """Mapped 0.8 m with a radius σ of 0.15 m, the tree may really be under 0.4 m,
    too thin for the extractor at that range: its absence is no evidence at the
    default margin (3.09 σ at level 0.999), and is with no margin."""
    log = _with_absent_trees(0.8, 0.15)
    rep = _classify(log)
    assert rep.status_of(9001) == ChangeStatus.UNOBSERVED
    assert rep.known[-2].scans_in_view < PARAMS.min_scans
    bare = _classify(log, dataclasses.replace(PARAMS, missing_radius_sigmas=0.0))
    assert bare.status_of(9001) == ChangeStatus.MISSING
    assert bare.known[-2].scans_in_view >= PARAMS.min_scans


def test_missing_radius_margin_follows_the_level_and_rejects_bad_values():
    assert PARAMS.radius_margin_sigmas() == pytest.approx(3.0902, abs=1e-4)
    assert ChangeParams(missing_radius_sigmas=1.5).radius_margin_sigmas() == 1.5
    for bad in (-1.0, math.nan, math.inf, True):
        with pytest.raises(ValueError, match="missing_radius_sigmas"):
            ChangeParams(missing_radius_sigmas=bad)


def test_shifted_map_is_confirmed_through_the_anchor():
    """A map shifted as a whole is a change of its frame: without GPS the anchor takes
    it, so nothing is moved."""
    log = _log()
    T = np.array([4.0, -2.0, 0.2])
    k = log.known_map
    p = np.array(
        [
            transform_feature(FeatureKind(int(kd)), inverse(T), x)[0]
            for kd, x in zip(k.kinds, k.params, strict=False)
        ]
    )
    rep = _classify(_replace_known(log, params=p), anchor_offset=inverse(T))
    assert rep.counts()["moved"] == 0
    assert rep.counts()["confirmed"] >= 15


def test_empty_intersection_is_all_unobserved():
    log = _log()
    k = log.known_map
    far = k.params.copy()
    far[:, :2] += 1000.0
    rep = _classify(_replace_known(log, params=far, ids=k.ids + 10_000))
    assert rep.counts()["unobserved"] == len(k)
    assert rep.counts()["moved"] == rep.counts()["confirmed"] == rep.counts()["missing"] == 0
    assert len(rep.new) == len({i for i in log.feat_true_id.tolist()})


def test_map_that_is_all_changes_is_all_moved():
    log = _log()
    k = log.known_map
    p = k.params.copy()
    rng = np.random.default_rng(5)
    a = rng.uniform(-math.pi, math.pi, len(k))
    p[:, 0] += 1.0 * np.cos(a)
    p[:, 1] += 1.0 * np.sin(a)
    rep = _classify(_replace_known(log, params=p))
    observed = [c for c in rep.known if c.n_obs > 0]
    assert len(observed) >= 15
    # A line moved along itself is not a change of it; only those moved across it count.
    for c, ang in zip(rep.known, a, strict=True):
        if c.n_obs == 0:
            continue
        if c.kind == FeatureKind.LINE:
            th = k.params[[x.known_id for x in rep.known].index(c.known_id), 2]
            if abs(math.sin(ang - th)) < 0.5:
                continue
        assert c.status == ChangeStatus.MOVED, c.known_id


@settings(max_examples=60, deadline=None)
@given(
    st.floats(-20, 20),
    st.floats(-20, 20),
    st.sampled_from([math.pi - 1e-3, -math.pi + 1e-3, 0.3, -2.0]),
    st.floats(-3, 3),
    st.floats(-3, 3),
    st.floats(-0.5, 0.5),
)
def test_line_residual_jacobians_match_numerical_derivatives(x, y, th, ax, ay, dth):
    ref = np.array([x, y, th])
    f = np.array([x + ax, y + ay, th + dth])
    _r, Ja, Jb = feature_residual(FeatureKind.LINE, ref, f)
    eps = 1e-6
    for J, base, which in ((Ja, ref, 0), (Jb, f, 1)):
        num = np.zeros((2, 3))
        for i in range(3):
            d = np.zeros(3)
            d[i] = eps
            args_p = (base + d, f) if which == 0 else (ref, base + d)
            args_m = (base - d, f) if which == 0 else (ref, base - d)
            rp = feature_residual(FeatureKind.LINE, *args_p)[0]
            rm = feature_residual(FeatureKind.LINE, *args_m)[0]
            num[:, i] = (rp - rm) / (2 * eps)
        assert np.allclose(J, num, atol=1e-5)


def test_line_residual_ignores_sliding_along_the_line():
    ref = np.array([1.0, 2.0, 0.4])
    f = np.array([1.0, 2.5, 0.45])
    r0 = feature_residual(FeatureKind.LINE, ref, f)[0]
    slid = compose(f, np.array([3.0, 0.0, 0.0]))
    assert feature_residual(FeatureKind.LINE, ref, slid)[0] == pytest.approx(r0, abs=1e-12)


def test_with_changes_draws_disjoint_changes_of_the_asked_size():
    sc = load_scenario("loop600")
    out = with_changes(sc, np.random.default_rng(1), moved=0.2, removed=0.1, added=0.1)
    spec = out.known_map
    n = len(sc.known_map.world_ids)
    assert len(spec.moved) == round(0.2 * n)
    assert len(spec.removed) == round(0.1 * n)
    assert len(spec.added) == len(sc.known_map.added) + round(0.1 * n)
    moved = {m.id for m in spec.moved}
    removed = {f.id for f in spec.removed}
    assert not moved & removed
    assert not moved & set(spec.added)
    assert not removed & set(out.world.ids)
    for m in spec.moved:
        assert 0.3 - 1e-9 <= math.hypot(m.dx, m.dy) <= 5.0 + 1e-9
        kind, _ = sc.world.feature(m.id)
        if kind == FeatureKind.LINE:
            assert 0.05 - 1e-9 <= abs(m.dtheta) <= 0.3 + 1e-9


def test_with_changes_rejects_bad_fractions():
    sc = load_scenario("loop600")
    with pytest.raises(ValueError, match="moved must be in"):
        with_changes(sc, np.random.default_rng(0), moved=1.5)
    with pytest.raises(ValueError, match="changes asked"):
        with_changes(sc, np.random.default_rng(0), moved=0.6, removed=0.6)


def test_change_params_reject_bad_values():
    with pytest.raises(ValueError, match="level"):
        ChangeParams(level=1.0)
    with pytest.raises(ValueError, match="min_scans"):
        ChangeParams(min_scans=0)
    with pytest.raises(ValueError, match="link_unviewed_lines must be a bool"):
        ChangeParams(link_unviewed_lines=1)  # type: ignore[arg-type]
    for bad in (0, -1, 1.5, True, "8"):
        with pytest.raises(ValueError, match="link_min_scans must be None or an int"):
            ChangeParams(link_min_scans=bad)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="link_unviewed_circles must be a bool"):
        ChangeParams(link_unviewed_circles="yes")  # type: ignore[arg-type]


def test_classify_rejects_decisions_of_another_log():
    log = _log()
    with pytest.raises(ValueError, match="decisions hold"):
        classify_changes(
            log,
            np.zeros(3, np.int64),
            np.zeros(3, np.int64),
            log.true_poses,
            np.zeros((log.n_steps, 3, 3)),
            np.zeros(3),
        )


@pytest.mark.slow
def test_changes_command_writes_json_and_png_with_a_score(tmp_path):
    import json

    from mapfuse.cli import main

    out = tmp_path / "ch"
    code = main(
        [
            "changes",
            "loop600",
            "--steps",
            "240",
            "--moved",
            "0.1",
            "--removed",
            "0.05",
            "--change-seed",
            "2",
            "--out",
            str(out),
            "--quiet",
        ]
    )
    assert code == 0
    d = json.loads((out / "changes.json").read_text())
    assert (out / "changes.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert {"known", "new", "counts", "score", "truth", "level"} <= set(d)
    assert len(d["known"]) == sum(
        d["counts"][k] for k in ("confirmed", "moved", "missing", "unobserved", "inconclusive")
    )
    assert d["verdict"] in ("conclusive", "inconclusive")
    assert d["consistency"]["evidence"] == "reference NEES"
    # Every true move and removal is named in the truth section.
    assert len(d["truth"]["moved"]) == round(0.1 * 63)
    assert len(d["truth"]["removed"]) == 3


def test_changes_command_refuses_to_perturb_a_log(tmp_path):
    from mapfuse.cli import main

    assert main(["changes", "x.npz", "--moved", "0.1", "--out", str(tmp_path)]) == 2


def test_a_line_moved_along_itself_is_not_a_significant_move():
    from mapfuse_core.evaluation.change_truth import ChangeTruth

    truth = ChangeTruth(
        moved={1: (2.0, 0.0, 0.0, 0.0), 2: (0.0, 0.6, 0.0, 0.0), 3: (0.0, 0.0, 0.12, 0.0)},
        lateral={1: 0.0, 2: 0.6, 3: 0.0},
        removed=(),
        removed_in_view=(),
        added=(),
        added_observed=(),
        observed=(1, 2, 3),
    )
    assert not truth.significant_move(1, 0.5, 0.1)
    assert truth.significant_move(2, 0.5, 0.1)
    assert truth.significant_move(3, 0.5, 0.1)


def _change(kid: int, status: ChangeStatus) -> object:
    from mapfuse_core.changes.report import FeatureChange

    z = np.zeros(3)
    return FeatureChange(
        known_id=kid,
        kind=FeatureKind.LINE,
        status=status,
        displacement=z,
        residual=z[:2],
        residual_cov=np.eye(2),
        statistic=0.0,
        dof=2,
        threshold=1.0,
        n_obs=5,
        scans_in_view=10,
        associated=True,
        landmark=-1,
    )


def test_truth_names_the_moves_whose_surveyed_place_came_into_view():
    """Two walls in view of the drive: one surveyed 1 m across itself, one 500 m off.
    Only the first one's surveyed place comes into view; the score counts the moves of
    each kind apart."""
    from mapfuse_core.changes.report import ChangeReport
    from mapfuse_core.changes.visibility import scans_in_view, world_as_map
    from mapfuse_core.evaluation.change_truth import change_truth, score_changes
    from mapfuse_core.sim.scenario import FeatureMove
    from mapfuse_core.sim.simulate import simulate

    base = dataclasses.replace(load_scenario("loop600"), steps=300)
    params = ChangeParams().with_sensor(base.laser)
    poses = simulate(base, seed=0, workers=1).log.true_poses
    assert poses is not None
    counts = scans_in_view(world_as_map(base.world), poses, params)
    known = set(base.known_map.ids)
    walls = [w for w in base.world.segments if w.id in known and counts[w.id] >= 60]
    near, far = walls[:2]
    theta = near.spmap()[2]
    normal = (-math.sin(theta), math.cos(theta))
    moves = (
        FeatureMove(near.id, normal[0], normal[1], 0.0, 0.0),
        FeatureMove(far.id, 0.0, 500.0, 0.0, 0.0),
    )
    sc = dataclasses.replace(base, known_map=dataclasses.replace(base.known_map, moved=moves))
    log = simulate(sc, seed=0, workers=1).log
    truth = change_truth(sc, log, params)
    assert truth.moved_surveyed_in_view == (near.id,)
    assert {near.id, far.id} <= set(truth.observed)
    report = ChangeReport(
        known=(_change(near.id, ChangeStatus.MOVED), _change(far.id, ChangeStatus.CONFIRMED)),  # type: ignore[arg-type]
        new=(),
        duplicates=0,
        level=0.999,
        x_Wknown_Wglobal=np.zeros(3),
    )
    s = score_changes(report, truth).as_dict()
    assert (s["moved"]["tp"], s["moved"]["fn"]) == (1, 1)
    assert s["moved_surveyed_in_view"] == {"tp": 1, "fn": 0, "recall": 1.0}


@pytest.mark.parametrize(
    ("estimator", "estimate", "before_map"),
    [("ekf", "filtered", True), ("fixedlag", "smoothed", True), ("batch", "smoothed", False)],
)
def test_detect_changes_gives_the_anchor_covariance_where_poses_predate_the_match(
    monkeypatch, estimator, estimate, before_map
):
    """A filter's poses up to its match step (the match follows that step's update),
    and a fixed-lag smoother's that left its window before the match, carry the
    anchor's uncertainty; a batch smoother's were estimated with the known map.
    ``detect_changes`` passes the anchor's covariance, and the first step after the
    match, for the first two only."""
    import types

    import mapfuse.changes as mc

    seen = {}

    def spy(*args, **kwargs):
        seen.update(kwargs)
        return "report"

    monkeypatch.setattr(mc, "classify_changes", spy)
    monkeypatch.setattr(mc, "withhold_changes", lambda report, consistency: report)
    anchor = types.SimpleNamespace(
        x_Wknown_Wglobal=np.zeros(3), cov=np.eye(3) * 0.04, accepted_at_step=77
    )
    decisions = types.SimpleNamespace(arrays=(np.zeros(2, np.int64), np.zeros(2, np.int64)))
    result = types.SimpleNamespace(
        estimator=estimator,
        fusion=True,
        anchor=anchor,
        decisions=decisions,
        poses=np.zeros((5, 3)),
        covs=np.zeros((5, 3, 3)),
        smoothed=None if estimate == "filtered" else types.SimpleNamespace(),
        map=types.SimpleNamespace(
            tracks=np.array([5, 6, 7, -1]),
            known_ids=np.array([-1, 2, -1, 3]),
            params_known=np.array([[1.0, 2.0, 0.3], [np.nan] * 3, [np.nan] * 3, [np.nan] * 3]),
            covs_known=np.array([np.eye(3) * 0.01] + [np.full((3, 3), np.nan)] * 3),
        ),
    )
    assert mc.detect_changes(result, _log()) == "report"  # type: ignore[arg-type]
    # Only the landmark kept apart from the known map with a finite estimate is passed.
    assert set(seen["landmark_estimates"]) == {5}
    np.testing.assert_array_equal(seen["landmark_estimates"][5][0], [1.0, 2.0, 0.3])
    if before_map:
        assert seen["anchored_from_step"] == 78
        np.testing.assert_array_equal(seen["anchor_cov"], anchor.cov)
    else:
        assert seen["anchored_from_step"] == 0
        assert seen["anchor_cov"] is None


@pytest.mark.parametrize("bad", [0, -1, 2.5, True])
def test_min_beams_present_must_be_a_positive_int(bad):
    with pytest.raises(ValueError, match="min_beams_present"):
        ChangeParams(min_beams_present=bad)


def test_a_landmark_seen_only_before_the_match_is_read_through_the_estimators_estimate():
    """The tree most in view moved 3 m, its landmark kept apart.  Given the estimator's
    final estimate of that landmark as 2 cm off the moved place, σ 5 cm, it is tested
    through it when every observation precedes the match (the displacement is the
    estimate's, to 1e-9); when the landmark is also seen after the match, or with
    ``filter_estimates`` off, its observations decide."""
    moved, circ, kid = _most_viewed_tree_surveyed_3m_off()
    lm, kn = _true_decisions(moved, kid)
    start, poses, covs = _true_trajectory(moved)
    p = moved.known_map.params
    value = p[circ] - np.array([2.98, 0.0, 0.0])
    estimates = {kid: (value, np.diag([0.05**2, 0.05**2, 0.02**2]))}
    last = int(moved.feat_step[moved.feat_true_id == kid].max())

    def classify(until: int, filter_estimates: bool = True):
        return classify_changes(
            moved,
            lm,
            kn,
            poses,
            covs,
            start,
            dataclasses.replace(PARAMS, relocalize=False, filter_estimates=filter_estimates),
            anchor_cov=np.zeros((3, 3)),
            anchored_from_step=until,
            landmark_estimates=estimates,
        ).known[circ]

    before = classify(last + 1)
    assert before.status == ChangeStatus.MOVED
    np.testing.assert_allclose(before.displacement[:2], value[:2] - p[circ, :2], atol=1e-9)
    after = classify(last)
    assert after.status == ChangeStatus.MOVED
    assert abs(after.displacement[0] - (value[0] - p[circ, 0])) > 1e-4
    assert after.displacement[0] == pytest.approx(-3.0, abs=0.3)
    # Switched off, the observations decide even for a landmark seen only before.
    off = classify(last + 1, filter_estimates=False)
    np.testing.assert_allclose(off.displacement, after.displacement, atol=1e-9)
