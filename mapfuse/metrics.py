"""A run's :class:`~mapfuse_core.estimate.RunMetrics`, computed from its result and its
log alone: :func:`run_metrics`.

The same for every estimator (README, *metrics.json*): scenario, seed, estimator,
fusion, steps; pose errors and NEES against truth (or position errors against GPS on
real data); the anchor; the map size; per-step run times.  A result with a smoothed
estimate also says which estimate the metrics are of (``estimate``) and, when it has
a filtered one too, adds that one's errors (``nees_filtered``,
``position_error_filtered``); a result that took its association decisions as an
input names their source (``association``); a log that says how it was made
(``MeasurementLog.metadata``, e.g. a CARMEN log's ``odometry: simulated from
reference``) has it under ``log``.  Every run also reports its map-matching outcome
(``matching``) and its ``warnings`` (:mod:`mapfuse.diagnostics`, ``docs/warnings.md``).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from mapfuse.diagnostics import matching_block, run_warnings
from mapfuse_core.estimate import (
    Anchor,
    AnchorMetrics,
    EstimatorResult,
    HeadingError,
    KnownMapGating,
    MapMetrics,
    NeesSummary,
    PoseTrack,
    PositionError,
    RunMetrics,
)
from mapfuse_core.evaluation import (
    anchor_metrics,
    anchor_truth,
    gps_position_metrics,
    pose_metrics,
    runtime_metrics,
    truth_in_global,
)
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.measlog import MeasurementLog

__all__ = ["anchor_block", "run_metrics"]


def anchor_block(
    anchor: Anchor | None,
    true_poses: FloatArray | None,
    known_frame: FloatArray | None = None,
) -> AnchorMetrics | None:
    """The anchor's metrics (``None`` without an anchor)."""
    if anchor is None:
        return None
    truth = anchor_truth(true_poses, known_frame) if true_poses is not None else None
    return anchor_metrics(
        anchor.x_Wknown_Wglobal, truth, anchor.accepted_at_step, anchor.pairings, anchor.cov
    )


def _known_gating(result: EstimatorResult) -> KnownMapGating | None:
    """The known-map gate's report of ``result``, or of the run whose decisions it
    consumed (a graph backend honours the EKF's un-fuse decisions)."""
    for r in (result, result.upstream):
        if r is not None and r.decisions is not None and r.decisions.known_gating is not None:
            return r.decisions.known_gating
    return None


def _track_errors(
    track: PoseTrack,
    log: MeasurementLog,
    anchor: AnchorMetrics | None,
) -> tuple[PositionError | None, HeadingError | None, NeesSummary | None]:
    """Errors of ``track`` against truth, else position errors against GPS (through the
    anchor when there is one), else none."""
    n = track.poses.shape[0]
    if log.true_poses is not None:
        return pose_metrics(track.poses, track.covs, truth_in_global(log.true_poses[:n]))
    if log.gps is None:
        return None, None, None
    ref = None if anchor is None else np.asarray(anchor.estimate, dtype=float)
    pos = gps_position_metrics(log.timestamps[:n], track.poses, log.gps[0], log.gps[1], ref)
    return pos, None, None


def run_metrics(
    result: EstimatorResult,
    log: MeasurementLog,
    which: Literal["smoothed", "filtered"] | None = None,
) -> RunMetrics:
    """The metrics of ``result``, a run on ``log``.

    ``which``: ``"smoothed"`` or ``"filtered"``, the estimate to evaluate (default
    :attr:`EstimatorResult.estimate`, the smoothed one when there is one).
    """
    which = result.estimate if which is None else which
    if which not in ("smoothed", "filtered"):
        raise ValueError(f"which must be 'smoothed' or 'filtered', got {which!r}")
    track = result.filtered if which == "filtered" else result.smoothed
    if track is None:
        raise ValueError(f"the {result.estimator} result has no {which} estimate")
    anchor = anchor_block(result.anchor, log.true_poses, log.known_frame)
    position, heading, nees = _track_errors(track, log, anchor)
    f = result.filtered
    nees_f: NeesSummary | None = None
    position_f: PositionError | None = None
    if which == "smoothed" and f is not None:
        position_f, _, nees_f = _track_errors(f, log, anchor)
    gating = _known_gating(result)
    return RunMetrics(
        scenario=result.scenario,
        seed=int(result.seed),
        estimator=result.estimator,
        fusion=bool(result.fusion),
        steps=int(track.poses.shape[0]),
        position_error=position,
        heading_error=heading,
        nees=nees,
        anchor=anchor,
        map=MapMetrics(
            features=len(result.map.kinds),
            matched_known=result.map.matched_known,
            seen_once=result.map.seen_once,
            tentative_dropped=int(result.tentative_dropped),
        ),
        runtime=runtime_metrics(result.step_time_s),
        matching=matching_block(result),
        log=dict(log.metadata) if log.metadata else None,
        association=result.association,
        known_map_rejections=None if gating is None else gating.as_dict(),
        estimate=which if result.smoothed is not None else None,
        nees_filtered=nees_f,
        position_error_filtered=position_f,
        warnings=tuple(run_warnings(result, log, nees, track.covs)),
    )
