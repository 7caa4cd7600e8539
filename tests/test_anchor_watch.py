"""The EKF's checks of a map match at and after its fusion: the joint test refuses a
wrong match before it is fused (``AssociationConfig.match_joint_test``), the anchor
watch undoes a fused anchor the known features contradict and matches again
(:mod:`ekf_reference.anchor_watch`), and a right match passes both."""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings

import numpy as np
import pytest
from scipy.stats import f as f_dist

import ekf_reference.pipeline as pipeline
from ekf_reference import EKFConfig, run_ekf
from ekf_reference.anchor_watch import (
    AnchorWatch,
    AnchorWatchParams,
    GateState,
    _Step,
    joint_nis,
)
from ekf_reference.association import Candidate
from ekf_reference.pipeline import ANCHOR_CONTRADICTED, JOINTLY_INCONSISTENT, UNDONE_BEFORE
from ekf_reference.result import EKFDetails
from ekf_reference.state import Element, ElementKind, GaussianMap, Role
from mapfuse_core.estimate import EstimatorResult
from mapfuse_core.evaluation import anchor_truth
from mapfuse_core.matching import chi2_gate
from mapfuse_core.measlog import MeasurementLog
from tests.synthetic import synthetic_log
from tests.test_ccda_joint_test import _Swapping
from tests.test_known_gating import scenario_log

#: Steps of the synthetic drive: CCDA first accepts at the join of step 79.
STEPS = 300
SEED = 4


@functools.lru_cache(maxsize=1)
def _log() -> MeasurementLog:
    return synthetic_log(steps=STEPS, seed=SEED)


def _config(joint_test: bool, watch: bool) -> EKFConfig:
    cfg = EKFConfig(anchor_watch=AnchorWatchParams() if watch else None)
    assoc = dataclasses.replace(cfg.data_association, match_joint_test=joint_test)
    return dataclasses.replace(cfg, data_association=assoc)


@functools.lru_cache(maxsize=8)
def _run(joint_test: bool, watch: bool, swapped: bool = True) -> EstimatorResult:
    """The drive with, when ``swapped``, CCDA's first accepted match given one wrong
    pairing (a map circle paired with a known circle no pairing uses); later calls
    are CCDA's own."""
    original = pipeline.ccda_match
    if swapped:
        pipeline.ccda_match = _Swapping(persistent=False)  # type: ignore[assignment]
    try:
        with warnings.catch_warnings():
            # The wrong match, fused, does not converge and says so.
            warnings.simplefilter("ignore", RuntimeWarning)
            return run_ekf(_log(), _config(joint_test, watch), fusion=True)
    finally:
        pipeline.ccda_match = original


def _details(res: EstimatorResult) -> EKFDetails:
    assert isinstance(res.details, EKFDetails)
    return res.details


def _anchor_error(x: np.ndarray, log: MeasurementLog) -> float:
    assert log.true_poses is not None
    truth = anchor_truth(log.true_poses, log.known_frame)
    return math.hypot(x[0] - truth[0], x[1] - truth[1])


def _wrong_known_obs(res: EstimatorResult, log: MeasurementLog) -> int:
    assert res.decisions is not None
    kn = res.decisions.obs_known_id
    return int(np.count_nonzero((kn >= 0) & (kn != log.feat_true_id)))


def _reasons(res: EstimatorResult) -> dict[str, int]:
    assert res.matching is not None
    assert sum(res.matching.reasons.values()) == res.matching.attempts
    return dict(res.matching.reasons)


# --------------------------------------------------------------------------- end to end


def test_a_wrong_match_is_refused_by_the_joint_test_and_never_fused() -> None:
    res = _run(joint_test=True, watch=True)
    assert _reasons(res) == {"too few pairings": 1, JOINTLY_INCONSISTENT: 1, "accepted": 1}
    ((step, c2, dof),) = _details(res).ccda_refused
    # The swapped circle is metres from its partner while the map's features are known
    # to centimetres relative to each other: χ² in the thousands on 22 dof.
    assert step == 79
    assert dof == 22
    assert c2 > 100 * chi2_gate(0.999, dof)
    # Matched again at once without that map feature; nothing fused was undone.
    assert res.anchor is not None
    assert res.anchor.accepted_at_step == 79
    assert _details(res).anchors_undone == ()
    assert all(t == k for t, k in res.anchor.pairings)
    assert _anchor_error(res.anchor.x_Wknown_Wglobal, _log()) < 0.03
    assert _wrong_known_obs(res, _log()) == 0


def test_without_either_check_the_wrong_match_is_fused_and_kept() -> None:
    # What the two checks are for: the same run with neither keeps an anchor 0.6 m off
    # and merges 35 observations with the wrong known feature.
    res = _run(joint_test=False, watch=False)
    assert res.anchor is not None
    assert res.anchor.accepted_at_step == 79
    assert [(t, k) for t, k in res.anchor.pairings if t != k] == [(106, 107)]
    assert _anchor_error(res.anchor.x_Wknown_Wglobal, _log()) == pytest.approx(0.60, abs=0.03)
    assert _wrong_known_obs(res, _log()) == 35


def test_a_fused_anchor_the_known_features_contradict_is_undone_and_matched_again() -> None:
    # Without the joint test the wrong match is fused at step 79.  The known features
    # met after it fail the known-map gate one after the other (the anchor's 0.05 rad
    # turns them away from where they are seen); at step 232 nine of them are
    # un-fused against four still confirming it: more than twice as many.
    res = _run(joint_test=False, watch=True)
    (undone,) = _details(res).anchors_undone
    assert (undone.fused_at_step, undone.undone_at_step) == (79, 232)
    assert undone.test == "known features un-fused"
    assert (undone.statistic, undone.threshold) == (9.0, 8.0)
    assert [(t, k) for t, k in undone.pairings if t != k] == [(106, 107)]
    assert _anchor_error(undone.x_Wknown_Wglobal, _log()) == pytest.approx(0.60, abs=0.03)
    # Filtering went back to step 79 without that match; CCDA's next call, at the join
    # of step 119, is its own and right.  The call that made the undone anchor is
    # counted as contradicted, not accepted.
    assert _reasons(res) == {"too few pairings": 1, ANCHOR_CONTRADICTED: 1, "accepted": 1}
    assert res.anchor is not None
    assert res.anchor.accepted_at_step == 119
    assert all(t == k for t, k in res.anchor.pairings)
    assert _anchor_error(res.anchor.x_Wknown_Wglobal, _log()) < 0.03
    # The final decisions are those of the steps filtered again: no observation is
    # merged with a wrong known feature.
    assert _wrong_known_obs(res, _log()) == 0
    # The filtered track keeps what the filter gave at each step the first time: at
    # step 100 it was anchored (to the wrong match).
    assert np.all(np.isfinite(_details(res).poses_in_known[100]))
    assert np.all(np.isnan(_details(res).poses_in_known[:79]))


def test_a_right_match_passes_both_checks_and_the_watch_changes_nothing() -> None:
    res = _run(joint_test=True, watch=True, swapped=False)
    assert _reasons(res) == {"too few pairings": 1, "accepted": 1}
    assert _details(res).ccda_refused == ()
    assert _details(res).anchors_undone == ()
    assert res.anchor is not None
    assert res.anchor.accepted_at_step == 79
    assert _anchor_error(res.anchor.x_Wknown_Wglobal, _log()) < 0.03
    # The watch only watched: the same run to the last bit as without it.
    off = _run(joint_test=True, watch=False, swapped=False)
    np.testing.assert_array_equal(res.poses, off.poses)
    np.testing.assert_array_equal(res.covs, off.covs)


def test_known_features_moved_after_the_anchor_stay_a_minority_and_it_is_kept() -> None:
    # Four circles moved 0.4 m, all the same way, are the first known features met
    # after the anchor: the gate un-fuses them, and the features confirming the anchor
    # (its own match's included) stay more than half as many.
    log = scenario_log("later_moved")
    res = run_ekf(log, EKFConfig(anchor_watch=AnchorWatchParams()))
    assert _details(res).anchors_undone == ()
    assert res.anchor is not None
    off = run_ekf(log, EKFConfig(anchor_watch=None))
    np.testing.assert_array_equal(res.poses, off.poses)


def test_an_anchor_most_of_the_known_map_contradicts_is_undone_and_not_matched_again() -> None:
    # CCDA's ten matched circles moved 0.5 m together since the survey: the anchor
    # takes their offset, and the seven known features met after it are un-fused
    # against three confirming it.  Nothing tells which part of the map moved, so
    # the run ends without an anchor: the same match is refused as compatible with
    # the undone one, the others as ambiguous.
    log = scenario_log("matched_shifted")
    res = run_ekf(log, EKFConfig(anchor_watch=AnchorWatchParams()))
    (undone,) = _details(res).anchors_undone
    assert (undone.fused_at_step, undone.undone_at_step) == (119, 214)
    assert undone.test == "known features un-fused"
    assert (undone.statistic, undone.threshold) == (7.0, 6.0)
    assert res.anchor is None
    reasons = _reasons(res)
    assert reasons[ANCHOR_CONTRADICTED] == 1
    assert reasons[UNDONE_BEFORE] >= 1
    assert "accepted" not in reasons
    assert _wrong_known_obs(res, log) == 0


# --------------------------------------------------------------------------- the tests


def _watch_with(nis_dof: list[tuple[int, float, int]], **params: object) -> AnchorWatch:
    """A watch whose window holds ``(step, NIS, dof)``."""
    watch = AnchorWatch(AnchorWatchParams(**params))  # type: ignore[arg-type]
    for step, nis, dof in nis_dof:
        watch.steps.append(_Step(step, nis, dof))
    return watch


def test_the_innovation_test_refuses_above_its_quantile_over_its_window_only() -> None:
    gate = chi2_gate(0.99999, 60)
    watch = _watch_with([(10, 30.0, 30), (20, gate - 30.0 + 0.1, 30)])
    v = watch.verdict(20, None)
    assert v is not None
    assert v.test == "innovations"
    assert (v.statistic, v.threshold, v.dof) == pytest.approx((gate + 0.1, gate, 60))
    watch = _watch_with([(10, 30.0, 30), (20, gate - 30.0 - 0.1, 30)])
    assert watch.verdict(20, None) is None
    # Step 10 leaves a 10-step window ending at step 20.
    watch = _watch_with([(10, 1e6, 30), (20, 10.0, 30)], window_steps=10)
    assert watch.verdict(20, None) is None
    assert watch.innovations(20) == (10.0, 30)


def test_the_gate_tests_need_a_majority_against_the_anchor() -> None:
    watch = _watch_with([])
    match = frozenset(range(1, 9))
    paired = frozenset(range(1, 21))
    # Five of the match's eight features un-fused: more than half.
    v = watch.verdict(5, GateState(paired, frozenset({1, 2, 3, 4, 5}), match))
    assert v is not None
    assert (v.test, v.statistic, v.threshold) == ("pairings un-fused", 5.0, 4.0)
    assert watch.verdict(5, GateState(paired, frozenset({1, 2, 3, 4}), match)) is None
    # Outside the match: seven un-fused against three paired and still fused.
    few = frozenset({1, 2, 3})
    many = frozenset(range(11, 18))
    v = watch.verdict(5, GateState(few | many, many, match))
    assert v is not None
    assert (v.test, v.statistic, v.threshold) == ("known features un-fused", 7.0, 6.0)
    six = frozenset(range(11, 17))
    assert watch.verdict(5, GateState(few | six, six, match)) is None
    # Fewer than min_unfused decide nothing, even against none confirming.
    two = frozenset({11, 12})
    assert watch.verdict(5, GateState(two, two, match)) is None


def test_joint_nis_is_the_stacked_innovation_against_the_prior() -> None:
    m = GaussianMap()
    m.add(Element(ElementKind.CIRCLE, Role.FEATURE, False, 0), np.zeros(3), np.eye(3))
    m.add(
        Element(ElementKind.CIRCLE, Role.FEATURE, False, 1),
        np.zeros(3),
        2.0 * np.eye(3),
        np.full((3, 3), 0.5),
    )
    c1 = Candidate(0, np.array([1.0, 0.0, 0.0]), [0], np.eye(3), 0.1 * np.eye(3), 0.0)
    c2 = Candidate(1, np.array([0.0, 2.0, 0.0]), [1], np.eye(3), 0.1 * np.eye(3), 0.0)
    S = np.block([[1.1 * np.eye(3), np.full((3, 3), 0.5)], [np.full((3, 3), 0.5), 2.1 * np.eye(3)]])
    r = np.array([1.0, 0.0, 0.0, 0.0, 2.0, 0.0])
    assert joint_nis(m, [c1, c2]) == (pytest.approx(float(r @ np.linalg.solve(S, r))), 6)
    assert joint_nis(m, []) is None


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"level": 1.0}, "level"),
        ({"window_steps": 0}, "window_steps"),
        ({"min_unfused": 2.5}, "min_unfused"),
        ({"majority": 0.5}, "majority"),
        ({"majority": math.inf}, "majority"),
    ],
)
def test_watch_params_reject_bad_values(kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        AnchorWatchParams(**kwargs)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="anchor_watch must be"):
        EKFConfig(anchor_watch=0.99)  # type: ignore[arg-type]


def test_the_innovation_test_scales_with_the_local_pairings_rate_above_one() -> None:
    # Model error common to every pairing (local NIS 2 per dof over 10,000 dof)
    # doubles what the known pairings may reach, up to the F quantile's widening;
    # a local rate below one leaves the test no stricter than with no reference.
    watch = _watch_with([(10, 300.0, 200)])
    chi2 = chi2_gate(0.99999, 200)
    assert watch.innovation_threshold(200) == pytest.approx(chi2)
    watch.local_nis, watch.local_dof = 20_000.0, 10_000
    assert watch.innovation_threshold(200) == pytest.approx(
        200 * 2.0 * f_dist.ppf(0.99999, 200, 10_000)
    )
    # Many local degrees of freedom: F·dof tends to the χ² quantile (within 1 %).
    assert watch.innovation_threshold(200) == pytest.approx(2.0 * chi2, rel=0.01)
    assert watch.verdict(10, None) is None
    watch.local_nis = 5_000.0
    assert watch.innovation_threshold(200) == pytest.approx(200 * f_dist.ppf(0.99999, 200, 10_000))
    # Few local degrees of freedom: the threshold widens, never narrows.
    watch.local_nis, watch.local_dof = 40.0, 20
    assert watch.innovation_threshold(200) > 2.0 * chi2
