"""The distribution of a run's mean NEES from the joint covariance of its errors."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from mapfuse_core.evaluation import (
    consistent_error_draws,
    consistent_nees_draws,
    joint_nees,
    nees_mean_distribution,
    nees_series,
    pooled_nees_mean_distribution,
)

DOF = 3


def persistent_errors(steps: int = 200, phi: float = 0.97, common: float = 0.5) -> np.ndarray:
    """Joint covariance of AR(1) pose errors (correlated components) plus an error that
    lasts the whole run, like an anchor's: the case a NEES series alone misjudges."""
    rng = np.random.default_rng(1)
    A = rng.normal(size=(DOF, DOF))
    C = A @ A.T + np.eye(DOF)
    k = np.arange(steps)
    R = phi ** np.abs(k[:, None] - k[None, :])
    return np.kron(R, C) + np.kron(np.ones((steps, steps)), common * np.diag([1.0, 2.0, 0.3]))


def direct_mean_nees(S: np.ndarray, n: int, seed: int) -> np.ndarray:
    """Mean NEES of errors drawn from ``S`` by its Cholesky factor, each pose normalised
    by its own block (independent of the module's whitening)."""
    steps = S.shape[0] // DOF
    e = (np.linalg.cholesky(S) @ np.random.default_rng(seed).standard_normal((S.shape[0], n))).T
    e = e.reshape(n, steps, DOF)
    blocks = np.array([S[DOF * i : DOF * i + DOF, DOF * i : DOF * i + DOF] for i in range(steps)])
    out: np.ndarray = np.einsum("nti,tij,ntj->nt", e, np.linalg.inv(blocks), e).mean(axis=1)
    return out


def test_independent_poses_give_the_textbook_chi2() -> None:
    rng = np.random.default_rng(4)
    blocks = [
        (lambda A: A @ A.T + 0.1 * np.eye(DOF))(rng.normal(size=(DOF, DOF))) for _ in range(50)
    ]
    S = np.zeros((150, 150))
    for i, B in enumerate(blocks):
        S[DOF * i : DOF * i + DOF, DOF * i : DOF * i + DOF] = B
    d = nees_mean_distribution(S)
    assert d.steps == 50
    assert d.mean == pytest.approx(3.0, rel=1e-12)
    assert d.sd == pytest.approx(np.sqrt(2 * DOF / 50), rel=1e-12)
    assert d.equivalent_poses == pytest.approx(50.0, rel=1e-12)
    # Satterthwaite is exact here: the mean NEES is χ²(150) / 50.
    np.testing.assert_allclose(d.interval, chi2.ppf([0.025, 0.975], 150) / 50, rtol=1e-10)


def test_moments_match_draws_when_errors_persist() -> None:
    S = persistent_errors()
    d = nees_mean_distribution(S)
    x = direct_mean_nees(S, 4000, seed=3)
    # 4,000 draws: the standard error of the mean is sd/63 and of the sd about sd/89
    # (a little more for this skewed distribution), so 4 standard errors on the mean
    # and 4 % on the sd.
    assert d.mean == pytest.approx(3.0, rel=1e-12)
    assert abs(x.mean() - d.mean) <= 4 * d.sd / np.sqrt(x.size)
    assert x.std() == pytest.approx(d.sd, rel=0.04)
    # The run is worth a handful of poses, not 200.
    assert 3.0 <= d.equivalent_poses <= 6.0, d.equivalent_poses


def test_interval_covers_about_its_probability() -> None:
    S = persistent_errors()
    d = nees_mean_distribution(S)
    x = consistent_nees_draws(S, 20_000, np.random.default_rng(2)).mean(axis=1)
    cover = float(np.mean((x >= d.interval[0]) & (x <= d.interval[1])))
    # Measured 0.962 for a nominal 0.95: the scaled χ² is a moment match, a little
    # wide below and narrow above on a run worth ~4 poses (binomial se 0.0014).
    assert 0.94 <= cover <= 0.975, cover
    # What a series-only interval would claim for 200 steps is far narrower.
    assert d.interval[1] - d.interval[0] > 4 * (chi2.ppf(0.975, 600) - chi2.ppf(0.025, 600)) / 200


def test_draws_have_chi2_marginals() -> None:
    S = persistent_errors(steps=40)
    v = consistent_nees_draws(S, 20_000, np.random.default_rng(5))
    assert v.shape == (20_000, 40)
    # Every pose's NEES is χ²(3): mean 3, variance 6 (se of the mean 0.017).
    np.testing.assert_allclose(v.mean(axis=0), 3.0, atol=0.08)
    np.testing.assert_allclose(v.var(axis=0), 6.0, rtol=0.08)
    # Same seed, same draws.
    np.testing.assert_array_equal(v, consistent_nees_draws(S, 20_000, np.random.default_rng(5)))


def test_pooling_independent_runs() -> None:
    a = nees_mean_distribution(persistent_errors(steps=100))
    b = nees_mean_distribution(persistent_errors(steps=100, phi=0.9))
    pooled = pooled_nees_mean_distribution([a, b])
    assert pooled.steps == 200
    assert pooled.mean == pytest.approx(3.0)
    assert pooled.sd == pytest.approx(0.5 * np.hypot(a.sd, b.sd))
    same = pooled_nees_mean_distribution([a])
    assert same.sd == pytest.approx(a.sd)
    np.testing.assert_allclose(same.interval, a.interval)


def test_bad_input_is_named() -> None:
    S = persistent_errors(steps=5)
    with pytest.raises(ValueError, match="multiple of 3"):
        nees_mean_distribution(S[:14, :14])
    with pytest.raises(ValueError, match="square"):
        nees_mean_distribution(S[:, :12])
    bad = S.copy()
    bad[0, 4] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        nees_mean_distribution(bad)
    singular = S.copy()
    singular[3:6, :] = 0.0
    singular[:, 3:6] = 0.0
    with pytest.raises(ValueError, match="not positive definite"):
        nees_mean_distribution(singular)
    with pytest.raises(ValueError, match="at least one run"):
        pooled_nees_mean_distribution([])
    with pytest.raises(ValueError, match="n_draws"):
        consistent_nees_draws(S, 0, np.random.default_rng(0))


def test_error_draws_have_the_joint_covariance() -> None:
    S = persistent_errors(steps=10)
    e = consistent_error_draws(S, 40_000, np.random.default_rng(6))
    assert e.shape == (40_000, 10, 3)
    emp = np.cov(e.reshape(40_000, 30), rowvar=False)
    # 40,000 draws: entries within ~4 standard errors (√(2/n) of the scale).
    scale = np.sqrt(np.outer(np.diag(S), np.diag(S)))
    assert np.max(np.abs(emp - S) / scale) < 4 * np.sqrt(2 / 40_000) * 1.5
    with pytest.raises(ValueError, match="n_draws"):
        consistent_error_draws(S, 0, np.random.default_rng(0))


def test_joint_nees_is_each_poses_nees_against_its_marginal() -> None:
    S = persistent_errors(steps=8)
    e = consistent_error_draws(S, 5, np.random.default_rng(7))
    blocks = np.array([S[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] for i in range(8)])
    got = joint_nees(e, S)
    assert got.shape == (5, 8)
    for d in range(5):
        np.testing.assert_allclose(got[d], nees_series(e[d], blocks), rtol=1e-10)
    with pytest.raises(ValueError, match=r"end in \(8, 3\)"):
        joint_nees(e[:, :7], S)
