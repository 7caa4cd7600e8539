"""NEES statistics: per-step NEES, the interval and distribution of its mean,
and draws of consistent errors from a joint covariance.

Errors of one run are correlated in time (and, with fusion, share the anchor's and
the known map's), so the mean NEES needs more than a per-step χ² bound
(``docs/results/known-gaps.md``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from mapfuse_core.estimate.metrics import NeesMeanInterval
from mapfuse_core.geometry.se2 import FloatArray

__all__ = [
    "CHI2_3_95",
    "NeesMeanDistribution",
    "consistent_error_draws",
    "consistent_nees_draws",
    "integrated_autocorrelation_time",
    "joint_nees",
    "nees_mean_distribution",
    "nees_mean_interval",
    "nees_series",
    "pooled_nees_mean_distribution",
]


CHI2_3_95 = float(chi2.ppf(0.95, 3))


def nees_series(dx: FloatArray, covs: FloatArray) -> FloatArray:
    """NEES ``eᵀ P⁻¹ e`` per step; NaN where the covariance is singular (e.g. step 0)."""
    out = np.full(dx.shape[0], np.nan)
    for k in range(dx.shape[0]):
        P = covs[k]
        if not np.all(np.isfinite(P)):
            continue
        w = np.linalg.eigvalsh(P)
        if w.min() <= 1e-14 * max(w.max(), 1e-300):
            continue
        out[k] = float(dx[k] @ np.linalg.solve(P, dx[k]))
    return out


def integrated_autocorrelation_time(x: FloatArray, window_factor: float = 5.0) -> float:
    """Integrated autocorrelation time ``τ = 1 + 2 Σ_k ρ(k)`` of a series, in samples.

    Sokal's automatic window: the sum stops at the first lag ``M ≥ window_factor·τ(M)``,
    which keeps the noise of the far lags out.  ``N / τ`` samples of the series carry
    as much information about its mean as that many independent ones.  ``1.0`` for a
    series too short or constant.
    """
    v = np.asarray(x, dtype=float)
    v = v[np.isfinite(v)]
    n = v.size
    if n < 4:
        return 1.0
    d = v - v.mean()
    var = float(d @ d)
    if var <= 0.0:
        return 1.0
    f = np.fft.rfft(d, 2 * n)
    acf = np.fft.irfft(f * np.conj(f))[:n] / var
    tau = 1.0
    for m in range(1, n):
        tau += 2.0 * float(acf[m])
        if m >= window_factor * tau:
            break
    return max(tau, 1.0)


def nees_mean_interval(nees: FloatArray, dof: int = 3, p: float = 0.95) -> NeesMeanInterval:
    """Two-sided ``p`` acceptance region of the mean NEES of a consistent estimator,
    honestly.

    Consecutive NEES values of a smoother (or a slowly mixing filter) are strongly
    correlated: on loop600 the whitened smoothed errors have τ of 300–470 steps, so a
    2,400-step run holds only a handful of independent samples and the textbook
    interval ``χ²(N·dof)/N`` is far too narrow.  Here ``N`` is replaced by the effective
    number of samples ``N/τ`` (τ of the NEES series itself).  Still approximate: a run
    only ~20τ long underestimates τ (the sample mean absorbs part of the slow error),
    and the interval then misses about 14 % of consistent runs instead of 5 %.

    It is far too narrow when part of the error lasts the whole run, which a series
    cannot show.  On loop600 with fusion, the anchor's and the known map's errors are
    such a part: the batch smoother's own joint covariance puts the standard deviation
    of a run's mean NEES at 1.4 (seeds 0–4), its 40-seed spread is 1.3, and this
    interval is ±0.4 wide on seed 4.  When the joint covariance of the errors is known
    (a smoother's), :func:`nees_mean_distribution` gives the exact moments instead.
    """
    v = np.asarray(nees, dtype=float)
    v = v[np.isfinite(v)]
    tau = integrated_autocorrelation_time(v)
    n_eff = max(v.size / tau, 1.0)
    lo = float(chi2.ppf(0.5 * (1.0 - p), dof * n_eff) / n_eff)
    hi = float(chi2.ppf(0.5 * (1.0 + p), dof * n_eff) / n_eff)
    return NeesMeanInterval(
        autocorrelation_steps=tau, effective_samples=n_eff, acceptance_95=(lo, hi)
    )


@dataclass(frozen=True)
class NeesMeanDistribution:
    """Distribution of a run's mean NEES for an estimator whose joint error covariance
    is known: what a consistent estimator's mean NEES would scatter over."""

    steps: int
    """Poses the mean is taken over."""
    dof: int
    """Dimension of each pose's error."""
    mean: float
    """Expected mean NEES (``dof``: the blocks are the poses' marginals)."""
    sd: float
    """Its standard deviation, exact for Gaussian errors."""
    equivalent_poses: float
    """Independent poses carrying the same information about the mean:
    ``2·mean² / (dof·sd²)``.  Much fewer than :attr:`steps` when errors persist."""
    interval: tuple[float, float]
    """Two-sided interval of :attr:`p` of the moment-matched scaled χ² (Satterthwaite)."""
    p: float
    """Probability of :attr:`interval`."""


def _satterthwaite(steps: int, dof: int, mean: float, var: float, p: float) -> NeesMeanDistribution:
    # a·χ²(ν) with the same mean and variance: a = var / (2 mean), ν = 2 mean² / var.
    a, nu = var / (2.0 * mean), 2.0 * mean * mean / var
    lo = float(chi2.ppf(0.5 * (1.0 - p), nu))
    hi = float(chi2.ppf(0.5 * (1.0 + p), nu))
    return NeesMeanDistribution(
        steps=steps,
        dof=dof,
        mean=mean,
        sd=math.sqrt(var),
        equivalent_poses=nu / dof,
        interval=(float(a * lo), float(a * hi)),
        p=p,
    )


def _block_inverse_factors(joint_cov: FloatArray, dof: int) -> tuple[FloatArray, FloatArray]:
    """The checked ``joint_cov`` and the inverse Cholesky factors (T, dof, dof) of its
    diagonal blocks: ``L_t⁻¹ e_t`` whitens pose ``t``'s error by its own marginal."""
    S = np.asarray(joint_cov, dtype=float)
    if S.ndim != 2 or S.shape[0] != S.shape[1] or S.shape[0] % dof or S.shape[0] == 0:
        raise ValueError(
            f"joint_cov must be square with a side that is a positive multiple of {dof}, "
            f"got shape {S.shape}"
        )
    if not np.all(np.isfinite(S)):
        raise ValueError("joint_cov has non-finite entries")
    n = S.shape[0] // dof
    blocks = S.reshape(n, dof, n, dof)[np.arange(n), :, np.arange(n), :]
    try:
        L = np.linalg.cholesky(0.5 * (blocks + blocks.transpose(0, 2, 1)))
    except np.linalg.LinAlgError as exc:
        raise ValueError("a diagonal block of joint_cov is not positive definite") from exc
    Li: FloatArray = np.linalg.inv(L)
    return S, Li


def _whitened_joint(joint_cov: FloatArray, dof: int) -> FloatArray:
    """``D^{-1/2} Σ D^{-T/2}`` with ``D`` the diagonal blocks of ``Σ`` (Cholesky factors)."""
    S, Li = _block_inverse_factors(joint_cov, dof)
    n = Li.shape[0]
    W = np.einsum("sab,sbtc,tdc->satd", Li, S.reshape(n, dof, n, dof), Li)
    W = W.reshape(n * dof, n * dof)
    out: FloatArray = 0.5 * (W + W.T)
    return out


def nees_mean_distribution(
    joint_cov: FloatArray, dof: int = 3, p: float = 0.95
) -> NeesMeanDistribution:
    """Exact mean and standard deviation of the mean NEES over ``T`` poses whose errors
    are jointly Gaussian with covariance ``joint_cov`` ((T·dof)², pose by pose), and an
    interval of probability ``p``.

    Each pose's NEES uses its own marginal, the diagonal block.  With ``W`` the joint
    covariance whitened by those blocks, the mean NEES is ``‖z‖² / T`` for
    ``z ~ N(0, W)``: mean ``tr W / T = dof`` and variance ``2 ‖W‖_F² / T²``.  The
    interval is that of the scaled χ² with these moments (Satterthwaite), which is
    close when the run is worth a few independent poses or more (checked against
    draws in the tests).

    Unlike :func:`nees_mean_interval` this sees errors that last the whole run: use it
    where a smoother gives the joint covariance of its poses.
    """
    W = _whitened_joint(joint_cov, dof)
    n = W.shape[0] // dof
    mean = float(np.trace(W)) / n
    var = 2.0 * float(np.sum(W * W)) / (n * n)
    return _satterthwaite(n, dof, mean, var, p)


def pooled_nees_mean_distribution(
    parts: list[NeesMeanDistribution], p: float = 0.95
) -> NeesMeanDistribution:
    """The distribution of the mean NEES over several independent runs' poses taken
    together (each run weighted by its number of poses)."""
    if not parts:
        raise ValueError("pooled_nees_mean_distribution needs at least one run")
    dofs = {d.dof for d in parts}
    if len(dofs) != 1:
        raise ValueError(f"runs of different dof cannot be pooled: {sorted(dofs)}")
    total = sum(d.steps for d in parts)
    mean = sum(d.steps * d.mean for d in parts) / total
    var = sum((d.steps * d.sd) ** 2 for d in parts) / total**2
    return _satterthwaite(total, parts[0].dof, mean, var, p)


def consistent_error_draws(
    joint_cov: FloatArray, n_draws: int, rng: np.random.Generator, dof: int = 3
) -> FloatArray:
    """Errors (n_draws, T, dof) drawn from ``joint_cov``: those of a consistent estimator
    with this joint covariance (for the maximum error over a run, for one)."""
    if n_draws < 1:
        raise ValueError(f"n_draws must be >= 1, got {n_draws}")
    S, _ = _block_inverse_factors(joint_cov, dof)
    w, V = np.linalg.eigh(0.5 * (S + S.T))
    root = V * np.sqrt(np.clip(w, 0.0, None))
    out: FloatArray = (rng.standard_normal((n_draws, S.shape[0])) @ root.T).reshape(
        n_draws, -1, dof
    )
    return out


def joint_nees(errors: FloatArray, joint_cov: FloatArray, dof: int = 3) -> FloatArray:
    """NEES (…, T) of errors (…, T, dof), each pose's against its own diagonal block of
    ``joint_cov`` (the pose's marginal), e.g. of :func:`consistent_error_draws`."""
    _, Li = _block_inverse_factors(joint_cov, dof)
    e = np.asarray(errors, dtype=float)
    if e.shape[-2:] != (Li.shape[0], dof):
        raise ValueError(
            f"errors must end in ({Li.shape[0]}, {dof}) to match joint_cov, got {e.shape}"
        )
    z = np.einsum("tab,...tb->...ta", Li, e)
    out: FloatArray = np.sum(z * z, axis=-1)
    return out


def consistent_nees_draws(
    joint_cov: FloatArray, n_draws: int, rng: np.random.Generator, dof: int = 3
) -> FloatArray:
    """NEES series (n_draws, T) of errors drawn from ``joint_cov`` itself: what a
    consistent estimator with this joint covariance would show, for statistics without
    a closed form (the fraction of steps within a χ² bound, for one)."""
    return joint_nees(consistent_error_draws(joint_cov, n_draws, rng, dof), joint_cov, dof)
