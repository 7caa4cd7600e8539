"""Where the raw scans saw through a mapped circle or wall: the free-space evidence of
``mapfuse_core/changes/freespace.py`` and how the classification uses it."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mapfuse_core.changes import ChangeParams, ChangeStatus
from mapfuse_core.changes.freespace import circles_seen_occupied, scans_seen_empty
from mapfuse_core.changes.visibility import map_world
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog
from mapfuse_core.sensor import LaserParams
from mapfuse_core.sim.laser import cast_rays, simulate_scan
from mapfuse_core.sim.world import CircleObstacle, WallSegment, World
from tests.test_changes import PARAMS, _classify, _log, _most_in_view, _with_absent_trees

LASER = LaserParams()
BEARINGS = LASER.bearings()
ONE = ChangeParams(view_stride=1)
N = 5
POSES = np.zeros((N, 3))
COVS = np.tile(np.eye(3) * 1e-6, (N, 1, 1))


def _tree(x: float, r: float, sigma_xy: float = 0.0, sigma_r: float = 0.0) -> KnownMapArrays:
    return KnownMapArrays(
        ids=np.array([7], dtype=np.int64),
        kinds=np.array([1], dtype=np.int8),
        params=np.array([[x, 0.0, r]]),
        covs=np.diag([sigma_xy**2, sigma_xy**2, sigma_r**2])[None],
        extents=np.full((1, 2), np.nan),
    )


def _scans(world: World | None, noise: float = 0.0, seed: int = 0) -> np.ndarray:
    """(N, B) ranges the laser records at the origin in ``world`` (nothing: all inf)."""
    if world is None:
        return np.full((N, BEARINGS.size), np.inf, dtype=np.float32)
    rng = np.random.default_rng(seed)
    rows = []
    for _ in range(N):
        r, _hit = cast_rays(world, np.zeros(3), BEARINGS, LASER.max_range_m)
        rows.append(r + noise * rng.standard_normal(r.shape))
    return np.array(rows, dtype=np.float32)


BEHIND = WallSegment(50, (20.0, -10.0), (20.0, 10.0))


def _empty(known: KnownMapArrays, ranges: np.ndarray, params: ChangeParams = ONE) -> int:
    return scans_seen_empty(known, [0], POSES, COVS, BEARINGS, ranges, params)[7]


def test_beams_through_an_empty_place_see_it_empty_every_scan() -> None:
    # Nothing returns, or the beams return from a wall behind the surveyed place.
    assert _empty(_tree(8.0, 0.3), _scans(None)) == N
    assert _empty(_tree(8.0, 0.3), _scans(World(segments=(BEHIND,), circles=()))) == N


def test_a_trunk_where_the_map_has_it_is_never_seen_empty_even_off_by_its_sigmas() -> None:
    # The trunk stands 0.15 m off its mapped place and is 0.1 m thinner, inside 3 σ of
    # the map's position (0.05 m) and radius (0.05 m) errors; the ranges carry noise.
    real = World(segments=(BEHIND,), circles=(CircleObstacle(7, (8.0, 0.15), 0.2),))
    known = _tree(8.0, 0.3, sigma_xy=0.05, sigma_r=0.05)
    assert _empty(known, _scans(real, noise=0.05)) == 0
    # The same trunk where it is mapped.
    exact = World(segments=(BEHIND,), circles=(CircleObstacle(7, (8.0, 0.0), 0.3),))
    assert _empty(_tree(8.0, 0.3), _scans(exact, noise=0.05)) == 0


def test_a_place_hidden_behind_something_else_says_nothing() -> None:
    front = World(segments=(BEHIND,), circles=(CircleObstacle(1, (4.0, 0.0), 0.6),))
    assert _empty(_tree(8.0, 0.3), _scans(front)) == 0


def test_a_trunk_thinner_than_its_position_uncertainty_is_seen_empty_when_swept() -> None:
    # r = 0.3 m against a lateral σ of 0.1 m: 3.09 σ leaves no beam sure to hit it, but
    # the beams 0.5° apart go through every place within 0.31 m where it could stand.
    assert _empty(_tree(8.0, 0.3, sigma_xy=0.1), _scans(None)) == N
    # The heading error counts too: 0.02 rad at 8 m is 0.16 m, swept the same way.
    covs = np.tile(np.diag([1e-6, 1e-6, 0.02**2]), (N, 1, 1))
    got = scans_seen_empty(_tree(8.0, 0.3), [0], POSES, covs, BEARINGS, _scans(None), ONE)
    assert got[7] == N


def test_a_trunk_inside_its_position_uncertainty_is_never_seen_empty() -> None:
    # Off by 2.5 σ (0.25 m), or by 0.45 m, beyond the 3.09 σ reach but still in the
    # beams' way: either way a beam returns from it.
    known = _tree(8.0, 0.3, sigma_xy=0.1)
    for off in (0.25, -0.25, 0.45):
        real = World(segments=(BEHIND,), circles=(CircleObstacle(7, (8.0, off), 0.3),))
        assert _empty(known, _scans(real, noise=0.05)) == 0, off


def test_a_swept_place_partly_hidden_or_too_thin_for_the_beams_gives_no_evidence() -> None:
    # A post at 4 m hides the places left of the mapped centre where the trunk, 8 m
    # away, could stand: a trunk there would be behind it, so nothing is said.
    front = World(segments=(BEHIND,), circles=(CircleObstacle(1, (4.0, 0.2), 0.25),))
    assert _empty(_tree(8.0, 0.3, sigma_xy=0.1), _scans(front)) == 0
    # A 6 cm trunk at 25 m fits between two beams 0.5° (22 cm) apart.
    assert _empty(_tree(25.0, 0.06, sigma_xy=0.1), _scans(None)) == 0
    # Thinner than its own radius σ allows for: no evidence at all.
    assert _empty(_tree(8.0, 0.3, sigma_xy=0.1, sigma_r=0.1), _scans(None)) == 0


def test_a_post_hiding_the_middle_of_the_swept_place_leaves_a_gap() -> None:
    # A 0.4 m post at 4 m shadows the middle of the places an 0.3 m trunk could stand
    # at 8 m, wider than the trunk: a trunk there would be hidden.  A 6 cm post is not.
    known = _tree(8.0, 0.3, sigma_xy=0.1)
    post = World(segments=(BEHIND,), circles=(CircleObstacle(1, (4.0, 0.0), 0.2),))
    assert _empty(known, _scans(post)) == 0
    thin = World(segments=(BEHIND,), circles=(CircleObstacle(1, (4.0, 0.0), 0.03),))
    assert _empty(known, _scans(thin)) == N


@pytest.mark.parametrize(("d", "r", "sigma_xy"), [(15.0, 0.1, 0.05), (25.0, 0.15, 0.1)])
def test_a_standing_thin_far_trunk_is_not_read_empty_through_the_beams_bearing_noise(
    d: float, r: float, sigma_xy: float
) -> None:
    """Each beam leaves 0.25° (σ) off its recorded bearing, more than a thin far trunk's
    angular half-width: a beam recorded as aimed at it may have missed it.  None of 200
    noisy scans reads the standing trunk's place empty; the same scans with the trunk
    gone would need a beam spacing finer than the noise, and read nothing either."""
    laser = LaserParams()
    params = ChangeParams(view_stride=1).with_sensor(laser)
    rng = np.random.default_rng(7)
    n = 200
    poses = np.zeros((n, 3))
    covs = np.tile(np.eye(3) * 1e-6, (n, 1, 1))
    far = WallSegment(50, (d + 10.0, -20.0), (d + 10.0, 20.0))
    known = _tree(d, r, sigma_xy=sigma_xy)
    for circles in ((CircleObstacle(7, (d, 0.0), r),), ()):
        world = World(segments=(far,), circles=circles)
        ranges = np.array([simulate_scan(world, p, laser, rng).ranges for p in poses])
        got = scans_seen_empty(known, [0], poses, covs, BEARINGS, ranges, params)[7]
        assert got == 0


def test_only_circles_within_max_range_are_read_and_counts_follow_the_stride() -> None:
    assert _empty(_tree(35.0, 0.5), _scans(None)) == 0  # max_range_m 30 m
    assert _empty(_tree(35.0, 0.5), _scans(None), dataclasses.replace(ONE, max_range_m=40.0)) == N
    # Every 2nd of 5 scans, each counting 2.
    assert _empty(_tree(8.0, 0.3), _scans(None), ChangeParams(view_stride=2)) == 6


def _wall(
    x: float = 8.0, half: float = 2.0, sigma: float = 0.0, extents: bool = True
) -> KnownMapArrays:
    """Known wall 7 across the scanner's view at ``x``, from y = −half to +half."""
    return KnownMapArrays(
        ids=np.array([7], dtype=np.int64),
        kinds=np.array([0], dtype=np.int8),
        params=np.array([[x, 0.0, np.pi / 2]]),
        covs=np.diag([sigma**2, sigma**2, (sigma / 10.0) ** 2])[None],
        extents=np.array([[-half, half]]) if extents else np.full((1, 2), np.nan),
    )


def test_beams_through_an_empty_wall_place_see_it_empty() -> None:
    assert _empty(_wall(), _scans(None)) == N
    assert _empty(_wall(), _scans(World(segments=(BEHIND,), circles=()))) == N
    # A wall without extents has no place to look through.
    assert _empty(_wall(extents=False), _scans(None)) == 0


def test_a_wall_where_the_map_has_it_is_never_seen_empty_even_off_by_its_sigmas() -> None:
    # Standing 0.15 m behind and turned 0.01 rad from its mapped place: inside 3 σ of a
    # 0.05 m / 5 mrad map; ranges with noise.  Also with a doorway in it.
    off = WallSegment(7, (8.15 - 0.02, -2.0), (8.15 + 0.02, 2.0))
    known = _wall(sigma=0.05)
    assert _empty(known, _scans(World(segments=(off, BEHIND), circles=()), noise=0.05)) == 0
    door = (WallSegment(7, (8.0, -2.0), (8.0, -0.5)), WallSegment(8, (8.0, 0.5), (8.0, 2.0)))
    assert _empty(_wall(), _scans(World(segments=(*door, BEHIND), circles=()))) == 0


def test_a_wall_seen_through_only_a_narrow_stretch_gives_no_evidence() -> None:
    # Trunks in front hide all of the absent wall but about 0.5 m of it: fewer beams
    # pass than the extractor needs to see a wall.
    front = tuple(CircleObstacle(i, (4.0, y), 0.55) for i, y in enumerate((-0.9, 0.55)))
    ranges = _scans(World(segments=(BEHIND,), circles=front))
    crossing = np.abs(8.0 * np.tan(BEARINGS)) < 2.0
    passing = int(np.count_nonzero(crossing & (ranges[0] > 19.0)))
    assert 0 < passing < ONE.min_beams_line
    assert _empty(_wall(), ranges) == 0
    # Nearly along the beams (the wall is seen edge-on from the origin): nothing read.
    along = KnownMapArrays(
        ids=np.array([7], dtype=np.int64),
        kinds=np.array([0], dtype=np.int8),
        params=np.array([[3.0, 0.0, 0.0]]),
        covs=np.zeros((1, 3, 3)),
        extents=np.array([[0.0, 6.0]]),
    )
    assert _empty(along, _scans(None)) == 0


def _with_scans(log: MeasurementLog) -> MeasurementLog:
    """``log`` with the raw scans its world gives from the true poses, noise-free."""
    assert log.world is not None
    assert log.true_poses is not None
    world = map_world(log.world)
    assert world is not None
    ranges = [cast_rays(world, p, p[2] + BEARINGS, LASER.max_range_m)[0] for p in log.true_poses]
    return dataclasses.replace(
        log, scan_bearings=BEARINGS, scan_ranges=np.array(ranges, dtype=np.float32)
    )


def test_a_removed_tree_the_extractor_rule_cannot_vouch_for_is_missing_from_the_scans() -> None:
    """Mapped 0.8 m with a radius σ of 0.15 m, the absent tree is not missing by the
    extractor's rule (the real one may be too thin to extract); the beams that went
    through its place say it is missing.  The tree 200 m away stays unobserved."""
    log = _with_scans(_with_absent_trees(0.8, 0.15))
    rep = _classify(log)
    assert rep.status_of(9001) == ChangeStatus.MISSING
    assert rep.known[-2].scans_in_view < PARAMS.min_scans
    assert rep.known[-2].scans_seen_empty >= PARAMS.min_scans
    assert rep.status_of(9002) == ChangeStatus.UNOBSERVED
    assert rep.known[-1].scans_seen_empty == 0
    off = _classify(log, dataclasses.replace(PARAMS, free_space=False))
    assert off.status_of(9001) == ChangeStatus.UNOBSERVED
    assert off.known[-2].scans_seen_empty == 0


def test_no_tree_of_a_noisy_map_that_stands_where_surveyed_is_seen_empty() -> None:
    """Every known tree of the test log stands in its world, the map drawn with its σ:
    read from every step of the drive, none is seen empty, while the absent one is."""
    log = _with_scans(_with_absent_trees(0.8, 0.15))
    known = log.known_map
    rows = [r for r in range(len(known)) if int(known.kinds[r]) == 1]
    assert len(rows) >= 5
    assert log.true_poses is not None
    assert log.scan_ranges is not None
    covs = np.tile(np.eye(3) * 1e-6, (log.n_steps, 1, 1))
    got = scans_seen_empty(
        known, rows, log.true_poses, covs, BEARINGS, log.scan_ranges, ChangeParams()
    )
    assert got[9001] >= PARAMS.min_scans
    assert all(got[int(known.ids[r])] == 0 for r in rows if int(known.ids[r]) < 9000)


@pytest.mark.parametrize("bad", [1, None, "yes"])
def test_free_space_switch_must_be_a_bool(bad: object) -> None:
    with pytest.raises(ValueError, match="free_space"):
        ChangeParams(free_space=bad)  # type: ignore[arg-type]


def test_a_moved_tree_never_seen_where_it_went_counts_neither_way_when_missing() -> None:
    """Tree 1 moved and was never observed again, tree 2 moved and was observed, tree 3
    is where the map has it, tree 4 was removed: called missing, 1 counts neither way,
    2 and 3 are false removals, 4 is found."""
    from mapfuse_core.changes.report import ChangeReport
    from mapfuse_core.evaluation.change_truth import ChangeTruth, score_changes
    from tests.test_changes import _change

    truth = ChangeTruth(
        moved={1: (2.0, 0.0, 0.0, 0.0), 2: (2.0, 0.0, 0.0, 0.0)},
        lateral={},
        removed=(4,),
        removed_in_view=(4,),
        added=(),
        added_observed=(),
        observed=(2, 3),
    )
    report = ChangeReport(
        known=tuple(_change(k, ChangeStatus.MISSING) for k in (1, 2, 3, 4)),  # type: ignore[misc]
        new=(),
        duplicates=0,
        level=0.999,
        x_Wknown_Wglobal=np.zeros(3),
    )
    s = score_changes(report, truth)
    assert (s.removed_tp, s.removed_fp, s.removed_fn) == (1, 2, 0)
    assert (s.moved_tp, s.moved_fn) == (0, 1)


def test_a_removed_tree_out_of_view_found_missing_counts_for_precision_not_recall() -> None:
    """Trees 4 and 5 were removed, only 4 came into view; 6 stands.  Called missing,
    5 is right but outside the recall's population: recall 1 of 1 in view, precision
    2 of 3 calls."""
    from mapfuse_core.changes.report import ChangeReport
    from mapfuse_core.evaluation.change_truth import ChangeTruth, score_changes
    from tests.test_changes import _change

    truth = ChangeTruth(
        moved={},
        lateral={},
        removed=(4, 5),
        removed_in_view=(4,),
        added=(),
        added_observed=(),
        observed=(6,),
    )
    report = ChangeReport(
        known=tuple(_change(k, ChangeStatus.MISSING) for k in (4, 5, 6)),  # type: ignore[misc]
        new=(),
        duplicates=0,
        level=0.999,
        x_Wknown_Wglobal=np.zeros(3),
    )
    s = score_changes(report, truth)
    assert (s.removed_tp, s.removed_beyond_view_tp, s.removed_fp, s.removed_fn) == (1, 1, 1, 0)
    d = s.as_dict()["removed"]
    assert d["recall"] == 1.0
    assert d["precision"] == pytest.approx(2 / 3)
    assert d["beyond_view_tp"] == 1


def _with_absent_wall() -> MeasurementLog:
    """The test log with a 4 m wall 9001 in its known map and not in its world, across
    the start pose's view 8 m ahead (σ 5 cm, 5 mrad)."""
    from mapfuse_core.geometry.se2 import compose
    from tests.test_changes import _log, _replace_known

    log = _log()
    assert log.true_poses is not None
    k = log.known_map
    assert k.extents is not None
    start = log.true_poses[0]
    near = compose(start, np.array([8.0, 0.0, 0.0]))
    wall = np.array([[near[0], near[1], float(start[2]) + np.pi / 2]])
    return _with_scans(
        _replace_known(
            log,
            ids=np.concatenate([k.ids, [9001]]),
            kinds=np.concatenate([k.kinds, [0]]).astype(np.int8),
            params=np.vstack([k.params, wall]),
            covs=np.vstack([k.covs, np.diag([0.05**2, 0.05**2, 0.005**2])[None]]),
            extents=np.vstack([k.extents, [[-2.0, 2.0]]]),
        )
    )


def test_no_wall_that_stands_where_surveyed_is_seen_empty_and_an_absent_one_is() -> None:
    log = _with_absent_wall()
    known = log.known_map
    assert known.extents is not None
    rows = [r for r in range(len(known)) if int(known.kinds[r]) == 0]
    assert len(rows) >= 3
    assert log.true_poses is not None
    assert log.scan_ranges is not None
    covs = np.tile(np.eye(3) * 1e-6, (log.n_steps, 1, 1))
    got = scans_seen_empty(
        known, rows, log.true_poses, covs, BEARINGS, log.scan_ranges, ChangeParams()
    )
    assert got[9001] >= PARAMS.min_scans
    standing = [int(known.ids[r]) for r in rows if int(known.ids[r]) < 9000]
    assert all(got[kid] == 0 for kid in standing)
    # Each standing wall has core beams for K scans: with no returns it reads empty.
    blank = np.full_like(log.scan_ranges, np.inf)
    seen = scans_seen_empty(known, rows, log.true_poses, covs, BEARINGS, blank, ChangeParams())
    assert all(seen[kid] >= PARAMS.min_scans for kid in standing)
    rep = _classify(log)
    assert rep.status_of(9001) == ChangeStatus.MISSING
    assert rep.known[-1].scans_seen_empty >= PARAMS.min_scans


def _occupied(known: KnownMapArrays, ranges: np.ndarray, params: ChangeParams = ONE) -> int:
    return circles_seen_occupied(known, [0], POSES, COVS, BEARINGS, ranges, params)[7][0]


def test_a_trunk_where_the_map_has_it_is_seen_standing_and_an_empty_place_is_not() -> None:
    exact = World(segments=(BEHIND,), circles=(CircleObstacle(7, (8.0, 0.0), 0.3),))
    assert _occupied(_tree(8.0, 0.3), _scans(exact, noise=0.01)) == N
    counted, reach = circles_seen_occupied(
        _tree(8.0, 0.3), [0], POSES, COVS, BEARINGS, _scans(exact), ONE
    )[7]
    assert counted == N
    # The radius and 3.09 σ of the pose: 1e-6 m² in position, 1e-6 rad² times 8² m².
    assert reach == pytest.approx(0.3 + 3.0902 * math.sqrt(1e-6 + 64e-6), abs=1e-4)
    assert _occupied(_tree(8.0, 0.3), _scans(None)) == 0
    assert _occupied(_tree(8.0, 0.3), _scans(World(segments=(BEHIND,), circles=()))) == 0


def test_a_trunk_moved_out_of_reach_or_hidden_does_not_occupy_its_surveyed_place() -> None:
    # Moved 3 m further along the beams: its returns are out of reach of the surveyed
    # centre's range.  Hidden behind a trunk in front: the returns are short.
    moved = World(segments=(BEHIND,), circles=(CircleObstacle(7, (11.0, 0.0), 0.3),))
    assert _occupied(_tree(8.0, 0.3), _scans(moved)) == 0
    front = World(segments=(BEHIND,), circles=(CircleObstacle(1, (4.0, 0.0), 0.6),))
    assert _occupied(_tree(8.0, 0.3), _scans(front)) == 0
    # Fewer beams on it than min_beams_present: no reading.
    exact = World(segments=(BEHIND,), circles=(CircleObstacle(7, (8.0, 0.0), 0.3),))
    few = dataclasses.replace(ONE, min_beams_present=10**6)
    assert _occupied(_tree(8.0, 0.3), _scans(exact), few) == 0


def _standing_unextracted(keep_w: bool) -> tuple[MeasurementLog, int]:
    """The test log with known tree 9001 standing 3 m from tree W (in the world and in
    the raw scans) but never observed, as if the extractor missed it; with
    ``keep_w=False`` W is struck from the known map, so its landmark is unassociated.
    Returns the log and W's id."""
    log = _log()
    row = _most_in_view(log, FeatureKind.CIRCLE)
    k = log.known_map
    w_id = int(k.ids[row])
    t = k.params[row] + np.array([0.0, 3.0, 0.0])
    keep = np.ones(len(k), dtype=bool)
    keep[row] = keep_w
    known = KnownMapArrays(
        ids=np.append(k.ids[keep], 9001),
        kinds=np.append(k.kinds[keep], 1).astype(np.int8),
        params=np.vstack([k.params[keep], t]),
        covs=np.concatenate([k.covs[keep], k.covs[row][None]]),
        extents=np.vstack([k.extents[keep], [np.nan, np.nan]]),
    )
    assert log.world is not None
    assert log.true_poses is not None
    w = log.world
    with_t = KnownMapArrays(
        ids=np.append(w.ids, 9001),
        kinds=np.append(w.kinds, 1).astype(np.int8),
        params=np.vstack([w.params, t]),
        covs=np.concatenate([w.covs, w.covs[:1]]),
        extents=np.vstack([w.extents, [np.nan, np.nan]]),
    )
    world = map_world(with_t)
    assert world is not None
    ranges = [cast_rays(world, p, p[2] + BEARINGS, LASER.max_range_m)[0] for p in log.true_poses]
    scanned = dataclasses.replace(
        log, known_map=known, scan_bearings=BEARINGS, scan_ranges=np.array(ranges, np.float32)
    )
    return scanned, w_id


def test_a_tree_the_scans_find_standing_is_not_linked_to_another_tree_nearby() -> None:
    """W is not in the known map, and its landmark is within the move limits of 9001,
    whose surveyed place was predicted in view: without the occupancy reading W is
    taken for 9001's move.  The raw scans find 9001 standing, out of reach of W, so W
    is new and 9001 is not moved."""
    scanned, w_id = _standing_unextracted(keep_w=False)
    rep = _classify(scanned)
    tree = rep.known[-1]
    assert tree.known_id == 9001
    assert tree.status == ChangeStatus.UNOBSERVED
    assert tree.scans_seen_occupied >= PARAMS.link_min_scans
    assert tree.scans_seen_occupied > tree.scans_seen_empty
    assert w_id in {n.true_id for n in rep.new}
    blind = _classify(scanned, dataclasses.replace(PARAMS, min_beams_present=10**6))
    assert blind.known[-1].status == ChangeStatus.MOVED
    assert blind.known[-1].scans_seen_occupied == 0
    assert w_id not in {n.true_id for n in blind.new}


def test_a_tree_the_scans_find_standing_is_not_called_missing() -> None:
    """W stays in the known map (so its landmark is W's, not a move of 9001), and the
    view rule is made to call 9001 missing (K of 8 scans, no radius margin): the raw
    scans find it standing in more scans than K, so it is unobserved, not missing."""
    scanned, _ = _standing_unextracted(keep_w=True)
    eager = dataclasses.replace(PARAMS, min_scans=8, missing_radius_sigmas=0.0)
    tree = _classify(scanned, eager).known[-1]
    assert tree.known_id == 9001
    assert tree.scans_seen_occupied >= eager.min_scans
    assert tree.status == ChangeStatus.UNOBSERVED
    blind = dataclasses.replace(eager, min_beams_present=10**6)
    assert _classify(scanned, blind).known[-1].status == ChangeStatus.MISSING


def test_a_tree_found_standing_in_k_scans_is_not_missing_though_more_saw_it_empty() -> None:
    """9001 comes into view in the drive's last 50 scans.  The last 20 are replaced by
    those of a world without it, as a pose further off than its σ would read them: the
    place is seen empty more often than standing, and standing in K scans.  Evidence
    both ways is not evidence of absence: unobserved, not missing."""
    scanned, _ = _standing_unextracted(keep_w=True)
    assert scanned.world is not None
    assert scanned.true_poses is not None
    assert scanned.scan_ranges is not None
    world = map_world(scanned.world)
    assert world is not None
    cut = scanned.n_steps - 20
    ranges = scanned.scan_ranges.copy()
    ranges[cut:] = [
        cast_rays(world, p, p[2] + BEARINGS, LASER.max_range_m)[0] for p in scanned.true_poses[cut:]
    ]
    eager = dataclasses.replace(PARAMS, min_scans=8, missing_radius_sigmas=0.0)
    tree = _classify(dataclasses.replace(scanned, scan_ranges=ranges), eager).known[-1]
    assert tree.known_id == 9001
    assert tree.scans_seen_occupied >= eager.min_scans
    assert tree.scans_seen_empty > tree.scans_seen_occupied
    assert tree.status == ChangeStatus.UNOBSERVED


def test_something_just_behind_an_empty_surveyed_place_does_not_occupy_it() -> None:
    """A wall 0.2 m behind the surveyed centre of a 0.3 m trunk that is gone, and a
    trunk 0.4 m behind it: a standing trunk returns from its near face, never from
    behind its centre, so neither reads as the trunk standing."""
    wall = WallSegment(50, (8.2, -3.0), (8.2, 3.0))
    assert _occupied(_tree(8.0, 0.3), _scans(World(segments=(wall,), circles=()))) == 0
    behind = World(segments=(BEHIND,), circles=(CircleObstacle(3, (8.4, 0.0), 0.3),))
    assert _occupied(_tree(8.0, 0.3), _scans(behind)) == 0


def test_a_tree_moved_in_front_of_its_surveyed_place_is_linked_through_the_hits_there() -> None:
    """The known entry of the tree most in view lies 0.6 m behind where the tree stands,
    seen from the drive, and the estimator never associated the two: the trunk hides
    its own surveyed place from the view model, so the place is predicted in view too
    rarely to link a landmark to it.  The raw beams aimed at the surveyed disc return
    from the trunk, within reach: the place is seen occupied, the landmark within that
    reach is linked, and the tree is moved by 0.6 m (within 0.3 m, three of the map's
    σ).  Without the occupancy reading it stays unobserved."""
    log = _log()
    row = _most_in_view(log, FeatureKind.CIRCLE)
    k = log.known_map
    w_id = int(k.ids[row])
    assert log.true_poses is not None
    seen = np.unique(log.feat_step[log.feat_true_id == w_id])
    away = k.params[row][:2] - log.true_poses[seen, :2].mean(axis=0)
    shift = 0.6 * away / np.linalg.norm(away)
    params = k.params.copy()
    params[row, :2] += shift
    scanned = _with_scans(dataclasses.replace(log, known_map=dataclasses.replace(k, params=params)))
    rep = _classify(scanned, unassociated=w_id)
    tree = rep.known[row]
    assert tree.scans_in_view < PARAMS.link_min_scans
    assert tree.scans_seen_occupied >= PARAMS.link_min_scans
    assert tree.status == ChangeStatus.MOVED
    assert tree.displacement[:2] == pytest.approx(-shift, abs=0.3)
    blind = _classify(
        scanned, dataclasses.replace(PARAMS, min_beams_present=10**6), unassociated=w_id
    )
    assert blind.known[row].status == ChangeStatus.UNOBSERVED
