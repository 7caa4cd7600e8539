"""Loop closure at a join: registration of local circles to global ones."""

from __future__ import annotations

import math

import numpy as np

from ekf_reference.loops import LoopClosureParams, accepted, register_circles


def _apply(T: np.ndarray, P: np.ndarray) -> np.ndarray:
    c, s = math.cos(T[2]), math.sin(T[2])
    return np.column_stack((T[0] + c * P[:, 0] - s * P[:, 1], T[1] + s * P[:, 0] + c * P[:, 1]))


def _inverse(T: np.ndarray) -> np.ndarray:
    c, s = math.cos(T[2]), math.sin(T[2])
    return np.array([-c * T[0] - s * T[1], s * T[0] - c * T[1], -T[2]])


def _park(rng: np.random.Generator, n: int = 400, size: float = 200.0) -> np.ndarray:
    """Trees at least 2 m apart, uniformly over a square."""
    pts: list[np.ndarray] = []
    while len(pts) < n:
        p = rng.uniform(0.0, size, 2)
        if all(np.hypot(*(p - q)) > 2.0 for q in pts):
            pts.append(p)
    return np.array(pts)


def test_a_drifted_local_map_is_registered() -> None:
    rng = np.random.default_rng(1)
    G = _park(rng)
    near = np.nonzero(np.hypot(*(G - [100.0, 100.0]).T) < 35.0)[0]
    T_true = np.array([6.0, -4.0, math.radians(4.0)])
    # Local centres: the global ones seen through the wrong relative pose, with noise,
    # plus ten trees the global map does not have.
    L = _apply(_inverse(T_true), G[near]) + rng.normal(0.0, 0.1, (near.size, 2))
    L = np.vstack([L, rng.uniform(70.0, 130.0, (10, 2))])
    n_obs = np.arange(L.shape[0])[::-1]
    p = LoopClosureParams()
    reg = register_circles(L, G, n_obs, p)
    assert reg is not None
    assert reg.inliers >= near.size - 3
    assert reg.at_identity < 0.2 * reg.inliers
    assert abs(math.degrees(reg.T[2]) - 4.0) < 0.2
    assert np.allclose(_apply(reg.T, L[:5]), G[near[:5]], atol=0.4)
    assert all(g == near[i] for i, g in reg.pairs if i < near.size)
    assert accepted(reg, p)


def test_a_consistent_local_map_is_not_a_loop_closure() -> None:
    rng = np.random.default_rng(2)
    G = _park(rng)
    near = np.nonzero(np.hypot(*(G - [100.0, 100.0]).T) < 35.0)[0]
    L = G[near] + rng.normal(0.0, 0.1, (near.size, 2))
    reg = register_circles(L, G, np.ones(near.size), LoopClosureParams())
    assert reg is not None
    assert reg.at_identity >= near.size - 3
    assert not accepted(reg, LoopClosureParams())


def test_new_ground_is_not_a_loop_closure() -> None:
    rng = np.random.default_rng(3)
    G = _park(rng)
    L = _park(np.random.default_rng(4), n=60, size=60.0) + 70.0
    reg = register_circles(L, G, np.ones(L.shape[0]), LoopClosureParams())
    assert not accepted(reg, LoopClosureParams())


def test_a_regular_plantation_is_ambiguous() -> None:
    # Rows 6 m apart, trees 6 m apart: every shift by a multiple of 6 m fits as well.
    xs, ys = np.meshgrid(np.arange(0.0, 120.0, 6.0), np.arange(0.0, 120.0, 6.0))
    G = np.column_stack((xs.ravel(), ys.ravel()))
    near = np.nonzero(np.hypot(*(G - [60.0, 60.0]).T) < 25.0)[0]
    L = G[near] + np.array([3.0, 1.0])
    reg = register_circles(L, G, np.ones(near.size), LoopClosureParams())
    assert reg is not None
    assert reg.runner_up * LoopClosureParams().ambiguity_ratio > reg.inliers
    assert not accepted(reg, LoopClosureParams())
