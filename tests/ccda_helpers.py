"""Map builders, perturbations and error measures shared by the CCDA tests."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from mapfuse_core.geometry.features import FeatureKind, transform_feature
from mapfuse_core.geometry.se2 import compose, rot2, wrap_angle
from mapfuse_core.matching.ccda import pairing_chi2
from mapfuse_core.measlog import KnownMapArrays

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
