"""``benchmarks/carmen_filter.py``: the redrawn observations, the scaled odometry noise
and the summary over seeds."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mapfuse_core.data.datasets import IncrementNoise
from mapfuse_core.data.datasets.floorplan import express_line_in
from mapfuse_core.geometry.features import FeatureKind
from tests.scripts import load_benchmark
from tests.synthetic import synthetic_log


@pytest.fixture(scope="module")
def cf():  # type: ignore[no-untyped-def]
    return load_benchmark("carmen_filter")


def test_scaled_noise_scales_every_term(cf) -> None:  # type: ignore[no-untyped-def]
    d, s = IncrementNoise(), cf.scaled_noise(0.2)
    for f in dataclasses.fields(d):
        assert getattr(s, f.name) == pytest.approx(0.2 * getattr(d, f.name), rel=1e-12)


def test_redrawn_lines_lie_on_their_wall_and_unlabelled_ones_go(cf) -> None:  # type: ignore[no-untyped-def]
    log = synthetic_log(steps=30, seed=1)
    assert log.world is not None
    assert log.true_poses is not None
    walls = log.world
    lines = log.feat_kind == int(FeatureKind.LINE)
    # Labels as a plan gives them: the wall's index, −1 for everything else.
    labels = np.where(lines, log.feat_true_id - int(walls.ids[0]), -1)
    # A stated covariance of 1e-12 m² and rad²: the redrawn line is its wall.
    covs = np.where(lines[:, None, None], 1e-12 * np.eye(3), log.feat_cov)
    log = dataclasses.replace(log, feat_true_id=labels, feat_cov=covs)
    out = cf.redrawn_from_plan(log, walls, seed=0)
    assert out.n_features == int(lines.sum()) > 0
    assert np.all(out.feat_kind == int(FeatureKind.LINE))
    for j in range(out.n_features):
        pose = out.true_poses[int(out.feat_step[j])]
        wall = express_line_in(pose, walls.params[int(out.feat_true_id[j])])[0]
        x, y, th = out.feat_params[j]
        # Same direction (up to its sense) and the redrawn point on the wall's line.
        assert abs(math.sin(th - wall[2])) < 1e-4
        lateral = -(x - wall[0]) * math.sin(wall[2]) + (y - wall[1]) * math.cos(wall[2])
        assert abs(lateral) < 1e-4


def test_summary_is_the_mean_and_median_of_the_runs(cf) -> None:  # type: ignore[no-untyped-def]
    rows = [
        {
            "log": "x",
            "variant": "redrawn",
            "anchored": a,
            "ekf_nees": e,
            "ekf_rmse_m": 0.1 * e,
            "isam2_filtered_nees": i,
            "isam2_filtered_rmse_m": 0.01 * i,
            "anchored_steps": 10 if a else 0,
            "ekf_plan_frame_nees": k,
            "ekf_plan_frame_rmse_m": 0.02 * k,
            "ekf_global_same_steps_nees": 2.0 * k,
        }
        for a, e, i, k in (
            (True, 3.0, 2.0, 2.0),
            (False, 9.0, 4.0, math.nan),
            (True, 30.0, 3.0, 6.0),
        )
    ]
    s = cf.summarise(rows)
    assert (s["runs"], s["anchored"]) == (3, 2)
    assert s["ekf_anees"] == pytest.approx(14.0)
    assert s["ekf_median"] == pytest.approx(9.0)
    assert s["ekf_rmse_median_m"] == pytest.approx(0.9)
    assert s["isam2_filtered_anees"] == pytest.approx(3.0)
    assert s["isam2_filtered_median"] == pytest.approx(3.0)
    # The plan's frame: over the anchored runs only.
    assert s["ekf_plan_frame_anees"] == pytest.approx(4.0)
    assert s["ekf_plan_frame_median"] == pytest.approx(4.0)
    assert s["ekf_plan_frame_rmse_median_m"] == pytest.approx(0.08)
    assert s["ekf_global_same_steps_anees"] == pytest.approx(8.0)


def test_plan_frame_nees_is_over_the_anchored_steps(cf) -> None:  # type: ignore[no-untyped-def]
    from types import SimpleNamespace

    from mapfuse_core.estimate import PoseTrack

    reference = np.zeros((4, 3))
    cov = np.tile(np.diag([0.01, 1.0, 1.0]), (4, 1, 1))
    known = np.full((4, 3), np.nan)
    known[2:] = [0.1, 0.0, 0.0]  # anchored from step 2 on, 0.1 m (1 σ) off
    details = SimpleNamespace(poses_in_known=known, covs_in_known=cov)
    filtered = PoseTrack(np.tile([0.2, 0.0, 0.0], (4, 1)), cov)  # 2 σ off in Wglobal
    out = cf.in_plan_frame(filtered, details, reference, reference)
    assert out["anchored_steps"] == 2
    assert out["ekf_plan_frame_nees"] == pytest.approx(1.0)
    assert out["ekf_plan_frame_rmse_m"] == pytest.approx(0.1)
    assert out["ekf_global_same_steps_nees"] == pytest.approx(4.0)
    none = cf.in_plan_frame(
        filtered,
        SimpleNamespace(poses_in_known=np.full((4, 3), np.nan), covs_in_known=cov),
        reference,
        reference,
    )
    assert none["anchored_steps"] == 0
    assert math.isnan(none["ekf_plan_frame_nees"])
