"""The fixed-lag smoother: GTSAM's ``IncrementalFixedLagSmoother`` over the same graph.

The factors, fusion and anchor are those of iSAM2 (the same
:class:`~mapfuse_graph.builder.GraphBuilder` steps, the same :class:`ISAM2Options`);
the smoother adds a timestamp per variable (the log's ``timestamps``) and, at each
update, marginalises every variable whose timestamp is older than the newest one by
more than :attr:`FixedLagOptions.lag_s`.  Marginalising is GTSAM's
(``ISAM2::marginalizeLeaves``): the variable leaves the Bayes tree and its information
stays as a linear factor on its neighbours, linearised where it was, so nothing is
dropped but nothing before the window is relinearised again.

Which estimate is which, at step ``k`` (time ``t_k``):

* **filtered** (the result's ``filtered`` track): ``X_k`` right
  after update ``k`` (steps ``0..k``), the exact solution of that update's linear
  system, read from one marginal of the smoother's Bayes tree, as iSAM2's;
* **final** (the result's ``smoothed`` track): ``X_j`` is final once
  ``t_k > t_j + lag``: it is the estimate after the last update that still held ``X_j``
  (steps ``0..k−1``, the pose of ``k − lag`` at a constant step time), recorded with its
  marginal covariance just before GTSAM marginalises it;
* **smoothed window**: the poses still in the window at the end (after
  ``final_updates`` extra updates and, with :attr:`ISAM2Options.final_gauss_newton`, one
  Gauss–Newton step on the window's graph), with the smoothed marginals of the window's
  linear system, linearised as :attr:`ISAM2Options.final_marginals` says
  (:func:`~mapfuse_graph.marginals.bayes_tree_marginals`).

With ``lag_s = inf`` nothing leaves: it is iSAM2 with GTSAM's full relinearisation
check (:attr:`ISAM2Options.partial_relinearization_check`; hence batch, within iSAM2's
tolerance).  With ``lag_s = 0`` each pose leaves one update after it enters: the final
estimate is the filtered one, and the filtered one is iSAM2's except that marginalised
poses are never relinearised.

Landmarks (:attr:`FixedLagOptions.landmarks`):

* ``"keep"``: every landmark's timestamp is refreshed at each update, so the map is
  never marginalised; at lag 0 the state is the EKF's, the current pose and the map.
* ``"window"``: a landmark's timestamp is refreshed when it is observed; unobserved for
  more than the lag, GTSAM marginalises it.  A marginalised key cannot come back, so a
  landmark re-observed after that is a new variable: :func:`split_by_lag` relabels the
  (fixed) association beforehand, exactly where the smoother will have marginalised it.

The anchor, the known features and every landmark paired with a known feature have
their timestamps refreshed at every update: they never leave the window (their tie
factors, added while the graph grows, need them).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_graph.builder import GraphBuilder
from mapfuse_graph.factors import pose_of
from mapfuse_graph.isam2 import (
    _DIMS,
    ISAM2Options,
    _newest_pose_marginal,
    final_step,
    isam2_params,
)
from mapfuse_graph.keys import anchor_key, known_key, landmark_key, pose_key, radius_key
from mapfuse_graph.marginals import _key_dims, bayes_tree_marginals, body_to_abs_cov
from mapfuse_graph.results import _anchor, _landmarks, _pose_covs, _Solved

__all__ = ["LANDMARK_POLICIES", "FixedLagOptions", "split_by_lag", "window_graph"]

LANDMARK_POLICIES: tuple[str, ...] = ("keep", "window")


@dataclass(frozen=True)
class FixedLagOptions:
    """Settings of the fixed-lag smoother (its iSAM2 takes :class:`ISAM2Options`)."""

    lag_s: float = 5.0
    """Length of the window in seconds of the log's timestamps: a variable whose
    timestamp is older than the newest one by more than this is marginalised.
    ``0``: only the newest step's variables (a filter); ``inf``: nothing leaves."""
    landmarks: str = "keep"
    """``"keep"`` (the map stays in the window) or ``"window"`` (a landmark unobserved
    for longer than the lag is marginalised; needs a fixed association)."""

    def __post_init__(self) -> None:
        lag = self.lag_s
        if isinstance(lag, bool) or not isinstance(lag, int | float) or math.isnan(lag):
            raise ValueError(f"lag_s must be a number, got {lag!r}")
        if lag < 0:
            raise ValueError(f"lag_s must be >= 0 (or inf), got {lag}")
        if self.landmarks not in LANDMARK_POLICIES:
            raise ValueError(
                f"landmarks must be one of {', '.join(LANDMARK_POLICIES)}, got {self.landmarks!r}"
            )


def split_by_lag(
    obs_landmark: np.ndarray,
    obs_known_id: np.ndarray,
    feat_step: np.ndarray,
    timestamps: FloatArray,
    lag_s: float,
) -> np.ndarray:
    """Landmark labels with each unpaired landmark cut where the smoother drops it.

    A landmark last observed at step ``s`` is marginalised by the first update ``k`` with
    ``t_k − t_s > lag_s``; an observation at step ``k`` after such an update (that is,
    with ``t_{k−1} − t_s > lag_s``) starts a new label.  Landmarks paired with a known
    feature (``obs_known_id >= 0`` on any observation) stay in the window and keep
    their label.
    """
    lm = np.asarray(obs_landmark, dtype=np.int64)
    out = lm.copy()
    paired = set(np.unique(lm[(np.asarray(obs_known_id) >= 0) & (lm >= 0)]).tolist())
    next_label = int(lm.max()) + 1 if lm.size else 0
    last: dict[int, tuple[int, int]] = {}  # label → (last step, current label)
    for j in np.argsort(feat_step, kind="stable"):
        label = int(lm[j])
        if label < 0 or label in paired:
            continue
        k = int(feat_step[j])
        prev = last.get(label)
        cur = label if prev is None else prev[1]
        if prev is not None and k > 0 and timestamps[k - 1] - timestamps[prev[0]] > lag_s:
            cur, next_label = next_label, next_label + 1
        out[j] = cur
        last[label] = (k, cur)
    return out


class _FixedLagEstimate:
    """The builder's view of the smoother: the window, and the final values of what left."""

    def __init__(self, smoother: gtsam.IncrementalFixedLagSmoother, filtered: FloatArray) -> None:
        self.smoother = smoother
        self.filtered_covs = filtered
        self.last_pose: tuple[int, FloatArray] = (-1, np.zeros(3))
        self.gone_poses: dict[int, FloatArray] = {}
        self.gone_vectors: dict[int, FloatArray] = {}

    def pose(self, k: int) -> FloatArray:
        if k == self.last_pose[0]:
            return self.last_pose[1]
        if k in self.gone_poses:
            return self.gone_poses[k]
        return pose_of(self.smoother.calculateEstimatePose2(pose_key(k)))

    def vector(self, key: int) -> FloatArray:
        if key in self.gone_vectors:
            return self.gone_vectors[key]
        return np.asarray(self.smoother.calculateEstimateVector(key), dtype=float)

    def anchor(self) -> FloatArray:
        return pose_of(self.smoother.calculateEstimatePose2(anchor_key()))

    def pose_cov(self, k: int) -> FloatArray | None:
        return np.asarray(self.filtered_covs[k])

    def cov(self, key: int) -> FloatArray | None:
        if key in self.gone_vectors:
            return None
        return np.asarray(self.smoother.marginalCovariance(key), dtype=float)


def window_graph(
    factors: gtsam.NonlinearFactorGraph, linearization_point: gtsam.Values
) -> gtsam.NonlinearFactorGraph:
    """The smoother's factors as a graph that can be linearised anywhere.

    What GTSAM leaves when it marginalises (``ISAM2::marginalizeLeaves``) is a
    ``LinearContainerFactor`` holding the marginal as a linear factor in the deltas of its
    keys from their linearisation point then, which iSAM2 never moves again (those keys
    become its *fixed* variables), but the container is made without that point: its
    ``linearize`` returns the same linear factor at any values.  Linearised at the
    smoother's estimate instead, as the final Gauss–Newton step and the window's
    marginals do, it would read those deltas from the wrong origin.  Each container is
    made again here with its keys' linearisation point, so that GTSAM shifts it to
    wherever it is linearised.  The other factors are kept as they are; removed slots
    are dropped."""
    out = gtsam.NonlinearFactorGraph()
    for i in range(factors.size()):
        f = factors.at(i)
        if f is None:
            continue
        if isinstance(f, gtsam.LinearContainerFactor):
            # GTSAM keeps, of the values given, those of the container's own keys.
            f = gtsam.LinearContainerFactor(f.factor(), linearization_point)
        out.add(f)
    return out


def _landmark_keys(builder: GraphBuilder, i: int) -> list[int]:
    kind = builder.landmarks[i].kind
    keys = [landmark_key(i, kind)]
    if builder.split_circles and kind == FeatureKind.CIRCLE:
        keys.append(radius_key(i))
    return keys


def _run_fixedlag(
    builder: GraphBuilder,
    options: FixedLagOptions | None,
    isam2: ISAM2Options | None,
    marginals: bool,
    progress: Callable[[int, int], None] | None,
) -> _Solved:
    fl = options or FixedLagOptions()
    opts = isam2 or ISAM2Options()
    log = builder.log
    n = builder.n_steps
    t_of = np.asarray(log.timestamps, dtype=float)
    lag = float(fl.lag_s)
    smoother = gtsam.IncrementalFixedLagSmoother(
        lag, isam2_params(opts, builder.split_circles, smoother=True)
    )
    isam = smoother.getISAM2()
    # Held for the whole run: callbacks then receive this object, not a deep copy.
    linearization_point = smoother.getLinearizationPoint()
    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    f_poses = np.zeros((n, 3))
    f_covs = np.zeros((n, 3, 3))
    final_poses = np.full((n, 3), np.nan)
    final_covs = np.full((n, 3, 3), np.nan)
    est = _FixedLagEstimate(smoother, f_covs)
    stamp: dict[int, float] = {}  # mirror of the smoother's timestamps
    always: set[int] = set()  # keys refreshed at every update
    times = np.zeros(n)
    cpu = np.zeros(n)
    relin = 0
    keep = fl.landmarks == "keep"
    for k in range(n):
        t0, c0 = time.perf_counter(), time.process_time()
        tk = float(t_of[k])
        sg = builder.step(k, est)
        xk = pose_key(k)
        new_stamps: dict[Any, Any] = {xk: tk}
        sl = log.feature_slice(k)
        for j in range(sl.start, sl.stop):
            i = int(builder.obs_landmark[j])
            if i >= 0:
                for key in _landmark_keys(builder, i):
                    new_stamps[key] = tk
        if sg.anchor_added:
            always.add(anchor_key())
            for r in range(len(builder.known)):
                always.add(known_key(r, FeatureKind(int(builder.known.kinds[r]))))
        for i, lmk in enumerate(builder.landmarks):
            if lmk.created and (keep or lmk.known >= 0):
                always.update(_landmark_keys(builder, i))
        for key in always:
            new_stamps[key] = tk
        stamp.update(new_stamps)
        smoother.update(sg.factors, sg.values, new_stamps)
        relin += int(smoother.getISAM2Result().getVariablesRelinearized())
        graph.push_back(sg.factors)
        initial.insert(sg.values)
        x, P = _newest_pose_marginal(isam, linearization_point, xk)
        f_poses[k] = x
        f_covs[k] = body_to_abs_cov(P, x[2])
        est.last_pose = (k, x)
        if k + 1 < n:
            # What the next update marginalises: record its final estimate now.
            # The next update first refreshes the keys it observes and those kept.
            cut = float(t_of[k + 1]) - lag
            refreshed = set(always)
            nxt = log.feature_slice(k + 1)
            for i in builder.obs_landmark[nxt.start : nxt.stop]:
                if 0 <= i < len(builder.landmarks):
                    refreshed.update(_landmark_keys(builder, int(i)))
            leaving = [key for key, t in stamp.items() if t < cut and key not in refreshed]
            for key in leaving:
                del stamp[key]
                sym = gtsam.Symbol(key)
                if chr(sym.chr()) == "x":
                    s = int(sym.index())
                    if key == xk:
                        final_poses[s], final_covs[s] = x, f_covs[k]
                    else:
                        xs = pose_of(smoother.calculateEstimatePose2(key))
                        Ps = np.asarray(smoother.marginalCovariance(key), dtype=float)
                        final_poses[s], final_covs[s] = xs, body_to_abs_cov(Ps, xs[2])
                    est.gone_poses[s] = final_poses[s]
                else:
                    est.gone_vectors[key] = np.asarray(
                        smoother.calculateEstimateVector(key), dtype=float
                    )
        times[k] = time.perf_counter() - t0
        cpu[k] = time.process_time() - c0
        if progress is not None:
            progress(k + 1, n)
    t0 = time.perf_counter()
    # The smoother's update cannot force the relinearisation check: enough empty updates
    # that ``final_updates`` of them check whatever ``relinearize_skip``.
    for _ in range(opts.final_updates * opts.relinearize_skip):
        smoother.update()
    window, tree_of = final_step(
        window_graph(smoother.getFactors(), linearization_point),
        isam.calculateBestEstimate(),
        linearization_point,
        opts,
    )
    solve = time.perf_counter() - t0
    t0 = time.perf_counter()
    window_covs: dict[int, FloatArray] = {}
    if marginals:
        window_covs = bayes_tree_marginals(tree_of.tree(), dict(_key_dims(linearization_point)))
    values = gtsam.Values()
    values.insert(window)
    for s, xs in est.gone_poses.items():
        values.insert(pose_key(s), gtsam.Pose2(float(xs[0]), float(xs[1]), float(xs[2])))
    for key, v in est.gone_vectors.items():
        values.insert(key, v)
    in_window = np.array([window.exists(pose_key(k)) for k in range(n)], dtype=bool)
    poses = final_poses.copy()
    for w in np.nonzero(in_window)[0]:
        poses[w] = pose_of(window.atPose2(pose_key(int(w))))

    def cov_of(key: int) -> FloatArray:
        if key in window_covs:
            return window_covs[key]
        d = _DIMS.get(chr(gtsam.Symbol(key).chr()), 1)
        return np.full((d, d), np.nan)

    win_covs = _pose_covs(poses, cov_of if marginals else None)
    covs = np.where(in_window[:, None, None], win_covs, final_covs)
    if not marginals:
        covs = np.where(in_window[:, None, None], np.nan, final_covs)
    landmarks, variables = _landmarks(builder, values, cov_of, poses)
    anchor = _anchor(builder, values, cov_of)
    marg = time.perf_counter() - t0
    del linearization_point, isam
    extra: dict[str, Any] = {
        "lag_s": lag,
        "landmarks_policy": fl.landmarks,
        "window_steps": int(in_window.sum()),
        "marginalised_landmarks": len(est.gone_vectors),
        "variables_relinearized": relin,
        "final_gauss_newton_step_max": tree_of.step_max,
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
