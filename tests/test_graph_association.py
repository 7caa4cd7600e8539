"""The factor graph's data association (its own, the EKF's, truth) and its refusal of bad input."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
import pytest

from ekf_reference import EKFConfig, run_ekf
from mapfuse_core.estimate import AssociationDecisions, EstimatorResult
from mapfuse_core.evaluation import pose_errors, truth_in_global
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import wrap_angle
from mapfuse_core.matching import AssociationConfig, chi2_gate
from mapfuse_core.matching.ccda import CCDAParams
from mapfuse_core.measlog import MeasurementLog
from mapfuse_graph.graph import GraphBuilder, GraphOptions
from mapfuse_graph.solvers import ISAM2Options, run_graph
from tests.synthetic import synthetic_log

pytestmark = pytest.mark.usefixtures("jacobian_checks")


# --------------------------------------------------------------------------- association


def _purity(lm: np.ndarray, true_ids: np.ndarray) -> float:
    ok = n = 0
    for i in np.unique(lm[lm >= 0]):
        _, counts = np.unique(true_ids[lm == i], return_counts=True)
        ok += int(counts.max())
        n += int(counts.sum())
    return ok / n


def test_own_association_recovers_the_world() -> None:
    log = synthetic_log(steps=200, seed=0)
    res = run_graph(log, "isam2", fusion=True, association="own")
    assert res.decisions is not None
    assert _purity(res.decisions.obs_landmark, log.feat_true_id) == 1.0
    assert len(res.map.kinds) == len(np.unique(log.feat_true_id))
    assert res.anchor is not None
    assert res.anchor.source == "ccda"
    assert all(t == k for t, k in res.anchor.pairings)
    assert log.true_poses is not None
    d = res.anchor.x_Wknown_Wglobal - log.true_poses[0]
    d[2] = float(wrap_angle(d[2]))
    assert float(d @ np.linalg.solve(res.anchor.cov, d)) <= 16.27  # χ²(3, 0.999)


def test_ekf_and_graph_read_one_association_config(monkeypatch: pytest.MonkeyPatch) -> None:
    """The EKF's CCDA call and the graph's own CCDA call both receive the parameters of
    the one AssociationConfig they are given, and the graph gates with its χ² probability."""
    import ekf_reference.pipeline
    import mapfuse_graph.own_association
    from mapfuse_core.matching import ccda

    cfg = AssociationConfig(gate_prob=0.995, ccda=CCDAParams(min_pairings=5))
    seen: dict[str, list[CCDAParams]] = {"ekf": [], "graph": []}

    def spy(who: str) -> Callable[..., ccda.CCDAResult]:
        def call(a: object, b: object, params: CCDAParams) -> ccda.CCDAResult:
            seen[who].append(params)
            return ccda.ccda_match(a, b, params)  # type: ignore[arg-type]

        return call

    monkeypatch.setattr(ekf_reference.pipeline, "ccda_match", spy("ekf"))
    monkeypatch.setattr(mapfuse_graph.own_association, "ccda_match", spy("graph"))
    log = synthetic_log(steps=120, seed=0)
    run_ekf(log, EKFConfig(data_association=cfg), fusion=True)
    opts = GraphOptions(data_association=cfg)
    run_graph(log, "isam2", fusion=True, association="own", options=opts)
    assert seen["ekf"]
    assert seen["graph"]
    assert all(p is cfg.ccda for p in seen["ekf"] + seen["graph"])
    b = GraphBuilder(log, opts, association="own")
    assert b._gate == {2: chi2_gate(0.995, 2), 3: chi2_gate(0.995, 3)}


def test_mapfuse_defaults_give_the_graph_the_ekfs_association_config(
    small_log: MeasurementLog,
) -> None:
    from mapfuse import registry
    from mapfuse.profiles import default_options

    ekf = default_options(registry.get("ekf"), small_log).data_association
    graph = default_options(registry.get("batch"), small_log).graph.data_association
    assert graph == ekf
    assert graph.ccda.min_pairings == 8


def _line_landmarks_taking_two_segments(res: EstimatorResult, log: MeasurementLog) -> int:
    """Scans in which one line landmark takes two or more observations."""
    assert res.decisions is not None
    n = 0
    for k in range(log.n_steps):
        sl = log.feature_slice(k)
        lm = res.decisions.obs_landmark[sl][(log.feat_kind[sl] == int(FeatureKind.LINE))]
        lm = lm[lm >= 0]
        n += int(lm.size - np.unique(lm).size)
    return n


def test_own_association_gives_a_wall_every_segment_of_a_scan() -> None:
    """loop600's trees split walls into several segments of one scan: by default they all
    go to the wall's landmark, each to the landmark of its own world wall; with one
    observation per line, never two to one landmark."""
    import dataclasses as dc

    from mapfuse_core.sim.scenario import load_scenario
    from mapfuse_core.sim.simulate import simulate

    log = simulate(dc.replace(load_scenario("loop600"), steps=120), seed=0).log
    res = run_graph(log, "isam2", fusion=False, association="own", marginals=False)
    assert _line_landmarks_taking_two_segments(res, log) > 10
    assert res.decisions is not None
    assert _purity(res.decisions.obs_landmark, log.feat_true_id) == 1.0
    strict = GraphOptions(data_association=AssociationConfig(one_observation_per_line=True))
    res1 = run_graph(log, "isam2", fusion=False, association="own", options=strict, marginals=False)
    assert _line_landmarks_taking_two_segments(res1, log) == 0
    assert len(res1.map.kinds) > len(res.map.kinds)


def test_graph_options_refuse_a_bad_association_config(small_log: MeasurementLog) -> None:
    with pytest.raises(ValueError, match="data_association must be an AssociationConfig"):
        GraphOptions(data_association={"gate_prob": 0.99})  # type: ignore[arg-type]
    jcbb = GraphOptions(data_association=AssociationConfig(method="jcbb"))
    with pytest.raises(ValueError, match="nearest neighbour only"):
        GraphBuilder(small_log, jcbb, association="own")
    with pytest.raises(ValueError, match="nearest neighbour only"):
        run_graph(small_log, "isam2", association="own", options=jcbb)
    # The other associations decide nothing by search: the setting is theirs to carry.
    assert GraphBuilder(small_log, jcbb, association="truth").association == "truth"
    given = AssociationDecisions(*GraphBuilder(small_log, association="truth").planned_arrays())
    assert GraphBuilder(small_log, jcbb, decisions=given).association == "given"


def test_ekf_association_with_fusion_uses_the_ekf_anchor() -> None:
    log = synthetic_log(steps=120, seed=0)
    ekf = run_ekf(log, EKFConfig(), fusion=True)
    assert ekf.anchor is not None
    res = run_graph(log, "isam2", fusion=True, association="given", decisions=ekf.decisions)
    assert res.anchor is not None
    assert res.anchor.source == "given"
    assert res.anchor.accepted_at_step == ekf.anchor.accepted_at_step
    assert ekf.decisions is not None
    merged = {int(k) for k in ekf.decisions.obs_known_id if k >= 0}
    assert {k for _, k in res.anchor.pairings} == merged
    assert log.true_poses is not None
    err = pose_errors(res.poses, truth_in_global(log.true_poses)).position
    assert err.max() < 0.2


@pytest.mark.parametrize("backend", ["isam2", "batch"])
def test_a_graph_cut_before_the_ekf_matched_has_no_anchor_and_equals_the_unfused_one(
    backend: str,
) -> None:
    log = synthetic_log(steps=120, seed=0)
    ekf = run_ekf(log, EKFConfig(), fusion=True)
    assert ekf.anchor is not None
    cut = ekf.anchor.accepted_at_step  # steps 0 .. cut - 1: the match is not known yet
    assert cut > 5
    common = {"association": "given", "decisions": ekf.decisions, "steps": cut}
    fused = run_graph(log, backend, fusion=True, **common)
    plain = run_graph(log, backend, fusion=False, **common)
    assert fused.anchor is None
    d = fused.poses - plain.poses
    d[:, 2] = wrap_angle(d[:, 2])
    assert np.abs(d).max() <= 1e-9
    # One step more and the anchor is in, at the EKF's step.
    later = run_graph(log, backend, fusion=True, **{**common, "steps": cut + 1})
    assert later.anchor is not None
    assert later.anchor.accepted_at_step == cut


def test_fusion_off_has_no_anchor_and_no_known_variables() -> None:
    log = synthetic_log(steps=40, seed=0)
    res = run_graph(log, "batch", fusion=False, association="truth")
    assert res.anchor is None
    n_lm = len(res.map.kinds)
    assert res.details.n_variables == log.n_steps + n_lm
    assert np.all(res.map.known_ids == -1)


def test_graph_result_decisions_round_trip_the_associations() -> None:
    log = synthetic_log(steps=40, seed=0)
    res = run_graph(log, "isam2", fusion=True, association="truth")
    assert isinstance(res, EstimatorResult)
    d = res.decisions
    assert d is not None
    assert d.anchor is not None
    assert res.anchor is not None
    np.testing.assert_array_equal(d.anchor.x_Wknown_Wglobal, res.anchor.x_Wknown_Wglobal)
    # Truth association: every associated observation names the map feature of its id.
    associated = np.nonzero(d.obs_landmark >= 0)[0]
    np.testing.assert_array_equal(
        res.map.true_ids[d.obs_landmark[associated]], log.feat_true_id[associated]
    )
    known = res.map.known_ids
    for i in associated[:50]:
        assert d.obs_known_id[i] == known[d.obs_landmark[i]]
    again = run_graph(
        log, "isam2", fusion=True, association="given", decisions=AssociationDecisions(*d.arrays)
    )
    np.testing.assert_allclose(again.poses, res.poses, atol=1e-9)


# --------------------------------------------------------------------------- validation


def _tampered(log: MeasurementLog, **arrays: np.ndarray) -> MeasurementLog:
    """A copy of ``log`` with arrays replaced, bypassing the log's own validation.

    The graph must not trust its input to have been validated elsewhere.
    """
    out = dataclasses.replace(log)
    for name, a in arrays.items():
        object.__setattr__(out, name, a)
    return out


def test_split_circles_refuses_what_would_change_the_model(small_log: MeasurementLog) -> None:
    split = GraphOptions(split_circles=True)
    with pytest.raises(ValueError, match="fixed association"):
        run_graph(small_log, "isam2", fusion=False, association="own", options=split)
    with pytest.raises(ValueError, match="robust"):
        run_graph(
            small_log,
            "isam2",
            fusion=False,
            association="truth",
            options=GraphOptions(split_circles=True, robust="huber"),
        )
    with pytest.raises(ValueError, match="known map with circles"):
        run_graph(small_log, "isam2", fusion=True, association="truth", options=split)
    cov = small_log.feat_cov.copy()
    j = int(np.nonzero(small_log.feat_kind == int(FeatureKind.CIRCLE))[0][0])
    cov[j, 0, 2] = cov[j, 2, 0] = 0.1 * math.sqrt(cov[j, 0, 0] * cov[j, 2, 2])
    with pytest.raises(ValueError, match=f"observation {j} correlates"):
        run_graph(
            _tampered(small_log, feat_cov=cov),
            "isam2",
            fusion=False,
            association="truth",
            options=split,
        )


@pytest.fixture(scope="module")
def small_log() -> MeasurementLog:
    return synthetic_log(steps=20, seed=0)


def test_rejects_unknown_feature_kind(small_log: MeasurementLog) -> None:
    kinds = small_log.feat_kind.copy()
    kinds[3] = 7
    with pytest.raises(ValueError, match="observation 3 has unknown feature kind 7"):
        run_graph(_tampered(small_log, feat_kind=kinds), "isam2", association="truth")


def test_rejects_nan(small_log: MeasurementLog) -> None:
    p = small_log.feat_params.copy()
    p[5, 1] = np.nan
    with pytest.raises(ValueError, match="feat_params"):
        run_graph(_tampered(small_log, feat_params=p), "isam2", association="truth")


def test_rejects_singular_observation_noise(small_log: MeasurementLog) -> None:
    c = small_log.feat_cov.copy()
    c[2] = 0.0
    with pytest.raises(ValueError, match="observation 2"):
        run_graph(_tampered(small_log, feat_cov=c), "isam2", association="truth")


def test_rejects_singular_odometry_noise(small_log: MeasurementLog) -> None:
    c = small_log.odometry_cov.copy()
    c[4] = 0.0
    with pytest.raises(ValueError, match="odometry covariance of step 4"):
        run_graph(_tampered(small_log, odometry_cov=c), "batch", association="truth")


def test_rejects_bad_association_arrays(small_log: MeasurementLog) -> None:
    m = small_log.n_features
    lm = np.arange(m, dtype=np.int64)
    with pytest.raises(ValueError, match="shape"):
        run_graph(
            small_log,
            "isam2",
            association="given",
            decisions=AssociationDecisions(lm[:-1], np.full(m, -1)),
        )
    with pytest.raises(ValueError, match=f"shape \\({m - 1},\\), the log has {m} observations"):
        run_graph(
            small_log,
            "isam2",
            association="given",
            decisions=AssociationDecisions(lm[:-1], np.full(m - 1, -1)),
        )
    with pytest.raises(ValueError, match="missing from the map"):
        run_graph(
            small_log,
            "isam2",
            association="given",
            decisions=AssociationDecisions(lm, np.full(m, 999_999)),
        )
    kinds_differ = np.zeros(m, dtype=np.int64)  # one landmark for lines and circles
    with pytest.raises(ValueError, match="observed both as a"):
        run_graph(
            small_log,
            "isam2",
            association="given",
            decisions=AssociationDecisions(kinds_differ, np.full(m, -1)),
        )
    orphan = lm.copy()
    orphan[0] = -1
    kn = np.full(m, -1)
    kn[0] = int(small_log.known_map.ids[0])
    with pytest.raises(ValueError, match="has no landmark"):
        run_graph(
            small_log, "isam2", association="given", decisions=AssociationDecisions(orphan, kn)
        )
    with pytest.raises(ValueError, match="integers"):
        run_graph(
            small_log,
            "isam2",
            association="given",
            decisions=AssociationDecisions(lm + 0.5, np.full(m, -1)),
        )


def test_rejects_bad_arguments(small_log: MeasurementLog) -> None:
    with pytest.raises(ValueError, match="needs decisions"):
        run_graph(small_log, "isam2", association="given")
    none = np.full(small_log.n_features, -1, dtype=np.int64)
    with pytest.raises(ValueError, match="makes its own decisions"):
        run_graph(small_log, "isam2", association="own", decisions=AssociationDecisions(none, none))
    with pytest.raises(ValueError, match="backend"):
        run_graph(small_log, "lm", association="truth")
    with pytest.raises(ValueError, match="association"):
        run_graph(small_log, "isam2", association="nn")
    with pytest.raises(ValueError, match="robust"):
        run_graph(small_log, "isam2", association="truth", options=GraphOptions(robust="tukey"))
    with pytest.raises(ValueError, match="steps"):
        run_graph(small_log, "isam2", association="truth", steps=0)
    with pytest.raises(ValueError, match="relinearize_threshold"):
        ISAM2Options(relinearize_threshold={"x": (0.1, 0.1)})
    for kw in (
        {"joint_stride": 0},
        {"joint_stride": 2.5},
        {"joint_stride": 20},
        {"joint_stride": 5, "marginals": False},
    ):
        with pytest.raises(ValueError, match="joint_stride"):
            run_graph(small_log, "batch", association="truth", **kw)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="joint_stride"):
        run_graph(small_log, "isam2", association="truth", joint_stride=5)


def test_builder_refuses_out_of_order_steps(small_log: MeasurementLog) -> None:
    b = GraphBuilder(small_log, GraphOptions(), association="truth")
    with pytest.raises(ValueError, match="in order"):
        b.step(1, None)  # type: ignore[arg-type]


def test_isam2_survives_rejected_input(small_log: MeasurementLog) -> None:
    """A rejected run leaves nothing behind: the next run on good input is unaffected."""
    kinds = small_log.feat_kind.copy()
    kinds[0] = 9
    with pytest.raises(ValueError, match="unknown feature kind"):
        run_graph(_tampered(small_log, feat_kind=kinds), "isam2", association="truth")
    res = run_graph(small_log, "isam2", association="truth")
    assert np.all(np.isfinite(res.poses))
    assert math.isfinite(res.details.final_error)
