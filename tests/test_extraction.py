"""Feature extraction: exact recovery from noise-free scans, labels, rejections, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.optimize import least_squares

from mapfuse_core.geometry.features import FeatureKind, canonical_line, express_in, line_to_normal
from mapfuse_core.models import line_pairing
from mapfuse_core.perception import extraction as ex
from mapfuse_core.perception.extraction import ExtractedFeature, ExtractionParams, extract_features
from mapfuse_core.sensor import LaserParams, Scan
from mapfuse_core.sim.laser import simulate_scan
from mapfuse_core.sim.world import CircleObstacle, WallSegment, World

EXACT = LaserParams(sigma_range_m=0.0, sigma_bearing_rad=0.0)
ORIGIN = np.zeros(3)


def scan_of(world: World, pose: np.ndarray, laser: LaserParams = EXACT, seed: int = 0) -> Scan:
    return simulate_scan(world, pose, laser, np.random.default_rng(seed))


def only(features: tuple[ExtractedFeature, ...], kind: FeatureKind) -> list[ExtractedFeature]:
    return [f for f in features if f.kind == kind]


def assert_line_matches(f: ExtractedFeature, world: World, pose: np.ndarray, tol: float) -> None:
    kind, true_w = world.feature(f.true_id)
    assert kind == FeatureKind.LINE
    true_s = express_in(FeatureKind.LINE, pose, true_w)[0]
    r, _, _ = line_pairing(f.params, true_s)
    assert abs(r[0]) < tol
    assert abs(r[1]) < tol


# --------------------------------------------------------------------------- exact recovery


def test_noise_free_wall_is_recovered_exactly() -> None:
    world = World((WallSegment(1, (10.0, -8.0), (10.0, 8.0)),), ())
    res = extract_features(scan_of(world, ORIGIN), EXACT)
    assert len(res.features) == 1
    f = res.features[0]
    assert f.kind == FeatureKind.LINE
    assert f.true_id == 1
    # The SPmap frame sits on the line, its y axis towards the sensor.
    assert abs(f.params[0] - 10.0) < 1e-9
    assert np.allclose(canonical_line(f.params), f.params)
    normal, _ = line_to_normal(f.params)
    assert normal[0] == pytest.approx(10.0, abs=1e-9)
    assert normal[1] == pytest.approx(0.0, abs=1e-9)
    # Midpoint of the fitted points, which are symmetric about y = 0.
    assert abs(f.params[1]) < 0.1
    lo, hi = f.extent
    assert lo == pytest.approx(-hi, abs=1e-6)
    assert 7.0 < hi <= 8.0  # trimmed ends of a 16 m wall
    assert f.n_points > 50


def assert_circle_within_silhouette_step(f: ExtractedFeature, truth: np.ndarray) -> None:
    """A noise-free scan reads a trunk's silhouette only to the beam grid: each edge lies
    somewhere in the half spacing beyond the outermost return.  Exact ranges pin the near
    side, so the radius and the centre can be off by at most about the distance times
    half a spacing (both edges off the same way), and the stated covariance (the
    uniform grid's ``Δβ²/12`` per edge) must cover that."""
    dist = math.hypot(truth[0], truth[1])
    step = dist * EXACT.beam_spacing_rad
    err = f.params - truth
    assert abs(err[2]) <= 0.5 * step
    assert math.hypot(err[0], err[1]) <= 0.75 * step
    assert float(err @ np.linalg.solve(f.cov, err)) <= 16.27  # χ²(3) at 0.999


def test_noise_free_circle_is_recovered_to_the_beam_grid() -> None:
    world = World((), (CircleObstacle(5, (4.0, 1.0), 0.6),))
    res = extract_features(scan_of(world, ORIGIN), EXACT)
    assert len(res.features) == 1
    f = res.features[0]
    assert f.kind == FeatureKind.CIRCLE
    assert f.true_id == 5
    assert_circle_within_silhouette_step(f, np.array([4.0, 1.0, 0.6]))
    assert math.isnan(f.extent[0])
    assert math.isnan(f.extent[1])


def test_circle_fit_is_exact_on_exact_ranges_and_edges() -> None:
    """The range model and the silhouette model are exact: ranges and edge readings at
    their means give back the circle."""
    laser = LaserParams()
    noise = ex._Noise(laser.sigma_range_m**2, laser.sigma_bearing_rad**2, 1e-12)
    truth = np.array([5.0, 1.5, 0.45])
    d = math.hypot(truth[0], truth[1])
    phi, half = math.atan2(truth[1], truth[0]), math.asin(truth[2] / d)
    b = phi + np.linspace(-0.6, 0.6, 9) * half
    r = ex._circle_system(b, truth, noise)[0]
    edges = ex._Edges(
        tau=phi + np.array([-1.0, 1.0]) * (half - 0.001),
        side=np.array([-1.0, 1.0]),
        bias=-0.001,
        var=1e-5,
        v_min=-math.inf,
    )
    fit = ex._refine_circle(r, b, truth + np.array([0.05, -0.04, 0.1]), noise, edges)
    assert fit is not None
    np.testing.assert_allclose(fit.x, truth, rtol=0.0, atol=1e-9)


def test_noise_free_corner_gives_two_exact_lines() -> None:
    world = World(
        (WallSegment(1, (12.0, -10.0), (12.0, 4.0)), WallSegment(2, (12.0, 4.0), (-6.0, 10.0))),
        (),
    )
    pose = np.array([0.0, 0.0, 0.4])
    res = extract_features(scan_of(world, pose), EXACT)
    lines = only(res.features, FeatureKind.LINE)
    assert sorted(f.true_id for f in lines) == [1, 2]
    for f in lines:
        assert_line_matches(f, world, pose, 1e-8)


wall_pose = st.tuples(
    st.floats(min_value=3.0, max_value=40.0),  # distance of the wall
    st.floats(min_value=-1.0, max_value=1.0),  # its tilt w.r.t. the sensor
    st.floats(min_value=-math.pi, max_value=math.pi),  # sensor heading in the world
)


@given(wall_pose)
def test_noise_free_wall_any_pose(p: tuple[float, float, float]) -> None:
    d, tilt, heading = p
    c, s = math.cos(tilt), math.sin(tilt)
    # Wall through (d, 0) in the sensor frame, tilted; 30 m long. World = sensor rotated.
    a = np.array([d - 15.0 * s, 15.0 * c])
    b = np.array([d + 15.0 * s, -15.0 * c])
    rot = np.array(
        [[math.cos(heading), -math.sin(heading)], [math.sin(heading), math.cos(heading)]]
    )
    pw1, pw2 = rot @ a, rot @ b
    world = World((WallSegment(3, tuple(pw1), tuple(pw2)),), ())
    pose = np.array([0.0, 0.0, heading])
    res = extract_features(scan_of(world, pose), EXACT)
    lines = only(res.features, FeatureKind.LINE)
    assert len(lines) >= 1
    for f in lines:
        assert f.true_id == 3
        assert_line_matches(f, world, pose, 1e-7)
        assert np.allclose(canonical_line(f.params), f.params)


@given(
    st.floats(min_value=2.5, max_value=6.0),
    st.floats(min_value=-1.2, max_value=1.2),
    st.floats(min_value=0.4, max_value=1.0),
)
def test_noise_free_circle_any_pose(dist: float, bearing: float, radius: float) -> None:
    centre = (dist * math.cos(bearing), dist * math.sin(bearing))
    world = World((), (CircleObstacle(9, centre, radius),))
    res = extract_features(scan_of(world, ORIGIN), EXACT)
    circles = only(res.features, FeatureKind.CIRCLE)
    assert len(circles) == 1
    assert_circle_within_silhouette_step(circles[0], np.array([*centre, radius]))


# --------------------------------------------------------------------------- covariances


def test_covariances_are_symmetric_positive_and_pseudo_variance_along_line() -> None:
    world = World(
        (WallSegment(1, (10.0, -8.0), (10.0, 8.0)),), (CircleObstacle(2, (4.0, -3.0), 0.8),)
    )
    res = extract_features(scan_of(world, ORIGIN, LaserParams(), seed=5), LaserParams())
    kinds = {f.kind for f in res.features}
    assert kinds == {FeatureKind.LINE, FeatureKind.CIRCLE}
    for f in res.features:
        assert f.cov.shape == (3, 3)
        assert np.allclose(f.cov, f.cov.T)
        assert np.all(np.linalg.eigvalsh(f.cov) > 0.0)
        if f.kind == FeatureKind.LINE:
            t = np.array([math.cos(f.params[2]), math.sin(f.params[2]), 0.0])
            length = f.extent[1] - f.extent[0]
            # L²/12, plus the small along-line motion of the origin when α changes (ρ σα).
            assert t @ f.cov @ t == pytest.approx(length**2 / 12.0, rel=1e-3)
            # The pairing with the observation first does not see the pseudo-variance.
            _, Ja, _ = line_pairing(f.params, f.params + np.array([0.5, 0.01, 0.002]))
            assert np.allclose(Ja @ t, 0.0, atol=1e-2)


def test_extraction_is_deterministic() -> None:
    world = World(
        (WallSegment(1, (10.0, -8.0), (10.0, 8.0)),), (CircleObstacle(2, (4.0, -3.0), 0.8),)
    )
    scan = scan_of(world, ORIGIN, LaserParams(), seed=11)
    a = extract_features(scan, LaserParams())
    b = extract_features(scan, LaserParams())
    assert a.rejected == b.rejected
    assert len(a.features) == len(b.features)
    for fa, fb in zip(a.features, b.features, strict=True):
        assert np.array_equal(fa.params, fb.params)
        assert np.array_equal(fa.cov, fb.cov)


@pytest.mark.parametrize("seed", range(6))
def test_circle_fits_solve_the_problem_least_squares_solved(seed: int) -> None:
    """The circle fits call MINPACK through ``leastsq`` (and estimate the point-space
    Jacobian themselves) to skip ``least_squares``' overhead: same solver, same problem,
    so the same solution as ``least_squares(method="lm")`` with its default Jacobian."""
    laser = LaserParams()
    world = World((), (CircleObstacle(3, (6.0, 1.0 - 0.4 * seed), 0.3 + 0.1 * seed),))
    scan = scan_of(world, ORIGIN, laser, seed=seed)
    hit = scan.hit_ids == 3
    r, b = scan.ranges[hit][1:-1], scan.bearings[hit][1:-1]
    P = np.column_stack((r * np.cos(b), r * np.sin(b)))
    noise = ex._Noise(laser.sigma_range_m**2, laser.sigma_bearing_rad**2, 1e-12)
    geo = ex._geometric_circle(P, r, b, noise, 8.0)
    assert geo is not None
    x = ex._kasa(P)
    assert x is not None
    for _ in range(2):
        sig = np.sqrt(ex._normal_var(noise, r, ex._beam_cos_inc(x, np.sin(b), np.cos(b))))

        def fun(p: np.ndarray, sig: np.ndarray = sig) -> np.ndarray:
            return np.asarray((np.hypot(*(P - p[:2]).T) - p[2]) / sig)

        x = least_squares(fun, x, method="lm", xtol=1e-10, ftol=1e-10).x
    x[2] = abs(x[2])
    np.testing.assert_allclose(geo.x, x, rtol=0.0, atol=1e-9)
    fit = ex._refine_circle(r, b, geo.x, noise)
    assert fit is not None
    x = geo.x.copy()
    for _ in range(2):
        sig = np.sqrt(ex._circle_system(b, x, noise)[2])

        def res(p: np.ndarray, sig: np.ndarray = sig) -> np.ndarray:
            return np.asarray((r - ex._circle_system(b, p, noise)[0]) / sig)

        def jac(p: np.ndarray, sig: np.ndarray = sig) -> np.ndarray:
            return np.asarray(-ex._circle_system(b, p, noise)[1] / sig[:, None])

        x = least_squares(res, x, jac=jac, method="lm", xtol=1e-12, ftol=1e-12).x
    x[2] = abs(x[2])
    np.testing.assert_allclose(fit.x, x, rtol=0.0, atol=1e-9)


# --------------------------------------------------------------------------- silhouette


def test_edge_reading_model_matches_the_simulated_laser() -> None:
    """The model of where the beams stop hitting a trunk (``_edge_moments``): exact at
    σβ = 0 (uniform over a spacing), and matching 3,000 simulated scans of one trunk
    at the paper's σβ = Δβ/2.  Per edge and scan the reading varies by about 0.55
    spacings, so the mean of 6,000 readings is known to ±0.007 spacings (σ) and their
    variance to ±0.006 spacings²: the bounds are about 3.5 of those."""
    mean0, var0 = ex._edge_moments(0.0)
    assert mean0 == pytest.approx(0.0, abs=1e-12)
    assert var0 == pytest.approx(1.0 / 12.0, rel=1e-4)
    laser = LaserParams()
    spacing = laser.beam_spacing_rad
    mean, var = ex._edge_moments(laser.sigma_bearing_rad / spacing)
    assert -0.03 < mean < -0.02  # an inner beam that misses ends the cluster early
    world = World((), (CircleObstacle(1, (6.0, 0.0), 0.5),))
    rng = np.random.default_rng(3)
    err = []
    for _ in range(3000):
        heading = float(rng.uniform(-0.01, 0.01))
        scan = simulate_scan(world, np.array([0.0, 0.0, heading]), laser, rng)
        hits = np.flatnonzero(scan.hit_ids == 1)
        runs = np.split(hits, np.flatnonzero(np.diff(hits) != 1) + 1)
        trunk = max(runs, key=len)  # a stray hit beyond a missed beam is another cluster
        first, last = trunk[0], trunk[-1]
        half = math.asin(0.5 / 6.0)
        err.append((scan.bearings[last] + 0.5 * spacing - (-heading + half)) / spacing)
        err.append(-(scan.bearings[first] - 0.5 * spacing - (-heading - half)) / spacing)
    assert float(np.mean(err)) == pytest.approx(mean, abs=0.025)
    assert float(np.var(err)) == pytest.approx(var, abs=0.02)


def test_every_cluster_above_the_smallest_candidate_size_is_a_candidate() -> None:
    """``r / σ_r`` of the hypothetical circle falls back when the grazing cut drops a
    pair of beams: at 1.8 m a cluster of 22 returns qualifies and one of 23 does not.
    The detection rule is the smallest qualifying size, so a 23-return cluster is a
    candidate too, and the fit's bound on the silhouette's width has no gaps."""
    laser = LaserParams()
    noise = ex._Noise(laser.sigma_range_m**2, laser.sigma_bearing_rad**2, 1e-12)
    params = ExtractionParams()
    sizes = np.arange(7, 40)
    snr, usable = ex._silhouette_candidates(1.8, laser.beam_spacing_rad, sizes, noise, params)
    i22, i23 = 22 - 7, 23 - 7
    assert snr[i22] >= params.min_circle_snr > snr[i23]
    assert int(sizes[np.flatnonzero(snr >= params.min_circle_snr)[0]]) == 22
    assert np.count_nonzero(usable[i23]) < np.count_nonzero(usable[i22]) + 1
    # A cluster of 23 returns at that range is a candidate.
    b = (np.arange(21) - 10.0) * laser.beam_spacing_rad
    span = (float(b[0] - laser.beam_spacing_rad), float(b[-1] + laser.beam_spacing_rad))
    chosen = ex._candidate_beams(np.full(21, 1.8), b, span, noise, params)
    assert chosen is not None
    assert chosen[2] == 22


def test_detection_correction_only_acts_near_the_detection_limit() -> None:
    """Far above the smallest detectable width the fit is left alone; at the limit the
    width read is lowered by about σλ(α) through the fit's gain, and the radius with it."""
    x = np.array([15.0, 0.0, 0.9])
    # The near side is known far better than the radius: centre and radius move together.
    cov = np.array(
        [[0.04**2, 0.0, 0.95 * 0.04**2], [0.0, 0.03**2, 0.0], [0.95 * 0.04**2, 0.0, 0.04**2]]
    )
    spacing = LaserParams().beam_spacing_rad
    half = math.asin(0.9 / 15.0)
    tau = np.array([-half, half])
    far = ex._Edges(tau, np.array([-1.0, 1.0]), 0.0, 0.3 * spacing**2, 2 * half - 10 * spacing)
    x_far, cov_far = ex._detection_correction(x, cov, far)
    np.testing.assert_array_equal(x_far, x)
    np.testing.assert_allclose(cov_far, cov, atol=1e-15)
    near = ex._Edges(tau, np.array([-1.0, 1.0]), 0.0, 0.3 * spacing**2, 2 * half)
    x_near, _ = ex._detection_correction(x, cov, near)
    assert x_near[2] < x[2] - 0.003  # the radius comes down
    assert x_near[0] < x[0]  # and the centre nearer


# --------------------------------------------------------------------------- labels


def test_hit_ids_only_label_the_features() -> None:
    world = World(
        (WallSegment(1, (10.0, -8.0), (10.0, 8.0)),), (CircleObstacle(2, (4.0, -3.0), 0.8),)
    )
    scan = scan_of(world, ORIGIN, LaserParams(), seed=2)
    blind = Scan(scan.bearings, scan.ranges, np.full(scan.hit_ids.shape, -1))
    a = extract_features(scan, LaserParams())
    b = extract_features(blind, LaserParams())
    assert len(a.features) == len(b.features)
    for fa, fb in zip(a.features, b.features, strict=True):
        assert fa.kind == fb.kind
        assert np.array_equal(fa.params, fb.params)
        assert fb.true_id == -1


def test_majority_label() -> None:
    world = World((WallSegment(1, (10.0, -8.0), (10.0, 8.0)),), ())
    scan = scan_of(world, ORIGIN)
    ids = scan.hit_ids.copy()
    hit = np.flatnonzero(ids == 1)
    mixed = ids.copy()
    mixed[hit[: hit.size // 2]] = 7  # half the wall's points claim another id
    few = ids.copy()
    few[hit[1:4]] = 7  # a handful do
    f_mixed = extract_features(Scan(scan.bearings, scan.ranges, mixed), EXACT).features[0]
    f_few = extract_features(Scan(scan.bearings, scan.ranges, few), EXACT).features[0]
    assert f_mixed.true_id == -1
    assert f_few.true_id == 1
    strict = ExtractionParams(label_majority=1.0)
    assert (
        extract_features(Scan(scan.bearings, scan.ranges, few), EXACT, strict).features[0].true_id
        == -1
    )


# --------------------------------------------------------------------------- rejections


def test_empty_and_blank_scans_give_no_features() -> None:
    empty = Scan(np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64))
    res = extract_features(empty, LaserParams())
    assert res.features == ()
    assert res.rejected == {}
    laser = LaserParams()
    blank = Scan(laser.bearings(), np.full(laser.n_beams, np.inf), np.full(laser.n_beams, -1))
    res = extract_features(blank, laser)
    assert res.features == ()
    assert res.rejected == {}


def test_small_far_things_are_rejected_with_reasons() -> None:
    world = World(
        (WallSegment(1, (10.0, 0.0), (10.0, 1.5)),),  # 1.5 m of wall: too short
        (CircleObstacle(2, (40.0, -10.0), 0.3),),  # 2 beams on a far trunk: too few points
    )
    res = extract_features(scan_of(world, ORIGIN, LaserParams()), LaserParams())
    assert res.features == ()
    assert res.rejected.get("too_short", 0) + res.rejected.get("too_few_points", 0) == 2
    assert res.rejected.get("too_few_points", 0) >= 1


def test_circle_cut_by_the_field_of_view_is_not_a_circle() -> None:
    world = World((), (CircleObstacle(2, (0.3, 4.0), 0.8),))  # straddles the +90° beam
    res = extract_features(scan_of(world, ORIGIN), EXACT)
    assert only(res.features, FeatureKind.CIRCLE) == []


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"jump_abs_m": -1.0}, "jump_abs_m must be >= 0"),
        ({"min_line_points": 2}, "min_line_points must be >= 3"),
        ({"min_circle_points": 3}, "min_circle_points must be >= 4"),
        ({"end_trim": 1.5}, "end_trim must be an integer"),
        ({"chi2_quantile": 1.0}, "chi2_quantile must be in"),
        ({"label_majority": 0.5}, "label_majority must be in"),
        ({"circle_radius_min_m": 3.0}, "circle_radius_min_m must be <"),
        ({"max_line_incidence_rad": 2.0}, "max_line_incidence_rad must be in"),
        ({"sigma_floor_m": 0.0}, "sigma_floor_m must be > 0"),
        ({"split_tol_sigma": math.nan}, "split_tol_sigma must be finite"),
        ({"min_circle_snr": "5"}, "min_circle_snr must be a number"),
        ({"occluded_end_margin": 1}, "occluded_end_margin must be a bool"),
    ],
)
def test_bad_extraction_params_raise(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        ExtractionParams(**kwargs)  # type: ignore[arg-type]


def test_bad_arguments_raise() -> None:
    laser = LaserParams()
    scan = scan_of(World((WallSegment(1, (10.0, -8.0), (10.0, 8.0)),), ()), ORIGIN, laser)
    with pytest.raises(ValueError, match="scan must be a Scan"):
        extract_features("scan", laser)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="laser must be a LaserParams"):
        extract_features(scan, None)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="params must be an ExtractionParams"):
        extract_features(scan, laser, {})  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="n_beams=181"):
        extract_features(scan, LaserParams(n_beams=181))
    backwards = Scan(scan.bearings[::-1].copy(), scan.ranges, scan.hit_ids)
    with pytest.raises(ValueError, match="strictly increasing"):
        extract_features(backwards, laser)
