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
  estimate and covariance (comparable with the EKF's) are the last rows of the root
  clique (:func:`_newest_pose_marginal`); at the end a few extra updates finish
  relinearisation and all smoothed marginals are read in one pass
  (:func:`tree_marginals`).

Covariances: GTSAM's Pose2 marginals are in the body tangent (``X ⊕ Exp(δ)``);
mapfuse reports absolute ``(x, y, θ)`` covariances, ``G P Gᵀ`` with
``G = blockdiag(R(θ), 1)`` (:func:`body_to_abs_cov`).

Entry point: :func:`run_graph`.  One module although long: both solvers share the
Bayes-tree marginal readers and the pose, landmark and anchor extraction.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import gtsam
import numpy as np

from mapfuse_core.decisions import AnchorDecision, AssociationDecisions
from mapfuse_core.features import FeatureKind, line_from_normal
from mapfuse_core.measlog import MeasurementLog
from mapfuse_core.se2 import FloatArray, inverse_jacobian
from mapfuse_graph.factors import pose_of
from mapfuse_graph.graph import (
    ASSOCIATIONS,
    GraphBuilder,
    GraphOptions,
    anchor_key,
    landmark_key,
    pose_key,
    radius_key,
)
from mapfuse_graph.keys import key_map

__all__ = [
    "BACKENDS",
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

BACKENDS: tuple[str, ...] = ("batch", "isam2")
Backend = Literal["batch", "isam2"]


@dataclass(frozen=True)
class LMOptions:
    """Levenberg–Marquardt settings of the batch solver."""

    max_iterations: int = 100
    """Most outer iterations (linearisations)."""
    lambda_initial: float = 1e-5
    """Initial damping λ (added as ``λ·I`` to the Gauss–Newton Hessian)."""
    lambda_factor: float = 10.0
    """λ is divided by this after an accepted step and multiplied after a rejected one."""
    lambda_bounds: tuple[float, float] = (1e-12, 1e10)
    """λ is kept within these; reaching the upper bound ends the run (no descent left)."""
    relative_error_tol: float = 1e-9
    """Stop when an accepted step lowers the error by less than this fraction."""
    absolute_error_tol: float = 1e-9
    """Stop when an accepted step lowers the error by less than this."""

    def __post_init__(self) -> None:
        if self.max_iterations < 1 or not self.lambda_factor > 1.0:
            raise ValueError("max_iterations must be >= 1 and lambda_factor > 1")
        lo, hi = self.lambda_bounds
        if not 0.0 < lo <= self.lambda_initial <= hi:
            raise ValueError("need 0 < lambda_bounds[0] <= lambda_initial <= lambda_bounds[1]")


_DIMS = {"x": 3, "l": 2, "c": 3, "k": 2, "q": 3, "a": 3}
_DEFAULT_THRESHOLDS: dict[str, tuple[float, ...]] = {
    "x": (0.05, 0.05, 0.005),
    "l": (0.05, 0.005),
    "c": (0.05, 0.05, 0.05),
    "k": (0.05, 0.005),
    "q": (0.05, 0.05, 0.05),
    "a": (0.05, 0.05, 0.005),
}


@dataclass(frozen=True)
class ISAM2Options:
    """iSAM2 settings."""

    relinearize_threshold: float | dict[str, tuple[float, ...]] = field(
        default_factory=lambda: dict(_DEFAULT_THRESHOLDS)
    )
    """Relinearise a variable when any entry of its linear delta exceeds this: one float
    for all, or per symbol character (``x`` poses, ``l``/``c`` line/circle landmarks,
    ``k``/``q`` known lines/circles, ``a`` the anchor) a tuple of the variable's
    dimension.  The defaults (5 cm, 5 mrad) keep the final estimate close to the batch
    optimum while relinearising far fewer variables than 0.01 for all
    (``docs/performance.md``): a line landmark seen from hundreds of poses costs
    hundreds of Python callbacks each time it is relinearised.  With
    ``GraphOptions.split_circles`` the ``c`` entries ``(x, y, r)`` go to the centre and
    the radius variables."""
    relinearize_skip: int = 1
    """Check for relinearisation every this many updates."""
    factorization: str = "CHOLESKY"
    """``"CHOLESKY"`` (faster) or ``"QR"`` (more robust to ill conditioning)."""
    final_updates: int = 5
    """Extra empty updates at the end so the final estimate is fully relinearised."""
    final_marginals: str = "isam2"
    """Smoothed marginals of iSAM2's own linear system (``"isam2"``: the graph linearised
    at iSAM2's linearisation point, whose marginals are those of its Bayes tree; close
    to, not equal to, the exact ones because a variable's linearisation point may lag
    its estimate by up to the relinearisation threshold) or of a fresh linearisation at the
    final estimate (``"relinearized"``: exact, one more pass of the Python callbacks).
    Both are read by :func:`tree_marginals`."""

    def __post_init__(self) -> None:
        th = self.relinearize_threshold
        if isinstance(th, dict):
            for ch, v in th.items():
                if ch not in _DIMS or len(v) != _DIMS[ch] or not all(t > 0 for t in v):
                    raise ValueError(
                        f"relinearize_threshold[{ch!r}] must be {_DIMS.get(ch, '?')} positive "
                        f"values for a symbol among {', '.join(_DIMS)}, got {v!r}"
                    )
        elif not th > 0:
            raise ValueError("relinearize_threshold must be > 0")
        if self.relinearize_skip < 1:
            raise ValueError("relinearize_skip must be >= 1")
        if self.factorization not in ("CHOLESKY", "QR"):
            raise ValueError(f"factorization must be CHOLESKY or QR, got {self.factorization!r}")
        if self.final_updates < 0:
            raise ValueError("final_updates must be >= 0")
        if self.final_marginals not in ("isam2", "relinearized"):
            raise ValueError(
                f"final_marginals must be 'isam2' or 'relinearized', got {self.final_marginals!r}"
            )


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
    """(true world id of the landmark's first observation or −1, known-map id) per tie."""


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
    """``"batch"`` or ``"isam2"``."""
    fusion: bool
    """Whether the known map was fused."""
    association: str
    """Association source used."""
    poses: FloatArray
    """(N, 3) final (smoothed) pose ``x^Wglobal_R`` of every step."""
    covs: FloatArray
    """(N, 3, 3) smoothed marginal covariances, absolute ``(x, y, θ)`` (NaN if not computed)."""
    filtered_poses: FloatArray | None
    """(N, 3) iSAM2 only: estimate of ``X_k`` right after update ``k`` (uses steps 0..k):
    its linearisation point moved by the exact solution of that update's linear system."""
    filtered_covs: FloatArray | None
    """(N, 3, 3) iSAM2 only: its absolute covariance."""
    step_time_s: FloatArray
    """(N,) iSAM2: wall time of each step (build + update + filtered estimate and
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
    graph: gtsam.NonlinearFactorGraph | None = field(default=None, compare=False, repr=False)
    """The final nonlinear factor graph, to optimise with another solver or export
    (:mod:`mapfuse_graph.export`); its keys are named by :attr:`keys`.  The observation
    and tie factors are Python ``CustomFactor`` objects: GTSAM's serialisation and
    ``writeG2o`` cannot hold them."""
    values: gtsam.Values | None = field(default=None, compare=False, repr=False)
    """The final estimate of every variable."""
    initial: gtsam.Values | None = field(default=None, compare=False, repr=False)
    """The values the solver started from (batch: Levenberg–Marquardt's start; iSAM2:
    each variable's value when it was added)."""

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
    initial: gtsam.Values | None = None
    """The values the solver started from."""


# --------------------------------------------------------------------------- helpers


def _body_to_abs(thetas: FloatArray) -> FloatArray:
    """(k, 3, 3) ``G`` of each heading: a body-tangent perturbation is ``G δ`` absolute."""
    G = np.zeros((thetas.size, 3, 3))
    c, s = np.cos(thetas), np.sin(thetas)
    G[:, 0, 0], G[:, 0, 1], G[:, 1, 0], G[:, 1, 1], G[:, 2, 2] = c, -s, s, c, 1.0
    return G


def body_to_abs_cov(P_body: FloatArray, theta: float) -> FloatArray:
    """Pose2 covariance in GTSAM's body tangent → absolute ``(x, y, θ)``: ``G P Gᵀ``."""
    G = _body_to_abs(np.array([theta]))[0]
    out: FloatArray = G @ P_body @ G.T
    return 0.5 * (out + out.T)


def _joint_pose_cov(
    marginals: gtsam.Marginals, poses: FloatArray, stride: int
) -> JointPoseCovariance:
    """Every ``stride``-th pose from step ``stride`` on (step 0 is held by its prior)."""
    steps = np.arange(stride, poses.shape[0], stride, dtype=np.int64)
    keys = gtsam.KeyVector([pose_key(int(k)) for k in steps])
    P = np.asarray(marginals.jointMarginalCovariance(keys).fullMatrix(), dtype=float)
    # GTSAM orders the blocks as the keys were given; body tangent -> absolute per pose.
    G = _body_to_abs(poses[steps, 2])
    n = steps.size
    out = np.einsum("sab,sbtc,tdc->satd", G, P.reshape(n, 3, n, 3), G).reshape(3 * n, 3 * n)
    return JointPoseCovariance(steps=steps, cov=0.5 * (out + out.T))


class _ValuesEstimate:
    """The builder's view of a ``Values`` being assembled (batch initial values)."""

    def __init__(self, values: gtsam.Values) -> None:
        self.values = values

    def pose(self, k: int) -> FloatArray:
        return pose_of(self.values.atPose2(pose_key(k)))

    def vector(self, key: int) -> FloatArray:
        return np.asarray(self.values.atVector(key), dtype=float)

    def anchor(self) -> FloatArray:
        return pose_of(self.values.atPose2(anchor_key()))

    def pose_cov(self, k: int) -> FloatArray | None:
        return None

    def cov(self, key: int) -> FloatArray | None:
        return None


class _ISAM2Estimate:
    """The builder's view of iSAM2's current estimate."""

    def __init__(self, isam: gtsam.ISAM2, filtered_covs: FloatArray) -> None:
        self.isam = isam
        self.filtered_covs = filtered_covs
        self.last_pose: tuple[int, FloatArray] = (-1, np.zeros(3))

    def pose(self, k: int) -> FloatArray:
        if k == self.last_pose[0]:
            return self.last_pose[1]
        return pose_of(self.isam.calculateEstimatePose2(pose_key(k)))

    def vector(self, key: int) -> FloatArray:
        return np.asarray(self.isam.calculateEstimateVector(key), dtype=float)

    def anchor(self) -> FloatArray:
        return pose_of(self.isam.calculateEstimatePose2(anchor_key()))

    def pose_cov(self, k: int) -> FloatArray | None:
        return np.asarray(self.filtered_covs[k])

    def cov(self, key: int) -> FloatArray | None:
        return np.asarray(self.isam.marginalCovariance(key), dtype=float)


def _key_dims(values: gtsam.Values) -> list[tuple[int, int]]:
    zero = values.zeroVectors()
    return [(int(k), int(zero.at(k).shape[0])) for k in list(values.keys())]


def tree_marginals(lin: gtsam.GaussianFactorGraph, dims: dict[int, int]) -> dict[int, FloatArray]:
    """Marginal covariance of every variable of the linear system ``lin`` (tangent space).

    ``dims`` maps each key to its tangent dimension.  One multifrontal elimination, then
    one pass down the Bayes tree: a clique's conditional ``R δ_F + S δ_S = d`` (whitened)
    and the joint covariance ``Σ_SS`` of its separator, taken from its parent's joint
    covariance, give ``Σ_FS = −R⁻¹ S Σ_SS`` and ``Σ_FF = R⁻¹ R⁻ᵀ − Σ_FS (R⁻¹ S)ᵀ``.
    Exact, like ``gtsam.Marginals``, but each clique is handled once: asking GTSAM for
    every variable's ``marginalCovariance`` re-eliminates the clique's conditional with
    its separator marginal for each variable, which costs an order of magnitude more
    where separators reach a few hundred dimensions (Victoria Park;
    ``docs/performance.md``).
    """
    out: dict[int, FloatArray] = {}
    bt = lin.eliminateMultifrontal()
    roots = bt.roots()
    # (clique, offset of each key in the parent's joint covariance, that covariance)
    stack: list[tuple[Any, dict[int, int], FloatArray]] = [
        (roots[i], {}, np.zeros((0, 0))) for i in range(len(roots))
    ]
    while stack:
        clique, parent_at, parent_cov = stack.pop()
        cond = clique.conditional()
        keys = list(map(int, cond.keys()))
        Ab = np.asarray(cond.augmentedJacobian())  # whitened [R S d]
        nf = Ab.shape[0]  # R is square: one row per frontal dimension
        Rinv = np.linalg.inv(Ab[:, :nf])
        n_front, width = 0, 0
        while width < nf:
            width += dims[keys[n_front]]
            n_front += 1
        seps = keys[n_front:]
        n_children = clique.nrChildren()
        # Leaves need their frontal block only; parents the whole joint for their children.
        size = Ab.shape[1] - 1 if n_children else nf
        joint = np.empty((size, size))
        if seps:
            idx = [i for k in seps for i in range(parent_at[k], parent_at[k] + dims[k])]
            cov_ss = parent_cov[idx][:, idx]
            G = Rinv @ Ab[:, nf:-1]
            cov_fs = -G @ cov_ss
            joint[:nf, :nf] = Rinv @ Rinv.T - cov_fs @ G.T
            if n_children:
                joint[:nf, nf:] = cov_fs
                joint[nf:, :nf] = cov_fs.T
                joint[nf:, nf:] = cov_ss
        else:
            joint[:nf, :nf] = Rinv @ Rinv.T
        at = 0
        for k in keys[:n_front]:
            d = dims[k]
            block = joint[at : at + d, at : at + d]
            out[k] = 0.5 * (block + block.T)
            at += d
        if n_children == 0:
            continue
        key_at: dict[int, int] = {}
        at = 0
        for k in keys:
            key_at[k] = at
            at += dims[k]
        stack.extend((clique[i], key_at, joint) for i in range(n_children))
    return out


def levenberg_marquardt(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    options: LMOptions | None = None,
    error_from_linearization: bool = False,
) -> tuple[gtsam.Values, LMReport]:
    """Levenberg–Marquardt driven from Python (no per-callback ``Values`` copies).

    Each outer iteration linearises once; inner iterations add ``√λ·I`` rows per
    variable to a copy of the linear system, solve it (multifrontal, COLAMD ordering
    computed once), retract and accept the step if the error decreases.

    ``error_from_linearization=True`` takes the error of a candidate from its own
    linearisation (``½‖b‖²`` of the whitened system, exact for Gaussian noise models,
    *not* for robust ones) instead of a separate ``graph.error`` pass: an accepted
    candidate's linearisation is the next iteration's system, so every Python
    callback runs once per iteration instead of twice.
    """
    out, report, _ = _levenberg_marquardt(graph, values, options, error_from_linearization)
    return out, report


def _levenberg_marquardt(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    options: LMOptions | None,
    error_from_linearization: bool,
) -> tuple[gtsam.Values, LMReport, gtsam.GaussianFactorGraph | None]:
    """:func:`levenberg_marquardt`, also returning the linearisation at the result if made."""
    opts = options or LMOptions()
    lam_lo, lam_hi = opts.lambda_bounds
    dims = _key_dims(values)
    eyes = {d: np.eye(d) for _, d in dims}
    zeros = {d: np.zeros(d) for _, d in dims}
    unit = {d: gtsam.noiseModel.Unit.Create(d) for _, d in dims}
    zero_delta = values.zeroVectors()

    def evaluate(v: gtsam.Values) -> tuple[float, gtsam.GaussianFactorGraph | None]:
        if error_from_linearization:
            lin_v = graph.linearize(v)
            return float(lin_v.error(zero_delta)), lin_v
        return float(graph.error(v)), None

    err, lin = evaluate(values)
    err0 = err
    lam = opts.lambda_initial
    ordering = None
    converged = False
    it = 0
    while it < opts.max_iterations:
        it += 1
        if lin is None:
            lin = graph.linearize(values)
        if ordering is None:
            ordering = gtsam.Ordering.ColamdGaussianFactorGraph(lin)
        accepted = False
        while True:
            damped = lin.clone()
            sq = math.sqrt(lam)
            for key, d in dims:
                damped.add(key, sq * eyes[d], zeros[d], unit[d])
            try:
                delta = damped.optimize(ordering)
                new_values = values.retract(delta)
                new_err, new_lin = evaluate(new_values)
            except RuntimeError:
                new_err, new_lin = math.inf, None
            if math.isfinite(new_err) and new_err <= err:
                accepted = True
                break
            if lam >= lam_hi:
                break
            lam = min(lam * opts.lambda_factor, lam_hi)
        if not accepted:
            converged = True  # no descent direction left at any damping: a minimum
            break
        decrease = err - new_err
        values, err, lin = new_values, new_err, new_lin
        lam = max(lam / opts.lambda_factor, lam_lo)
        if decrease <= opts.absolute_error_tol or decrease <= opts.relative_error_tol * err:
            converged = True
            break
    return values, LMReport(it, err0, err, converged, lam), lin


# --------------------------------------------------------------------------- results


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
    pairings = tuple(
        (int(log.feat_true_id[builder.landmarks[i].first_obs]), int(builder.known.ids[r]))
        for i, r in builder.pairings
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


# --------------------------------------------------------------------------- runs


def _run_batch(
    builder: GraphBuilder,
    lm: LMOptions | None,
    init_poses: FloatArray | None,
    marginals: bool,
    progress: Callable[[int, int], None] | None,
    joint_stride: int | None = None,
) -> _Solved:
    n = builder.n_steps
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    est = _ValuesEstimate(values)
    times = np.zeros(n)
    t_build = time.perf_counter()
    for k in range(n):
        t0 = time.perf_counter()
        sg = builder.step(k, est, None if init_poses is None else init_poses[k])
        graph.push_back(sg.factors)
        values.insert(sg.values)
        times[k] = time.perf_counter() - t0
        if progress is not None:
            progress(k + 1, n)
    build = time.perf_counter() - t_build
    t0 = time.perf_counter()
    exact = builder.options.robust is None
    initial = gtsam.Values(values)
    values, report, lin = _levenberg_marquardt(graph, values, lm, exact)
    solve = time.perf_counter() - t0
    t0 = time.perf_counter()
    cov_of: Callable[[int], FloatArray] | None = None
    poses = _poses_from(values, n)
    extra: dict[str, Any] = {}
    joint: JointPoseCovariance | None = None
    if marginals:
        # Marginals on the final linearisation, called from Python: no Values copies.
        m = gtsam.Marginals(lin if lin is not None else graph.linearize(values), values)
        cov_of = m.marginalCovariance
        if joint_stride is not None:
            joint = _joint_pose_cov(m, poses, joint_stride)
    covs = _pose_covs(poses, cov_of)
    landmarks = _landmarks(builder, values, cov_of, poses)
    anchor = _anchor(builder, values, cov_of)
    marg = time.perf_counter() - t0
    # Spread the solve over the steps so that the per-step times add up to the run's
    # cost (metrics.json's runtime total); their percentiles mean nothing for batch.
    times = times + (solve + marg) / n
    return _Solved(
        graph=graph,
        values=values,
        poses=poses,
        covs=covs,
        filtered_poses=None,
        filtered_covs=None,
        step_time_s=times,
        build_time_s=build,
        solve_time_s=solve,
        marginals_time_s=marg,
        anchor=anchor,
        landmarks=landmarks,
        lm=report,
        extra=extra,
        joint_pose_cov=joint,
        initial=initial,
    )


def _newest_last(observed: list[int], newest: int) -> gtsam.KeyGroupMap | None:
    """iSAM2 ordering constraint of one update: the keys of its new factors last (GTSAM's
    own default) and, among them, the newest pose the very last.

    The newest pose then ends the root clique's conditional, where its marginal is read
    off the last rows (:class:`_LastVariableMarginal`).  Without it the pose often sits in
    a child of the root, and GTSAM's marginal through a large root clique (hundreds of
    dimensions on Victoria Park) dominates the step's cost.  The groups
    must stay below the number of variables re-eliminated (CCOLAMD's bound), which the
    keys of the new factors are part of: two groups need three such keys.
    """
    if len(observed) < 2:
        return None
    groups = gtsam.KeyGroupMap()
    low = 1 if len(observed) >= 3 else 0
    for key in observed:
        if key != newest:
            groups.insert2(key, low)
    groups.insert2(newest, low + 1)
    return groups


class _LastVariableMarginal:
    """Elimination function for ``ISAM2.marginalFactor(key, ·)`` when ``key`` is the last
    variable of the root clique.

    GTSAM computes the marginal of a root variable by eliminating every other variable
    of the root's conditional, O(D³) in its dimension D.  For the last variable of an
    upper-triangular ``[R | d]`` that marginal is just its last rows ``[R_kk | d_k]``, so
    when GTSAM hands over exactly that case (the root conditional alone, ``key`` last,
    all other keys to eliminate, unit noise) this returns it directly; anything else goes
    to ``gtsam.EliminateQR``.  The conditional it returns for the eliminated keys is the
    root's own: GTSAM's ``marginalMultifrontalBayesNet`` discards that part.
    """

    def __init__(self, key: int, dim: int) -> None:
        self.key, self.dim = key, dim
        self.shortcut = False

    def __call__(self, graph: gtsam.GaussianFactorGraph, ordering: gtsam.Ordering) -> Any:
        if graph.size() == 1:
            f = graph.at(0)
            if isinstance(f, gtsam.GaussianConditional) and f.get_model() is None:
                keys = f.keys()
                d = self.dim
                if keys[-1] == self.key and ordering.size() == len(keys) - 1:
                    R, rhs = f.R(), f.d()  # views into the conditional
                    if R.shape[0] == R.shape[1] == rhs.shape[0] and not R[-d:, :-d].any():
                        self.shortcut = True
                        marginal = gtsam.JacobianFactor(
                            self.key,
                            np.array(R[-d:, -d:]),
                            np.array(rhs[-d:]),
                            gtsam.noiseModel.Unit.Create(d),
                        )
                        return f, marginal
        return gtsam.EliminateQR(graph, ordering)


def _newest_pose_marginal(
    isam: gtsam.ISAM2, linearization_point: gtsam.Values, key: int
) -> tuple[FloatArray, FloatArray, bool]:
    """Filtered estimate and body-tangent covariance of the pose just added, from one
    marginal of iSAM2's Bayes tree; also whether the root shortcut applied.

    The marginal Gaussian ``p(δ_k)`` gives both: its mean is the Gauss–Newton step of
    ``X_k`` and its information the inverse covariance.  Asking instead for
    ``calculateEstimatePose2`` runs the wildfire back-substitution over every clique
    re-eliminated by the update, each step; left alone, the next relinearisation check
    does that once per ``relinearize_skip`` updates.  The mean is the exact linear
    solve, where the wildfire one stops propagating changes below 1e-3 (sub-millimetre
    differences).
    """
    elim = _LastVariableMarginal(key, 3)
    m = isam.marginalFactor(key, elim)
    delta = m.solve(gtsam.VectorValues()).at(key)
    x = pose_of(linearization_point.atPose2(key).retract(delta))
    P: FloatArray = np.linalg.inv(np.asarray(m.information(), dtype=float))
    return x, P, elim.shortcut


def _run_isam2(
    builder: GraphBuilder,
    options: ISAM2Options | None,
    marginals: bool,
    progress: Callable[[int, int], None] | None,
) -> _Solved:
    opts = options or ISAM2Options()
    n = builder.n_steps
    params = gtsam.ISAM2Params()
    th = opts.relinearize_threshold
    if isinstance(th, dict):
        if builder.split_circles and "c" in th:
            # The circle's (x, y, r) thresholds go to its centre and radius variables.
            th = {**th, "c": tuple(th["c"][:2]), "r": tuple(th["c"][2:])}
        tmap = gtsam.ISAM2ThresholdMap()
        for ch, v in th.items():
            tmap.insert((ch, np.asarray(v, dtype=float)))
        params.setRelinearizeThreshold(tmap)
    else:
        params.setRelinearizeThreshold(float(th))
    params.relinearizeSkip = opts.relinearize_skip
    params.setFactorization(opts.factorization)
    isam = gtsam.ISAM2(params)
    # Held for the whole run: callbacks then receive this object, not a deep copy.
    linearization_point = isam.getLinearizationPoint()
    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    f_poses = np.zeros((n, 3))
    f_covs = np.zeros((n, 3, 3))
    est = _ISAM2Estimate(isam, f_covs)
    times = np.zeros(n)
    relin = 0
    shortcuts = 0
    for k in range(n):
        t0 = time.perf_counter()
        sg = builder.step(k, est)
        xk = pose_key(k)
        # Bound to a name first: iterating the temporary KeySet directly segfaults (the
        # binding's iterator does not keep it alive).
        new_keys = sg.factors.keys()
        order = _newest_last([int(key) for key in new_keys], xk)
        res = isam.update(sg.factors, sg.values, [], order)
        relin += int(res.getVariablesRelinearized())
        graph.push_back(sg.factors)
        initial.insert(sg.values)
        x, P, fast = _newest_pose_marginal(isam, linearization_point, xk)
        shortcuts += fast
        f_poses[k] = x
        f_covs[k] = body_to_abs_cov(P, x[2])
        est.last_pose = (k, x)
        times[k] = time.perf_counter() - t0
        if progress is not None:
            progress(k + 1, n)
    t0 = time.perf_counter()
    for _ in range(opts.final_updates):
        isam.update()
    # Full back-substitution: calculateEstimate() stops propagating changes below the
    # wildfire threshold (1e-3), a millimetre-level difference from the batch optimum.
    values = isam.calculateBestEstimate()
    solve = time.perf_counter() - t0
    t0 = time.perf_counter()
    cov_of: Callable[[int], FloatArray] | None = None
    if marginals:
        # iSAM2's linear system is the graph linearised at its linearisation point (each
        # cached linear factor was made at the current values of its keys): its
        # marginals are iSAM2's own, read in one pass instead of one query per variable.
        at = linearization_point if opts.final_marginals == "isam2" else values
        cov_of = tree_marginals(graph.linearize(at), dict(_key_dims(at))).__getitem__
    poses = _poses_from(values, n)
    covs = _pose_covs(poses, cov_of)
    landmarks = _landmarks(builder, values, cov_of, poses)
    anchor = _anchor(builder, values, cov_of)
    marg = time.perf_counter() - t0
    del linearization_point
    extra = {"variables_relinearized": relin, "filtered_marginal_shortcuts": shortcuts}
    return _Solved(
        graph=graph,
        values=values,
        poses=poses,
        covs=covs,
        filtered_poses=f_poses,
        filtered_covs=f_covs,
        step_time_s=times,
        build_time_s=0.0,
        solve_time_s=solve,
        marginals_time_s=marg,
        anchor=anchor,
        landmarks=landmarks,
        lm=None,
        extra=extra,
        initial=initial,
    )


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
    steps: int | None = None,
    init: str = "auto",
    init_poses: FloatArray | None = None,
    marginals: bool = True,
    progress: Callable[[int, int], None] | None = None,
    joint_stride: int | None = None,
) -> GraphResult:
    """Build the factor graph of ``log`` and solve it with ``backend``.

    ``backend``: ``"batch"`` (Levenberg–Marquardt over all steps) or ``"isam2"`` (one
    update per step; also gives per-step filtered estimates).  ``association``:
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
    if backend == "batch" and associations is None and association == "own":
        # Own association is decided against an incremental estimate: run iSAM2 first.
        pre = GraphBuilder(log, opts, decisions, None, steps)
        _run_isam2(pre, isam2, False, None)
        associations = _arrays_of(pre)
        if pre.anchor_added:
            assert pre.anchor_init is not None
            anchor_given = (pre.anchor_init, pre.anchor_step, pre.anchor_source)
    builder = GraphBuilder(log, opts, decisions, associations, steps)
    if anchor_given is not None:
        builder.anchor_init, builder.anchor_step, builder.anchor_source = anchor_given
    n = builder.n_steps
    if backend == "batch":
        if init == "given" and init_poses is None:
            raise ValueError("init 'given' needs init_poses")
        start = None if init == "odometry" or init_poses is None else init_poses[:n]
        out = _run_batch(builder, lm, start, marginals, progress, joint_stride)
    else:
        out = _run_isam2(builder, isam2, marginals, progress)
    return GraphResult(
        scenario=log.scenario,
        seed=log.seed,
        backend=backend,
        fusion=opts.fusion,
        association=association if associations is None else "given",
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
