"""CCDA map-to-map matching: recovery, rejection of symmetric/degenerate maps, transforms."""

from __future__ import annotations

import math
from dataclasses import dataclass

import networkx as nx
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.stats import chi2

from mapfuse_core import ccda
from mapfuse_core.ccda import CCDAParams, ccda_match, estimate_transform, pairing_chi2
from mapfuse_core.features import FeatureKind, pairing_residual, transform_feature
from mapfuse_core.measlog import KnownMapArrays
from mapfuse_core.se2 import compose, inverse, rot2, wrap_angle

LINE, CIRCLE = int(FeatureKind.LINE), int(FeatureKind.CIRCLE)
#: Along-line pseudo-standard deviation of line covariances: huge, and must not matter.
PSEUDO_ALONG_M = 100.0
#: The paper's simulation: the known map seen from the vehicle's start frame.
START = np.array([-29.0, -11.0, math.pi / 3])


# --------------------------------------------------------------------------- helpers


def make_map(kinds: list[int] | np.ndarray, params: np.ndarray, covs: np.ndarray) -> KnownMapArrays:
    n = len(kinds)
    return KnownMapArrays(
        ids=np.arange(n, dtype=np.int64),
        kinds=np.asarray(kinds, dtype=np.int8),
        params=np.asarray(params, dtype=float).reshape(n, 3),
        covs=np.asarray(covs, dtype=float).reshape(n, 3, 3),
    )


def line_cov(theta: float, s_lat: float, s_th: float, rho: float = 0.0) -> np.ndarray:
    """Absolute (x, y, θ) covariance of an SPmap line: pseudo-variance along it,
    ``s_lat`` across it, ``s_th`` on the angle, correlation ``rho`` lateral–angle."""
    R = rot2(theta)
    S = np.zeros((3, 3))
    S[:2, :2] = R @ np.diag([PSEUDO_ALONG_M**2, s_lat**2]) @ R.T
    n = R[:, 1]
    S[:2, 2] = S[2, :2] = rho * s_lat * s_th * n
    S[2, 2] = s_th**2
    return S


def circle_cov(s_xy: float, s_r: float) -> np.ndarray:
    return np.diag([s_xy**2, s_xy**2, s_r**2])


def move(kind: int, T: np.ndarray, f: np.ndarray) -> np.ndarray:
    return transform_feature(FeatureKind(kind), T, f)[0]


def rotate_cov(kind: int, T: np.ndarray, S: np.ndarray) -> np.ndarray:
    """Covariance of ``T ⊕ f`` for a fixed ``T``: rotate the position block."""
    R = np.eye(3)
    R[:2, :2] = rot2(float(T[2]))
    return R @ S @ R.T


def perturb(
    rng: np.random.Generator, kind: int, f: np.ndarray, S: np.ndarray, along_m: float = 5.0
) -> tuple[np.ndarray, np.ndarray]:
    """A noisy copy of ``f`` drawn from its covariance ``S``, and the covariance to state.

    Circles: ``N(f, S)``, stated ``S``.  Lines: the SPmap perturbation
    ``L ⊕ (e_along, e_lat, e_θ)`` with ``(e_lat, e_θ)`` from the lateral/angle block of
    ``S`` and the along-line origin moved arbitrarily (uniform ±``along_m``), as a
    partially seen wall would; the stated covariance is ``S`` turned with the line,
    so that its along-line axis follows the noisy line as it does in the EKF and in
    extraction (a pseudo-variance along the *true* direction would leak into the
    lateral one).
    """
    if kind == CIRCLE:
        return f + rng.multivariate_normal(np.zeros(3), S), S
    n = np.array([-math.sin(f[2]), math.cos(f[2])])
    C = np.array([[n @ S[:2, :2] @ n, n @ S[:2, 2]], [n @ S[:2, 2], S[2, 2]]])
    e_lat, e_th = rng.multivariate_normal(np.zeros(2), C)
    return compose(f, np.array([rng.uniform(-along_m, along_m), e_lat, e_th])), rotate_cov(
        kind, np.array([0.0, 0.0, e_th]), S
    )


def random_feature(
    rng: np.random.Generator, kind: int, extent: float
) -> tuple[np.ndarray, np.ndarray]:
    """A random feature near the origin and a random covariance for it."""
    x, y = rng.uniform(-extent, extent, size=2)
    if kind == CIRCLE:
        return np.array([x, y, rng.uniform(0.1, 1.5)]), circle_cov(
            rng.uniform(0.03, 0.15), rng.uniform(0.02, 0.1)
        )
    th = rng.uniform(-math.pi, math.pi)
    S = line_cov(th, rng.uniform(0.02, 0.1), rng.uniform(0.003, 0.015), rng.uniform(-0.5, 0.5))
    return np.array([x, y, th]), S


@dataclass(frozen=True)
class Overlap:
    """A random partial-overlap case with its ground truth."""

    map_a: KnownMapArrays
    map_b: KnownMapArrays
    x_A_B: np.ndarray
    truth: dict[int, int]
    """index in A → index in B of every shared feature."""


def confusable_pairs(
    a: KnownMapArrays, b: KnownMapArrays, T: np.ndarray, truth: dict[int, int]
) -> list[tuple[int, int]]:
    """Wrong pairings ``(i, j)`` that are χ²-compatible under the true transform."""
    wrong = [
        (i, j)
        for i in range(len(a))
        for j in range(len(b))
        if a.kinds[i] == b.kinds[j] and truth.get(i, -1) != j
    ]
    if not wrong:
        return []
    c2, dof = pairing_chi2(a, b, T, wrong)
    return [p for p, ok in zip(wrong, c2 <= chi2.ppf(0.999, dof), strict=True) if ok]


def random_overlap(seed: int) -> Overlap:
    """Map B: 10–40 circles and 5–15 lines with varied radii and angles.  Map A: a
    40–80 % subset of B moved by a random rigid transform, plus spurious features;
    both noisy with their stated covariances.

    Well posed: the case is redrawn when, under the true transform, a spurious
    feature of A or a shared one with a wrong partner is χ²-compatible with a
    feature of B (infinite lines coincide by chance); then no matcher could tell
    the right pairing, so "all pairings correct" would not be defined.
    """
    rng = np.random.default_rng(seed)
    while True:
        n_c, n_l = int(rng.integers(10, 41)), int(rng.integers(5, 16))
        extent = rng.uniform(30.0, 80.0)
        kinds = [CIRCLE] * n_c + [LINE] * n_l
        world, covs_b = zip(*(random_feature(rng, k, extent) for k in kinds), strict=True)
        T = np.array([*rng.uniform(-60.0, 60.0, size=2), rng.uniform(-math.pi, math.pi)])
        b_noisy = [perturb(rng, k, f, S) for k, f, S in zip(kinds, world, covs_b, strict=True)]
        b_params, covs_b = [f for f, _ in b_noisy], [S for _, S in b_noisy]
        shared = rng.choice(len(kinds), size=int(rng.uniform(0.4, 0.8) * len(kinds)), replace=False)
        a_kinds, a_params, a_covs, a_src = [], [], [], []
        for j in shared.tolist():
            k = kinds[j]
            S = rotate_cov(k, T, covs_b[j])
            # The stated covariance of A's copy: the same shape, its own scale.
            S = S * rng.uniform(0.5, 2.0) ** 2
            f, S = perturb(rng, k, move(k, T, world[j]), S)
            a_kinds.append(k)
            a_params.append(f)
            a_covs.append(S)
            a_src.append(j)
        for _ in range(int(rng.integers(3, 15))):
            k = CIRCLE if rng.random() < 0.7 else LINE
            f, S = random_feature(rng, k, extent)
            f, S = perturb(rng, k, move(k, T, f), rotate_cov(k, T, S))
            a_kinds.append(k)
            a_params.append(f)
            a_covs.append(S)
            a_src.append(-1)
        perm = rng.permutation(len(a_kinds))
        map_a = make_map(
            [a_kinds[p] for p in perm], [a_params[p] for p in perm], [a_covs[p] for p in perm]
        )
        map_b = make_map(kinds, b_params, covs_b)
        truth = {i: a_src[p] for i, p in enumerate(perm.tolist()) if a_src[p] >= 0}
        confusable = confusable_pairs(map_a, map_b, T, truth)
        if not confusable:
            return Overlap(map_a, map_b, T, truth)


def transform_error(x: np.ndarray, truth: np.ndarray) -> np.ndarray:
    e = np.asarray(x, dtype=float) - truth
    e[2] = float(wrap_angle(e[2]))
    return e


def nees(x: np.ndarray, cov: np.ndarray, truth: np.ndarray) -> float:
    e = transform_error(x, truth)
    return float(e @ np.linalg.solve(cov, e))


def circle_map(
    points: list[tuple[float, float]], r: float = 0.5, s: float = 0.05
) -> KnownMapArrays:
    P = np.array([[x, y, r] for x, y in points])
    return make_map([CIRCLE] * len(points), P, [circle_cov(s, s)] * len(points))


def moved_copy(m: KnownMapArrays, T: np.ndarray) -> KnownMapArrays:
    """Noise-free copy of ``m`` as seen from a frame in which ``m``'s frame is ``T``."""
    P = [move(int(k), T, f) for k, f in zip(m.kinds, m.params, strict=True)]
    S = [rotate_cov(int(k), T, c) for k, c in zip(m.kinds, m.covs, strict=True)]
    return make_map(m.kinds, P, S)


T_SYM = np.array([3.0, -2.0, 0.7])


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


def test_parallel_lines_and_one_circle_are_fixed() -> None:
    lines = np.array([[0, 0, 0], [5, 3, 0], [-4, 7, math.pi], [2, 12, 0]], float)
    params = np.vstack([lines, [[3.0, 5.0, 0.4]]])
    covs = [line_cov(f[2], 0.05, 0.01) for f in lines] + [circle_cov(0.05, 0.05)]
    B = make_map([LINE] * 4 + [CIRCLE], params, covs)
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


# --------------------------------------------------------------------------- estimate_transform


def mixed_map(rng: np.random.Generator, n_c: int, n_l: int) -> KnownMapArrays:
    kinds = [CIRCLE] * n_c + [LINE] * n_l
    feats = [random_feature(rng, k, 40.0) for k in kinds]
    return make_map(kinds, [f for f, _ in feats], [S for _, S in feats])


def noisy_match(
    rng: np.random.Generator, B_true: KnownMapArrays, inflate: bool = False
) -> tuple[KnownMapArrays, KnownMapArrays, np.ndarray]:
    """A random transform ``T`` and noisy copies ``(A, B)`` of ``B_true`` moved by ``T``
    and of ``B_true``, each feature drawn from its covariance (times a random 1–30 with
    ``inflate``)."""
    T = np.array([*rng.uniform(-50, 50, size=2), rng.uniform(-math.pi, math.pi)])
    kinds = [int(k) for k in B_true.kinds]
    maps = []
    for truth in (B_true, moved_copy(B_true, T)):
        noisy = [
            perturb(rng, k, f, S * float(rng.uniform(1, 30)) if inflate else S)
            for k, f, S in zip(kinds, truth.params, truth.covs, strict=True)
        ]
        maps.append(make_map(kinds, [f for f, _ in noisy], [S for _, S in noisy]))
    B, A = maps
    return A, B, T


@pytest.mark.parametrize(("n_c", "n_l"), [(4, 0), (0, 3), (1, 2), (6, 5)])
def test_estimate_transform_exact_from_noise_free_pairings(n_c: int, n_l: int) -> None:
    for seed in range(20):
        rng = np.random.default_rng(seed)
        B = mixed_map(rng, n_c, n_l)
        T = np.array([*rng.uniform(-80, 80, size=2), rng.uniform(-math.pi, math.pi)])
        A = moved_copy(B, T)
        # Lines keep their origin anywhere along them: slide A's copies.
        P = A.params.copy()
        for i in np.nonzero(A.kinds == LINE)[0]:
            P[i] = compose(P[i], np.array([rng.uniform(-20, 20), 0.0, 0.0]))
        A = make_map(A.kinds, P, A.covs)
        x, cov = estimate_transform(A, B, [(i, i) for i in range(len(B))])
        np.testing.assert_allclose(transform_error(x, T), 0.0, atol=1e-8)
        np.testing.assert_allclose(cov, cov.T)
        assert np.all(np.linalg.eigvalsh(cov) > 0)


def test_estimate_transform_from_a_start() -> None:
    rng = np.random.default_rng(3)
    B = mixed_map(rng, 3, 3)
    T = np.array([10.0, -4.0, 2.9])
    A = moved_copy(B, T)
    x, _ = estimate_transform(A, B, [(i, i) for i in range(6)], x0=T + np.array([0.5, -0.5, 0.1]))
    np.testing.assert_allclose(transform_error(x, T), 0.0, atol=1e-8)


def test_estimate_transform_covariance_is_consistent() -> None:
    trials = 300
    values = []
    for seed in range(trials):
        rng = np.random.default_rng(10_000 + seed)
        B_true = mixed_map(rng, int(rng.integers(2, 8)), int(rng.integers(0, 6)))
        A, B, T = noisy_match(rng, B_true)
        x, cov = estimate_transform(A, B, [(i, i) for i in range(len(B_true.kinds))])
        values.append(nees(x, cov, T))
    mean = float(np.mean(values))
    lo, hi = chi2.ppf([0.005, 0.995], 3 * trials) / trials
    assert lo <= mean <= hi, mean


def test_estimate_transform_rejects_bad_pairings() -> None:
    B = circle_map([(0, 0), (1, 5), (7, 2)])
    L = make_map([LINE], [[0.0, 0.0, 0.0]], [line_cov(0.0, 0.1, 0.01)])
    with pytest.raises(ValueError, match="at least one pairing"):
        estimate_transform(B, B, [])
    with pytest.raises(ValueError, match=r"map_b\[5\]"):
        estimate_transform(B, B, [(0, 5)])
    with pytest.raises(ValueError, match="different kinds"):
        estimate_transform(L, B, [(0, 0)])


# --------------------------------------------------------------------------- internals


def reference_chi2(
    a: KnownMapArrays, b: KnownMapArrays, T: np.ndarray, i: int, j: int
) -> tuple[np.ndarray, float]:
    """Residual and χ² through ``features`` directly, lines through (e_lat, e_θ)."""
    kind = FeatureKind(int(a.kinds[i]))
    bT, _, Jb = transform_feature(kind, T, b.params[j])
    r, J1, J2 = pairing_residual(kind, a.params[i], bT)

    def noise(f: np.ndarray, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if kind == FeatureKind.CIRCLE:
            return np.eye(3), S + np.eye(3) * 1e-8  # the module's variance floor
        s, c = math.sin(f[2]), math.cos(f[2])
        P = np.array([[-s, 0.0], [c, 0.0], [0.0, 1.0]])
        n = np.array([-s, c])
        C = np.array([[n @ S[:2, :2] @ n + 1e-8, n @ S[:2, 2]], [n @ S[:2, 2], S[2, 2] + 1e-10]])
        return P, C

    Pa, Ca = noise(a.params[i], a.covs[i])
    Pb, Cb = noise(b.params[j], b.covs[j])
    Ea, Eb = J1 @ Pa, J2 @ Jb @ Pb
    S = Ea @ Ca @ Ea.T + Eb @ Cb @ Eb.T
    return r, float(r @ np.linalg.solve(S, r))


def test_vectorised_residuals_match_the_feature_models() -> None:
    rng = np.random.default_rng(21)
    A, B = mixed_map(rng, 6, 6), mixed_map(rng, 6, 6)
    for _ in range(10):
        T = np.array([*rng.uniform(-30, 30, size=2), rng.uniform(-math.pi, math.pi)])
        pairs = [(i, j) for i in range(12) for j in range(12) if A.kinds[i] == B.kinds[j]]
        c2, dof = pairing_chi2(A, B, T, pairs)
        pa = ccda._prepare(A, "map_a", CCDAParams())
        pb = ccda._prepare(B, "map_b", CCDAParams())
        ii = np.array([p[0] for p in pairs])
        jj = np.array([p[1] for p in pairs])
        r, J, _, _ = ccda._residuals(pa, pb, T, ii, jj)
        for k, (i, j) in enumerate(pairs):
            ref_r, ref_c2 = reference_chi2(A, B, T, i, j)
            d = int(dof[k])
            assert d == ref_r.size
            np.testing.assert_allclose(r[k, :d], ref_r, atol=1e-9)
            np.testing.assert_allclose(c2[k], ref_c2, rtol=1e-6)
            # ∂r/∂T against the features module's chain rule.
            kind = FeatureKind(int(A.kinds[i]))
            bT, JT, _ = transform_feature(kind, T, B.params[j])
            _, _, J2 = pairing_residual(kind, A.params[i], bT)
            np.testing.assert_allclose(J[k, :d], J2 @ JT, atol=1e-9)


def test_line_pseudo_variance_along_the_line_is_ignored() -> None:
    rng = np.random.default_rng(8)
    B = mixed_map(rng, 3, 4)
    A = moved_copy(B, T_SYM)
    pairs = [(i, i) for i in range(len(B))]
    base = pairing_chi2(A, B, T_SYM + np.array([0.05, -0.05, 0.002]), pairs)[0]
    x0, cov0 = estimate_transform(A, B, pairs)
    # Inflate only the along-line variance of every line, by 10⁶.
    covs = B.covs.copy()
    for i in np.nonzero(B.kinds == LINE)[0]:
        t = np.array([math.cos(B.params[i, 2]), math.sin(B.params[i, 2])])
        covs[i, :2, :2] += 1e6 * np.outer(t, t)
    B2 = make_map(B.kinds, B.params, covs)
    np.testing.assert_allclose(
        pairing_chi2(A, B2, T_SYM + np.array([0.05, -0.05, 0.002]), pairs)[0], base, rtol=1e-6
    )
    x1, cov1 = estimate_transform(A, B2, pairs)
    np.testing.assert_allclose(x1, x0, atol=1e-9)
    np.testing.assert_allclose(cov1, cov0, rtol=1e-5)


def test_gauss_newton_never_ends_above_its_start() -> None:
    """On wrong pairings the residual covariance's dependence on ``T`` can make the
    Gauss–Newton step raise the true cost at every length; the fit must then stop
    where it is, not take a step uphill, and report the cost of what it returns."""
    stuck = 0
    for seed in range(60):
        rng = np.random.default_rng(500 + seed)
        A, B = mixed_map(rng, 2, 6), mixed_map(rng, 2, 6)
        pa = ccda._prepare(A, "map_a", CCDAParams())
        pb = ccda._prepare(B, "map_b", CCDAParams())
        # Unrelated maps paired kind by kind: a wrong hypothesis.
        ii = np.arange(8)
        jj = np.concatenate([rng.permutation(2), 2 + rng.permutation(6)])
        x0 = np.array([*rng.uniform(-30, 30, size=2), rng.uniform(-math.pi, math.pi)])
        P = ccda._pair_set(pa, pb, ii, jj)
        T, _, cost = ccda._gauss_newton(pa, pb, ii, jj, x0)
        assert cost <= ccda._cost(P, x0) * (1 + 1e-12) + 1e-12
        assert cost == pytest.approx(ccda._cost(P, T), rel=1e-12)
        H, g, _ = ccda._normal_equations(P, T)
        dx = ccda._solve(H, g)
        if -float(g @ dx) > 1e-12 * max(cost, 1.0):
            stuck += 1  # stopped on a step none of whose sampled lengths is cheaper
            for step in 2.0 ** -np.arange(0, 21, 4):
                assert ccda._cost(P, ccda._step(T, dx, step)) > cost
    # Most of these fits stop on such a step (58 of the 60): the case is exercised.
    assert stuck >= 30, stuck


@pytest.mark.parametrize("seed", [253, 387])
def test_gauss_newton_finds_a_dip_between_the_longest_and_shortest_steps(seed: int) -> None:
    """Correct pairings from a start metres and a radian off, where the full step and
    the shortest one both raise the cost but a quarter step lowers it: the fit must go
    on to the solution (a line search that probes only the two ends stops at the
    start, cost ~10⁴)."""
    rng = np.random.default_rng(seed)
    B_true = mixed_map(rng, int(rng.integers(0, 5)), int(rng.integers(2, 7)))
    A, B, T = noisy_match(rng, B_true, inflate=True)
    pa = ccda._prepare(A, "map_a", CCDAParams())
    pb = ccda._prepare(B, "map_b", CCDAParams())
    ii = jj = np.arange(len(B_true.kinds))
    x0s = [T + np.array([*rng.normal(0, 10, 2), rng.normal(0, 0.7)]) for _ in range(3)]
    best = ccda._estimate(pa, pb, ii, jj, None)[0]
    P = ccda._pair_set(pa, pb, ii, jj)
    for x0 in x0s:
        x, _, cost = ccda._gauss_newton(pa, pb, ii, jj, x0)
        assert cost == pytest.approx(ccda._cost(P, best), rel=1e-6), (x0, x)


@pytest.mark.parametrize("seed", range(12))
def test_clique_search_is_exact(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(20, 120))
    p = rng.uniform(0.05, 0.5)
    G = nx.gnp_random_graph(n, p, seed=seed)
    planted = rng.choice(n, size=int(rng.integers(3, 12)), replace=False).tolist()
    G.add_edges_from((a, b) for k, a in enumerate(planted) for b in planted[k + 1 :])
    edges = np.array(list(G.edges()), dtype=np.int64).reshape(-1, 2)
    ids = np.arange(n, dtype=np.int64)
    search = ccda._CliqueGraph(ids, edges[:, 0], edges[:, 1], ids, ids)
    found = search.max_clique().tolist()
    expected, _ = nx.max_weight_clique(G, weight=None)
    assert len(found) == len(expected)
    assert all(G.has_edge(a, b) for k, a in enumerate(found) for b in found[k + 1 :])
    # After removing it, the next search finds the best clique of what remains.
    search.remove(np.array(found, dtype=np.int64))
    H = G.copy()
    H.remove_nodes_from(found)
    again = search.max_clique().tolist()
    assert len(again) == len(nx.max_weight_clique(H, weight=None)[0])
    assert search.max_clique(at_least=len(again) + 1).size == 0
