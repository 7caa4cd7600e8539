"""The batch solver: Levenberg–Marquardt driven from Python over the whole log.

Each outer iteration linearises once (``graph.linearize(values)``), adds ``√λ·I``
damping rows per variable, eliminates (multifrontal, COLAMD), ``values.retract``,
``graph.error``, adapts λ: no Python factor callback receives a ``Values`` that Python
does not own.  Smoothed marginals from ``gtsam.Marginals`` on the final linearisation.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_graph.builder import GraphBuilder
from mapfuse_graph.factors import pose_of
from mapfuse_graph.keys import anchor_key, pose_key
from mapfuse_graph.marginals import _body_to_abs, _key_dims
from mapfuse_graph.results import (
    JointPoseCovariance,
    LMReport,
    _anchor,
    _landmarks,
    _pose_covs,
    _poses_from,
    _Solved,
)

__all__ = ["LMOptions", "levenberg_marquardt"]


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
    landmarks, variables = _landmarks(builder, values, cov_of, poses)
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
        variables=variables,
        lm=report,
        extra=extra,
        joint_pose_cov=joint,
        initial=initial,
    )
