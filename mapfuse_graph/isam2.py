"""The iSAM2 solver: one ``ISAM2.update`` per step.

It holds a reference to ``isam.getLinearizationPoint()`` for the whole run (callbacks
then get that object instead of a copy).  Each update orders the newest pose last, so
that its *filtered* estimate and covariance (comparable with the EKF's) come from the
root clique (:func:`_newest_pose_marginal`).  At the end a few extra updates
finish relinearisation, one Gauss–Newton step on the whole graph removes the lag its
thresholds leave (:attr:`ISAM2Options.final_gauss_newton`), and all smoothed marginals
are read in one pass down the same elimination
(:func:`~mapfuse_graph.marginals.bayes_tree_marginals`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np

from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_graph.builder import GraphBuilder
from mapfuse_graph.factors import pose_of
from mapfuse_graph.keys import anchor_key, pose_key
from mapfuse_graph.marginals import _key_dims, bayes_tree_marginals, body_to_abs_cov
from mapfuse_graph.results import (
    _anchor,
    _landmarks,
    _pose_covs,
    _poses_from,
    _Solved,
)

__all__ = ["ISAM2Options", "isam2_params"]


_DIMS = {"x": 3, "l": 2, "c": 3, "k": 2, "q": 3, "a": 3}


# Angles 10 mrad; positions, line distances and radii 25 cm.  Every residual of the graph
# is affine in the position-like entries once the angles are fixed (observation, odometry,
# tie and prior factors alike), so a position-only change moves a factor's linearisation
# only through position × angle cross terms: 25 cm × 10 mrad = 2.5 mm, and the angle-only
# term is ½ (10 mrad)² × a 50 m lever arm = 2.5 mm, both a fraction of the observation
# noise.  The lag they leave in the final estimate is removed by the final Gauss–Newton
# step (``ISAM2Options.final_gauss_newton``); ``docs/results/performance.md`` gives the measured
# cost and accuracy of these values against tighter ones.
_POS_M = 0.25
_ANG_RAD = 0.01
_DEFAULT_THRESHOLDS: dict[str, tuple[float, ...]] = {
    "x": (_POS_M, _POS_M, _ANG_RAD),
    "l": (_POS_M, _ANG_RAD),
    "c": (_POS_M, _POS_M, _POS_M),
    "k": (_POS_M, _ANG_RAD),
    "q": (_POS_M, _POS_M, _POS_M),
    "a": (_POS_M, _POS_M, _ANG_RAD),
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
    dimension.  The defaults (25 cm for positions, line distances and radii, 10 mrad for
    angles) keep the filtered estimates within a few hundredths of a σ of much tighter
    thresholds while relinearising far fewer variables (``docs/results/performance.md``): a line
    landmark seen
    from hundreds of poses costs hundreds of Python callbacks each time it is
    relinearised, and a long, sparsely observed trajectory that a loop closure shifts
    by centimetres would otherwise be relinearised whole at every step.  The residuals
    are affine in the position-like entries for fixed angles, hence the looser
    position thresholds.  With
    ``GraphOptions.split_circles`` the ``c`` entries ``(x, y, r)`` go to the centre and
    the radius variables."""
    relinearize_skip: int = 10
    """Check for relinearisation every this many updates (GTSAM's default).  The check
    back-substitutes the whole Bayes tree and compares variables' deltas with their
    thresholds (every variable, or the top of the tree with
    :attr:`partial_relinearization_check`), which costs more than an update that
    relinearises nothing; between checks each update still solves its linear system
    exactly, at the last linearisation point."""
    partial_relinearization_check: bool | None = None
    """At a check, GTSAM's partial check (``ISAM2Params.enablePartialRelinearizationCheck``):
    it walks the Bayes tree from the root and descends into a clique's children only
    where that clique has a variable to relinearise, instead of comparing every
    variable's delta with its threshold.  A variable below a clique that needs nothing
    can then keep a delta above its threshold until an ancestor moves.  ``None`` (the
    default): on for iSAM2, off for the fixed-lag smoother.

    * iSAM2: the keys of each update's new factors are ordered last, so what new
      information moves (the newest poses, the landmarks in view, a loop closure's old
      landmark) sits at the top of the tree, and the final Gauss–Newton step
      (:attr:`final_gauss_newton`) relinearises everything.  The filtered estimates stay
      close to the full check's, for a shorter ``ISAM2.update`` (measured in
      ``docs/results/performance.md``).
    * Fixed-lag smoother: marginalising a variable freezes the linearisation of every
      factor it leaves behind, so a pose should not leave the window with a stale
      linearisation point; the full check costs the smoother no measurable time and
      keeps its NEES lower (measured in ``docs/results/fixedlag.md``)."""

    factorization: str = "CHOLESKY"
    """``"CHOLESKY"`` (faster) or ``"QR"`` (more robust to ill conditioning).  A Cholesky
    run that GTSAM finds indeterminate (the anchor's loose prior beside its ties can
    make a pivot vanish in round-off) is solved again from the start with QR, with a
    ``RuntimeWarning`` and ``details.extra["factorization"]`` saying so (``isam2`` and
    ``fixedlag`` runs; not the iSAM2 pass of ``batch`` with ``association="own"``)."""
    final_updates: int = 5
    """Extra empty updates at the end, each checking for relinearisation whatever
    :attr:`relinearize_skip`.  With the partial check they relinearise only what the
    top of the tree shows; what lies below keeps its linearisation point, and only
    :attr:`final_gauss_newton` takes the final estimate to the optimum."""
    final_gauss_newton: bool = True
    """After the final updates, one Gauss–Newton step on the whole graph linearised at
    iSAM2's estimate.  iSAM2 keeps each variable's linearisation point until its delta
    passes the relinearisation threshold, so its estimate stops short of the optimum
    (further with the partial check, for a variable deep in the tree:
    ``docs/results/performance.md``); one step from there, where the problem is nearly linear,
    lands on the batch optimum.  With
    ``final_marginals="relinearized"`` the step reuses the marginals' elimination, so it
    costs one back-substitution.  The filtered (per-step) estimates are iSAM2's alone
    either way."""
    final_marginals: str = "relinearized"
    """Smoothed marginals of a fresh linearisation at iSAM2's final estimate, the point
    :attr:`final_gauss_newton` steps from (``"relinearized"``; exact there, and the step
    moves the estimate by hundredths of a σ) or of iSAM2's own linear system (``"isam2"``: the graph
    linearised at iSAM2's linearisation point, whose marginals are those of its Bayes
    tree; close to, not equal to, the exact ones because a variable's linearisation
    point may lag its estimate by up to the relinearisation threshold).  Both linearise
    the whole graph once and are read by :func:`bayes_tree_marginals`, so they cost the
    same."""

    def partial_check(self, *, smoother: bool) -> bool:
        """Whether the check is partial for iSAM2 (``smoother=False``) or the fixed-lag
        smoother (``True``): :attr:`partial_relinearization_check`, or its default."""
        if self.partial_relinearization_check is None:
            return not smoother
        return self.partial_relinearization_check

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
        partial = self.partial_relinearization_check
        if not (partial is None or isinstance(partial, bool)):
            raise ValueError(
                "partial_relinearization_check must be None, True or False, "
                f"got {self.partial_relinearization_check!r}"
            )
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


def _newest_last(observed: list[int], newest: int) -> gtsam.KeyGroupMap | None:
    """iSAM2 ordering constraint of one update: the keys of its new factors last (GTSAM's
    own default) and, among them, the newest pose the very last.

    The newest pose then ends the root clique's conditional, so its marginal eliminates
    only the root's other frontals.  Without it the pose often sits in a child of the
    root, and GTSAM's marginal through a large root clique (hundreds of dimensions on
    Victoria Park) dominates the step's cost.  The groups
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


def _newest_pose_marginal(
    isam: gtsam.ISAM2, linearization_point: gtsam.Values, key: int
) -> tuple[FloatArray, FloatArray]:
    """Filtered estimate and body-tangent covariance of the pose just added, from one
    marginal of iSAM2's Bayes tree.

    The marginal is a Gaussian conditional ``R δ_k = d`` with no parents (``R`` 3×3
    upper triangular, whitened): its mean ``R⁻¹ d`` is the Gauss–Newton step of ``X_k``
    and its covariance ``R⁻¹ R⁻ᵀ``, both solved here in closed form.  Asking instead for
    ``calculateEstimatePose2`` runs the wildfire back-substitution over every clique
    re-eliminated by the update, each step; left alone, the next relinearisation check
    does that once per ``relinearize_skip`` updates.  The mean is the exact linear
    solve, where the wildfire one stops propagating changes below 1e-3 (sub-millimetre
    differences).  With the newest pose ordered last (:func:`_newest_last`) it is a
    frontal of the root clique, so GTSAM's marginal (its own C++ elimination, no Python
    callback) eliminates only the root's other frontals.
    """
    m = isam.marginalFactor(key)
    (a, b, c), (_, e, f), (_, _, h) = m.R().tolist()
    d0, d1, d2 = m.d().tolist()
    # Back-substitution, and the rows of R⁻¹ = [[1/a, −b/(ae), (bf − ce)/(aeh)],
    # [0, 1/e, −f/(eh)], [0, 0, 1/h]].
    ia, ie, ih = 1.0 / a, 1.0 / e, 1.0 / h
    s2 = d2 * ih
    s1 = (d1 - f * s2) * ie
    s0 = (d0 - b * s1 - c * s2) * ia
    r0 = (ia, -b * ia * ie, (b * f - c * e) * ia * ie * ih)
    r1 = (ie, -f * ie * ih)
    P: FloatArray = np.array(
        [
            [
                r0[0] * r0[0] + r0[1] * r0[1] + r0[2] * r0[2],
                r0[1] * r1[0] + r0[2] * r1[1],
                r0[2] * ih,
            ],
            [0.0, r1[0] * r1[0] + r1[1] * r1[1], r1[1] * ih],
            [0.0, 0.0, ih * ih],
        ]
    )
    P[1, 0], P[2, 0], P[2, 1] = P[0, 1], P[0, 2], P[1, 2]
    x = pose_of(linearization_point.atPose2(key).retract(np.array([s0, s1, s2])))
    return x, P


def isam2_params(
    opts: ISAM2Options, split_circles: bool, *, smoother: bool = False
) -> gtsam.ISAM2Params:
    """GTSAM parameters of ``opts`` for iSAM2, or (``smoother=True``) for the fixed-lag
    smoother's iSAM2."""
    params = gtsam.ISAM2Params()
    th = opts.relinearize_threshold
    if isinstance(th, dict):
        if split_circles and "c" in th:
            # The circle's (x, y, r) thresholds go to its centre and radius variables.
            th = {**th, "c": tuple(th["c"][:2]), "r": tuple(th["c"][2:])}
        tmap = gtsam.ISAM2ThresholdMap()
        for ch, v in th.items():
            tmap.insert((ch, np.asarray(v, dtype=float)))
        params.setRelinearizeThreshold(tmap)
    else:
        params.setRelinearizeThreshold(float(th))
    params.relinearizeSkip = opts.relinearize_skip
    params.enablePartialRelinearizationCheck = opts.partial_check(smoother=smoother)
    params.setFactorization(opts.factorization)
    return params


class _FinalTree:
    """The Bayes tree the final marginals are read from, eliminated at most once."""

    def __init__(
        self, graph: gtsam.NonlinearFactorGraph, at: gtsam.Values, tree: Any, step_max: float
    ) -> None:
        self.graph, self.at, self._tree, self.step_max = graph, at, tree, step_max

    def tree(self) -> Any:
        if self._tree is None:
            self._tree = self.graph.linearize(self.at).eliminateMultifrontal()
        return self._tree


def final_step(
    graph: gtsam.NonlinearFactorGraph,
    estimate: gtsam.Values,
    linearization_point: gtsam.Values,
    opts: ISAM2Options,
) -> tuple[gtsam.Values, _FinalTree]:
    """The final estimate (``estimate`` after :attr:`ISAM2Options.final_gauss_newton`'s
    step on ``graph``) and the tree of its marginals: the graph linearised at
    ``estimate`` (``final_marginals="relinearized"``, the step's own elimination) or at
    ``linearization_point`` (``"isam2"``).  Shared by iSAM2 and the fixed-lag smoother
    (whose ``graph`` is its window's, marginal factors included)."""
    values, tree, step_max = estimate, None, 0.0
    if opts.final_gauss_newton:
        tree = graph.linearize(estimate).eliminateMultifrontal()
        step = tree.optimize()
        flat = np.asarray(step.vector(), dtype=float)
        step_max = float(np.abs(flat).max()) if flat.size else 0.0
        values = estimate.retract(step)
    if opts.final_marginals == "isam2":
        # iSAM2's linear system is the graph linearised at its linearisation point (each
        # cached linear factor was made at the current values of its keys): its
        # marginals are iSAM2's own.
        return values, _FinalTree(graph, linearization_point, None, step_max)
    return values, _FinalTree(graph, estimate, tree, step_max)


def _run_isam2(
    builder: GraphBuilder,
    options: ISAM2Options | None,
    marginals: bool,
    progress: Callable[[int, int], None] | None,
) -> _Solved:
    opts = options or ISAM2Options()
    n = builder.n_steps
    isam = gtsam.ISAM2(isam2_params(opts, builder.split_circles))
    # Held for the whole run: callbacks then receive this object, not a deep copy.
    linearization_point = isam.getLinearizationPoint()
    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    f_poses = np.zeros((n, 3))
    f_covs = np.zeros((n, 3, 3))
    est = _ISAM2Estimate(isam, f_covs)
    times = np.zeros(n)
    cpu = np.zeros(n)
    relin = 0
    for k in range(n):
        t0, c0 = time.perf_counter(), time.process_time()
        sg = builder.step(k, est)
        xk = pose_key(k)
        order = _newest_last(sg.factors.keyVector(), xk)
        res = isam.update(sg.factors, sg.values, [], order)
        relin += int(res.getVariablesRelinearized())
        graph.push_back(sg.factors)
        initial.insert(sg.values)
        x, P = _newest_pose_marginal(isam, linearization_point, xk)
        f_poses[k] = x
        f_covs[k] = body_to_abs_cov(P, x[2])
        est.last_pose = (k, x)
        times[k] = time.perf_counter() - t0
        cpu[k] = time.process_time() - c0
        if progress is not None:
            progress(k + 1, n)
    t0 = time.perf_counter()
    final_params = gtsam.ISAM2UpdateParams()
    final_params.force_relinearize = True
    for _ in range(opts.final_updates):
        isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), final_params)
    # Full back-substitution: calculateEstimate() stops propagating changes below the
    # wildfire threshold (1e-3), a millimetre-level difference from the batch optimum.
    values, tree_of = final_step(graph, isam.calculateBestEstimate(), linearization_point, opts)
    step_max = tree_of.step_max
    solve = time.perf_counter() - t0
    t0 = time.perf_counter()
    cov_of: Callable[[int], FloatArray] | None = None
    if marginals:
        cov_of = bayes_tree_marginals(tree_of.tree(), dict(_key_dims(values))).__getitem__
    poses = _poses_from(values, n)
    covs = _pose_covs(poses, cov_of)
    landmarks, variables = _landmarks(builder, values, cov_of, poses)
    anchor = _anchor(builder, values, cov_of)
    marg = time.perf_counter() - t0
    del linearization_point
    extra = {
        "variables_relinearized": relin,
        "final_gauss_newton_step_max": step_max,
    }
    return _Solved(
        graph=graph,
        values=values,
        poses=poses,
        covs=covs,
        filtered_poses=f_poses,
        filtered_covs=f_covs,
        step_time_s=times,
        step_cpu_s=cpu,
        build_time_s=0.0,
        solve_time_s=solve,
        marginals_time_s=marg,
        anchor=anchor,
        landmarks=landmarks,
        variables=variables,
        lm=None,
        extra=extra,
        initial=initial,
    )
