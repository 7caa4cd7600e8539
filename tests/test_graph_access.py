"""The solved GTSAM graph in a user's hands: its key map, their own optimizer, the export."""

from __future__ import annotations

import json
from pathlib import Path

import gtsam
import numpy as np
import pytest

from mapfuse.runner import run
from mapfuse_core.estimate import EstimatorResult
from mapfuse_core.geometry.se2 import wrap_angle
from mapfuse_graph.export import export_graph
from mapfuse_graph.keys import describe_key, symbol_name
from mapfuse_graph.results import GraphDetails
from tests.synthetic import synthetic_log


@pytest.fixture(scope="module")
def batch() -> EstimatorResult:
    g = run(synthetic_log(80, 2), "batch", fusion=True).result
    assert isinstance(g.details, GraphDetails)
    return g


def _poses(values: gtsam.Values, n: int) -> np.ndarray:
    out = []
    for k in range(n):
        p = values.atPose2(gtsam.symbol("x", k))
        out.append([p.x(), p.y(), p.theta()])
    return np.array(out)


def test_key_map_names_every_variable(batch: EstimatorResult) -> None:
    assert batch.details.graph is not None
    assert batch.details.values is not None
    keys = batch.details.keys
    assert len(keys) == batch.details.values.size() == batch.details.n_variables
    assert keys["x0"] == "vehicle pose x^Wglobal_R of step 0 (Pose2)"
    assert list(keys)[:3] == ["x0", "x1", "x2"]
    assert keys["a0"].startswith("anchor A = x^Wglobal_Wknown")
    assert {k[0] for k in keys} <= set("xlcrkqa")
    assert sum(k[0] == "x" for k in keys) == batch.poses.shape[0]
    with pytest.raises(ValueError, match="not a mapfuse graph variable"):
        describe_key(gtsam.symbol("z", 1))
    assert symbol_name(gtsam.symbol("l", 7)) == "l7"


def test_users_levenberg_marquardt_gives_our_answer(batch: EstimatorResult) -> None:
    assert batch.details.graph is not None
    assert batch.details.initial is not None
    n = batch.poses.shape[0]
    # The start is the EKF's poses, far from the optimum in places.
    start = _poses(batch.details.initial, n)
    assert np.max(np.hypot(*(start[:, :2] - batch.poses[:, :2]).T)) > 1e-3
    opt = gtsam.LevenbergMarquardtOptimizer(
        batch.details.graph, batch.details.initial, gtsam.LevenbergMarquardtParams()
    )
    values = opt.optimize()
    got = _poses(values, n)
    # Both stop at the same minimum within their convergence tolerances (1e-9 relative
    # error decrease): micrometres.
    assert np.max(np.hypot(*(got[:, :2] - batch.poses[:, :2]).T)) < 1e-6
    assert np.max(np.abs(wrap_angle(got[:, 2] - batch.poses[:, 2]))) < 1e-6
    assert batch.details.graph.error(values) == pytest.approx(batch.details.final_error, rel=1e-9)


def test_export_names_everything_the_g2o_file_leaves_out(
    batch: EstimatorResult, tmp_path: Path
) -> None:
    assert batch.details.graph is not None
    assert batch.details.values is not None
    ex = export_graph(batch, tmp_path)
    n = batch.poses.shape[0]
    assert (ex.vertices, ex.edges) == (n, n - 1)
    # Read back with GTSAM's own g2o reader: the poses and the odometry chain.
    graph, values = gtsam.readG2o(str(ex.g2o), False)
    assert values.size() == n
    assert graph.size() == n - 1
    read = np.array(
        [
            [values.atPose2(k).x(), values.atPose2(k).y(), values.atPose2(k).theta()]
            for k in range(n)
        ]
    )
    assert np.allclose(read[:, :2], batch.poses[:, :2], atol=1e-9, rtol=0)
    assert np.allclose(wrap_angle(read[:, 2] - batch.poses[:, 2]), 0.0, atol=1e-9)
    # Every factor is either written or named; so is every variable.
    side = json.loads(ex.sidecar.read_text())
    assert ex.edges + sum(side["left_out"]["factors"].values()) == batch.details.graph.size()
    assert n + len(side["left_out"]["variables"]) == batch.details.values.size()
    factors = side["left_out"]["factors"]
    assert factors["prior on the first pose (fixes Wglobal)"] == 1
    assert factors["circle observation"] > 0
    assert any(name.startswith("circle tie") for name in factors)
    assert side["left_out"]["variables"]["a0"]["is"].startswith("anchor")
    assert "left out" in ex.summary()
    assert not any(line.startswith("#") for line in ex.g2o.read_text().splitlines())
