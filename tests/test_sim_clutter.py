"""Spurious features and gross outliers added by the simulator (``mapfuse_core.sim.clutter``)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.measlog import MeasurementLog
from mapfuse_core.sim.clutter import ClutterParams
from mapfuse_core.sim.scenario import load_scenario
from mapfuse_core.sim.simulate import simulate

STEPS = 40


@pytest.fixture(scope="module")
def logs() -> tuple[MeasurementLog, MeasurementLog]:
    sc = dataclasses.replace(load_scenario("loop600"), steps=STEPS)
    plain = simulate(sc, seed=3, workers=1).log
    clutter = ClutterParams(features_per_scan=5, outlier_fraction=0.1)
    return plain, simulate(sc, seed=3, workers=1, clutter=clutter).log


def test_clutter_adds_spurious_features_of_no_world_feature(
    logs: tuple[MeasurementLog, MeasurementLog],
) -> None:
    plain, hostile = logs
    spurious = hostile.feat_true_id < 0
    # Five per scan, on top of what extraction finds (loop600's extraction labels
    # every feature it keeps, so the plain log has no −1).
    assert int(np.sum(plain.feat_true_id < 0)) == 0
    assert np.all(np.bincount(hostile.feat_step[spurious], minlength=STEPS) == 5)
    kinds = hostile.feat_kind[spurious]
    # Half circles, half lines: 200 draws, the binomial σ is 7.
    assert 100 - 25 <= int(np.sum(kinds == int(FeatureKind.CIRCLE))) <= 100 + 25
    rng = np.hypot(hostile.feat_params[spurious, 0], hostile.feat_params[spurious, 1])
    assert rng.min() >= 1.0 - 1e-12
    assert rng.max() <= 30.0 + 1e-12
    # A spurious line's normal points to the sensor, as extraction states lines.
    lines = spurious & (hostile.feat_kind == int(FeatureKind.LINE))
    p = hostile.feat_params[lines]
    n = np.column_stack([-np.sin(p[:, 2]), np.cos(p[:, 2])])
    assert np.all(np.sum(n * -p[:, :2], axis=1) >= 0.0)


def test_outliers_move_real_features_by_2_to_10_m(
    logs: tuple[MeasurementLog, MeasurementLog],
) -> None:
    plain, hostile = logs
    real = hostile.feat_true_id >= 0
    # The real features come in the same order, unchanged except for the outliers.
    assert np.array_equal(hostile.feat_true_id[real], plain.feat_true_id)
    d = np.hypot(*(hostile.feat_params[real, :2] - plain.feat_params[:, :2]).T)
    moved = d > 0.0
    assert np.all((d[moved] >= 2.0 - 1e-9) & (d[moved] <= 10.0 + 1e-9))
    # 10 % of about 200 real features: the binomial σ is about 4.
    frac = float(np.mean(moved))
    assert 0.1 - 0.06 <= frac <= 0.1 + 0.06, frac
    np.testing.assert_array_equal(hostile.feat_cov[real], plain.feat_cov)


def test_the_rest_of_the_log_is_that_of_the_same_seed(
    logs: tuple[MeasurementLog, MeasurementLog],
) -> None:
    plain, hostile = logs
    np.testing.assert_array_equal(hostile.odometry, plain.odometry)
    np.testing.assert_array_equal(hostile.true_poses, plain.true_poses)
    np.testing.assert_array_equal(hostile.known_map.params, plain.known_map.params)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("features_per_scan", -1),
        ("features_per_scan", 2.5),
        ("circle_fraction", 1.5),
        ("outlier_fraction", -0.1),
        ("max_range_m", 0.5),
        ("outlier_min_m", math.nan),
        ("outlier_max_m", 1.0),
    ],
)
def test_bad_clutter_params_are_named(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field):
        ClutterParams(**{field: value})  # type: ignore[arg-type]
