"""The fixed-lag backend: agreement with batch (lag ∞) and iSAM2's filter (lag 0),
what leaves the window and when, landmark relabelling, options and registration."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapfuse_core.estimate import EstimatorResult
from mapfuse_core.geometry.se2 import wrap_angle
from mapfuse_core.measlog import MeasurementLog
from mapfuse_graph.fixedlag import split_by_lag
from mapfuse_graph.isam2 import isam2_params
from mapfuse_graph.solvers import FixedLagOptions, ISAM2Options, run_graph
from tests.loop600 import loop600_log
from tests.synthetic import synthetic_log

INF = math.inf


pytestmark = pytest.mark.usefixtures("jacobian_checks")


def _abs_diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = a - b
    d[:, 2] = wrap_angle(d[:, 2])
    return np.asarray(np.abs(d))


def _rel_diff(a: np.ndarray, b: np.ndarray, covs: np.ndarray) -> np.ndarray:
    """|a − b| / σ per step and coordinate, step 0 (held by its prior) excluded."""
    sig = np.sqrt(np.einsum("kii->ki", covs))
    return _abs_diff(a, b)[1:] / sig[1:]


def _fixedlag(
    log: MeasurementLog,
    lag: float,
    steps: int | None = None,
    isam2: ISAM2Options | None = None,
    **kw: object,
) -> EstimatorResult:
    return run_graph(
        log,
        "fixedlag",
        fusion=True,
        association="truth",
        steps=steps,
        fixedlag=FixedLagOptions(lag_s=lag, **kw),  # type: ignore[arg-type]
        isam2=isam2,
    )


# --------------------------------------------------------------------------- agreement


@pytest.mark.slow
def test_infinite_lag_equals_batch_on_loop600() -> None:
    """Lag ∞ marginalises nothing: the final estimate is iSAM2's, which its final
    Gauss–Newton step puts at the batch optimum: bounds 0.01 mm, 1 µrad, 0.1 % of every
    pose's σ, variances within 0.1 % (measured values, 25–40× smaller, in
    ``docs/results/fixedlag.md``)."""
    log = loop600_log(0)
    fl = _fixedlag(log, INF, steps=300)
    bat = run_graph(log, "batch", fusion=True, association="truth", steps=300)
    assert fl.details.extra["window_steps"] == 300
    d = _abs_diff(fl.poses, bat.poses)
    assert d[:, :2].max() <= 1e-5
    assert d[:, 2].max() <= 1e-6
    assert _rel_diff(fl.poses, bat.poses, bat.covs).max() <= 1e-3
    np.testing.assert_allclose(
        np.einsum("kii->ki", fl.covs[1:]), np.einsum("kii->ki", bat.covs[1:]), rtol=1e-3
    )
    assert fl.details.final_error == pytest.approx(bat.details.final_error, rel=1e-7)


@pytest.mark.slow
def test_zero_lag_filter_equals_isam2_filter_on_loop600() -> None:
    """Lag 0 keeps the newest pose and the map: its filtered estimate is iSAM2's except
    that past poses are never relinearised (the EKF's linearisation, where iSAM2 moves
    old poses' linearisation points): bounds 0.25 σ of iSAM2's filtered covariance at
    any step, 0.05 σ on average, covariances within 5 % (``docs/results/fixedlag.md``).  Each
    pose is final as soon as it is filtered."""
    log = loop600_log(0)
    fl = _fixedlag(log, 0.0, steps=300)
    inc = run_graph(log, "isam2", fusion=True, association="truth", steps=300)
    assert fl.filtered is not None
    assert inc.filtered is not None
    assert fl.details.extra["window_steps"] == 1
    rel = _rel_diff(fl.filtered.poses, inc.filtered.poses, inc.filtered.covs)
    assert rel.max() <= 0.25
    assert rel.mean() <= 0.05
    np.testing.assert_allclose(
        np.einsum("kii->ki", fl.filtered.covs[1:]),
        np.einsum("kii->ki", inc.filtered.covs[1:]),
        rtol=0.05,
    )
    np.testing.assert_array_equal(fl.poses[:-1], fl.filtered.poses[:-1])


@pytest.mark.parametrize("partial", [False, True])
def test_infinite_lag_equals_isam2_on_a_synthetic_loop(partial: bool) -> None:
    """Same updates, same relinearisation: with nothing to marginalise the smoother is
    iSAM2 (its filtered poses to 1e-6 m, its final ones to 1e-3 σ)."""
    log = synthetic_log(steps=150, seed=3)
    opts = ISAM2Options(partial_relinearization_check=partial)
    fl = _fixedlag(log, INF, isam2=opts)
    inc = run_graph(log, "isam2", fusion=True, association="truth", isam2=opts)
    assert fl.filtered is not None
    assert inc.filtered is not None
    assert _abs_diff(fl.filtered.poses, inc.filtered.poses).max() <= 1e-6
    assert _rel_diff(fl.poses, inc.poses, inc.covs).max() <= 1e-3
    assert fl.anchor is not None
    assert inc.anchor is not None


def test_the_partial_relinearisation_check_is_isam2s_default_and_not_the_smoothers() -> None:
    """A pose leaves the smoother's window with the linearisation it has; the partial
    check would let it leave stale (``docs/results/fixedlag.md``)."""
    default = ISAM2Options()
    assert isam2_params(default, False).enablePartialRelinearizationCheck
    assert not isam2_params(default, False, smoother=True).enablePartialRelinearizationCheck
    for forced in (False, True):
        opts = ISAM2Options(partial_relinearization_check=forced)
        for smoother in (False, True):
            assert (
                isam2_params(opts, False, smoother=smoother).enablePartialRelinearizationCheck
                is forced
            )
    for bad in ("yes", 1, 0.0):
        with pytest.raises(ValueError, match="partial_relinearization_check must be"):
            ISAM2Options(partial_relinearization_check=bad)  # type: ignore[arg-type]


def test_window_graph_linearises_marginal_factors_where_they_are_evaluated() -> None:
    """GTSAM's marginal factors come without their linearisation point (the same linear
    factor wherever they are linearised); remade with it, each one's linearisation
    anywhere has the factor's own error at zero delta."""
    import gtsam

    from mapfuse_graph.fixedlag import window_graph
    from mapfuse_graph.keys import pose_key

    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.1, 0.1, 0.01]))
    smoother = gtsam.IncrementalFixedLagSmoother(2.0, gtsam.ISAM2Params())
    for k in range(8):
        f = gtsam.NonlinearFactorGraph()
        v = gtsam.Values()
        if k == 0:
            f.add(gtsam.PriorFactorPose2(pose_key(k), gtsam.Pose2(), noise))
        else:
            u = gtsam.Pose2(1.0, 0.0, 0.1)
            f.add(gtsam.BetweenFactorPose2(pose_key(k - 1), pose_key(k), u, noise))
        v.insert(pose_key(k), gtsam.Pose2(1.05 * k, 0.02 * k, 0.09 * k))
        smoother.update(f, v, {pose_key(k): float(k)})
    raw = smoother.getFactors()
    est = smoother.calculateEstimate()
    moved = gtsam.Values()
    held = est.keys()
    for key in held:
        moved.insert(key, est.atPose2(key).retract(np.array([0.3, -0.2, 0.05])))
    zero = moved.zeroVectors()
    remade = window_graph(raw, smoother.getLinearizationPoint())
    got = [remade.at(i) for i in range(remade.size())]
    theirs = [raw.at(i) for i in range(raw.size())]
    theirs = [f for f in theirs if isinstance(f, gtsam.LinearContainerFactor)]
    ours = [f for f in got if isinstance(f, gtsam.LinearContainerFactor)]
    assert len(ours) == len(theirs) >= 1  # poses 0..4 have left the window
    lp = smoother.getLinearizationPoint()
    for mine, gtsams in zip(ours, theirs, strict=True):
        # At its own linearisation point the remade container is GTSAM's linear factor.
        assert mine.linearize(lp).error(zero) == pytest.approx(
            gtsams.factor().error(zero), rel=1e-12
        )
        assert mine.linearize(moved).error(zero) == pytest.approx(mine.error(moved), rel=1e-9)
        assert mine.error(moved) > 1.0
        assert gtsams.linearize(moved).error(zero) == pytest.approx(
            gtsams.linearize(est).error(zero), rel=1e-12
        )
    assert len(got) == sum(raw.at(i) is not None for i in range(raw.size()))


def test_final_step_of_the_window_starts_from_the_smoothers_optimum() -> None:
    """The final Gauss–Newton step on the window is small (measured 2e-4 on this log).
    GTSAM's marginal factors linearised from the wrong origin make it 0.12, with the
    window's poses off by several σ."""
    log = synthetic_log(steps=200, seed=1)
    fl = _fixedlag(log, 1.0)
    assert fl.details.extra["final_gauss_newton_step_max"] <= 0.01
    assert fl.filtered is not None
    w = fl.details.extra["window_steps"]
    assert w == 9
    # The last pose, smoothed at the end, stays within a fraction of its σ of its
    # filtered estimate (both have the same information).
    sig = np.sqrt(np.diag(fl.covs[-1]))
    assert np.all(_abs_diff(fl.poses[-1:], fl.filtered.poses[-1:])[0] <= 0.05 * sig)


# --------------------------------------------------------------------------- the window


def test_poses_leave_the_window_after_the_lag() -> None:
    """With lag L the final window holds the steps with t_k >= t_end − L, and every pose
    outside it is final: the estimate, with its marginal, before it was marginalised."""
    log = synthetic_log(steps=120, seed=4)
    lag = 2.0
    fl = _fixedlag(log, lag)
    t = log.timestamps[:120]
    assert fl.details.extra["window_steps"] == int(np.sum(t >= t[-1] - lag))
    assert np.all(np.isfinite(fl.poses))
    assert np.all(np.isfinite(fl.covs))
    # The full smoother refines each final pose with the steps after it left the window:
    # the change has a covariance below the final pose's own, and stays within 3 σ of it.
    full = _fixedlag(log, INF)
    assert _rel_diff(full.poses, fl.poses, fl.covs).max() <= 3.0


def test_window_policy_marginalises_unobserved_landmarks() -> None:
    """``landmarks="window"``: a landmark unobserved for longer than the lag is
    marginalised by GTSAM; seen again it is a new landmark; paired ones stay."""
    log = synthetic_log(steps=160, seed=5)
    kept = _fixedlag(log, 0.5)
    win = _fixedlag(log, 0.5, landmarks="window")
    assert kept.details.extra["marginalised_landmarks"] == 0
    assert win.details.extra["marginalised_landmarks"] > 0
    assert len(win.map.kinds) > len(kept.map.kinds)
    assert np.all(np.isfinite(win.poses))
    assert win.anchor is not None
    # Tied landmarks keep one label each.
    tied = win.map.known_ids[win.map.known_ids >= 0]
    assert tied.size == np.unique(tied).size > 0


def test_split_by_lag_cuts_where_the_smoother_marginalises() -> None:
    t = np.arange(10) * 1.0
    steps = np.array([0, 1, 3, 4, 8, 0, 9])
    lm = np.array([0, 0, 0, 0, 0, 1, 1])
    kn = np.array([-1, -1, -1, -1, -1, 7, -1])
    out = split_by_lag(lm, kn, steps, t, lag_s=1.0)
    # 0→1: t0 = 0 is the previous step's time, 0 − 0 <= 1: same; 1→3: t2 − t1 = 1: same;
    # 4→8: t7 − t4 = 3 > 1: new label.  Landmark 1 is paired: never cut.
    np.testing.assert_array_equal(out, [0, 0, 0, 0, 2, 1, 1])
    assert split_by_lag(lm, kn, steps, t, lag_s=INF).tolist() == lm.tolist()


# --------------------------------------------------------------------------- inputs


@pytest.mark.parametrize(
    ("kw", "msg"),
    [
        ({"lag_s": -1.0}, "lag_s must be >= 0"),
        ({"lag_s": math.nan}, "lag_s must be a number"),
        ({"lag_s": "5"}, "lag_s must be a number"),
        ({"landmarks": "drop"}, "landmarks must be one of keep, window"),
    ],
)
def test_bad_fixedlag_options_are_rejected(kw: dict[str, object], msg: str) -> None:
    with pytest.raises(ValueError, match=msg):
        FixedLagOptions(**kw)  # type: ignore[arg-type]


def test_window_policy_refuses_own_association() -> None:
    log = synthetic_log(steps=20, seed=0)
    with pytest.raises(ValueError, match="needs a fixed association"):
        run_graph(
            log,
            "fixedlag",
            association="own",
            fixedlag=FixedLagOptions(lag_s=1.0, landmarks="window"),
        )


def test_fixedlag_runs_as_a_registered_estimator() -> None:
    from mapfuse import registry
    from mapfuse.estimators.graph import FixedLagEstimator
    from mapfuse.runner import run

    if "fixedlag" not in registry.available():
        registry.register(FixedLagEstimator())
    log = synthetic_log(steps=80, seed=6)
    r = run(log, "fixedlag", fusion=True, association="truth", fixedlag=FixedLagOptions(lag_s=1.0))
    assert r.estimator == "fixedlag"
    assert r.result.filtered is not None
    assert r.metrics.nees is not None
    assert r.metrics.position_error is not None
    assert r.metrics.position_error.rmse < 0.5
