"""Solvers of the mapfuse factor graph: batch Levenberg–Marquardt and iSAM2.

Both are driven so that no Python factor callback ever receives a ``Values`` that
Python does not own (GTSAM's own optimizers deep-copy the ``Values`` on every
callback; costs in ``docs/performance.md``):

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
from collections.abc import Callable
from typing import Literal

import numpy as np

from mapfuse_core.data.measlog import MeasurementLog
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.matching.decisions import AssociationDecisions
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
from mapfuse_graph.options import ASSOCIATIONS, GraphOptions
from mapfuse_graph.results import (
    GraphAnchor,
    GraphLandmarks,
    GraphResult,
    JointPoseCovariance,
    LMReport,
)
from mapfuse_graph.threads import single_threaded_blas

__all__ = [
    "BACKENDS",
    "FixedLagOptions",
    "GraphAnchor",
    "GraphLandmarks",
    "GraphResult",
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
    backend: str = "isam2",
    fusion: bool = True,
    association: str = "ekf",
    decisions: AssociationDecisions | None = None,
    robust: str | None = None,
    *,
    options: GraphOptions | None = None,
    associations: tuple[np.ndarray, np.ndarray] | None = None,
    lm: LMOptions | None = None,
    isam2: ISAM2Options | None = None,
    fixedlag: FixedLagOptions | None = None,
    steps: int | None = None,
    init: str = "auto",
    init_poses: FloatArray | None = None,
    marginals: bool = True,
    progress: Callable[[int, int], None] | None = None,
    joint_stride: int | None = None,
) -> GraphResult:
    """Build the factor graph of ``log`` and solve it with ``backend``.

    ``backend``: ``"batch"`` (Levenberg–Marquardt over all steps), ``"isam2"`` (one
    update per step; also gives per-step filtered estimates) or ``"fixedlag"`` (iSAM2
    over a window of ``fixedlag.lag_s`` seconds, :mod:`mapfuse_graph.fixedlag`).  ``association``:
    ``"ekf"`` (needs ``decisions``, the EKF's), ``"truth"`` or ``"own"`` (for
    ``batch``, decided by an iSAM2 pass first); ``associations`` (arrays) overrides it.
    ``fusion`` and ``robust`` override the same fields of ``options``.  ``steps`` solves
    only the first ``steps`` steps.  ``init`` (batch): ``"given"`` starts from
    ``init_poses`` (e.g. the EKF's, one per step of the log), ``"odometry"`` from dead
    reckoning, ``"auto"`` from ``init_poses`` when given.
    ``marginals=False`` skips the smoothed marginals (covariances NaN).
    ``joint_stride`` (batch, with marginals) also computes the joint covariance of every
    ``joint_stride``-th pose (:attr:`GraphResult.joint_pose_cov`); its cost grows with
    the cube of the number of poses it keeps.
    BLAS runs on one thread during the run (:mod:`mapfuse_graph.threads`).
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
    base = options or GraphOptions()
    opts = GraphOptions(
        **{**base.__dict__, "fusion": bool(fusion), "association": association, "robust": robust}
    )
    anchor_given: tuple[FloatArray, int, str] | None = None
    pre_reasons: dict[str, int] | None = None
    if backend == "batch" and associations is None and association == "own":
        # Own association is decided against an incremental estimate: run iSAM2 first.
        pre = GraphBuilder(log, opts, decisions, None, steps)
        _run_isam2(pre, isam2, False, None)
        associations = _arrays_of(pre)
        if pre.anchor_added:
            assert pre.anchor_init is not None
            anchor_given = (pre.anchor_init, pre.anchor_step, pre.anchor_source)
        pre_reasons = pre.ccda_reasons
    label = association if associations is None else "given"
    fl = fixedlag or FixedLagOptions()
    if backend == "fixedlag" and fl.landmarks == "window":
        if associations is None and association == "own":
            raise ValueError(
                "fixedlag with landmarks='window' needs a fixed association ('ekf', 'truth' "
                "or arrays): a marginalised landmark cannot be matched again"
            )
        pre = GraphBuilder(log, opts, decisions, associations, steps)
        lm_ids, kn_ids = pre.planned_arrays()
        associations = (
            split_by_lag(lm_ids, kn_ids, log.feat_step, log.timestamps, fl.lag_s),
            kn_ids,
        )
    builder = GraphBuilder(log, opts, decisions, associations, steps)
    if anchor_given is not None:
        builder.anchor_init, builder.anchor_step, builder.anchor_source = anchor_given
    n = builder.n_steps
    if backend == "batch":
        if init == "given" and init_poses is None:
            raise ValueError("init 'given' needs init_poses")
        start = None if init == "odometry" or init_poses is None else init_poses[:n]
        out = _run_batch(builder, lm, start, marginals, progress, joint_stride)
    elif backend == "fixedlag":
        out = _run_fixedlag(builder, fl, isam2, marginals, progress)
    else:
        out = _run_isam2(builder, isam2, marginals, progress)
    return GraphResult(
        scenario=log.scenario,
        seed=log.seed,
        backend=backend,
        fusion=opts.fusion,
        association=label,
        poses=out.poses,
        covs=out.covs,
        filtered_poses=out.filtered_poses,
        filtered_covs=out.filtered_covs,
        step_time_s=out.step_time_s,
        build_time_s=out.build_time_s,
        solve_time_s=out.solve_time_s,
        marginals_time_s=out.marginals_time_s,
        total_time_s=time.perf_counter() - t_start,
        total_cpu_s=time.process_time() - cpu_start,
        anchor=out.anchor,
        landmarks=out.landmarks,
        obs_landmark=builder.obs_landmark.copy(),
        n_factors=int(out.graph.size()),
        n_variables=int(out.values.size()),
        final_error=float(out.graph.error(out.values)),
        lm=out.lm,
        extra=out.extra,
        joint_pose_cov=out.joint_pose_cov,
        ccda_reasons=(
            dict(pre_reasons)
            if pre_reasons is not None
            else dict(builder.ccda_reasons)
            if association == "own" and associations is None
            else None
        ),
        step_cpu_s=out.step_cpu_s,
        graph=out.graph,
        values=out.values,
        initial=out.initial,
    )


def _arrays_of(builder: GraphBuilder) -> tuple[np.ndarray, np.ndarray]:
    """Association decisions of a finished builder as (obs_landmark, obs_known_id)."""
    lm = builder.obs_landmark.copy()
    known = builder.landmark_known_ids()
    kn = np.where(lm >= 0, known[np.clip(lm, 0, None)] if known.size else -1, -1)
    return lm, np.asarray(kn, dtype=np.int64)
