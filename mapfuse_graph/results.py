"""What a graph solver returns (:class:`GraphResult` and its parts) and how poses,
landmarks and the anchor are read off a solution."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np

from mapfuse_core.estimate.decisions import AnchorDecision, AssociationDecisions
from mapfuse_core.evaluation.labels import landmark_labels
from mapfuse_core.geometry.features import FeatureKind, line_from_normal
from mapfuse_core.geometry.se2 import FloatArray, inverse_jacobian
from mapfuse_graph.builder import GraphBuilder
from mapfuse_graph.factors import pose_of
from mapfuse_graph.keys import anchor_key, key_map, landmark_key, pose_key, radius_key
from mapfuse_graph.marginals import _body_to_abs, body_to_abs_cov

__all__ = ["GraphAnchor", "GraphLandmarks", "GraphResult", "JointPoseCovariance", "LMReport"]


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
class GraphAnchor:
    """The pose of ``Wglobal`` in the known map, as :class:`ekf_reference.AnchorResult`."""

    x_Wknown_Wglobal: FloatArray
    """(3,) pose of ``Wglobal`` in ``Wknown`` (inverse of the graph's ``A = x^Wglobal_Wknown``)."""
    cov: FloatArray
    """(3, 3) its absolute covariance."""
    accepted_at_step: int
    """Step at which the anchor entered the graph."""
    source: str
    """Where its initial value came from: ``"ekf"``, ``"fit"`` (truth pairings), ``"ccda"``,
    ``"given"``."""
    pairings: tuple[tuple[int, int], ...]
    """(true world id of the landmark or −1, known-map id) per tie: the id most of the
    landmark's observations carry (:func:`~mapfuse_core.evaluation.landmark_labels`)."""


@dataclass(frozen=True)
class GraphLandmarks:
    """The estimated landmarks in ``Wglobal``."""

    kinds: np.ndarray
    """(L,) int8 feature kinds."""
    params: FloatArray
    """(L, 3) SPmap lines (origin at the mean foot of their observations) / circles."""
    covs: FloatArray
    """(L, 3, 3) covariance of :attr:`params` (lines: zero along the line)."""
    variables: FloatArray
    """(L, 3) the graph variables: ``(ρ, α, NaN)`` for lines, ``(x, y, r)`` for circles."""
    known_ids: np.ndarray
    """(L,) known-map id each landmark is tied to, −1 if none."""
    true_ids: np.ndarray
    """(L,) world id of each landmark's first observation (−1 unknown)."""
    n_obs: np.ndarray
    """(L,) observations per landmark."""


@dataclass(frozen=True)
class JointPoseCovariance:
    """Smoothed joint covariance of a subset of the poses (batch, ``joint_stride``)."""

    steps: np.ndarray
    """(T,) the steps, ascending."""
    cov: FloatArray
    """(3T, 3T) joint covariance of their absolute ``(x, y, θ)`` errors, pose by pose:
    block ``(i, i)`` is ``covs[steps[i]]``."""


@dataclass(frozen=True)
class GraphResult:
    """Result of :func:`run_graph`."""

    scenario: str
    """Scenario name of the log."""
    seed: int
    """Seed of the log."""
    backend: str
    """``"batch"``, ``"isam2"`` or ``"fixedlag"``."""
    fusion: bool
    """Whether the known map was fused."""
    association: str
    """Association source used."""
    poses: FloatArray
    """(N, 3) final (smoothed) pose ``x^Wglobal_R`` of every step (fixedlag: each pose as
    it left the window, see :mod:`mapfuse_graph.fixedlag`)."""
    covs: FloatArray
    """(N, 3, 3) smoothed marginal covariances, absolute ``(x, y, θ)`` (NaN if not computed;
    fixedlag: the marginal of :attr:`poses` when it was read)."""
    filtered_poses: FloatArray | None
    """(N, 3) iSAM2 and fixedlag: estimate of ``X_k`` right after update ``k`` (uses steps 0..k):
    its linearisation point moved by the exact solution of that update's linear system."""
    filtered_covs: FloatArray | None
    """(N, 3, 3) iSAM2 and fixedlag: its absolute covariance."""
    step_time_s: FloatArray
    """(N,) iSAM2, fixedlag: wall time of each step (build + update + filtered estimate and
    marginal).  Batch: each step's build time plus an equal share of the solve and the
    marginals, so that the sum is the run's cost (per-step percentiles are meaningless)."""
    build_time_s: float
    """Validation and factor construction (batch); included in step times for iSAM2."""
    solve_time_s: float
    """Optimisation time: LM for batch; the extra final updates for iSAM2."""
    marginals_time_s: float
    """Time spent on the final smoothed marginals."""
    total_time_s: float
    """Wall time of the whole :func:`run_graph` call."""
    total_cpu_s: float
    """CPU time of this process during the call (robust to other load on the machine)."""
    anchor: GraphAnchor | None
    """The anchor, or ``None`` without fusion or if it never entered the graph."""
    landmarks: GraphLandmarks
    """Final landmark estimates."""
    obs_landmark: np.ndarray
    """(M,) dense landmark index of every logged observation, −1 if not in the graph."""
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
    ccda_reasons: dict[str, int] | None = None
    """``association="own"``: CCDA calls per outcome (a
    :data:`~mapfuse_core.matching.ccda.REASONS` entry, or ``"anchor refused"`` for an
    accepted match the anchor check turned down); ``None`` with any other association."""
    step_cpu_s: FloatArray | None = None
    """(N,) iSAM2 and fixedlag: CPU time of this process in each step (the same span as
    :attr:`step_time_s`); unlike wall time, it does not grow with other load on the
    machine."""
    graph: gtsam.NonlinearFactorGraph | None = field(default=None, compare=False, repr=False)
    """The final nonlinear factor graph, to optimise with another solver or export
    (:mod:`mapfuse_graph.export`); its keys are named by :attr:`keys`.  The observation
    and tie factors are Python ``CustomFactor`` objects: GTSAM's serialisation and
    ``writeG2o`` cannot hold them."""
    values: gtsam.Values | None = field(default=None, compare=False, repr=False)
    """The final estimate of every variable."""
    initial: gtsam.Values | None = field(default=None, compare=False, repr=False)
    """The values the solver started from (batch: Levenberg–Marquardt's start; iSAM2
    and fixed-lag: each variable's value when it was added)."""

    @property
    def keys(self) -> dict[str, str]:
        """``{symbol: what it is}`` of every variable (:func:`mapfuse_graph.keys.key_map`)."""
        if self.values is None:
            return {}
        return key_map(self.values)

    @property
    def obs_known_id(self) -> np.ndarray:
        """(M,) known-map id of every observation's landmark, −1 if none (or not in the graph)."""
        lm, known = self.obs_landmark, self.landmarks.known_ids
        if not known.size:
            return np.full(lm.shape, -1, dtype=np.int64)
        return np.asarray(np.where(lm >= 0, known[np.clip(lm, 0, None)], -1), dtype=np.int64)

    @property
    def decisions(self) -> AssociationDecisions:
        """The association decisions the graph was built with, and its anchor."""
        anchor = None
        if self.anchor is not None:
            anchor = AnchorDecision(self.anchor.x_Wknown_Wglobal, self.anchor.accepted_at_step)
        return AssociationDecisions(self.obs_landmark, self.obs_known_id, anchor)


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
    """(N,) per-step wall time (see :attr:`GraphResult.step_time_s`)."""
    build_time_s: float
    """Factor construction time outside the steps (batch), else 0."""
    solve_time_s: float
    """Optimisation time."""
    marginals_time_s: float
    """Final marginals time."""
    anchor: GraphAnchor | None
    """The anchor estimate."""
    landmarks: GraphLandmarks
    """The landmark estimates."""
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
) -> GraphLandmarks:
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
    return GraphLandmarks(
        kinds=kinds,
        params=params,
        covs=covs,
        variables=variables,
        known_ids=builder.landmark_known_ids(),
        true_ids=np.asarray(true_first, dtype=np.int64),
        n_obs=builder.landmark_n_obs(),
    )


def _anchor(
    builder: GraphBuilder, values: gtsam.Values, cov_of: Callable[[int], FloatArray] | None
) -> GraphAnchor | None:
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
    return GraphAnchor(
        x_Wknown_Wglobal=x,
        cov=J @ P @ J.T,
        accepted_at_step=builder.anchor_step,
        source=builder.anchor_source,
        pairings=pairings,
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
