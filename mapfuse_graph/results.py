"""What a graph run reports beyond the :class:`~mapfuse_core.estimate.EstimatorResult`
every estimator returns (:class:`GraphDetails`), and how poses, landmarks and the anchor
are read off a solution."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np

from mapfuse_core.estimate import Anchor, MapEstimate
from mapfuse_core.evaluation.labels import landmark_labels
from mapfuse_core.geometry.features import FeatureKind, line_from_normal
from mapfuse_core.geometry.se2 import FloatArray, inverse_jacobian
from mapfuse_graph.builder import GraphBuilder
from mapfuse_graph.factors import pose_of
from mapfuse_graph.keys import anchor_key, key_map, landmark_key, pose_key, radius_key
from mapfuse_graph.marginals import _body_to_abs, body_to_abs_cov

__all__ = ["GraphDetails", "JointPoseCovariance", "LMReport"]


@dataclass(frozen=True)
class LMReport:
    """How a Levenberg–Marquardt run went."""

    iterations: int
    """Outer iterations (linearisations) done."""
    initial_error: float
    """``graph.error`` (½ Σ whitened residual²) at the initial values."""
    final_error: float
    """``graph.error`` at the solution."""
    converged: bool
    """True if a tolerance was met (not the iteration or λ limit)."""
    final_lambda: float
    """λ at the end."""


@dataclass(frozen=True)
class JointPoseCovariance:
    """Smoothed joint covariance of a subset of the poses (batch, ``joint_stride``)."""

    steps: np.ndarray
    """(T,) the steps, ascending."""
    cov: FloatArray
    """(3T, 3T) joint covariance of their absolute ``(x, y, θ)`` errors, pose by pose:
    block ``(i, i)`` is ``covs[steps[i]]``."""


@dataclass(frozen=True, eq=False)
class GraphDetails:
    """What only a graph backend reports, beside its
    :class:`~mapfuse_core.estimate.EstimatorResult` (``result.details``)."""

    build_time_s: float
    """Validation and factor construction (batch); included in step times for iSAM2."""
    solve_time_s: float
    """Optimisation time: LM for batch; the extra final updates for iSAM2."""
    marginals_time_s: float
    """Time spent on the final smoothed marginals."""
    total_time_s: float
    """Wall time of the whole :func:`~mapfuse_graph.solvers.run_graph` call."""
    total_cpu_s: float
    """CPU time of this process during the call (robust to other load on the machine)."""
    landmark_variables: FloatArray
    """(L, 3) the graph variables of the result's map features, in order: ``(ρ, α, NaN)``
    for lines, ``(x, y, r)`` for circles."""
    n_factors: int
    """Factors in the final graph."""
    n_variables: int
    """Variables in the final graph."""
    final_error: float
    """``graph.error`` at the final estimate."""
    lm: LMReport | None = None
    """Batch only: the Levenberg–Marquardt report."""
    extra: dict[str, Any] = field(default_factory=dict)
    """Diagnostics (e.g. iSAM2 relinearisation counts)."""
    joint_pose_cov: JointPoseCovariance | None = None
    """Batch with ``joint_stride``: the joint covariance of every ``joint_stride``-th pose,
    for consistency statistics that need it (``evaluation.nees_mean_distribution``)."""
    step_cpu_s: FloatArray | None = None
    """(N,) iSAM2 and fixedlag: CPU time of this process in each step (the same span as
    the result's ``step_time_s``); unlike wall time, it does not grow with other load on
    the machine."""
    graph: gtsam.NonlinearFactorGraph | None = field(default=None, repr=False)
    """The final nonlinear factor graph, to optimise with another solver or export
    (:mod:`mapfuse_graph.export`); its keys are named by :attr:`keys`.  The observation
    and tie factors are Python ``CustomFactor`` objects: GTSAM's serialisation and
    ``writeG2o`` cannot hold them."""
    values: gtsam.Values | None = field(default=None, repr=False)
    """The final estimate of every variable."""
    initial: gtsam.Values | None = field(default=None, repr=False)
    """The values the solver started from (batch: Levenberg–Marquardt's start; iSAM2
    and fixed-lag: each variable's value when it was added)."""

    @property
    def keys(self) -> dict[str, str]:
        """``{symbol: what it is}`` of every variable (:func:`mapfuse_graph.keys.key_map`)."""
        if self.values is None:
            return {}
        return key_map(self.values)


@dataclass(frozen=True, eq=False)
class _Solved:
    """What one solver pass hands back to :func:`run_graph`."""

    graph: gtsam.NonlinearFactorGraph
    """The final nonlinear graph."""
    values: gtsam.Values
    """The final estimate."""
    poses: FloatArray
    """(N, 3) smoothed poses."""
    covs: FloatArray
    """(N, 3, 3) their absolute covariances (NaN without marginals)."""
    filtered_poses: FloatArray | None
    """(N, 3) per-step filtered poses (iSAM2), else ``None``."""
    filtered_covs: FloatArray | None
    """(N, 3, 3) their covariances (iSAM2), else ``None``."""
    step_time_s: FloatArray
    """(N,) per-step wall time (the result's ``step_time_s``)."""
    build_time_s: float
    """Factor construction time outside the steps (batch), else 0."""
    solve_time_s: float
    """Optimisation time."""
    marginals_time_s: float
    """Final marginals time."""
    anchor: Anchor | None
    """The anchor estimate."""
    landmarks: MapEstimate
    """The landmark estimates."""
    variables: FloatArray
    """(L, 3) the landmarks' graph variables (:attr:`GraphDetails.landmark_variables`)."""
    lm: LMReport | None
    """Batch: the Levenberg–Marquardt report."""
    extra: dict[str, Any]
    """Diagnostics."""
    joint_pose_cov: JointPoseCovariance | None = None
    """Batch with ``joint_stride``: the joint pose covariance."""
    step_cpu_s: FloatArray | None = None
    """(N,) per-step CPU time (iSAM2, fixedlag), else ``None``."""
    initial: gtsam.Values | None = None
    """The values the solver started from."""


def _landmarks(
    builder: GraphBuilder,
    values: gtsam.Values,
    cov_of: Callable[[int], FloatArray] | None,
    poses: FloatArray,
) -> tuple[MapEstimate, FloatArray]:
    """The landmarks of a solution as a map, and their graph variables."""
    log = builder.log
    lms = builder.landmarks
    n = len(lms)
    kinds = builder.landmark_kinds()
    params = np.zeros((n, 3))
    covs = np.full((n, 3, 3), np.nan)
    variables = np.full((n, 3), np.nan)
    # Mean along-line coordinate of each line's observed midpoints (vectorised).
    sel = np.nonzero(builder.obs_landmark >= 0)[0]
    lm_of = builder.obs_landmark[sel]
    X = poses[log.feat_step[sel]]
    z = log.feat_params[sel]
    c, s = np.cos(X[:, 2]), np.sin(X[:, 2])
    px = X[:, 0] + c * z[:, 0] - s * z[:, 1]
    py = X[:, 1] + s * z[:, 0] + c * z[:, 1]
    for i, lmk in enumerate(lms):
        key = landmark_key(i, lmk.kind)
        v = np.asarray(values.atVector(key), dtype=float)
        P = cov_of(key) if cov_of is not None else np.full((v.size, v.size), np.nan)
        if builder.split_circles and lmk.kind == FeatureKind.CIRCLE:
            # Centre and radius are independent: their joint covariance is block-diagonal.
            r = np.asarray(values.atVector(radius_key(i)), dtype=float)
            Pr = cov_of(radius_key(i)) if cov_of is not None else np.full((1, 1), np.nan)
            v = np.concatenate([v, r])
            P = np.block([[P, np.zeros((2, 1))], [np.zeros((1, 2)), Pr]])
        variables[i, : v.size] = v
        if lmk.kind == FeatureKind.CIRCLE:
            params[i], covs[i] = v, P
            continue
        mine = lm_of == i
        t = (
            float(np.mean(-px[mine] * math.sin(v[1]) + py[mine] * math.cos(v[1])))
            if np.any(mine)
            else 0.0
        )
        f, J = line_from_normal(float(v[0]), float(v[1]), t)
        params[i] = f
        covs[i] = J[:, :2] @ P @ J[:, :2].T
    true_first = log.feat_true_id[builder.landmark_first_obs()] if n else np.zeros(0, np.int64)
    landmarks = MapEstimate(
        kinds=kinds,
        params=params,
        covs=covs,
        known_ids=builder.landmark_known_ids(),
        true_ids=np.asarray(true_first, dtype=np.int64),
        n_obs=builder.landmark_n_obs(),
    )
    return landmarks, variables


def _anchor(
    builder: GraphBuilder, values: gtsam.Values, cov_of: Callable[[int], FloatArray] | None
) -> Anchor | None:
    if not builder.anchor_added or not values.exists(anchor_key()):
        return None
    A = pose_of(values.atPose2(anchor_key()))
    P = (
        body_to_abs_cov(cov_of(anchor_key()), A[2])
        if cov_of is not None
        else np.full((3, 3), np.nan)
    )
    x, J = inverse_jacobian(A)
    log = builder.log
    labels = landmark_labels(
        builder.obs_landmark, log.feat_true_id, [i for i, _ in builder.pairings]
    )
    pairings = tuple(
        (label, int(builder.known.ids[r]))
        for (_, r), label in zip(builder.pairings, labels, strict=True)
    )
    return Anchor(
        x_Wknown_Wglobal=x,
        cov=J @ P @ J.T,
        accepted_at_step=builder.anchor_step,
        pairings=pairings,
        source=builder.anchor_source,
    )


def _poses_from(values: gtsam.Values, n: int) -> FloatArray:
    return np.array([pose_of(values.atPose2(pose_key(k))) for k in range(n)]).reshape(n, 3)


def _pose_covs(poses: FloatArray, cov_of: Callable[[int], FloatArray] | None) -> FloatArray:
    n = poses.shape[0]
    if cov_of is None:
        return np.full((n, 3, 3), np.nan)
    P = np.array([cov_of(pose_key(k)) for k in range(n)]).reshape(n, 3, 3)
    G = _body_to_abs(poses[:, 2])
    out: FloatArray = G @ P @ G.transpose(0, 2, 1)
    return 0.5 * (out + out.transpose(0, 2, 1))
