"""The fixed-lag backend: agreement with batch (lag ∞) and iSAM2's filter (lag 0),
what leaves the window and when, landmark relabelling, options and registration."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapfuse_core.data.measlog import MeasurementLog
from mapfuse_core.geometry.se2 import wrap_angle
from mapfuse_graph.fixedlag import split_by_lag
from mapfuse_graph.isam2 import isam2_params
from mapfuse_graph.solvers import FixedLagOptions, GraphResult, ISAM2Options, run_graph
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
) -> GraphResult:
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
    ``docs/fixedlag.md``)."""
    log = loop600_log(0)
    fl = _fixedlag(log, INF, steps=300)
    bat = run_graph(log, "batch", fusion=True, association="truth", steps=300)
    assert fl.extra["window_steps"] == 300
    d = _abs_diff(fl.poses, bat.poses)
    assert d[:, :2].max() <= 1e-5
    assert d[:, 2].max() <= 1e-6
    assert _rel_diff(fl.poses, bat.poses, bat.covs).max() <= 1e-3
    np.testing.assert_allclose(
        np.einsum("kii->ki", fl.covs[1:]), np.einsum("kii->ki", bat.covs[1:]), rtol=1e-3
    )
    assert fl.final_error == pytest.approx(bat.final_error, rel=1e-7)


@pytest.mark.slow
def test_zero_lag_filter_equals_isam2_filter_on_loop600() -> None:
    """Lag 0 keeps the newest pose and the map: its filtered estimate is iSAM2's except
    that past poses are never relinearised (the EKF's linearisation, where iSAM2 moves
    old poses' linearisation points): bounds 0.25 σ of iSAM2's filtered covariance at
    any step, 0.05 σ on average, covariances within 5 % (``docs/fixedlag.md``).  Each
    pose is final as soon as it is filtered."""
    log = loop600_log(0)
    fl = _fixedlag(log, 0.0, steps=300)
    inc = run_graph(log, "isam2", fusion=True, association="truth", steps=300)
    assert fl.filtered_poses is not None
    assert fl.filtered_covs is not None
    assert inc.filtered_poses is not None
    assert inc.filtered_covs is not None
    assert fl.extra["window_steps"] == 1
    rel = _rel_diff(fl.filtered_poses, inc.filtered_poses, inc.filtered_covs)
    assert rel.max() <= 0.25
    assert rel.mean() <= 0.05
    np.testing.assert_allclose(
        np.einsum("kii->ki", fl.filtered_covs[1:]),
        np.einsum("kii->ki", inc.filtered_covs[1:]),
        rtol=0.05,
    )
    np.testing.assert_array_equal(fl.poses[:-1], fl.filtered_poses[:-1])


@pytest.mark.parametrize("partial", [False, True])
def test_infinite_lag_equals_isam2_on_a_synthetic_loop(partial: bool) -> None:
    """Same updates, same relinearisation: with nothing to marginalise the smoother is
    iSAM2 (its filtered poses to 1e-6 m, its final ones to 1e-3 σ)."""
    log = synthetic_log(steps=150, seed=3)
    opts = ISAM2Options(partial_relinearization_check=partial)
    fl = _fixedlag(log, INF, isam2=opts, relinearize_threshold=None, relinearize_skip=None)
    inc = run_graph(log, "isam2", fusion=True, association="truth", isam2=opts)
    assert fl.filtered_poses is not None
    assert inc.filtered_poses is not None
    assert _abs_diff(fl.filtered_poses, inc.filtered_poses).max() <= 1e-6
    assert _rel_diff(fl.poses, inc.poses, inc.covs).max() <= 1e-3
    assert fl.anchor is not None
    assert inc.anchor is not None


def test_the_partial_relinearisation_check_is_isam2s_default_and_not_the_smoothers() -> None:
    """A pose leaves the smoother's window with the linearisation it has; the partial
    check would let it leave stale (``docs/fixedlag.md``)."""
    default = ISAM2Options()
    assert isam2_params(default, False).enablePartialRelinearizationCheck
    assert not isam2_params(default, False, smoother=True).enablePartialRelinearizationCheck
    for forced in (False, True):
        opts = ISAM2Options(partial_relinearization_check=forced)
        for smoother in (False, True):
            assert isam2_params(opts, False, smoother).enablePartialRelinearizationCheck is forced
    with pytest.raises(ValueError, match="partial_relinearization_check must be"):
        ISAM2Options(partial_relinearization_check="yes")  # type: ignore[arg-type]


def test_the_smoother_relinearises_its_window_on_its_own_schedule(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """By default the smoother checks every update at 2 cm and 2 mrad, whatever iSAM2's
    settings; ``None`` takes iSAM2's."""
    import mapfuse_graph.fixedlag as fixedlag

    seen: list[ISAM2Options] = []
    original = fixedlag.isam2_params

    def spy(opts: ISAM2Options, split: bool, smoother: bool = False) -> object:
        seen.append(opts)
        return original(opts, split, smoother)

    monkeypatch.setattr(fixedlag, "isam2_params", spy)
    log = synthetic_log(steps=20, seed=0)
    mine = ISAM2Options(relinearize_skip=7, final_updates=2)
    run_graph(log, "fixedlag", fusion=False, association="truth", isam2=mine)
    theirs = FixedLagOptions(relinearize_threshold=None, relinearize_skip=None)
    run_graph(log, "fixedlag", fusion=False, association="truth", isam2=mine, fixedlag=theirs)
    own, isam2s = seen
    assert own.relinearize_skip == 1
    assert own.relinearize_threshold == {
        "x": (0.02, 0.02, 0.002),
        "l": (0.02, 0.002),
        "c": (0.02, 0.02, 0.02),
        "k": (0.02, 0.002),
        "q": (0.02, 0.02, 0.02),
        "a": (0.02, 0.02, 0.002),
    }
    assert own.final_updates == 2  # the rest of ISAM2Options is used as given
    assert isam2s == mine
    assert FixedLagOptions(relinearize_threshold=[0.1, 0.01]).relinearize_threshold == (0.1, 0.01)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- the window


def test_poses_leave_the_window_after_the_lag() -> None:
    """With lag L the final window holds the steps with t_k >= t_end − L, and every pose
    outside it is final: the estimate, with its marginal, before it was marginalised."""
    log = synthetic_log(steps=120, seed=4)
    lag = 2.0
    fl = _fixedlag(log, lag)
    t = log.timestamps[:120]
    assert fl.extra["window_steps"] == int(np.sum(t >= t[-1] - lag))
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
    assert kept.extra["marginalised_landmarks"] == 0
    assert win.extra["marginalised_landmarks"] > 0
    assert len(win.landmarks.kinds) > len(kept.landmarks.kinds)
    assert np.all(np.isfinite(win.poses))
    assert win.anchor is not None
    # Tied landmarks keep one label each.
    tied = win.landmarks.known_ids[win.landmarks.known_ids >= 0]
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
        ({"relinearize_threshold": (0.02,)}, "relinearize_threshold must be None or"),
        ({"relinearize_threshold": (0.0, 0.002)}, "relinearize_threshold must be None or"),
        ({"relinearize_threshold": (math.inf, 0.002)}, "relinearize_threshold must be None or"),
        ({"relinearize_threshold": "0.02,0.002"}, "relinearize_threshold must be None or"),
        ({"relinearize_threshold": (0.02, True)}, "relinearize_threshold must be None or"),
        ({"relinearize_skip": 0}, "relinearize_skip must be None or an integer >= 1"),
        ({"relinearize_skip": True}, "relinearize_skip must be None or an integer >= 1"),
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
    from mapfuse.run import run

    if "fixedlag" not in registry.available():
        registry.register(FixedLagEstimator())
    log = synthetic_log(steps=80, seed=6)
    r = run(log, "fixedlag", fusion=True, association="truth", fixedlag=FixedLagOptions(lag_s=1.0))
    assert r.estimator == "fixedlag"
    assert r.result.filtered is not None
    assert r.metrics["nees"] is not None
    assert r.metrics["position_error_m"]["rmse"] < 0.5
