"""Scenario files: validation errors, the known map, and the built-in loop600 (paper Sect. 4.2)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from mapfuse_core.evaluation import known_map_draw_offset
from mapfuse_core.geometry.features import FeatureKind, transform_feature
from mapfuse_core.geometry.se2 import compose, inverse, wrap_angle
from mapfuse_core.sim.laser import cast_rays
from mapfuse_core.sim.scenario import (
    ControlSegment,
    Scenario,
    ScenarioError,
    build_known_map,
    check_visibility,
    control_table,
    features_in_view,
    list_builtin_scenarios,
    load_scenario,
    simulate_drive,
)
from mapfuse_core.sim.simulate import simulate
from mapfuse_core.sim.vehicle import MotionResult, VehicleParams

BAD_DIR = Path(__file__).parent / "data" / "bad_scenarios"
CIRCLE_CONTROLS = Path(__file__).parent / "data" / "circle_controls.toml"
BAD_FILES = sorted(BAD_DIR.glob("*.toml"))

#: The extent of the paper's Fig. 4 (x_min, x_max, y_min, y_max).
PAPER_BOX = (-100.0, 80.0, -80.0, 100.0)

SMALL = """
[scenario]
name = "small"
seed = 3

[trajectory]
start = [0.0, 0.0, 0.0]
steps = 40
waypoints = [[0.0, 0.0], [20.0, 0.0]]

[world]
segments = [
    { id = 1, p1 = [5.0, 6.0], p2 = [15.0, 6.0] },
    { id = 2, p1 = [25.0, -5.0], p2 = [25.0, 5.0] },
]
circles = [
    { id = 10, centre = [8.0, -4.0], radius = 0.5 },
    { id = 11, centre = [14.0, -5.0], radius = 0.4 },
    { id = 12, centre = [18.0, 4.0], radius = 0.3 },
]

[known_map]
ids = [1, 2, 10, 12]
sigma_xy_m = 0.1
sigma_r_m = 0.08
sigma_theta_rad = 0.05
"""


def _write(tmp_path: Path, text: str, name: str = "scenario.toml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def _motion(scenario: Scenario, seed: int | None = None) -> MotionResult:
    """The drive exactly as the simulator makes it (first of three spawned streams)."""
    ss = np.random.SeedSequence(scenario.seed if seed is None else seed).spawn(3)[0]
    return simulate_drive(scenario, np.random.default_rng(ss))


# --------------------------------------------------------------------------- errors


def _expected(path: Path) -> tuple[str, str]:
    """Each fixture states the key and the reason it must be rejected for in its header."""
    lines = path.read_text(encoding="utf-8").splitlines()
    assert lines[1].startswith("# key:"), path
    assert lines[2].startswith("# reason:"), path
    key = lines[1].removeprefix("# key:").strip()
    reason = lines[2].removeprefix("# reason:").strip()
    return key, reason


def test_there_are_bad_fixtures() -> None:
    assert len(BAD_FILES) >= 30


@pytest.mark.parametrize("path", BAD_FILES, ids=[p.stem for p in BAD_FILES])
def test_bad_scenario_names_file_key_and_reason(path: Path) -> None:
    key, reason = _expected(path)
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    err = info.value
    assert err.file == str(path)
    assert err.key == key
    assert reason in err.reason
    message = str(err)
    assert str(path) in message
    assert key in message
    assert reason in message


def test_scenario_error_is_a_value_error() -> None:
    assert issubclass(ScenarioError, ValueError)
    assert str(ScenarioError("f.toml", "world.circles[3].radius", "must be > 0")) == (
        "f.toml: world.circles[3].radius: must be > 0"
    )


def test_missing_file_and_unknown_builtin(tmp_path: Path) -> None:
    with pytest.raises(ScenarioError, match="file not found"):
        load_scenario(tmp_path / "nope.toml")
    with pytest.raises(ScenarioError, match=r"no built-in scenario.*loop600"):
        load_scenario("loop601")


def test_trajectory_that_never_sees_a_feature_is_rejected(tmp_path: Path) -> None:
    far = SMALL.replace("[5.0, 6.0], p2 = [15.0, 6.0]", "[-500.0, 6.0], p2 = [-490.0, 6.0]")
    far = far.replace("[25.0, -5.0], p2 = [25.0, 5.0]", "[-525.0, -5.0], p2 = [-525.0, 5.0]")
    for x in ("8.0", "14.0", "18.0"):
        far = far.replace(f"centre = [{x},", f"centre = [-{x}00,")
    path = _write(tmp_path, far)
    scenario = load_scenario(path)
    with pytest.raises(ScenarioError) as info:
        check_visibility(scenario, _motion(scenario))
    assert info.value.key == "trajectory"
    assert "never sees" in info.value.reason
    assert str(path) in str(info.value)


# --------------------------------------------------------------------------- valid files


def test_small_scenario_loads(tmp_path: Path) -> None:
    s = load_scenario(_write(tmp_path, SMALL))
    assert s.name == "small"
    assert s.seed == 3
    assert s.steps == 40
    np.testing.assert_array_equal(s.start, [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(s.waypoints, [[0.0, 0.0], [20.0, 0.0]])
    assert [seg.id for seg in s.world.segments] == [1, 2]
    assert [c.id for c in s.world.circles] == [10, 11, 12]
    assert s.known_map.ids == (1, 2, 10, 12)
    np.testing.assert_array_equal(s.known_map.frame, np.zeros(3))
    with pytest.raises(ValueError, match="read-only"):
        s.start[0] = 1.0


def test_name_defaults_to_file_stem_and_sections_to_defaults(tmp_path: Path) -> None:
    text = SMALL.replace('name = "small"\n', "") + "\n[vehicle]\nsigma_v = 0.2\n"
    s = load_scenario(_write(tmp_path, text, "my_case.toml"))
    assert s.name == "my_case"
    assert s.vehicle.sigma_v == 0.2
    assert s.vehicle.dt_s == 0.125  # untouched fields keep their defaults
    assert s.laser.n_beams == 361


@pytest.mark.parametrize(
    ("text", "value"),
    [
        ('"pi/3"', math.pi / 3),
        ('"-pi/2"', -math.pi / 2),
        ('"2*pi/5"', 2 * math.pi / 5),
        ('" 0.5 * pi "', math.pi / 2),
        ('"pi"', math.pi),
        ("0.25", 0.25),
        ("1", 1.0),
    ],
)
def test_angles_may_be_written_as_multiples_of_pi(tmp_path: Path, text: str, value: float) -> None:
    s = load_scenario(
        _write(tmp_path, SMALL.replace("start = [0.0, 0.0, 0.0]", f"start = [0.0, 0.0, {text}]"))
    )
    assert s.start[2] == pytest.approx(value, abs=1e-15)


CHANGES = """
frame = [1.0, -2.0, "pi/6"]
added = [11]
moved = [
    { id = 1, dx = 0.5, dy = -0.2, dtheta = 0.1 },
    { id = 10, dx = -0.3, dr = 0.2 },
]

[known_map.removed]
segments = [{ id = 50, p1 = [0.0, 10.0], p2 = [10.0, 12.0] }]
circles = [{ id = 51, centre = [12.0, -8.0], radius = 0.6 }]
"""


def test_known_map_applies_frame_moves_removals_and_additions(tmp_path: Path) -> None:
    text = SMALL.replace("ids = [1, 2, 10, 12]", 'ids = "all"') + CHANGES
    s = load_scenario(_write(tmp_path, text))
    spec = s.known_map
    assert spec.world_ids == (1, 2, 10, 12)  # "all" minus the added 11
    assert spec.ids == (1, 2, 10, 12, 50, 51)
    assert spec.added == (11,)
    km = build_known_map(s, np.random.default_rng(0))
    assert km.ids.tolist() == [1, 2, 10, 12, 50, 51]
    assert km.kinds.dtype == np.int8
    assert km.kinds.tolist() == [0, 0, 1, 1, 0, 1]
    frame = np.array([1.0, -2.0, math.pi / 6])
    np.testing.assert_allclose(km.frame, frame)

    def in_map(kind: FeatureKind, p_W: np.ndarray) -> np.ndarray:
        # Expressed in the map frame by hand: rotate the offset by −θ.
        c, s_ = math.cos(frame[2]), math.sin(frame[2])
        d = p_W[:2] - frame[:2]
        xy = [c * d[0] + s_ * d[1], -s_ * d[0] + c * d[1]]
        third = float(wrap_angle(p_W[2] - frame[2])) if kind == FeatureKind.LINE else p_W[2]
        return np.array([*xy, third])

    seg1 = np.array([10.0 + 0.5, 6.0 - 0.2, 0.0 + 0.1])  # midpoint moved, rotated
    circ10 = np.array([8.0 - 0.3, -4.0, 0.5 + 0.2])
    seg50 = np.array([5.0, 11.0, math.atan2(2.0, 10.0)])
    circ51 = np.array([12.0, -8.0, 0.6])
    np.testing.assert_allclose(km.true_params[0], in_map(FeatureKind.LINE, seg1), atol=1e-12)
    np.testing.assert_allclose(km.true_params[2], in_map(FeatureKind.CIRCLE, circ10), atol=1e-12)
    np.testing.assert_allclose(km.true_params[4], in_map(FeatureKind.LINE, seg50), atol=1e-12)
    np.testing.assert_allclose(km.true_params[5], in_map(FeatureKind.CIRCLE, circ51), atol=1e-12)
    # Block-diagonal, per-type σ (paper eq. 11).
    line_cov = np.diag([0.1**2, 0.1**2, 0.05**2])
    circle_cov = np.diag([0.1**2, 0.1**2, 0.08**2])
    for kind, cov in zip(km.kinds, km.covs, strict=True):
        np.testing.assert_allclose(cov, line_cov if kind == 0 else circle_cov, atol=1e-15)


def test_known_map_draw_is_seeded(tmp_path: Path) -> None:
    s = load_scenario(_write(tmp_path, SMALL))
    a = build_known_map(s, np.random.default_rng(5))
    b = build_known_map(s, np.random.default_rng(5))
    c = build_known_map(s, np.random.default_rng(6))
    np.testing.assert_array_equal(a.params, b.params)
    assert not np.array_equal(a.params, c.params)
    np.testing.assert_array_equal(a.true_params, c.true_params)
    assert not a.params.flags.writeable


def test_known_map_noise_matches_its_covariance(tmp_path: Path) -> None:
    """Honesty of the map's σ: the normalised squared errors average to 1 per component."""
    s = load_scenario(_write(tmp_path, SMALL))
    rng = np.random.default_rng(2024)
    draws = 500
    z2 = []
    for _ in range(draws):
        km = build_known_map(s, rng)
        e = km.params - km.true_params
        lines = km.kinds == 0
        e[lines, 2] = wrap_angle(e[lines, 2])
        z2.append(e**2 / np.diagonal(km.covs, axis1=1, axis2=2))
    total = np.sum(z2)
    n = draws * len(s.known_map.ids) * 3
    assert chi2.ppf(0.005, n) <= total <= chi2.ppf(0.995, n)


def test_thin_poles_keep_a_positive_radius(tmp_path: Path) -> None:
    text = SMALL.replace("radius = 0.3", "radius = 0.02")
    s = load_scenario(_write(tmp_path, text))
    rng = np.random.default_rng(0)
    for _ in range(200):
        km = build_known_map(s, rng)
        assert np.all(km.params[km.kinds == 1, 2] > 0.0)


def test_check_visibility_counts_sampled_steps(tmp_path: Path) -> None:
    s = load_scenario(_write(tmp_path, SMALL))
    m = _motion(s)
    counts = check_visibility(s, m, stride=8)
    assert counts.shape == (len(range(0, 40, 8)) + 1,)  # and the last pose
    assert counts.min() >= 1


# --------------------------------------------------------------------------- controls

#: The trajectory of SMALL as a table of controls: 39 steps straight ahead.
SMALL_CONTROLS = SMALL.replace(
    "steps = 40\nwaypoints = [[0.0, 0.0], [20.0, 0.0]]",
    'controls = [[2.0, 0.0, 30], [1.5, "pi/64", 5], [2.0, -0.1, 4]]',
)


def test_controls_scenario_loads(tmp_path: Path) -> None:
    s = load_scenario(_write(tmp_path, SMALL_CONTROLS))
    assert s.controls == (
        ControlSegment(speed_mps=2.0, steer_rad=0.0, steps=30),
        ControlSegment(speed_mps=1.5, steer_rad=math.pi / 64, steps=5),
        ControlSegment(speed_mps=2.0, steer_rad=-0.1, steps=4),
    )
    assert s.steps == 40  # the start and the 39 steps the controls drive
    assert s.waypoints.shape == (0, 2)
    table = control_table(s.controls)
    assert table.shape == (39, 2)
    np.testing.assert_array_equal(table[29:31], [[2.0, 0.0], [1.5, math.pi / 64]])
    np.testing.assert_array_equal(table[-1], [2.0, -0.1])
    # steps may be given too, when it agrees with the controls
    agreed = SMALL_CONTROLS.replace("controls =", "steps = 40\ncontrols =")
    assert load_scenario(_write(tmp_path, agreed, "agreed.toml")).steps == 40


def test_waypoint_scenarios_have_no_controls(tmp_path: Path) -> None:
    s = load_scenario(_write(tmp_path, SMALL))
    assert s.controls == ()
    assert control_table(s.controls).shape == (0, 2)


def test_controls_steering_limit_is_the_vehicles(tmp_path: Path) -> None:
    """The limit is ``vehicle.max_steer_rad`` as the file sets it, not the default."""
    wide = SMALL_CONTROLS.replace("-0.1, 4]", "-0.7, 4]") + "\n[vehicle]\nmax_steer_rad = 0.75\n"
    assert load_scenario(_write(tmp_path, wide)).controls[-1].steer_rad == -0.7
    with pytest.raises(ScenarioError) as info:
        load_scenario(_write(tmp_path, wide.replace("0.75", "0.6"), "narrow.toml"))
    assert info.value.key == "trajectory.controls[2][1]"
    assert "max_steer_rad = 0.6" in info.value.reason


def test_controls_drive_the_expected_circle() -> None:
    """circle_controls.toml: 10 m straight east, then a circle of radius L / tan φ = 10 m
    about (10, 10).  With the slip made negligible the true path is exact; with the
    file's slip (σ 2 mm, 0.2 mrad per step) it stays within 20 cm."""
    s = load_scenario(CIRCLE_CONTROLS)
    assert s.steps == 1 + 40 + 252
    L, phi = s.vehicle.wheelbase_m, s.controls[1].steer_rad
    radius = L / math.tan(phi)
    assert radius == pytest.approx(10.0, abs=1e-12)
    quiet = dataclasses.replace(s, vehicle=VehicleParams(slip_sigma=(1e-12, 1e-12, 1e-12)))
    P = simulate_drive(quiet, np.random.default_rng(0)).true_poses
    np.testing.assert_allclose(P[:41, 0], 0.25 * np.arange(41), atol=1e-9)
    np.testing.assert_allclose(P[:41, 1:], 0.0, atol=1e-9)
    np.testing.assert_allclose(np.hypot(P[40:, 0] - 10.0, P[40:, 1] - 10.0), radius, atol=1e-8)
    turn = wrap_angle(np.diff(P[40:, 2]))
    np.testing.assert_allclose(turn, 0.25 / radius, atol=1e-12)  # Δθ = s / R, s = 0.25 m
    # One lap is 2πR / 0.25 m ≈ 251.3 steps: the end is just past the circle's start.
    assert np.hypot(*(P[-1, :2] - P[40, :2])) < 0.25
    noisy = _motion(s).true_poses
    assert np.abs(np.hypot(noisy[40:, 0] - 10.0, noisy[40:, 1] - 10.0) - radius).max() < 0.2
    np.testing.assert_array_equal(_motion(s).controls[1:], control_table(s.controls))


def test_controls_scenario_simulates_reproducibly() -> None:
    s = load_scenario(CIRCLE_CONTROLS)
    a = simulate(s, seed=3).log
    assert a.n_steps == s.steps
    assert a.true_poses is not None
    np.testing.assert_array_equal(a.true_poses, _motion(s, seed=3).true_poses)
    kinds = set(a.feat_kind.tolist())
    assert kinds == {int(FeatureKind.LINE), int(FeatureKind.CIRCLE)}
    assert set(a.feat_true_id.tolist()) >= {1, 2, 3, 4}
    b = simulate(s, seed=3).log
    np.testing.assert_array_equal(a.feat_params, b.feat_params)
    np.testing.assert_array_equal(a.odometry, b.odometry)


def test_shortened_controls_drive_the_first_steps() -> None:
    """``dataclasses.replace(scenario, steps=…)`` shortens a controls drive as it does a
    waypoint drive; it cannot lengthen it."""
    s = load_scenario(CIRCLE_CONTROLS)
    full = _motion(s)
    short = _motion(dataclasses.replace(s, steps=100))
    assert short.true_poses.shape == (100, 3)
    np.testing.assert_array_equal(short.true_poses, full.true_poses[:100])
    with pytest.raises(ValueError, match=r"steps must be in \[2, 293\]"):
        _motion(dataclasses.replace(s, steps=294))


# --------------------------------------------------------------------------- loop600


@pytest.fixture(scope="module")
def loop600() -> Scenario:
    return load_scenario("loop600")


@pytest.fixture(scope="module")
def loop600_motion(loop600: Scenario) -> MotionResult:
    return _motion(loop600)


def test_loop600_is_builtin_and_loads_by_path_too(loop600: Scenario) -> None:
    assert "loop600" in list_builtin_scenarios()
    by_path = load_scenario(Path(loop600.source))
    assert by_path.world == loop600.world
    np.testing.assert_array_equal(by_path.waypoints, loop600.waypoints)
    assert Path(loop600.source).name == "loop600.toml"


def test_loop600_has_the_papers_values(loop600: Scenario) -> None:
    s = loop600
    assert s.name == "loop600"
    assert s.seed == 0
    assert s.steps == 2400
    np.testing.assert_allclose(s.start, [-29.0, -11.0, math.pi / 3], atol=1e-15)
    # Table 1 and Sect. 4.2
    assert s.laser.sigma_range_m == 0.05
    assert s.laser.sigma_bearing_rad == pytest.approx(math.pi / 720, abs=1e-15)
    assert s.laser.max_range_m == 80.0
    assert s.laser.fov_rad == pytest.approx(math.pi, abs=1e-15)
    assert s.laser.n_beams == 361
    assert s.vehicle.sigma_v == 0.10
    assert s.vehicle.sigma_phi == pytest.approx(math.pi / 360, abs=1e-15)
    assert s.vehicle.dt_s == 0.125
    assert s.vehicle.step_length_m == pytest.approx(0.25)
    # Known map: Wknown = [0, 0, 0], 10 cm on coordinates and radii, 0.05 rad on angles.
    km = s.known_map
    np.testing.assert_array_equal(km.frame, np.zeros(3))
    assert (km.sigma_xy_m, km.sigma_r_m, km.sigma_theta_rad) == (0.10, 0.10, 0.05)
    assert km.moved == ()
    assert km.removed == ()
    assert km.added == ()


def test_loop600_world_has_lines_and_circles_in_the_papers_box(loop600: Scenario) -> None:
    w = loop600.world
    assert len(w.segments) >= 20
    assert len(w.circles) >= 40
    pts = np.vstack([w.seg_p1, w.seg_p2, w.circ_c])
    x0, x1, y0, y1 = PAPER_BOX
    assert np.all((pts[:, 0] >= x0) & (pts[:, 0] <= x1) & (pts[:, 1] >= y0) & (pts[:, 1] <= y1))
    lengths = np.array([s.length for s in w.segments])
    assert lengths.min() >= 10.0
    assert lengths.max() <= 60.0
    assert w.circ_r.min() >= 0.2
    assert w.circ_r.max() <= 1.0
    assert np.mean(w.circ_r >= 0.3) >= 0.9


def test_loop600_known_map_holds_part_of_the_world(loop600: Scenario) -> None:
    w, km = loop600.world, loop600.known_map
    frac = len(km.ids) / len(w.ids)
    assert 0.5 <= frac <= 0.7
    kinds = {s.id: 0 for s in w.segments} | {c.id: 1 for c in w.circles}
    assert {kinds[i] for i in km.ids} == {0, 1}  # both types
    # Everything near the start is known, so the match can happen early.
    start = loop600.start[:2]
    near = [
        fid
        for fid in w.ids
        if np.hypot(*(w.feature(fid)[1][:2] - start)) < 30.0  # midpoint / centre
    ]
    assert len(near) >= 8
    assert set(near) <= set(km.ids)


def test_loop600_drive_is_a_closed_600m_loop(
    loop600: Scenario, loop600_motion: MotionResult
) -> None:
    P = loop600_motion.true_poses
    assert P.shape == (2400, 3)
    np.testing.assert_array_equal(P[0], loop600.start)
    assert loop600_motion.path_length_m == pytest.approx(600.0, abs=12.0)
    assert np.hypot(*(P[-1, :2] - P[0, :2])) < 3.0
    x0, x1, y0, y1 = PAPER_BOX
    assert P[:, 0].min() > x0
    assert P[:, 0].max() < x1
    assert P[:, 1].min() > y0
    assert P[:, 1].max() < y1


def test_loop600_no_feature_within_3m_of_the_path(
    loop600: Scenario, loop600_motion: MotionResult
) -> None:
    P = loop600_motion.true_poses[:, :2]
    w = loop600.world
    d_circ = np.hypot(*(w.circ_c[:, None, :] - P[None, :, :]).transpose(2, 0, 1)).min(axis=1)
    assert (d_circ - w.circ_r).min() >= 3.0
    for s in w.segments:
        a, b = np.array(s.p1), np.array(s.p2)
        t = np.clip((P - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
        assert np.hypot(*(a + t[:, None] * (b - a) - P).T).min() >= 3.0, s.id


def test_loop600_three_features_in_view_at_every_step(
    loop600: Scenario, loop600_motion: MotionResult
) -> None:
    counts = features_in_view(loop600.world, loop600_motion.true_poses, loop600.laser)
    assert counts.shape == (2400,)
    assert counts.min() >= 3
    sampled = check_visibility(loop600, loop600_motion)
    assert sampled.min() >= 3


def test_loop600_walls_in_view_are_never_all_parallel(
    loop600: Scenario, loop600_motion: MotionResult
) -> None:
    """Where walls are well seen (≥ 10 beams), at least two differ by ≥ 15° in angle."""
    w = loop600.world
    angle = {s.id: math.atan2(s.p2[1] - s.p1[1], s.p2[0] - s.p1[0]) for s in w.segments}
    bearings = loop600.laser.bearings()
    for k, pose in enumerate(loop600_motion.true_poses):
        _, ids = cast_rays(w, pose, pose[2] + bearings, loop600.laser.max_range_m)
        u, n = np.unique(ids[ids >= 0], return_counts=True)
        a = np.array(
            [angle[i] for i, c in zip(u.tolist(), n, strict=True) if i in angle and c >= 10]
        )
        assert a.size >= 2, k
        diff = np.abs(wrap_angle(2.0 * (a[:, None] - a[None, :]))) / 2.0  # modulo π
        assert diff.max() >= math.radians(15.0), k


def test_draw_offset_of_a_rigidly_moved_map_is_that_motion() -> None:
    km = build_known_map(load_scenario("loop600"), np.random.default_rng(0))
    T = np.array([0.3, -0.2, 0.01])
    moved = np.array(
        [
            transform_feature(FeatureKind(int(k)), T, f)[0]
            for k, f in zip(km.kinds, km.true_params, strict=True)
        ]
    )
    off = known_map_draw_offset(km.kinds, moved, km.covs, km.true_params)
    np.testing.assert_allclose(off.offset, T, atol=1e-9)
    # 63 features at σ 0.1 m: about 0.1/√(≈48 effective) per axis.
    assert 0.01 < math.sqrt(off.cov[0, 0]) < 0.02


def test_draw_offset_does_not_depend_on_where_the_map_frame_is() -> None:
    """Far from the origin (map coordinates in UTM, say) the same draw gives the same
    rigid motion and NEES; an origin-dependent conditioning test once rejected it."""
    km = build_known_map(load_scenario("loop600"), np.random.default_rng(1))
    here = known_map_draw_offset(km.kinds, km.params, km.covs, km.true_params)
    far = np.array([3.0e5, 6.2e6, 0.4])  # a frame 6,000 km away, turned
    move = [
        (
            transform_feature(FeatureKind(int(k)), far, z),
            transform_feature(FeatureKind(int(k)), far, f),
        )
        for k, z, f in zip(km.kinds, km.params, km.true_params, strict=True)
    ]
    params = np.array([z[0] for z, _ in move])
    covs = np.array([z[2] @ C @ z[2].T for (z, _), C in zip(move, km.covs, strict=True)])
    there = known_map_draw_offset(km.kinds, params, covs, np.array([f[0] for _, f in move]))
    # The same rigid motion seen from the far frame: far ⊕ here ⊕ ⊖far.
    expected = compose(compose(far, here.offset), inverse(far))
    np.testing.assert_allclose(there.offset[2], expected[2], atol=1e-12)
    np.testing.assert_allclose(there.offset[:2], expected[:2], atol=1e-6)
    assert there.nees == pytest.approx(here.nees, rel=1e-6)
    assert not there.offset.flags.writeable


def test_draw_offset_is_chi2_over_draws_of_loop600() -> None:
    """The map's stated σ is honest as a whole too: the offset's NEES over 200 draws
    averages 3 (σ of the mean √(6/200) = 0.17; bounds ±3σ)."""
    s = load_scenario("loop600")
    rng = np.random.default_rng(7)
    nees = [
        known_map_draw_offset(km.kinds, km.params, km.covs, km.true_params).nees
        for km in (build_known_map(s, rng) for _ in range(200))
    ]
    assert 2.48 <= float(np.mean(nees)) <= 3.52


def test_draw_offset_rejects_bad_maps() -> None:
    km = build_known_map(load_scenario("loop600"), np.random.default_rng(0))
    # Walls at one angle only (either direction): nothing fixes the position along them.
    walls = np.array([[0.0, 0.0, 0.0], [0.0, 5.0, 0.0], [3.0, -4.0, math.pi]])
    kinds = np.zeros(3, dtype=np.int8)
    covs = np.tile(np.diag([0.01, 0.01, 0.0025]), (3, 1, 1))
    with pytest.raises(ValueError, match="do not fix a rigid frame"):
        known_map_draw_offset(kinds, walls, covs, walls)
    bad = km.params.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="params holds NaN"):
        known_map_draw_offset(km.kinds, bad, km.covs, km.true_params)
    with pytest.raises(ValueError, match="FeatureKind codes"):
        known_map_draw_offset(km.kinds.astype(float), km.params, km.covs, km.true_params)
    with pytest.raises(ValueError, match="FeatureKind codes"):
        known_map_draw_offset(km.kinds * 5, km.params, km.covs, km.true_params)
    covs = km.covs.copy()
    covs[2, 0, 1] = 0.001
    with pytest.raises(ValueError, match=r"covs\[2\] is not symmetric"):
        known_map_draw_offset(km.kinds, km.params, covs, km.true_params)
    with pytest.raises(ValueError, match=r"covs\[0\] is not positive definite"):
        known_map_draw_offset(km.kinds, km.params, -km.covs, km.true_params)
    with pytest.raises(ValueError, match="max_iterations"):
        known_map_draw_offset(km.kinds, km.params, km.covs, km.true_params, max_iterations=0)
    with pytest.raises(ValueError, match="no convergence in 1 iterations"):
        known_map_draw_offset(km.kinds, km.params, km.covs, km.true_params, max_iterations=1)
    with pytest.raises(ValueError, match="M ≥ 1"):
        known_map_draw_offset(km.kinds[:0], km.params[:0], km.covs[:0], km.true_params[:0])
    with pytest.raises(ValueError, match="M ≥ 1"):
        known_map_draw_offset(km.kinds, km.params[:-1], km.covs, km.true_params)
