"""Batch smoothing against the EKF on loop600, seeds 0–4 (slow).

Both consume the same log and the EKF's association decisions.  Per seed the smoothed
NEES is one strongly autocorrelated series, and part of its error (the anchor's, the
known map's) lasts the whole run, so the test pools the five runs and takes the
interval of their mean NEES from the smoother's own joint covariance of every 10th pose
(:func:`mapfuse_core.evaluation.nees_mean_distribution`).
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from scipy.stats import chi2

from ekf_reference import EKFConfig, run_ekf
from mapfuse.runner import Run, run
from mapfuse_core.evaluation import (
    CHI2_3_95,
    anchor_truth,
    nees_mean_distribution,
    nees_series,
    pooled_nees_mean_distribution,
    pose_errors,
    truth_in_global,
)
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.measlog import MeasurementLog
from tests.loop600 import SEEDS, ekf_metrics, loop600_ekf, loop600_log
from tests.synthetic import with_known

pytestmark = pytest.mark.slow


#: Every JOINT_STRIDE-th pose gets the smoother's joint covariance (239 of 2,400: the
#: errors persist for hundreds of steps, so the mean over them is the run's mean).
JOINT_STRIDE = 10


@functools.lru_cache(maxsize=5)
def _batch(seed: int) -> Run:
    log = loop600_log(seed)
    return run(
        log,
        "batch",
        fusion=True,
        upstream=loop600_ekf(seed, True),
        joint_stride=JOINT_STRIDE,
    )


def test_pooled_smoothed_nees_is_within_its_interval() -> None:
    """The smoother's mean NEES over seeds 0–4 against what its own joint covariance
    says a consistent smoother's would scatter over.

    The errors share the anchor's and the known map's, which last the whole run: by
    the joint covariance a run is worth about 3 independent poses (sd of its mean NEES
    1.4), in line with the spread of the mean NEES over 40 seeds (1.3,
    ``benchmarks/mc_loop600.py``).  The interval from the NEES series' own
    autocorrelation (:func:`nees_mean_interval`) cannot see such errors: it was
    [2.88, 3.12] for these five seeds, and the 3.16 measured looked like a 6 %
    overconfident smoother.  Over 40 seeds the mean is 3.19 with a standard error of
    0.21 (95 % about [2.78, 3.60]): no detectable inconsistency, which cannot rule out a
    few per cent either way.  Five runs this correlated test little: the interval would
    also pass a smoother some 40 % overconfident.
    """
    parts, series = [], []
    for s in SEEDS:
        b = _batch(s)
        joint = b.result.details.joint_pose_cov
        assert joint is not None
        truth = loop600_log(s).true_poses
        assert truth is not None
        v = nees_series(pose_errors(b.poses, truth_in_global(truth)).dx, b.covs)
        series.append(v[joint.steps])
        parts.append(nees_mean_distribution(joint.cov))
    pooled = pooled_nees_mean_distribution(parts)
    lo, hi = pooled.interval
    mean = float(np.mean(np.concatenate(series)))
    per_seed = [round(float(v.mean()), 2) for v in series]
    sds = [round(d.sd, 2) for d in parts]
    print(
        f"\nsmoothed NEES per seed {per_seed} (model sd {sds}), pooled {mean:.2f} "
        f"in [{lo:.2f}, {hi:.2f}]"
    )
    # Measured 3.20 in [1.90, 4.34] (per seed 3.29, 2.00, 2.74, 2.85, 5.12, model sd
    # 1.38-1.41).  A smoother whose covariances were half what they should be would be
    # at about 6.4 and fail.
    assert lo <= mean <= hi
    assert all(np.isfinite(v).all() for v in series)


def test_smoothing_is_more_accurate_than_filtering_pooled() -> None:
    sq_batch = sq_ekf = 0.0
    ratios = []
    for s in SEEDS:
        pe = _batch(s).metrics.position_error
        assert pe is not None
        b = pe.rmse
        f = ekf_metrics(loop600_ekf(s, True), loop600_log(s))["position_error_m"]["rmse"]
        sq_batch += b * b
        sq_ekf += f * f
        ratios.append(round(b / f, 2))
    pooled = math.sqrt(sq_batch / sq_ekf)
    print(f"\nbatch/EKF position RMSE per seed {ratios}, pooled {pooled:.2f}")
    # The target ratio is 0.7; the smoother's own covariance predicts about 0.85 on
    # this scenario (about 15 features in view per step leave the filter little to
    # gain from the future), so 0.7 is not expected; the bound guards against a
    # regression (measured figures: docs/results/known-gaps.md).
    assert pooled <= 0.9


@pytest.mark.parametrize("seed", SEEDS)
def test_the_logs_support_the_papers_fused_max_error(seed: int) -> None:
    """The paper's 0.15 m fused maximum is within what each log's data allow: the batch
    smoother with fusion meets it on every seed, also where the EKF does not (seeds 2
    and 4, xfail in test_loop600_ekf.py): their misses are the EKF's, not the data's.
    """
    m = _batch(seed).metrics.position_error
    assert m is not None
    # Measured: 0.091, 0.073, 0.089, 0.099, 0.112 m (EKF 0.084, 0.121, 0.151, 0.103,
    # 0.175); the largest is at the sparse north-east corner, steps 450–600.
    assert m.max <= 0.15, m


# ------------------------------------------------------------ filter against filter
# The smoother above sees the future; a filter is the closer yardstick for the EKF.
# iSAM2's estimate of X_k right after update k (the result's filtered track) uses the
# measurements of steps 0..k, relinearised, with the EKF's inputs.  Its associations
# are the EKF's *final* decisions applied from each feature's first sighting, so it
# knows at once what the EKF learns only at its next join.


@functools.lru_cache(maxsize=5)
def _isam2(seed: int) -> Run:
    log = loop600_log(seed)
    return run(log, "isam2", fusion=True, upstream=loop600_ekf(seed, True))


def _filtered(seed: int) -> tuple[float, np.ndarray]:
    """Max position error and NEES series of iSAM2's filtered estimates.

    Step 0 and non-finite values are left out of the NEES as ``ekf_metrics`` does (the
    EKF's step-0 covariance is zero; the graph's is its tiny prior's)."""
    g = _isam2(seed).result.filtered
    truth = loop600_log(seed).true_poses
    assert g is not None
    assert truth is not None
    dx = pose_errors(g.poses, truth_in_global(truth)).dx
    nees = nees_series(dx, g.covs)[1:]
    return float(np.hypot(dx[:, 0], dx[:, 1]).max()), nees[np.isfinite(nees)]


@pytest.mark.parametrize("seed", SEEDS)
def test_a_filter_on_the_same_inputs_meets_the_papers_fused_max_error(seed: int) -> None:
    """A filter that links a re-seen feature to its landmark at once meets 0.15 m on
    every seed.  The EKF links it only at its next join and misses on seeds 2 and 4
    (see test_loop600_ekf.py)."""
    worst, _ = _filtered(seed)
    # Measured 0.077, 0.109, 0.138, 0.097, 0.141 m (EKF 0.084, 0.121, 0.151, 0.103,
    # 0.175 m): the EKF's maximum is 6–24 % larger.  The largest, 0.141 m, leaves 9 mm;
    # the runs are deterministic per seed, so the margin only has to absorb library
    # round-off.
    assert worst <= 0.15


@pytest.mark.parametrize("seed", SEEDS)
def test_the_ekf_is_as_consistent_as_the_nonlinear_filter(seed: int) -> None:
    """Where the EKF's NEES leaves the χ² bound too often (seed 4), so does the
    relinearising filter on the same inputs and associations: that gap is not specific
    to the EKF's linearisation or its local maps."""
    _, nees = _filtered(seed)
    ekf = ekf_metrics(loop600_ekf(seed, True), loop600_log(seed))["nees"]
    within = float(np.mean(nees <= CHI2_3_95))
    print(
        f"\nseed {seed}: within EKF {ekf['fraction_within_chi2_95']:.3f} filter {within:.3f};"
        f" mean NEES EKF {ekf['mean']:.2f} filter {float(np.mean(nees)):.2f}"
    )
    # Measured fractions within 0.969/0.968, 0.985/0.985, 0.932/0.915, 0.981/0.980,
    # 0.853/0.839 and mean NEES 2.64/2.57, 2.26/2.26, 3.80/3.87, 2.74/2.67, 5.37/5.53
    # (EKF/filter): the EKF never less often within, its mean NEES at most 2.7 %
    # above.  The runs are deterministic per seed, so the bounds need not cover noise:
    # 0.02 and 10 % fail an EKF that becomes clearly less consistent than the filter.
    assert ekf["fraction_within_chi2_95"] >= within - 0.02
    assert ekf["mean"] <= 1.10 * float(np.mean(nees))


# ------------------------------------------------------------------ anchor consistency
# One anchor per run: pool the five seeds' 3-dof NEES.  A consistent anchor has a
# pooled sum ~ χ²(15); the bound is its 97.5 % quantile, as a mean (5.50).
ANCHOR_NEES_MEAN_BOUND = float(chi2.ppf(0.975, 3 * len(SEEDS))) / len(SEEDS)


def _anchor_nees(
    x: np.ndarray, cov: np.ndarray, seed: int, log: MeasurementLog | None = None
) -> float:
    truth = (loop600_log(seed) if log is None else log).true_poses
    assert truth is not None
    dx = pose_errors(x[None], anchor_truth(truth)[None]).dx
    return float(nees_series(dx, cov[None])[0])


def test_batch_anchor_covariance_is_consistent_pooled() -> None:
    values = []
    for s in SEEDS:
        a = _batch(s).result.anchor
        assert a is not None
        values.append(_anchor_nees(a.x_Wknown_Wglobal, a.cov, s))
    print(f"\nbatch anchor NEES per seed {[round(v, 1) for v in values]}")
    # Measured 2.8, 6.4, 0.8, 5.3, 3.8 (mean 3.8); over 40 seeds the mean is 3.06
    # (benchmarks/mc_loop600.py).
    assert float(np.mean(values)) <= ANCHOR_NEES_MEAN_BOUND


def test_ekf_anchor_covariance_is_consistent_pooled() -> None:
    values = []
    for s in SEEDS:
        a = loop600_ekf(s, True).anchor
        assert a is not None
        values.append(_anchor_nees(a.x_Wknown_Wglobal, a.cov, s))
    print(f"\nEKF anchor NEES per seed {[round(v, 1) for v in values]}")
    # Measured 2.5, 6.6, 0.7, 4.8, 4.1 (mean 3.7; the batch's 3.8).  A known wall's
    # residual measured at the wall's reference point instead of the observed segment
    # gives 1.1, 11.8, 1.1, 2.9, 16.8 (mean 6.7; docs/results/models.md).
    assert float(np.mean(values)) <= ANCHOR_NEES_MEAN_BOUND


@pytest.mark.parametrize("seed", [4, 12])
def test_ekf_anchor_agrees_with_the_batch_on_a_known_map_of_walls_only(seed: int) -> None:
    """Each known wall is observed thousands of times.  A pairing residual that depends
    on where the wall's reference point lies along it (the anchor's translation along
    the wall is uncertain) piles up information no wall holds; the line model measures
    the observed segment's offset from the wall instead (docs/method.md)."""
    log = loop600_log(seed)
    walls = np.flatnonzero(log.known_map.kinds == int(FeatureKind.LINE)).tolist()
    log = with_known(log, walls)
    ekf = run_ekf(log, EKFConfig(), fusion=True)
    assert ekf.anchor is not None
    graph = run(log, "batch", fusion=True, upstream=ekf).result
    assert graph.anchor is not None
    ratio = np.sqrt(np.diag(ekf.anchor.cov) / np.diag(graph.anchor.cov))
    nees = _anchor_nees(ekf.anchor.x_Wknown_Wglobal, ekf.anchor.cov, seed, log)
    print(f"\nseed {seed}, walls only: EKF/batch anchor σ {np.round(ratio, 3)}, NEES {nees:.1f}")
    # Measured σ ratios 0.956–0.978 and 0.948–0.969, NEES 4.7 and 1.2 (seeds 4, 12).
    # The bounds sit between those and the wall-reference-point residual's 0.70–0.77
    # and 34–74 (docs/results/models.md); the runs are deterministic per seed, so the margins
    # only absorb library round-off.
    assert np.all((ratio > 0.9) & (ratio < 1.1))
    assert nees <= CHI2_3_95
