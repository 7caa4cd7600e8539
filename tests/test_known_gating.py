"""The EKF's known-map gate (ekf_reference.known_gating) and how its decisions travel."""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
import pytest

from ekf_reference import EKFConfig, run_ekf
from ekf_reference.association import Query, evaluate, predict_all_targets
from ekf_reference.known_gating import KnownGate, KnownGatingParams, known_outcomes
from ekf_reference.state import Element, ElementKind, GaussianMap, Role, bind_line_cov
from mapfuse_core.estimate import (
    AssociationDecisions,
    EstimatorResult,
    KnownMapGating,
    load_associations,
)
from mapfuse_core.geometry.features import FeatureKind, transform_feature
from mapfuse_core.geometry.se2 import compose, inverse
from mapfuse_core.matching import AssociationConfig, chi2_gate
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog
from tests.synthetic import ring_world, synthetic_log

#: A precise known map (σ 2 cm, 0.01 rad): a move of a few decimetres is many σ.
SIGMA = (0.02, 0.02, 0.01)
#: Circles the vehicle sees only after the anchor is accepted (step 119), none of them
#: in CCDA's match, in the order the drive reaches them.
LATER = (112, 114, 115, 116)
#: The known features of CCDA's match on the unchanged map.
MATCHED = (100, 122, 101, 102, 124, 104, 108, 107, 110, 126)


@functools.lru_cache(maxsize=1)
def _log() -> MeasurementLog:
    return synthetic_log(steps=300, seed=3, known_fraction=0.7, known_sigma=SIGMA)


def _with_params(log: MeasurementLog, params: np.ndarray, ids=None) -> MeasurementLog:
    k = log.known_map
    known = KnownMapArrays(k.ids if ids is None else ids, k.kinds, params, k.covs, k.extents)
    return dataclasses.replace(log, known_map=known)


def _moved(ids: tuple[int, ...], dx: float) -> MeasurementLog:
    log = _log()
    p = log.known_map.params.copy()
    p[np.isin(log.known_map.ids, ids), 0] += dx
    return _with_params(log, p)


def scenario_log(name: str) -> MeasurementLog:
    """The log of one of the gate's scenarios: the map unchanged, the circles met after
    the anchor moved 0.4 m, or CCDA's matched features shifted 0.5 m."""
    logs = {
        "unchanged": _log,
        "later_moved": lambda: _moved(LATER, 0.4),
        "matched_shifted": lambda: _moved(MATCHED, 0.5),
    }
    return logs[name]()


@functools.lru_cache(maxsize=4)
def _run(name: str, gating: bool = True) -> EstimatorResult:
    # Without the anchor watch: these tests are about the gate alone
    # (tests/test_anchor_watch.py runs the same scenarios with it).
    return run_ekf(scenario_log(name), EKFConfig(known_map_gating=gating, anchor_watch=None))


def _decisions(res: EstimatorResult) -> AssociationDecisions:
    assert res.decisions is not None
    return res.decisions


def _gating(res: EstimatorResult) -> KnownMapGating:
    kg = _decisions(res).known_gating
    assert kg is not None
    return kg


def _fused_after_unfuse(res: EstimatorResult, log: MeasurementLog) -> int:
    late = 0
    for kid, step in _gating(res).unfused.items():
        late += int(
            np.count_nonzero((_decisions(res).obs_known_id == kid) & (log.feat_step > step))
        )
    return late


def test_unchanged_map_stays_fused_and_the_gate_changes_nothing():
    on, off = _run("unchanged"), _run("unchanged", gating=False)
    assert on.anchor is not None
    kg = _gating(on)
    assert kg.unfused == {}
    assert sum(kg.accepted.values()) > 100
    # Nothing un-fused, so the gate only watched: the same run to the last bit.
    np.testing.assert_array_equal(on.poses, off.poses)
    assert _decisions(off).known_gating is None


def test_features_moved_after_the_anchor_are_unfused_and_never_fused_again():
    res = _run("later_moved")
    kg = _gating(res)
    assert res.anchor is not None
    assert set(LATER) <= set(kg.unfused)
    for kid in LATER:
        # 0.4 m is beyond the gate at σ 2 cm: every pairing refused, each refusal counted.
        assert kg.accepted.get(kid, 0) == 0
        assert kg.rejected[kid] >= KnownGatingParams().max_rejections
        assert kg.unfused[kid] > res.anchor.accepted_at_step
    assert _fused_after_unfuse(res, _moved(LATER, 0.4)) == 0
    block = kg.as_dict()
    assert block["known_unfused"] == len(kg.unfused)
    assert block["known_rejected"] == sum(kg.rejected.values())
    assert block["per_feature"][str(LATER[0])]["unfused_at_step"] == kg.unfused[LATER[0]]
    assert not kg.anchor_refuted


def test_rigid_shift_of_the_matched_part_moves_the_anchor_and_unfuses_the_rest():
    """CCDA's match made only of features moved by one offset is a shifted anchor: the
    anchor takes the offset, and the unmoved features seen later are the inconsistent
    ones.  Without GPS nothing tells the two apart (docs/change-detection.md)."""
    res = _run("matched_shifted")
    assert res.anchor is not None
    kg = _gating(res)
    # The anchor is off by the shift (0.5 m in x), not by the estimate's noise.
    true_anchor = _log().true_poses[0]
    assert res.anchor.x_Wknown_Wglobal[0] - true_anchor[0] == pytest.approx(0.5, abs=0.05)
    assert kg.anchor_pairings == len(MATCHED)
    assert kg.anchor_pairings_unfused == 0
    assert not kg.anchor_refuted
    assert set(LATER) <= set(kg.unfused)


def test_shifted_map_is_absorbed_by_the_anchor_and_nothing_is_unfused():
    log = _log()
    T = np.array([4.0, -2.0, 0.2])
    k = log.known_map
    p = np.array(
        [
            transform_feature(FeatureKind(int(kd)), inverse(T), x)[0]
            for kd, x in zip(k.kinds, k.params, strict=True)
        ]
    )
    res = run_ekf(_with_params(log, p), EKFConfig())
    assert res.anchor is not None
    assert _gating(res).unfused == {}


def test_empty_intersection_and_all_changed_maps_fuse_nothing():
    """A known map of another place (nothing in it is ever seen; shifting this one
    away would be a change of frame, which the anchor takes) and a map whose every
    feature moved 1 m in its own direction: CCDA accepts no match, nothing is fused."""
    log = _log()
    k = log.known_map
    other = ring_world(seed=99)
    elsewhere = dataclasses.replace(
        log,
        known_map=dataclasses.replace(
            other,
            ids=other.ids + 10_000,
            covs=np.tile(np.diag([0.02**2, 0.02**2, 0.01**2]), (len(other), 1, 1)),
        ),
    )
    rng = np.random.default_rng(5)
    a = rng.uniform(-math.pi, math.pi, len(k))
    moved = k.params.copy()
    moved[:, 0] += np.cos(a)
    moved[:, 1] += np.sin(a)
    for changed in (elsewhere, _with_params(log, moved)):
        res = run_ekf(changed, EKFConfig())
        assert res.anchor is None
        assert not np.any(_decisions(res).obs_known_id >= 0)
        kg = _gating(res)
        assert (kg.accepted, kg.rejected, kg.unfused) == ({}, {}, {})


def test_running_test_unfuses_a_feature_whose_accepted_pairings_are_biased():
    gate = KnownGate(KnownGatingParams(), AssociationConfig())
    gate._dofs[7] = gate._dofs[8] = 3
    for _ in range(5):
        gate._push(7, 12.0)  # inside the 3-dof gate (16.3) every time, 60 in sum
        gate._push(8, 3.0)  # the mean of χ²₃: consistent
    assert gate._fails(7)
    assert not gate._fails(8)
    # Fewer pairings than min_pairings are not tested.
    gate._dofs[9] = 3
    for _ in range(4):
        gate._push(9, 15.0)
    assert not gate._fails(9)


def test_rejections_unfuse_only_when_they_outnumber_acceptances():
    gate = KnownGate(KnownGatingParams(max_rejections=3), AssociationConfig())
    gate._dofs[1] = 3
    for v in (1.0, 2.0, 1.0, 2.0, math.nan, math.nan, math.nan):
        gate._push(1, v)
    assert not gate._fails(1)  # 3 rejections, 4 acceptances
    gate._push(2, math.nan)
    gate._push(2, math.nan)
    assert not gate._fails(2)
    gate._push(2, math.nan)
    assert gate._fails(2)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"level": 1.0}, "level"),
        ({"window": 0}, "window"),
        ({"min_pairings": 1.5}, "min_pairings"),
        ({"max_rejections": True}, "max_rejections"),
    ],
)
def test_gating_params_reject_bad_values(kwargs, match):
    with pytest.raises(ValueError, match=match):
        KnownGatingParams(**kwargs)
    with pytest.raises(ValueError, match="known_gating must be"):
        EKFConfig(known_gating=0.99)  # type: ignore[arg-type]


def test_unfused_ids_survive_saving_the_decisions(tmp_path):
    res = _run("later_moved")
    path = _decisions(res).save(tmp_path / "assoc.npz")
    back = load_associations(path, _decisions(res).obs_landmark.size)
    assert back.unfused_known_ids == frozenset(_gating(res).unfused)
    assert back.known_gating is not None
    assert back.known_gating.unfused == _gating(res).unfused
    plain = AssociationDecisions(*_decisions(res).arrays)
    assert plain.unfused_known_ids == frozenset()


def test_graph_adds_no_tie_for_a_feature_the_ekf_unfused():
    from mapfuse_graph.builder import GraphBuilder
    from mapfuse_graph.options import GraphOptions

    log, res = _log(), _run("unchanged")
    rows_of = {int(i): r for r, i in enumerate(log.known_map.ids)}
    opts = GraphOptions()
    tied_all = set(
        GraphBuilder(
            log, opts, fusion=True, association="given", decisions=_decisions(res)
        )._planned_known.values()
    )
    # The EKF's decisions with two fused features marked un-fused (at step 150).
    gone = {LATER[0]: 150, MATCHED[0]: 150}
    gating = KnownMapGating(level=0.99999, rejected={}, accepted={}, unfused=gone)
    decisions = dataclasses.replace(_decisions(res), known_gating=gating)
    tied = set(
        GraphBuilder(
            log, opts, fusion=True, association="given", decisions=decisions
        )._planned_known.values()
    )
    assert {rows_of[k] for k in gone} <= tied_all
    assert tied == tied_all - {rows_of[k] for k in gone}


def _anchor_and_known_wall() -> tuple[GaussianMap, np.ndarray]:
    """An anchor ``x^R_Wknown`` at the origin (σ 5 cm, 2 mrad) and known wall 7, the
    line y = 5 m (σ 2 cm, 1 mrad); returns the map and the wall seen from the robot."""
    m = GaussianMap()
    m.add(
        Element(ElementKind.POSE, Role.ANCHOR, True, -1), np.zeros(3), np.diag([25e-4, 25e-4, 4e-6])
    )
    wall = np.array([0.0, 5.0, 0.0])
    m.add(
        Element(ElementKind.LINE, Role.KNOWN, False, 0, extent=(-10.0, 10.0), true_id=7),
        wall,
        bind_line_cov(wall, np.diag([4e-4, 4e-4, 1e-6])),
    )
    return m, transform_feature(FeatureKind.LINE, m.mean[0], m.mean[1])[0]


def _segment(pred: np.ndarray, lateral: float) -> Query:
    """A measured 4 m segment of the line ``pred`` moved ``lateral`` metres off it."""
    z = compose(pred, np.array([0.0, lateral, 0.0]))
    return Query(ElementKind.LINE, z, bind_line_cov(z, np.diag([100.0, 1e-4, 2.5e-5])), (-2.0, 2.0))


def _targets(m: GaussianMap) -> dict:
    return {k: v for k, v in predict_all_targets(m, lambda e: True).items()}


def test_an_observation_passing_the_known_walls_test_is_no_rejection_of_it() -> None:
    m, pred = _anchor_and_known_wall()
    config = AssociationConfig()
    near, far = _segment(pred, 0.05), _segment(pred, 0.8)  # d² ≈ 1 and ≈ 300
    assert evaluate(m, near, 1).d2 < chi2_gate(config.gate_prob, 2) < evaluate(m, far, 1).d2
    # Neither is paired with the known wall (the search sent them elsewhere).
    out = known_outcomes(m, [near, far], [None, None], _targets(m), config)
    assert out.refused == [(7, -1)]
    out = known_outcomes(m, [near], [None], _targets(m), config)
    assert out.refused == []


def test_a_landmark_failing_its_tie_counts_once_against_a_known_feature() -> None:
    m, pred = _anchor_and_known_wall()
    config = AssociationConfig()
    z = compose(pred, np.array([0.0, 0.8, 0.0]))
    i = m.add(
        Element(ElementKind.LINE, Role.FEATURE, True, 42, extent=(-2.0, 2.0)),
        z,
        np.diag([1e-4, 1e-4, 1e-6]),
    )
    j = m.add(
        Element(ElementKind.LINE, Role.FEATURE, True, 43, extent=(-2.0, 2.0)),
        compose(pred, np.array([1.0, 0.8, 0.0])),
        np.diag([1e-4, 1e-4, 1e-6]),
    )
    ties = [
        Query(ElementKind.LINE, m.mean[k], np.zeros((3, 3)), (-2.0, 2.0), element=k) for k in (i, j)
    ]
    known_row = _targets(m)[ElementKind.LINE][0].index(1)
    targets = {ElementKind.LINE: ([1], _targets(m)[ElementKind.LINE][1][[known_row]])}
    miss = _segment(pred, 0.8)
    out = known_outcomes(m, [*ties, miss], [None, None, None], targets, config)
    assert out.refused == [(7, -1), (7, 42), (7, 43)]  # the observation's first
    gate = KnownGate(KnownGatingParams(max_rejections=3), config)
    for step in range(5):
        gate.record(step, m, ties, [None, None], targets)
    # One rejection per landmark (one per step at most): steps 0 and 1.
    assert gate.rejected == {7: 2}
    assert gate.unfused == {}
    # Observations failing the test count at every step.
    for step in range(5, 7):
        gate.record(step, m, [miss], [None], targets)
    assert gate.rejected == {7: 4}
    assert gate.unfused == {7: 5}
