"""CCDA map-to-map matching: recovery, and rejection of symmetric, degenerate and
unrelated maps and of bad input.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.stats import chi2

from mapfuse_core.geometry.se2 import inverse
from mapfuse_core.matching.ccda import CCDAParams, ccda_match, estimate_transform, pairing_chi2
from mapfuse_core.measlog import KnownMapArrays
from tests.ccda_helpers import (
    CIRCLE,
    LINE,
    START,
    T_SYM,
    circle_cov,
    circle_map,
    line_cov,
    make_map,
    moved_copy,
    nees,
    random_feature,
    random_overlap,
    transform_error,
)

# --------------------------------------------------------------------------- recovery


N_SEEDS = 60


def test_random_partial_overlaps_are_recovered() -> None:
    failures = []
    nees_values = []
    for seed in range(N_SEEDS):
        case = random_overlap(seed)
        res = ccda_match(case.map_a, case.map_b)
        wrong = [(i, j) for i, j in res.pairings if case.truth.get(i) != j]
        q = nees(res.x_A_B, res.cov, case.x_A_B) if res.accepted else math.inf
        nees_values.append(q)
        # ~4σ in 3 dof.
        if not res.accepted or wrong or q > chi2.ppf(0.9999, 3):
            failures.append((seed, res.reason, wrong, q))
            continue
        # Nearly all shared features are paired (a few may miss their gate at 0.999).
        assert len(res.pairings) >= 0.9 * len(case.truth), (seed, len(res.pairings))
        assert res.clique_size >= 0.9 * len(case.truth)
        assert res.runner_up_size < len(res.pairings)
    success = 1.0 - len(failures) / N_SEEDS
    assert success == 1.0, f"success rate {success:.0%}; failures: {failures}"
    # The covariance of the match is consistent, not only small.
    mean_nees = float(np.mean(nees_values))
    lo, hi = chi2.ppf([0.005, 0.995], 3 * N_SEEDS) / N_SEEDS
    assert lo <= mean_nees <= hi, mean_nees


def test_every_accepted_pairing_passes_its_gate() -> None:
    case = random_overlap(1234)
    res = ccda_match(case.map_a, case.map_b)
    assert res.accepted
    c2, dof = pairing_chi2(case.map_a, case.map_b, res.x_A_B, res.pairings)
    assert np.all(c2 <= chi2.ppf(0.999, dof))
    assert len({i for i, _ in res.pairings}) == len(res.pairings)
    assert len({j for _, j in res.pairings}) == len(res.pairings)


def test_swapping_the_maps_inverts_the_transform() -> None:
    case = random_overlap(7)
    ab = ccda_match(case.map_a, case.map_b)
    ba = ccda_match(case.map_b, case.map_a)
    assert ab.accepted
    assert ba.accepted
    np.testing.assert_allclose(transform_error(inverse(ba.x_A_B), ab.x_A_B), 0.0, atol=1e-2)
    assert sorted((j, i) for i, j in ba.pairings) == sorted(ab.pairings)


def test_start_pose_of_the_paper() -> None:
    # Known map in Wknown; the global map is the same world seen from the start
    # frame, so x^Wglobal_Wknown = ⊖[−29, −11, π/3].
    rng = np.random.default_rng(5)
    kinds, params, covs = [], [], []
    for k in [CIRCLE] * 12 + [LINE] * 6:
        f, S = random_feature(rng, k, 60.0)
        kinds.append(k)
        params.append(f)
        covs.append(S)
    known = make_map(kinds, params, covs)
    truth = inverse(START)
    global_map = moved_copy(known, truth)
    res = ccda_match(global_map, known)
    assert res.accepted
    np.testing.assert_allclose(transform_error(res.x_A_B, truth), 0.0, atol=1e-9)
    assert res.pairings == tuple((i, i) for i in range(len(known)))


@given(
    st.floats(-100.0, 100.0),
    st.floats(-100.0, 100.0),
    st.floats(-math.pi, math.pi),
    st.permutations(list(range(9))),
)
def test_noise_free_match_recovers_any_transform(
    x: float, y: float, th: float, perm: list[int]
) -> None:
    base = circle_map([(0, 0), (13, 2), (4, 9), (-7, 3), (20, -5)])
    kinds = [CIRCLE] * 5 + [LINE] * 4
    lines = [np.array([1.0, 1.0, 0.3]), np.array([-5.0, 8.0, 1.4]), np.array([9, -4, 2.5])]
    lines.append(np.array([-3.0, -9.0, -0.6]))
    params = np.vstack([base.params, np.array(lines)])
    covs = np.concatenate([base.covs, [line_cov(f[2], 0.05, 0.01) for f in lines]])
    B = make_map(kinds, params, covs)
    T = np.array([x, y, th])
    A_full = moved_copy(B, T)
    A = make_map(A_full.kinds[perm], A_full.params[perm], A_full.covs[perm])
    res = ccda_match(A, B)
    assert res.accepted, res.reason
    np.testing.assert_allclose(transform_error(res.x_A_B, T), 0.0, atol=1e-6)
    assert sorted(res.pairings) == sorted((i, p) for i, p in enumerate(perm))


# --------------------------------------------------------------------------- rejections


@pytest.mark.parametrize(
    "points",
    [
        pytest.param([(0, 0), (10, 0), (10, 10), (0, 10)], id="square"),
        pytest.param([(0, 0), (10, 0), (10, 10), (0, 10), (5, 5)], id="square-and-centre"),
        pytest.param([(10 * i, 10 * j) for i in range(4) for j in range(4)], id="grid-4x4"),
        pytest.param([(10 * i, 7 * j) for i in range(4) for j in range(3)], id="rect-grid"),
        pytest.param(
            [(10 * math.cos(a), 10 * math.sin(a)) for a in np.arange(6) * math.pi / 3],
            id="hexagon",
        ),
    ],
)
def test_symmetric_maps_are_ambiguous(points: list[tuple[float, float]]) -> None:
    B = circle_map(points)
    A = moved_copy(B, T_SYM)
    res = ccda_match(A, B)
    assert not res.accepted
    assert res.reason == "ambiguous"
    # The rival is a symmetry: as many pairings as the best.
    assert res.runner_up_size == len(points)


def test_breaking_the_symmetry_by_radius_gives_a_match() -> None:
    B = circle_map([(0, 0), (10, 0), (10, 10), (0, 10)])
    B = make_map(B.kinds, np.column_stack([B.params[:, :2], [0.3, 0.6, 0.9, 1.2]]), B.covs)
    res = ccda_match(moved_copy(B, T_SYM), B)
    assert res.accepted
    np.testing.assert_allclose(transform_error(res.x_A_B, T_SYM), 0.0, atol=1e-9)
    assert res.runner_up_size == 0


def test_a_rival_within_the_margin_is_ambiguous() -> None:
    # A square plus one asymmetric circle: the right match has 5 pairings, each of
    # the square's rotations 4.  Within the default margin of one: ambiguous.
    B = circle_map([(0, 0), (10, 0), (10, 10), (0, 10), (3, 1)])
    A = moved_copy(B, T_SYM)
    res = ccda_match(A, B)
    assert res.reason == "ambiguous"
    assert len(res.pairings) == 5
    assert res.runner_up_size == 4
    strict = ccda_match(A, B, CCDAParams(ambiguity_margin=0))
    assert strict.accepted
    np.testing.assert_allclose(transform_error(strict.x_A_B, T_SYM), 0.0, atol=1e-9)


def test_too_large_graph_is_refused_quickly() -> None:
    case = random_overlap(3)
    res = ccda_match(case.map_a, case.map_b, CCDAParams(max_edges=100))
    assert not res.accepted
    assert res.reason == "graph too large"
    assert res.n_edges == 101
    assert res.n_nodes > 0


def test_parallel_lines_only_are_degenerate() -> None:
    lines = np.array([[0, 0, 0], [5, 3, 0], [-4, 7, math.pi], [2, 12, 0], [1, -6, 0]], float)
    B = make_map([LINE] * 5, lines, [line_cov(f[2], 0.05, 0.01) for f in lines])
    res = ccda_match(moved_copy(B, T_SYM), B)
    assert not res.accepted
    assert res.reason == "degenerate geometry"
    # The angle is fixed; the translation along the lines is not.
    assert math.sqrt(res.cov[2, 2]) < 0.01
    assert np.linalg.eigvalsh(res.cov[:2, :2]).max() > 1e6


def test_parallel_lines_and_one_circle_are_unverifiable() -> None:
    """The circle alone fixes the position along the lines: no other pairing checks it."""
    lines = np.array([[0, 0, 0], [5, 3, 0], [-4, 7, math.pi], [2, 12, 0]], float)
    params = np.vstack([lines, [[3.0, 5.0, 0.4]]])
    covs = [line_cov(f[2], 0.05, 0.01) for f in lines] + [circle_cov(0.05, 0.05)]
    B = make_map([LINE] * 4 + [CIRCLE], params, covs)
    res = ccda_match(moved_copy(B, T_SYM), B)
    assert not res.accepted
    assert res.reason == "unverifiable"
    # Without the rule the same pairings are accepted, with the right transform.
    loose = ccda_match(moved_copy(B, T_SYM), B, CCDAParams(redundant_pairings=False))
    assert loose.accepted, loose.reason
    np.testing.assert_allclose(transform_error(loose.x_A_B, T_SYM), 0.0, atol=1e-9)


def test_one_wrong_circle_beside_parallel_lines_would_slide_the_match() -> None:
    """The tree seen is another one, 3 m along the walls from the surveyed tree: the
    walls cannot tell, so the match would slide by 3 m; it is refused instead."""
    lines = np.array([[0, 0, 0], [5, 3, 0], [-4, 7, math.pi], [2, 12, 0]], float)
    params = np.vstack([lines, [[3.0, 5.0, 0.4]]])
    covs = [line_cov(f[2], 0.05, 0.01) for f in lines] + [circle_cov(0.05, 0.05)]
    B = make_map([LINE] * 4 + [CIRCLE], params, covs)
    seen = B.params.copy()
    seen[4, 0] += 3.0  # along the lines (angle 0)
    A = moved_copy(make_map([LINE] * 4 + [CIRCLE], seen, covs), T_SYM)
    loose = ccda_match(A, B, CCDAParams(redundant_pairings=False))
    assert loose.accepted
    err = transform_error(loose.x_A_B, T_SYM)
    assert math.hypot(err[0], err[1]) == pytest.approx(3.0, abs=0.05)
    res = ccda_match(A, B)
    assert not res.accepted
    assert res.reason == "unverifiable"


def test_parallel_lines_and_two_circles_are_fixed() -> None:
    lines = np.array([[0, 0, 0], [5, 3, 0], [-4, 7, math.pi], [2, 12, 0]], float)
    params = np.vstack([lines, [[3.0, 5.0, 0.4], [-6.0, 4.0, 0.3]]])
    covs = [line_cov(f[2], 0.05, 0.01) for f in lines] + [circle_cov(0.05, 0.05)] * 2
    B = make_map([LINE] * 4 + [CIRCLE] * 2, params, covs)
    res = ccda_match(moved_copy(B, T_SYM), B)
    assert res.accepted, res.reason
    np.testing.assert_allclose(transform_error(res.x_A_B, T_SYM), 0.0, atol=1e-9)


def test_non_parallel_lines_only_are_fixed() -> None:
    lines = np.array([[0, 0, 0], [5, 3, 0.5], [-4, 7, 1.2], [2, 12, 2.0], [1, -6, -0.7]])
    B = make_map([LINE] * 5, lines, [line_cov(f[2], 0.05, 0.01) for f in lines])
    res = ccda_match(moved_copy(B, T_SYM), B)
    assert res.accepted, res.reason
    np.testing.assert_allclose(transform_error(res.x_A_B, T_SYM), 0.0, atol=1e-9)


def test_three_shared_features_are_too_few() -> None:
    shared = [(0.0, 0.0, 0.4), (13.0, 2.0, 0.8), (4.0, 9.0, 1.2)]
    only_b = [(-30.0, 25.0, 0.2), (40.0, -35.0, 1.4)]
    only_a = [(55.0, 10.0, 0.25), (-20.0, -45.0, 1.45), (0.0, 60.0, 0.6)]
    B = make_map([CIRCLE] * 5, shared + only_b, [circle_cov(0.05, 0.05)] * 5)
    A_src = make_map([CIRCLE] * 6, shared + only_a, [circle_cov(0.05, 0.05)] * 6)
    A = moved_copy(A_src, T_SYM)
    res = ccda_match(A, B)
    assert not res.accepted
    assert res.reason == "too few pairings"
    assert res.pairings == ((0, 0), (1, 1), (2, 2))
    np.testing.assert_allclose(transform_error(res.x_A_B, T_SYM), 0.0, atol=1e-9)
    # Accepted when the caller allows three.
    assert ccda_match(A, B, CCDAParams(min_pairings=3)).accepted


def empty_map() -> KnownMapArrays:
    return make_map([], np.zeros((0, 3)), np.zeros((0, 3, 3)))


@pytest.mark.parametrize(
    ("a", "b", "reason"),
    [
        (empty_map(), circle_map([(0, 0), (1, 5), (7, 2), (3, 3)]), "empty map"),
        (circle_map([(0, 0), (1, 5), (7, 2), (3, 3)]), empty_map(), "empty map"),
        (empty_map(), empty_map(), "empty map"),
        (circle_map([(0, 0)]), circle_map([(0, 0), (1, 5), (7, 2), (3, 3)]), "too few features"),
        (circle_map([(0, 0), (1, 5), (7, 2), (3, 3)]), circle_map([(4, 4)]), "too few features"),
    ],
)
def test_tiny_maps_give_no_match(a: KnownMapArrays, b: KnownMapArrays, reason: str) -> None:
    res = ccda_match(a, b)
    assert not res.accepted
    assert res.reason == reason
    assert res.pairings == ()
    assert np.all(np.isnan(res.x_A_B))
    assert res.x_A_B.shape == (3,)
    assert res.cov.shape == (3, 3)


def test_unrelated_maps_do_not_match() -> None:
    rng = np.random.default_rng(99)
    A = circle_map([tuple(p) for p in rng.uniform(-50, 50, size=(12, 2))])
    B = circle_map([tuple(p) for p in rng.uniform(-50, 50, size=(12, 2))])
    res = ccda_match(A, B)
    assert not res.accepted
    assert res.reason in {"too few pairings", "ambiguous"}


def test_nan_and_malformed_input_raise_naming_the_array() -> None:
    good = circle_map([(0, 0), (1, 5), (7, 2), (3, 3)])
    params = good.params.copy()
    params[2, 1] = np.nan
    with pytest.raises(ValueError, match=r"map_a\.params\[2, 1\] is not finite"):
        ccda_match(make_map(good.kinds, params, good.covs), good)
    covs = good.covs.copy()
    covs[3, 0, 0] = np.inf
    with pytest.raises(ValueError, match=r"map_b\.covs\[3, 0, 0\] is not finite"):
        ccda_match(good, make_map(good.kinds, good.params, covs))
    with pytest.raises(ValueError, match=r"map_b\.kinds\[1\] = 7"):
        ccda_match(good, make_map([CIRCLE, 7, CIRCLE, CIRCLE], good.params, good.covs))
    bad_shape = KnownMapArrays(good.ids, good.kinds, good.params[:, :2], good.covs)
    with pytest.raises(ValueError, match=r"map_a\.params has shape"):
        ccda_match(bad_shape, good)
    with pytest.raises(ValueError, match="gate_prob"):
        ccda_match(good, good, CCDAParams(gate_prob=1.0))
    with pytest.raises(ValueError, match=r"map_a\.params\[2, 1\] is not finite"):
        estimate_transform(make_map(good.kinds, params, good.covs), good, [(0, 0)])
