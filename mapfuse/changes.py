"""Known-map change detection on an :class:`~mapfuse_core.estimate.EstimatorResult`.

The same classification (:func:`mapfuse_core.changes.classify_changes`) for every
estimator: it reads the run's association decisions, its main trajectory (the
smoothed one for a batch or iSAM2 graph, the filtered one for the EKF) and its
anchor.  With the smoothed trajectory every observation is put in ``Wknown`` with
the pose estimated from the whole log, so the evidence of a feature seen early is
as good as that of one seen late, and the pose covariance entering the test is the
smaller smoothed one: the graph's tests are sharper, and the pull of the tested
known feature on the trajectory it is tested with acts over the whole run
(``docs/change-detection.md``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from mapfuse import registry
from mapfuse_core.changes import (
    ChangeParams,
    ChangeReport,
    RunConsistency,
    classify_changes,
    consistency_from_innovations,
    no_consistency_evidence,
    withhold_changes,
)
from mapfuse_core.estimate import EstimatorResult
from mapfuse_core.evaluation import nees_series, pose_errors, truth_in_global
from mapfuse_core.evaluation.change_truth import ChangeTruth, change_truth, score_changes
from mapfuse_core.evaluation.run_consistency import consistency_from_nees
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.measlog import MeasurementLog
from mapfuse_core.sim.scenario import Scenario

__all__ = [
    "NoChangeEvidenceError",
    "change_report_lines",
    "change_section",
    "detect_changes",
    "run_consistency",
]


class NoChangeEvidenceError(ValueError):
    """A run that cannot tell a known map's changes: it put no known map in its frame
    (no accepted match), or it holds no association decisions."""


def detect_changes(
    result: EstimatorResult, log: MeasurementLog, params: ChangeParams | None = None
) -> ChangeReport:
    """Classify ``log``'s known map after ``result``'s run (a fused run with an anchor
    and association decisions; :class:`NoChangeEvidenceError` otherwise)."""
    if not result.fusion or result.anchor is None:
        raise NoChangeEvidenceError(
            f"{result.estimator}: change detection needs a fused run whose map match was "
            "accepted (no anchor: the known map was never put in the run's frame)"
        )
    if result.decisions is None:
        raise NoChangeEvidenceError(
            f"{result.estimator}: change detection needs the run's association decisions, "
            "and this run has none"
        )
    lm, kn = result.decisions.arrays
    # A filter's poses up to its match step (the match follows that step's update) were
    # estimated without the known map, and so were a fixed-lag smoother's poses that
    # left its window before the match: their observations carry the anchor's
    # uncertainty too (for the fixed-lag smoother, conservatively, every pose up to the
    # match).  A smoother over the whole run re-estimated them with the map.
    before_map = not _smooths_before_anchor(result)
    report = classify_changes(
        log,
        lm,
        kn,
        result.poses,
        result.covs,
        result.anchor.x_Wknown_Wglobal,
        params,
        anchor_cov=result.anchor.cov if before_map else None,
        anchored_from_step=result.anchor.accepted_at_step + 1 if before_map else 0,
        landmark_estimates=_landmark_estimates(result),
    )
    return withhold_changes(report, run_consistency(result, log))


def run_consistency(result: EstimatorResult, log: MeasurementLog) -> RunConsistency:
    """Whether ``result``'s run may be trusted to judge its known map
    (:mod:`mapfuse_core.changes.consistency`): its pose NEES against the log's reference
    trajectory when there is one, else the χ² of its observation innovations over the
    run when the estimator reports them (the EKF does), else no evidence."""
    if log.true_poses is not None:
        n = result.poses.shape[0]
        err = pose_errors(result.poses, truth_in_global(log.true_poses[:n]))
        return consistency_from_nees(nees_series(err.dx, result.covs))
    totals = getattr(result.details, "innovations", None)
    if totals is not None and totals.dof > 0:
        return consistency_from_innovations(totals.chi2, totals.dof)
    return no_consistency_evidence()


def _smooths_before_anchor(result: EstimatorResult) -> bool:
    """Whether ``result``'s estimator declares that it re-estimates the poses before
    its match with it (:attr:`~mapfuse.estimator.Capabilities.smooths_before_anchor`);
    ``False`` (the conservative reading) for a result without a smoothed track or of
    an estimator not registered here."""
    if result.smoothed is None or result.estimator not in registry.available():
        return False
    return registry.get(result.estimator).capabilities.smooths_before_anchor


def _landmark_estimates(result: EstimatorResult) -> dict[int, tuple[FloatArray, FloatArray]]:
    """The run's final estimates of the landmarks it kept apart from the known map, in
    ``Wknown`` with their joint covariance, by landmark id (empty when the estimator
    does not give them)."""
    m = result.map
    if m.tracks is None or m.params_known is None or m.covs_known is None:
        return {}
    out = {}
    for t, p, c, k in zip(m.tracks, m.params_known, m.covs_known, m.known_ids, strict=True):
        if t >= 0 and k < 0 and np.all(np.isfinite(p)) and np.all(np.isfinite(c)):
            out[int(t)] = (np.asarray(p, dtype=float), np.asarray(c, dtype=float))
    return out


def change_section(
    report: ChangeReport, truth: ChangeTruth | None, min_move_m: float = 0.5
) -> dict[str, Any]:
    """The ``changes`` object of ``changes.json``: the report, and its score when the
    truth is known."""
    out = report.as_dict()
    if truth is not None:
        out["score"] = score_changes(report, truth, min_move_m=min_move_m).as_dict()
        out["truth"] = {
            "moved": {str(k): list(v) for k, v in truth.moved.items()},
            "removed": list(truth.removed),
            "removed_in_view": list(truth.removed_in_view),
            "added": list(truth.added),
            "added_observed": list(truth.added_observed),
        }
    return out


def _verdict(report: ChangeReport) -> str:
    """The report's verdict with the consistency evidence it rests on."""
    c = report.consistency
    if c is None or c.evidence == "none":
        return "conclusive (consistency not judged)"
    word = "conclusive" if report.conclusive else "inconclusive"
    return f"{word} ({c.evidence} {c.statistic:.3g}, 95 % region {c.low:.3g}–{c.high:.3g})"


def _pr(d: dict[str, Any]) -> str:
    p, r = d["precision"], d["recall"]
    return " / ".join("–" if v is None else f"{v:.2f}" for v in (p, r))


def change_report_lines(
    results: Sequence[EstimatorResult], log: MeasurementLog, scenario: Scenario | None
) -> list[str]:
    """The change section of ``report.md``: per fused run with an anchor, the class
    counts and, when the scenario (hence the truth) is known, precision / recall."""
    params = ChangeParams()
    truth = None
    if scenario is not None:
        params = params.with_sensor(scenario.laser)
        truth = change_truth(scenario, log, params)
    rows = []
    for res in results:
        if not res.fusion or res.anchor is None or res.decisions is None:
            continue
        rep = detect_changes(res, log, params)
        c = rep.counts()
        cells = [res.estimator, *(str(c[k]) for k in ("confirmed", "moved", "missing"))]
        cells += [str(c["unobserved"]), str(c["new"])]
        if truth is not None:
            s = score_changes(rep, truth).as_dict()
            cells += [_pr(s["moved"]), _pr(s["removed"]), _pr(s["added"])]
        cells.append(_verdict(rep))
        rows.append("| " + " | ".join(cells) + " |")
    if not rows:
        return []
    head = ["run", "confirmed", "moved", "missing", "unobserved", "new"]
    if truth is not None:
        head += ["moved ≥ 0.5 m P / R", "removed P / R", "added P / R"]
    head.append("verdict")
    return [
        "",
        "## Known-map changes",
        "",
        f"χ² tests at level {params.level} (`mapfuse changes`, `docs/change-detection.md`).  An "
        "inconclusive run is more overconfident than its consistency evidence allows: "
        "none of its features is called moved, missing or new.",
        "",
        "| " + " | ".join(head) + " |",
        "| " + " | ".join(["---"] * len(head)) + " |",
        *rows,
    ]
