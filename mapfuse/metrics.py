"""``metrics.json``: one object per run, computed from its result and its log alone.

The schema is the same for every estimator (README, *Outputs*): scenario, seed,
backend, fusion, steps; pose errors and NEES against truth (or position errors
against GPS on real data); the anchor; the map size; per-step run times.  A result
with a smoothed estimate also says which estimate a metrics object is of
(``estimate``) and, when it has a filtered one too, adds that one's errors
(``nees_filtered``, ``position_error_filtered_m``); a result that took its
association decisions as an input names their source (``association``); a log that
says how it was made (``MeasurementLog.metadata``, e.g. a CARMEN log's ``odometry:
simulated from reference``) has it under ``log``.  Every object ends with the
map-matching outcome (``matching``) and the run's ``warnings``
(:mod:`mapfuse.diagnostics`, ``docs/warnings.md``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mapfuse.diagnostics import matching_block, run_warnings
from mapfuse.result import Anchor, EstimatorResult
from mapfuse_core.estimate.decisions import KnownMapGating
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

__all__ = ["anchor_block", "build_metrics", "run_metrics"]


def anchor_block(
    anchor: Anchor | None,
    true_poses: FloatArray | None,
    known_frame: FloatArray | None = None,
) -> dict[str, Any] | None:
    """The ``anchor`` block of ``metrics.json`` (``None`` without an anchor)."""
    if anchor is None:
        return None
    truth = anchor_truth(true_poses, known_frame) if true_poses is not None else None
    return anchor_metrics(anchor.x_Wknown_Wglobal, truth, anchor.accepted_at_step, anchor.pairings)


def build_metrics(
    *,
    scenario: str,
    seed: int,
    backend: str,
    fusion: bool,
    poses: FloatArray,
    covs: FloatArray,
    true_poses: FloatArray | None,
    step_time_s: FloatArray,
    anchor: dict[str, Any] | None,
    map_features: int,
    matched_known: int,
    timestamps: FloatArray | None = None,
    gps: tuple[FloatArray, FloatArray] | None = None,
) -> dict[str, Any]:
    """The common part of a ``metrics.json`` object, from arrays.

    Without true poses but with ``gps`` (times, East/North) and ``timestamps``, the
    position errors are against GPS (:func:`~mapfuse_core.evaluation.gps_position_metrics`,
    through the anchor when there is one); heading and NEES stay ``None``.
    """
    out: dict[str, Any] = {
        "scenario": scenario,
        "seed": int(seed),
        "backend": backend,
        "fusion": bool(fusion),
        "steps": int(poses.shape[0]),
    }
    if true_poses is not None:
        out.update(pose_metrics(poses, covs, truth_in_global(true_poses)))
    else:
        out.update({"position_error_m": None, "heading_error_rad": None, "nees": None})
        if gps is not None and timestamps is not None:
            ref = None if anchor is None else np.asarray(anchor["estimate"], dtype=float)
            out["position_error_m"] = gps_position_metrics(
                timestamps[: poses.shape[0]], poses, gps[0], gps[1], ref
            )
    out["anchor"] = anchor
    out["map"] = {"features": int(map_features), "matched_known": int(matched_known)}
    out["runtime_s"] = runtime_metrics(step_time_s)
    return out


def _known_gating(result: EstimatorResult) -> KnownMapGating | None:
    """The known-map gate's report of ``result``, or of the run whose decisions it
    consumed (a graph backend honours the EKF's un-fuse decisions)."""
    for r in (result, result.upstream):
        if r is not None and r.decisions is not None and r.decisions.known_gating is not None:
            return r.decisions.known_gating
    return None


def run_metrics(
    result: EstimatorResult, log: MeasurementLog, which: str | None = None
) -> dict[str, Any]:
    """``metrics.json`` of ``result``, a run on ``log``.

    ``which``: ``"smoothed"`` or ``"filtered"``, the estimate to evaluate (default
    :attr:`EstimatorResult.estimate`, the smoothed one when there is one).
    """
    which = result.estimate if which is None else which
    if which == "filtered":
        track = result.filtered
    elif which == "smoothed":
        track = result.smoothed
    else:
        raise ValueError(f"which must be 'smoothed' or 'filtered', got {which!r}")
    if track is None:
        raise ValueError(f"the {result.estimator} result has no {which} estimate")
    anchor = anchor_block(result.anchor, log.true_poses, log.known_frame)
    n = track.poses.shape[0]
    true_poses = None if log.true_poses is None else log.true_poses[:n]
    out = build_metrics(
        scenario=result.scenario,
        seed=result.seed,
        backend=result.estimator,
        fusion=result.fusion,
        poses=track.poses,
        covs=track.covs,
        true_poses=true_poses,
        step_time_s=result.step_time_s,
        anchor=anchor,
        map_features=len(result.map.kinds),
        matched_known=result.map.matched_known,
        timestamps=log.timestamps,
        gps=log.gps,
    )
    out["map"]["seen_once"] = result.map.seen_once
    out["map"]["tentative_dropped"] = int(result.tentative_dropped)
    out["matching"] = matching_block(result)
    if log.metadata:
        out["log"] = dict(log.metadata)
    if result.association is not None:
        out["association"] = result.association
    gating = _known_gating(result)
    if gating is not None:
        out["known_map_rejections"] = gating.as_dict()
    if result.smoothed is not None:
        out["estimate"] = which
    f = result.filtered
    if which == "smoothed" and f is not None and true_poses is not None:
        filtered = pose_metrics(f.poses, f.covs, truth_in_global(true_poses))
        out["nees_filtered"] = filtered["nees"]
        out["position_error_filtered_m"] = filtered["position_error_m"]
    elif which == "smoothed" and f is not None and log.gps is not None:
        ref = None if anchor is None else np.asarray(anchor["estimate"], dtype=float)
        out["position_error_filtered_m"] = gps_position_metrics(
            log.timestamps[: f.poses.shape[0]], f.poses, *log.gps, ref
        )
    out["warnings"] = run_warnings(result, log, out["nees"], track.covs)
    return out
