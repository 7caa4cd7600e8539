"""Laser simulation: exact ray casting against hand-computed geometry, noise model, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from mapfuse_core.sensor import LaserParams, Scan
from mapfuse_core.sim.laser import cast_rays, simulate_scan
from mapfuse_core.sim.world import CircleObstacle, WallSegment, World

ORIGIN = np.zeros(3)


def wall_world(x: float = 10.0, half: float = 5.0) -> World:
    """A single wall ``x = const`` from ``y = −half`` to ``y = +half`` (id 1)."""
    return World((WallSegment(1, (x, -half), (x, half)),), ())


# --------------------------------------------------------------------------- params


def test_default_params_match_table_1() -> None:
    p = LaserParams()
    b = p.bearings()
    assert b.shape == (361,)
    assert b[0] == pytest.approx(-math.pi / 2)
    assert b[-1] == pytest.approx(math.pi / 2)
    assert np.allclose(np.diff(b), math.radians(0.5))
    assert p.beam_spacing_rad == pytest.approx(math.radians(0.5))
    assert p.max_range_m == 80.0
    assert p.sigma_range_m == 0.05
    assert p.sigma_bearing_rad == pytest.approx(math.pi / 720)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"n_beams": 1}, "n_beams must be >= 2"),
        ({"n_beams": 2.5}, "n_beams must be an integer"),
        ({"fov_rad": 0.0}, "fov_rad must be in"),
        ({"fov_rad": 7.0}, "fov_rad must be in"),
        ({"fov_rad": math.nan}, "fov_rad must be a finite number"),
        ({"max_range_m": -1.0}, "max_range_m must be > 0"),
        ({"max_range_m": math.inf}, "max_range_m must be a finite number"),
        ({"sigma_range_m": -0.01}, "sigma_range_m must be >= 0"),
        ({"sigma_bearing_rad": -1e-3}, "sigma_bearing_rad must be >= 0"),
        ({"sigma_bearing_rad": math.nan}, "sigma_bearing_rad must be a finite number"),
    ],
)
def test_bad_params_raise(kwargs: dict[str, float], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        LaserParams(**kwargs)  # type: ignore[arg-type]


def test_full_circle_fov_is_allowed() -> None:
    b = LaserParams(fov_rad=2 * math.pi, n_beams=5).bearings()
    assert np.allclose(b, [-math.pi, -math.pi / 2, 0.0, math.pi / 2, math.pi])


# --------------------------------------------------------------------------- scan


def test_scan_valid_and_points() -> None:
    scan = Scan(
        bearings=np.array([-0.5, 0.0, 0.5]),
        ranges=np.array([2.0, np.inf, 4.0]),
        hit_ids=np.array([3, -1, 4]),
    )
    assert scan.valid().tolist() == [True, False, True]
    pts = scan.points()
    assert pts.shape == (2, 2)
    assert np.allclose(pts[0], [2 * math.cos(-0.5), 2 * math.sin(-0.5)])
    assert np.allclose(pts[1], [4 * math.cos(0.5), 4 * math.sin(0.5)])
    assert scan.hit_ids.dtype == np.int64


@pytest.mark.parametrize(
    ("bearings", "ranges", "ids", "message"),
    [
        ([0.0, 1.0], [1.0], [1, 1], "same shape"),
        ([[0.0, 1.0]], [[1.0, 1.0]], [[1, 1]], "1-D"),
        ([0.0, 1.0], [1.0, math.nan], [1, 1], "NaN"),
        ([0.0, 1.0], [1.0, -2.0], [1, 1], "must be > 0"),
        ([0.0, math.nan], [1.0, 2.0], [1, 1], "non-finite"),
        ([0.0, 1.0], [1.0, 2.0], [1.5, 1.0], "integers"),
    ],
)
def test_bad_scan_raises(
    bearings: list[float], ranges: list[float], ids: list[float], message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        Scan(bearings=np.array(bearings), ranges=np.array(ranges), hit_ids=np.array(ids))


def test_empty_scan_is_fine() -> None:
    scan = Scan(bearings=np.zeros(0), ranges=np.zeros(0), hit_ids=np.zeros(0, dtype=np.int64))
    assert scan.points().shape == (0, 2)
    assert scan.valid().shape == (0,)


# --------------------------------------------------------------------------- ray casting


def test_wall_at_known_distance() -> None:
    angles = np.array([0.0, 0.3, -0.4, math.atan2(5.0, 10.0) - 1e-9, 0.6, math.pi])
    r, ids = cast_rays(wall_world(), ORIGIN, angles, 80.0)
    expected = 10.0 / np.cos(angles[:4])
    assert np.allclose(r[:4], expected, rtol=0, atol=1e-12)
    assert ids[:4].tolist() == [1, 1, 1, 1]
    # 0.6 rad passes above the wall's end (10 tan 0.6 = 6.8 > 5); π points away from it.
    assert np.isinf(r[4:]).all()
    assert ids[4:].tolist() == [-1, -1]


def test_sensor_pose_is_applied() -> None:
    # Sensor at (1, 2) looking along +y; the wall y = 12 is 10 m ahead of it.
    world = World((WallSegment(7, (-20.0, 12.0), (20.0, 12.0)),), ())
    pose = np.array([1.0, 2.0, math.pi / 2])
    bearings = np.array([0.0, 0.5])
    r, ids = cast_rays(world, pose, pose[2] + bearings, 80.0)
    assert np.allclose(r, [10.0, 10.0 / math.cos(0.5)], atol=1e-12)
    assert ids.tolist() == [7, 7]


def test_circle_hit_matches_closed_form() -> None:
    world = World((), (CircleObstacle(2, (10.0, 0.0), 1.0),))
    angles = np.array([0.0, 0.05, -0.08])
    r, ids = cast_rays(world, ORIGIN, angles, 80.0)
    expected = 10.0 * np.cos(angles) - np.sqrt(1.0 - 100.0 * np.sin(angles) ** 2)
    assert np.allclose(r, expected, atol=1e-12)
    assert ids.tolist() == [2, 2, 2]
    # asin(1/10) ≈ 0.1002 rad is the silhouette.
    r, ids = cast_rays(world, ORIGIN, np.array([0.11, -0.11]), 80.0)
    assert np.isinf(r).all()
    assert ids.tolist() == [-1, -1]


def test_occlusion_nearest_hit_wins() -> None:
    world = World(
        (WallSegment(1, (10.0, -5.0), (10.0, 5.0)),), (CircleObstacle(2, (5.0, 0.0), 0.5),)
    )
    angles = np.array([0.0, 0.3])
    r, ids = cast_rays(world, ORIGIN, angles, 80.0)
    assert ids.tolist() == [2, 1]
    assert r[0] == pytest.approx(4.5, abs=1e-12)
    assert r[1] == pytest.approx(10.0 / math.cos(0.3), abs=1e-12)
    # Order of the features does not matter: a nearer wall occludes a circle too.
    world2 = World(
        (WallSegment(1, (3.0, -5.0), (3.0, 5.0)),), (CircleObstacle(2, (5.0, 0.0), 0.5),)
    )
    r, ids = cast_rays(world2, ORIGIN, np.array([0.0]), 80.0)
    assert ids.tolist() == [1]
    assert r[0] == pytest.approx(3.0)


def test_max_range_miss() -> None:
    r, ids = cast_rays(wall_world(x=100.0, half=50.0), ORIGIN, np.array([0.0, 0.2]), 80.0)
    assert np.isinf(r).all()
    assert ids.tolist() == [-1, -1]
    r, ids = cast_rays(wall_world(x=100.0, half=50.0), ORIGIN, np.array([0.0]), 100.0)
    assert r[0] == pytest.approx(100.0)
    assert ids[0] == 1


def test_beam_exactly_tangent_to_circle_hits_the_tangent_point() -> None:
    # Centre (5, 1), r = 1: the ray along +x touches it at (5, 0).
    world = World((), (CircleObstacle(3, (5.0, 1.0), 1.0),))
    r, ids = cast_rays(world, ORIGIN, np.array([0.0, -1e-6]), 80.0)
    assert r[0] == 5.0
    assert ids[0] == 3
    assert np.isinf(r[1])
    assert ids[1] == -1


def test_beam_parallel_to_segment_does_not_hit_it() -> None:
    world = World((WallSegment(4, (5.0, 0.0), (10.0, 0.0)),), ())
    r, ids = cast_rays(world, ORIGIN, np.array([0.0]), 80.0)
    assert np.isinf(r[0])
    assert ids[0] == -1


def test_segment_endpoint_is_hit() -> None:
    r, ids = cast_rays(wall_world(), ORIGIN, np.array([math.atan2(5.0, 10.0)]), 80.0)
    assert r[0] == pytest.approx(math.hypot(10.0, 5.0))
    assert ids[0] == 1


def test_from_inside_a_circle_the_far_side_is_hit() -> None:
    world = World((), (CircleObstacle(5, (0.5, 0.0), 2.0),))
    r, ids = cast_rays(world, ORIGIN, np.array([0.0, math.pi]), 80.0)
    assert np.allclose(r, [2.5, 1.5])
    assert ids.tolist() == [5, 5]


@pytest.mark.parametrize(
    ("pose", "angles", "max_range", "message"),
    [
        ([0.0, math.nan, 0.0], [0.0], 80.0, "non-finite"),
        ([0.0, 0.0], [0.0], 80.0, "shape"),
        ([0.0, 0.0, 0.0], [[0.0]], 80.0, "1-D"),
        ([0.0, 0.0, 0.0], [math.inf], 80.0, "non-finite"),
        ([0.0, 0.0, 0.0], [0.0], 0.0, "max_range must be > 0"),
        ([0.0, 0.0, 0.0], [0.0], math.nan, "max_range must be > 0"),
    ],
)
def test_cast_rays_bad_input(
    pose: list[float], angles: list[float], max_range: float, message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        cast_rays(wall_world(), np.array(pose), np.array(angles), max_range)


coords = st.floats(min_value=-30.0, max_value=30.0, allow_nan=False)


@given(
    st.tuples(coords, coords, st.floats(min_value=-math.pi, max_value=math.pi)),
    st.tuples(coords, coords, st.floats(min_value=0.1, max_value=3.0)),
    st.tuples(coords, coords, coords, coords),
)
def test_hits_lie_on_the_feature_and_nothing_is_closer(
    pose: tuple[float, float, float],
    circle: tuple[float, float, float],
    seg: tuple[float, float, float, float],
) -> None:
    p1, p2 = (seg[0], seg[1]), (seg[2], seg[3])
    assume(math.dist(p1, p2) > 0.1)
    # The sensor is never on a surface: keep it a few cm off both features.
    assume(abs(math.dist(pose[:2], circle[:2]) - circle[2]) > 0.05)
    e0 = np.subtract(p2, p1)
    u = float(np.clip(np.dot(np.subtract(pose[:2], p1), e0) / np.dot(e0, e0), 0.0, 1.0))
    assume(math.dist(pose[:2], tuple(np.add(p1, u * e0))) > 0.05)
    world = World((WallSegment(0, p1, p2),), (CircleObstacle(1, circle[:2], circle[2]),))
    x = np.array(pose)
    angles = x[2] + np.linspace(-math.pi, math.pi, 181)
    r, ids = cast_rays(world, x, angles, 1e3)
    hit = np.isfinite(r)
    pts = x[:2] + r[hit, None] * np.column_stack((np.cos(angles[hit]), np.sin(angles[hit])))
    c = np.array(circle[:2])
    on_circle = np.abs(np.hypot(*(pts - c).T) - circle[2]) < 1e-7
    e = np.array(p2) - np.array(p1)
    d = pts - np.array(p1)
    on_seg = np.abs(d[:, 0] * e[1] - d[:, 1] * e[0]) / np.hypot(*e) < 1e-7
    assert np.all(np.where(ids[hit] == 1, on_circle, on_seg))
    # Dense sampling along each ray finds no point inside the circle before the hit.
    for a, rr in zip(angles[hit], r[hit], strict=True):
        s = np.linspace(0.0, rr, 50)[1:-1]
        q = x[:2] + s[:, None] * np.array([math.cos(a), math.sin(a)])
        inside = np.hypot(*(q - c).T) < circle[2] - 1e-9
        start_inside = math.hypot(*(x[:2] - c)) < circle[2]
        assert start_inside or not inside.any()


# --------------------------------------------------------------------------- simulation


def test_noise_free_scan_equals_ray_casting() -> None:
    laser = LaserParams(sigma_range_m=0.0, sigma_bearing_rad=0.0)
    scan = simulate_scan(wall_world(), ORIGIN, laser, np.random.default_rng(0))
    r, ids = cast_rays(wall_world(), ORIGIN, laser.bearings(), laser.max_range_m)
    assert np.array_equal(scan.ranges, r)
    assert np.array_equal(scan.hit_ids, ids)
    assert np.array_equal(scan.bearings, laser.bearings())


def test_same_seed_same_scan_and_other_seed_differs() -> None:
    laser = LaserParams()
    a = simulate_scan(wall_world(), ORIGIN, laser, np.random.default_rng(42))
    b = simulate_scan(wall_world(), ORIGIN, laser, np.random.default_rng(42))
    c = simulate_scan(wall_world(), ORIGIN, laser, np.random.default_rng(43))
    assert np.array_equal(a.ranges, b.ranges)
    assert np.array_equal(a.hit_ids, b.hit_ids)
    assert not np.array_equal(a.ranges, c.ranges)


def test_random_stream_does_not_depend_on_geometry() -> None:
    laser = LaserParams()
    rng1, rng2 = np.random.default_rng(7), np.random.default_rng(7)
    simulate_scan(wall_world(), ORIGIN, laser, rng1)
    far = World((WallSegment(1, (500.0, 0.0), (500.0, 1.0)),), ())  # nothing in range
    scan = simulate_scan(far, ORIGIN, laser, rng2)
    assert not scan.valid().any()
    assert rng1.normal() == rng2.normal()


def test_noise_statistics_match_the_model() -> None:
    """Range error variance is σρ² + (ρ tan γ)² σβ² on a wall at incidence γ."""
    laser = LaserParams()
    rng = np.random.default_rng(1)
    beams = laser.bearings()
    k0, k1 = 180, 240  # 0° and 30°
    samples = np.array(
        [
            simulate_scan(wall_world(half=50.0), ORIGIN, laser, rng).ranges[[k0, k1]]
            for _ in range(4000)
        ]
    )
    r0, r1 = 10.0, 10.0 / math.cos(beams[k1])
    # The mean range along a tilted beam is pulled up by ½ ρ'' σβ² (second order).
    g = beams[k1]
    mean1 = r1 + 0.5 * r1 * (2 * math.tan(g) ** 2 + 1) * laser.sigma_bearing_rad**2
    var1 = laser.sigma_range_m**2 + (r1 * math.tan(g) * laser.sigma_bearing_rad) ** 2
    assert samples[:, 0].mean() == pytest.approx(r0, abs=4 * 0.05 / math.sqrt(4000))
    assert samples[:, 0].std() == pytest.approx(laser.sigma_range_m, rel=0.05)
    assert samples[:, 1].mean() == pytest.approx(mean1, abs=4 * math.sqrt(var1 / 4000))
    assert samples[:, 1].var() == pytest.approx(var1, rel=0.1)


def test_returns_beyond_max_range_are_no_returns() -> None:
    laser = LaserParams(max_range_m=10.0)
    scan = simulate_scan(wall_world(x=10.0, half=50.0), ORIGIN, laser, np.random.default_rng(3))
    assert np.all(scan.ranges[scan.valid()] <= 10.0)
    assert np.all(scan.hit_ids[~scan.valid()] == -1)
    # About half of the frontal beams (true range exactly 10 m) fall beyond the limit.
    assert 0 < scan.valid().sum() < laser.n_beams


@pytest.mark.parametrize(
    ("pose", "params", "rng", "message"),
    [
        ([math.nan, 0.0, 0.0], LaserParams(), np.random.default_rng(0), "non-finite"),
        ([0.0, 0.0, 0.0, 0.0], LaserParams(), np.random.default_rng(0), "shape"),
        ([0.0, 0.0, 0.0], "laser", np.random.default_rng(0), "LaserParams"),
        ([0.0, 0.0, 0.0], LaserParams(), 3, "Generator"),
    ],
)
def test_simulate_scan_bad_input(
    pose: list[float], params: object, rng: object, message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        simulate_scan(wall_world(), np.array(pose), params, rng)  # type: ignore[arg-type]
