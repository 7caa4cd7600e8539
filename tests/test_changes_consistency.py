"""Change detection on a run its own consistency evidence does not trust: inconclusive,
with no feature called moved, missing or new."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.stats import chi2

from mapfuse_core.changes import (
    ChangeStatus,
    classify_changes,
    consistency_from_innovations,
    no_consistency_evidence,
    withhold_changes,
)
from mapfuse_core.evaluation.run_consistency import consistency_from_nees
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.measlog import MeasurementLog
from tests.test_changes import PARAMS, _log, _replace_known, _true_decisions, _true_trajectory


def test_a_consistent_nees_series_is_trusted_and_an_overconfident_one_is_not() -> None:
    rng = np.random.default_rng(0)
    nees = rng.chisquare(3, 2000)
    c = consistency_from_nees(nees)
    assert c.evidence == "reference NEES"
    assert c.low < 3.0 < c.high
    assert c.trusted
    # Covariances 4 times too small: the mean NEES is 12, far above the region.
    over = consistency_from_nees(4.0 * nees)
    assert over.statistic == pytest.approx(4.0 * c.statistic)
    assert not over.trusted
    # Too cautious is not misplaced: a run below the region is trusted.
    assert consistency_from_nees(0.25 * nees).trusted
    # Steps without an estimate are left out; none at all is no evidence.
    assert consistency_from_nees(np.r_[np.nan, nees]).statistic == pytest.approx(c.statistic)
    assert consistency_from_nees(np.full(5, np.nan)).evidence == "none"


def test_innovations_are_judged_against_their_chi2_region() -> None:
    dof = 4000
    inside = consistency_from_innovations(float(dof), dof)
    assert inside.evidence == "innovations"
    assert inside.low == pytest.approx(chi2.ppf(0.025, dof) / dof)
    assert inside.high == pytest.approx(chi2.ppf(0.975, dof) / dof)
    assert inside.trusted
    # 5 % too large on 4000 degrees of freedom is beyond the region (its half-width
    # is 1.96·√(2/4000) = 4.4 %).
    assert not consistency_from_innovations(1.05 * dof, dof).trusted
    assert consistency_from_innovations(1.03 * dof, dof).trusted
    assert consistency_from_innovations(0.0, 0).evidence == "none"
    with pytest.raises(ValueError, match="dof"):
        consistency_from_innovations(1.0, -1)
    with pytest.raises(ValueError, match="chi2_sum"):
        consistency_from_innovations(math.nan, 3)


def _turned() -> tuple[MeasurementLog, int]:
    """The synthetic log whose known map has its first line turned by 0.3 rad, and
    that line's row."""
    log = _log()
    k = log.known_map
    line = int(np.nonzero(k.kinds == FeatureKind.LINE)[0][0])
    p = k.params.copy()
    p[line, 2] += 0.3
    return _replace_known(log, params=p), line


def test_an_untrusted_run_calls_nothing_moved_missing_or_new() -> None:
    log, line = _turned()
    lm, kn = _true_decisions(log)
    start, poses, covs = _true_trajectory(log)
    report = classify_changes(log, lm, kn, poses, covs, start, PARAMS)
    assert report.known[line].status == ChangeStatus.MOVED
    assert report.new, "the synthetic world has features the known map lacks"
    trusted = withhold_changes(report, consistency_from_nees(np.full(50, 3.0)))
    assert trusted.conclusive
    assert trusted.counts() == report.counts()
    assert trusted.as_dict()["verdict"] == "conclusive"

    untrusted = withhold_changes(report, consistency_from_nees(np.full(50, 30.0)))
    assert not untrusted.conclusive
    counts = untrusted.counts()
    assert counts["moved"] == counts["missing"] == counts["new"] == 0
    assert counts["inconclusive"] == report.counts()["moved"] + report.counts()["missing"]
    assert counts["confirmed"] == report.counts()["confirmed"]
    assert untrusted.withheld_new == len(report.new)
    # The evidence of the withheld calls stays with each feature.
    assert untrusted.known[line].statistic == report.known[line].statistic
    d = untrusted.as_dict()
    assert d["verdict"] == "inconclusive"
    assert d["consistency"]["evidence"] == "reference NEES"
    assert d["consistency"]["trusted"] is False
    # Without evidence the report stands as classified.
    assert withhold_changes(report, no_consistency_evidence()).counts() == report.counts()


def test_detect_changes_judges_a_run_by_its_nees_against_the_reference() -> None:
    """The same run twice: with its covariances honest the moved line is reported;
    with them shrunk 10⁴ times (errors of centimetres against σ of 0.1 mm) the NEES
    is far above its region and the report is inconclusive."""
    import types

    from mapfuse.changes import detect_changes, run_consistency

    log, line = _turned()
    lm, kn = _true_decisions(log)
    start, poses, _ = _true_trajectory(log)
    rng = np.random.default_rng(1)
    sigma = np.array([0.05, 0.05, 0.01])
    noisy = poses + rng.normal(0.0, sigma, poses.shape)
    honest = np.tile(np.diag(sigma**2), (poses.shape[0], 1, 1))

    def result(covs: np.ndarray) -> types.SimpleNamespace:
        return types.SimpleNamespace(
            estimator="test",
            fusion=True,
            anchor=types.SimpleNamespace(
                x_Wknown_Wglobal=start, cov=np.eye(3) * 1e-6, accepted_at_step=0
            ),
            decisions=types.SimpleNamespace(arrays=(lm, kn)),
            poses=noisy,
            covs=covs,
            smoothed=None,
            details=None,
            map=types.SimpleNamespace(
                tracks=None, known_ids=np.zeros(0), params_known=None, covs_known=None
            ),
        )

    ok = result(honest)
    assert run_consistency(ok, log).trusted  # type: ignore[arg-type]
    rep = detect_changes(ok, log, PARAMS)  # type: ignore[arg-type]
    assert rep.conclusive
    assert rep.known[line].status == ChangeStatus.MOVED

    over = result(honest * 1e-4)
    c = run_consistency(over, log)  # type: ignore[arg-type]
    assert c.evidence == "reference NEES"
    assert not c.trusted
    rep = detect_changes(over, log, PARAMS)  # type: ignore[arg-type]
    assert not rep.conclusive
    assert rep.counts()["moved"] == 0
    assert rep.counts()["missing"] == 0


def test_without_a_reference_the_ekfs_innovations_decide() -> None:
    import types

    from ekf_reference.result import InnovationTotals
    from mapfuse.changes import run_consistency

    log = dataclasses.replace(_log(), true_poses=None)

    def result(chi2_sum: float, dof: int) -> types.SimpleNamespace:
        return types.SimpleNamespace(
            poses=np.zeros((3, 3)),
            covs=np.zeros((3, 3, 3)),
            details=types.SimpleNamespace(innovations=InnovationTotals(chi2_sum, dof)),
        )

    assert run_consistency(result(1000.0, 1000), log).trusted  # type: ignore[arg-type]
    c = run_consistency(result(3000.0, 1000), log)  # type: ignore[arg-type]
    assert c.evidence == "innovations"
    assert c.statistic == pytest.approx(3.0)
    assert not c.trusted
    none = types.SimpleNamespace(poses=np.zeros((3, 3)), covs=np.zeros((3, 3, 3)), details=None)
    assert run_consistency(none, log).evidence == "none"  # type: ignore[arg-type]


def test_the_ekf_reports_its_innovations() -> None:
    from ekf_reference import run_ekf
    from tests.synthetic import synthetic_log

    log = synthetic_log(steps=120, seed=5, known_fraction=0.0)
    res = run_ekf(log, fusion=False)
    tot = res.details.innovations
    lines = int(np.count_nonzero(log.feat_kind == FeatureKind.LINE))
    circles = int(np.count_nonzero(log.feat_kind == FeatureKind.CIRCLE))
    # Every re-observation of a landmark is an update of 2 (line) or 3 (circle) dims.
    assert 0 < tot.dof <= 2 * lines + 3 * circles
    # A consistent filter on a simulated log: χ² per dof near 1 (gated at 99.9 %).
    assert 0.6 < tot.chi2 / tot.dof < 1.3
