"""The harness's own parts: profiles, the result type, metrics of every estimate,
association files and the run's outputs."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from ekf_reference import EKFConfig
from ekf_reference.loops import LoopClosureParams
from mapfuse.estimators.graph import GraphRunOptions
from mapfuse.execution import fusion_for
from mapfuse.metrics import run_metrics
from mapfuse.options import make_options
from mapfuse.outputs import write_outputs
from mapfuse.profiles import PROFILES, default_options
from mapfuse.registry import get
from mapfuse.runner import run
from mapfuse_core.data.datasets import VICTORIA_PARK_NAME
from mapfuse_core.estimate import EstimatorResult, MapEstimate, PoseTrack
from mapfuse_core.estimate.decisions import AnchorDecision, AssociationDecisions, load_associations
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog
from tests.synthetic import synthetic_log


@pytest.fixture(scope="module")
def log() -> MeasurementLog:
    return synthetic_log(40, 1)


def _victoria(log: MeasurementLog) -> MeasurementLog:
    return dataclasses.replace(log, scenario=VICTORIA_PARK_NAME)


def test_victoria_park_profile_changes_only_its_own_dataset(log: MeasurementLog) -> None:
    assert set(PROFILES) == {VICTORIA_PARK_NAME, "carmen:"}
    ekf = get("ekf")
    assert default_options(ekf, log) == EKFConfig()
    assert default_options(ekf, _victoria(log)) == EKFConfig(
        local_map_steps=200,
        min_obs_to_join=2,
        loop_closure=LoopClosureParams(),
        join_circle_sigma_m=0.1,
    )
    for name in ("batch", "isam2"):
        plain = default_options(get(name), log)
        vp = default_options(get(name), _victoria(log))
        assert isinstance(vp, GraphRunOptions)
        assert plain == GraphRunOptions()
        assert plain.isam2 == vp.isam2
        assert vp.split_circles_where_exact
        assert not plain.split_circles_where_exact


def test_split_circles_only_where_it_is_the_same_model(log: MeasurementLog) -> None:
    vp = _victoria(log)
    n_circles = int(np.sum(log.feat_kind == int(FeatureKind.CIRCLE)))
    assert n_circles > 0

    def variables(lg: MeasurementLog, **overrides: object) -> int:
        done = run(lg, "isam2", fusion=False, association="truth", **overrides)
        g = done.result
        return int(g.details.n_variables) - int(np.sum(g.map.kinds == int(FeatureKind.CIRCLE)))

    # Split: one radius variable more per circle landmark.
    split, plain = variables(vp), variables(log)
    assert split > plain
    assert variables(vp, graph={"robust": "huber"}) == plain
    cov = vp.feat_cov.copy()
    j = int(np.nonzero(vp.feat_kind == int(FeatureKind.CIRCLE))[0][0])
    cov[j, 1, 2] = cov[j, 2, 1] = 1e-6
    assert variables(dataclasses.replace(vp, feat_cov=cov)) == variables(
        dataclasses.replace(log, feat_cov=cov)
    )


def test_fusion_needs_a_known_map(log: MeasurementLog) -> None:
    k = log.known_map
    empty = KnownMapArrays(k.ids[:0], k.kinds[:0], k.params[:0], k.covs[:0])
    no_map = dataclasses.replace(log, known_map=empty)
    assert fusion_for(log, True)
    assert not fusion_for(log, False)
    assert not fusion_for(no_map, True)
    for name in ("ekf", "batch"):
        done = run(no_map, name, fusion=True)
        assert done.fusion is False
        assert done.metrics.fusion is False


def test_metrics_of_each_estimate(log: MeasurementLog) -> None:
    isam2 = run(log, "isam2", association="truth")
    m = isam2.metrics
    assert (m.estimator, m.association, m.estimate) == ("isam2", "truth", "smoothed")
    assert {"nees_filtered", "position_error_filtered_m"} <= set(m.to_json())
    assert m.anchor is not None
    assert m.anchor.correct_pairings == m.anchor.pairings > 0
    f = run_metrics(isam2.result, log, "filtered")
    assert f.estimate == "filtered"
    assert f.position_error == m.position_error_filtered
    batch = run(log, "batch", association="truth")
    with pytest.raises(ValueError, match="the batch result has no filtered estimate"):
        run_metrics(batch.result, log, "filtered")
    with pytest.raises(ValueError, match="which must be"):
        run_metrics(batch.result, log, "final")
    ekf = run(log, "ekf")
    assert "estimate" not in ekf.metrics.to_json()
    assert "association" not in ekf.metrics.to_json()
    assert ekf.result.estimate == "filtered"


def test_estimator_result_refuses_inconsistent_shapes() -> None:
    n = 5
    track = PoseTrack(np.zeros((n, 3)), np.zeros((n, 3, 3)))
    common = {
        "estimator": "x",
        "scenario": "s",
        "seed": 0,
        "fusion": False,
        "step_time_s": np.zeros(n),
        "map": MapEstimate.empty(),
    }
    with pytest.raises(ValueError, match="needs a filtered or a smoothed estimate"):
        EstimatorResult(timestamps=np.zeros(n), **common)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="filtered has 5 poses for 4 timestamps"):
        EstimatorResult(timestamps=np.zeros(4), filtered=track, **common)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"needs \(N, 3\) poses"):
        PoseTrack(np.zeros((n, 2)), np.zeros((n, 3, 3)))


def test_association_decisions_round_trip(tmp_path: Path) -> None:
    d = AssociationDecisions(
        np.array([0, 1, -1, 1]),
        np.array([-1, 7, -1, 7]),
        AnchorDecision(np.array([1.0, 2.0, 0.5]), 3),
    )
    back = load_associations(d.save(tmp_path / "a.npz"), 4)
    for x, y in zip(back.arrays, d.arrays, strict=True):
        np.testing.assert_array_equal(x, y)
    assert back.anchor is not None
    assert d.anchor is not None
    np.testing.assert_array_equal(back.anchor.x_Wknown_Wglobal, d.anchor.x_Wknown_Wglobal)
    assert back.anchor.accepted_at_step == 3
    with pytest.raises(ValueError, match="holds 4 decisions, the log has 5"):
        load_associations(tmp_path / "a.npz", 5)
    np.savez(tmp_path / "b.npz", x=np.zeros(2))
    with pytest.raises(ValueError, match="not a mapfuse associations file"):
        load_associations(tmp_path / "b.npz", 2)
    with pytest.raises(ValueError, match="one length"):
        AssociationDecisions(np.zeros(3, np.int64), np.zeros(2, np.int64))
    with pytest.raises(ValueError, match="integers"):
        AssociationDecisions(np.zeros(2), np.zeros(2))
    with pytest.raises(ValueError, match="finite"):
        AnchorDecision(np.array([np.nan, 0.0, 0.0]), 0)


def test_outputs_and_saved_decisions_feed_a_graph_run(log: MeasurementLog, tmp_path: Path) -> None:
    ekf = run(log, "ekf")
    paths = write_outputs(ekf, tmp_path / "ekf")
    assert json.loads(Path(paths["metrics"]).read_text()) == json.loads(
        json.dumps(ekf.metrics.to_json())
    )
    decisions = load_associations(paths["associations"], log.n_features)
    # Graph runs fed the saved decisions are the runs fed the EKF's result directly.
    direct = run(log, "isam2")
    given = dataclasses.replace(ekf.result, decisions=decisions)
    via_file = run(log, "isam2", upstream=given)
    np.testing.assert_array_equal(via_file.poses, direct.poses)
    graph_paths = write_outputs(direct, tmp_path / "isam2")
    assert "associations" not in graph_paths  # it consumed decisions, made none
    with pytest.raises(ValueError, match="the ekf estimator has no option robust"):
        make_options("ekf", log, robust="huber")


def test_builtins_load_without_package_metadata(monkeypatch: pytest.MonkeyPatch) -> None:
    from mapfuse import registry

    # A source tree on PYTHONPATH over an install that does not declare the group.
    monkeypatch.setattr(registry, "_entry_points", dict)
    monkeypatch.setattr(registry, "_loaded", {})
    assert registry.available() == ("ekf", "batch", "isam2")
    assert registry.get("batch").name == "batch"
    with pytest.raises(ValueError, match="unknown estimator 'toy'"):
        registry.get("toy")
