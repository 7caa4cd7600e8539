"""Solvers of the mapfuse factor graph: batch Levenberg–Marquardt and iSAM2.

Both are driven so that no Python factor callback ever receives a ``Values`` that
Python does not own (GTSAM's own optimizers deep-copy the ``Values`` on every
callback; costs in ``docs/results/performance.md``):

* **batch** — Levenberg–Marquardt written here: ``graph.linearize(values)``, add
  ``√λ·I`` damping rows per variable, eliminate (multifrontal, COLAMD),
  ``values.retract``, ``graph.error``, adapt λ.  Smoothed marginals from
  ``gtsam.Marginals`` on the final linearisation.
* **isam2** — one ``ISAM2.update`` per step while holding a reference to
  ``isam.getLinearizationPoint()`` for the whole run (callbacks then get that object
  instead of a copy).  Each update orders the newest pose last, so that its *filtered*
  estimate and covariance (comparable with the EKF's) come from the root clique
  (:func:`_newest_pose_marginal`); at the end a few extra updates finish
  relinearisation and all smoothed marginals are read in one pass
  (:func:`tree_marginals`).

Covariances: GTSAM's Pose2 marginals are in the body tangent (``X ⊕ Exp(δ)``);
mapfuse reports absolute ``(x, y, θ)`` covariances, ``G P Gᵀ`` with
``G = blockdiag(R(θ), 1)`` (:func:`body_to_abs_cov`).

Entry point: :func:`run_graph`.  The solvers live in :mod:`mapfuse_graph.batch` and
:mod:`mapfuse_graph.isam2`, the covariance readers in :mod:`mapfuse_graph.marginals`, the
result types and their extraction in :mod:`mapfuse_graph.results`; this module
re-exports their public names.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import replace
from typing import Literal

import numpy as np

from mapfuse_core.estimate import (
    AnchorDecision,
    AssociationDecisions,
    EstimatorResult,
    MatchAttempts,
    PoseTrack,
)
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.measlog import MeasurementLog
from mapfuse_graph.batch import LMOptions, _run_batch, levenberg_marquardt
from mapfuse_graph.batch import _joint_pose_cov as _joint_pose_cov
from mapfuse_graph.batch import _ValuesEstimate as _ValuesEstimate
from mapfuse_graph.builder import GraphBuilder
from mapfuse_graph.fixedlag import FixedLagOptions, _run_fixedlag, split_by_lag
from mapfuse_graph.isam2 import ISAM2Options, _run_isam2
from mapfuse_graph.isam2 import _ISAM2Estimate as _ISAM2Estimate
from mapfuse_graph.isam2 import _newest_last as _newest_last
from mapfuse_graph.isam2 import _newest_pose_marginal as _newest_pose_marginal
from mapfuse_graph.marginals import body_to_abs_cov, tree_marginals
from mapfuse_graph.options import ASSOCIATIONS, AssociationName, GraphOptions
from mapfuse_graph.results import GraphDetails, JointPoseCovariance, LMReport, _Solved
from mapfuse_graph.threads import single_threaded_blas

__all__ = [
    "BACKENDS",
    "FixedLagOptions",
    "GraphDetails",
    "ISAM2Options",
    "JointPoseCovariance",
    "LMOptions",
    "LMReport",
    "body_to_abs_cov",
    "levenberg_marquardt",
    "run_graph",
    "tree_marginals",
]

BACKENDS: tuple[str, ...] = ("batch", "isam2", "fixedlag")
Backend = Literal["batch", "isam2", "fixedlag"]


@single_threaded_blas
def run_graph(
    log: MeasurementLog,
    backend: Backend = "isam2",
    *,
    fusion: bool = True,
    association: AssociationName = "given",
    decisions: AssociationDecisions | None = None,
    options: GraphOptions | None = None,
    lm: LMOptions | None = None,
    isam2: ISAM2Options | None = None,
    fixedlag: FixedLagOptions | None = None,
    steps: int | None = None,
    init: Literal["auto", "given", "odometry"] = "auto",
    init_poses: FloatArray | None = None,
    marginals: bool = True,
    progress: Callable[[int, int], None] | None = None,
    joint_stride: int | None = None,
) -> EstimatorResult:
    """Build the factor graph of ``log`` and solve it with ``backend``.

    ``backend``: ``"batch"`` (Levenberg–Marquardt over all steps), ``"isam2"`` (one
    update per step; also gives per-step filtered estimates) or ``"fixedlag"`` (iSAM2
    over a window of ``fixedlag.lag_s`` seconds, :mod:`mapfuse_graph.fixedlag`).
    ``association`` (:mod:`mapfuse_graph.builder`): ``"given"`` takes the landmarks,
    known-map pairings and anchor of ``decisions`` (e.g. another estimator's, or
    arrays wrapped in an :class:`~mapfuse_core.estimate.AssociationDecisions`);
    ``"truth"`` the simulator's ids (and the anchor of ``decisions`` when given);
    ``"own"`` decides while the graph grows (for ``batch``, by an iSAM2 pass first).
    ``fusion``: whether the known map enters the graph.  ``steps`` solves only the
    first ``steps`` steps.  ``init`` (batch): ``"given"`` starts from ``init_poses``
    (e.g. the EKF's, one per step of the log), ``"odometry"`` from dead reckoning,
    ``"auto"`` from ``init_poses`` when given.  ``marginals=False`` skips the smoothed
    marginals (covariances NaN).  ``joint_stride`` (batch, with marginals) also computes
    the joint covariance of every ``joint_stride``-th pose
    (:attr:`GraphDetails.joint_pose_cov`); its cost grows with the cube of the number
    of poses it keeps.

    Returns the :class:`~mapfuse_core.estimate.EstimatorResult` every estimator returns
    (estimator ``backend``; the smoothed track, and the filtered one for iSAM2 and
    fixed-lag), with :class:`GraphDetails` as its ``details``.  BLAS runs on one thread
    during the run (:mod:`mapfuse_graph.threads`).
    """
    t_start = time.perf_counter()
    cpu_start = time.process_time()
    if backend not in BACKENDS:
        raise ValueError(f"unknown graph backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    if association not in ASSOCIATIONS:
        raise ValueError(
            f"association must be one of {', '.join(ASSOCIATIONS)}, got {association!r}"
        )
    if init not in ("auto", "given", "odometry"):
        raise ValueError(f"init must be 'auto', 'given' or 'odometry', got {init!r}")
    if joint_stride is not None and (
        backend != "batch"
        or not marginals
        or int(joint_stride) != joint_stride
        or not 1 <= joint_stride < (log.n_steps if steps is None else steps)
    ):
        raise ValueError(
            "joint_stride needs the batch backend with marginals and an integer from 1 to "
            "below the number of steps, "
            f"got joint_stride={joint_stride!r} with backend={backend!r}, marginals={marginals}"
        )
    if init_poses is not None:
        init_poses = np.asarray(init_poses, dtype=float)
        if init_poses.shape != (log.n_steps, 3):
            raise ValueError(
                f"init_poses has shape {init_poses.shape}, the log needs ({log.n_steps}, 3)"
            )
        if not np.all(np.isfinite(init_poses)):
            raise ValueError("init_poses has non-finite values")
    opts = options or GraphOptions()
    builder = _builder(log, backend, opts, fusion, association, decisions, fixedlag, isam2, steps)
    fl = fixedlag or FixedLagOptions()
    n = builder.n_steps
    if backend == "batch":
        if init == "given" and init_poses is None:
            raise ValueError("init 'given' needs init_poses")
        start = None if init == "odometry" or init_poses is None else init_poses[:n]
        out = _run_batch(builder, lm, start, marginals, progress, joint_stride)
    else:

        def incremental(options: ISAM2Options | None, b: GraphBuilder) -> _Solved:
            if backend == "fixedlag":
                return _run_fixedlag(b, fl, options, marginals, progress)
            return _run_isam2(b, options, marginals, progress)

        try:
            out = incremental(isam2, builder)
        except RuntimeError as err:
            first = isam2 or ISAM2Options()
            if not _indeterminate(err) or first.factorization == "QR":
                raise
            warnings.warn(
                f"{backend}: Cholesky elimination found the linear system indeterminate "
                "(a variable tied by factors of very different weights, such as the "
                "anchor's loose prior and its ties); solved again with QR factorization",
                RuntimeWarning,
                stacklevel=3,  # past single_threaded_blas's wrapper, to the caller
            )
            builder = _builder(
                log, backend, opts, fusion, association, decisions, fixedlag, isam2, steps
            )
            out = incremental(replace(first, factorization="QR"), builder)
            out.extra["factorization"] = "QR (Cholesky found the system indeterminate)"
    filtered = None
    if out.filtered_poses is not None and out.filtered_covs is not None:
        filtered = PoseTrack(out.filtered_poses, out.filtered_covs)
    reasons = builder.ccda_reasons if association == "own" else None
    anchor = out.anchor
    return EstimatorResult(
        estimator=backend,
        scenario=log.scenario,
        seed=log.seed,
        fusion=builder.fusion,
        timestamps=np.asarray(log.timestamps[:n], dtype=float),
        step_time_s=out.step_time_s,
        map=out.landmarks,
        filtered=filtered,
        smoothed=PoseTrack(out.poses, out.covs),
        anchor=anchor,
        decisions=AssociationDecisions(
            builder.obs_landmark.copy(),
            _obs_known_id(builder.obs_landmark, out.landmarks.known_ids),
            None
            if anchor is None
            else AnchorDecision(anchor.x_Wknown_Wglobal, anchor.accepted_at_step),
        ),
        association=association,
        matching=None
        if reasons is None or not builder.fusion
        else MatchAttempts(sum(reasons.values()), dict(reasons)),
        details=GraphDetails(
            build_time_s=out.build_time_s,
            solve_time_s=out.solve_time_s,
            marginals_time_s=out.marginals_time_s,
            total_time_s=time.perf_counter() - t_start,
            total_cpu_s=time.process_time() - cpu_start,
            landmark_variables=out.variables,
            n_factors=int(out.graph.size()),
            n_variables=int(out.values.size()),
            final_error=float(out.graph.error(out.values)),
            lm=out.lm,
            extra=out.extra,
            joint_pose_cov=out.joint_pose_cov,
            step_cpu_s=out.step_cpu_s,
            graph=out.graph,
            values=out.values,
            initial=out.initial,
        ),
    )


def _indeterminate(err: RuntimeError) -> bool:
    """Whether ``err`` is GTSAM's IndeterminateLinearSystemException (raised to Python
    as a ``RuntimeError`` with this text)."""
    return "Indeterminate linear system" in str(err)


def _builder(
    log: MeasurementLog,
    backend: Backend,
    opts: GraphOptions,
    fusion: bool,
    association: AssociationName,
    decisions: AssociationDecisions | None,
    fixedlag: FixedLagOptions | None,
    isam2: ISAM2Options | None,
    steps: int | None,
) -> GraphBuilder:
    """The builder of the graph to solve, its association fixed first where the backend
    cannot decide it while it solves: batch with ``"own"`` (an iSAM2 pass decides), a
    fixed-lag window that marginalises landmarks (a landmark is split at each lag)."""
    fl = fixedlag or FixedLagOptions()
    if backend == "batch" and association == "own":
        # Own association is decided against an incremental estimate: run iSAM2 first.
        pre = GraphBuilder(log, opts, fusion=fusion, association="own", steps=steps)
        _run_isam2(pre, isam2, False, None)
        lm, kn = _arrays_of(pre)
        builder = GraphBuilder(
            log,
            opts,
            fusion=fusion,
            association="given",
            decisions=AssociationDecisions(lm, kn),
            steps=steps,
        )
        if pre.anchor_added:
            assert pre.anchor_init is not None
            builder.anchor_init, builder.anchor_step = pre.anchor_init, pre.anchor_step
            builder.anchor_source = pre.anchor_source
        builder.ccda_reasons = dict(pre.ccda_reasons)
        return builder
    if backend == "fixedlag" and fl.landmarks == "window":
        if association == "own":
            raise ValueError(
                "fixedlag with landmarks='window' needs a fixed association ('given' or "
                "'truth'): a marginalised landmark cannot be matched again"
            )
        pre = GraphBuilder(
            log, opts, fusion=fusion, association=association, decisions=decisions, steps=steps
        )
        lm_ids, kn_ids = pre.planned_arrays()
        split = AssociationDecisions(
            split_by_lag(lm_ids, kn_ids, log.feat_step, log.timestamps, fl.lag_s),
            kn_ids,
            None if decisions is None else decisions.anchor,
        )
        return GraphBuilder(
            log, opts, fusion=fusion, association="given", decisions=split, steps=steps
        )
    return GraphBuilder(
        log, opts, fusion=fusion, association=association, decisions=decisions, steps=steps
    )


def _obs_known_id(obs_landmark: np.ndarray, known_ids: np.ndarray) -> np.ndarray:
    """(M,) known-map id of every observation's landmark, −1 if none (or not in the graph)."""
    if not known_ids.size:
        return np.full(obs_landmark.shape, -1, dtype=np.int64)
    out = np.where(obs_landmark >= 0, known_ids[np.clip(obs_landmark, 0, None)], -1)
    return np.asarray(out, dtype=np.int64)


def _arrays_of(builder: GraphBuilder) -> tuple[np.ndarray, np.ndarray]:
    """Association decisions of a finished builder as (obs_landmark, obs_known_id)."""
    lm = builder.obs_landmark.copy()
    known = builder.landmark_known_ids()
    kn = np.where(lm >= 0, known[np.clip(lm, 0, None)] if known.size else -1, -1)
    return lm, np.asarray(kn, dtype=np.int64)
