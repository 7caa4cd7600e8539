"""CCDA's transform estimate from pairings and its internals: residuals against the
feature models, Gauss–Newton and the clique search.
"""

from __future__ import annotations

import math

import networkx as nx
import numpy as np
import pytest
from scipy.stats import chi2

from mapfuse_core.geometry.features import FeatureKind, transform_feature
from mapfuse_core.geometry.se2 import compose
from mapfuse_core.matching import ccda
from mapfuse_core.matching.ccda import CCDAParams, estimate_transform, pairing_chi2
from mapfuse_core.measlog import KnownMapArrays
from mapfuse_core.models import pairing_residual
from tests.ccda_helpers import (
    CIRCLE,
    LINE,
    T_SYM,
    circle_map,
    line_cov,
    make_map,
    moved_copy,
    nees,
    perturb,
    random_feature,
    transform_error,
)

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
