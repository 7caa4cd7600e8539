"""A filter's poses from before its map match, re-placed on the known map:
:func:`relocalize_before_match`.

A filter estimates each pose once, with what it has seen so far.  Before its map
match that is its own map: the pose is known in ``Wglobal``, and through the anchor
found later it lands in ``Wknown`` with the anchor's covariance on top
(:func:`~mapfuse_core.changes.evidence.poses_in_known`), a metre or more
after a long unanchored stretch.  A feature seen only in that stretch is then tested
through a pose too loose to tell a move of a couple of metres from noise, and a
known feature's surveyed place is predicted in view from the wrong place.

Yet the run's own decisions say which observations of those steps are of features
the known map holds: their landmarks were merged with known features at or after the
match.  Those observations place the pose on the known map directly, step by step,
as a smoother would with the whole log.  Each pose before the match is re-estimated
by Gauss–Newton from its step's observations of merged landmarks against their known
features, each residual weighed with the observation's noise and the known feature's
own covariance, then fused with the filtered pose (in ``Wknown``, anchor covariance
included) as a prior.

A merged landmark can still be a changed feature the estimator took for right.  The
placement is therefore tested: when its χ² exceeds the level, the observation that
contributes most is set aside and the pose solved again, while three features remain;
a placement that stays inconsistent, disagrees with the filtered pose beyond their
joint covariance, does not fix all three degrees of freedom or does not converge is
refused, and the step is treated as one without features.  A circle enters with its
centre only: a short arc biases the fitted radius, which says nothing about the pose.
A tie whose covariance is not positive definite (an exact observation of an exact
map feature) cannot be weighed and is left out.

The known feature under test must not place the poses its own evidence is read
through: that would pull the evidence towards where the feature was surveyed.  For a
feature whose ties entered a placement, the placements are redone without them
(``exclude_known``), reusing every placement it took no part in.

A step that sees too few merged features is placed from the nearest placed step
before or after it, through the logged odometry and its covariance (dead reckoning
over a few steps drifts far less than the whole unanchored stretch), when that is
tighter than the filtered pose and agrees with it (the other direction is tried when
the tighter one does not agree).  The filter's first pose from the
match on counts as placed: the steps just before the match, where a feature seen
only before it is most often seen, are dead-reckoned back from it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from mapfuse_core.changes.residual import feature_residual
from mapfuse_core.geometry.features import FeatureKind, transform_feature
from mapfuse_core.geometry.se2 import (
    FloatArray,
    compose_jacobians,
    inverse_jacobian,
    wrap_scalar,
)
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog

__all__ = ["Relocalization", "relocalize_before_match"]

_MAX_ITER = 20
_STEP_TOL = 1e-8
_MIN_EIG = 1e-12
_MIN_TIES = 3
"""Merged features a step needs to be re-placed.  Two fix a pose with one degree of
freedom to spare, which a single changed feature among them can hide in; three leave
three to test it with."""
_POSE_ROWS = slice(0, 2)
"""Residual rows that depend on the pose: a line's two, a circle's centre (its radius
residual does not)."""


@dataclass(frozen=True, eq=False)
class Relocalization:
    """Poses in ``Wknown`` after re-placing those before the match on the known map."""

    poses: FloatArray
    """(N, 3) the poses; those neither placed nor bridged are the input's."""
    covs: FloatArray
    """(N, 3, 3) their covariances."""
    relocalized: int
    """Steps before the match whose pose was placed from its own merged features."""
    refused: int
    """Steps before the match with three or more merged features whose placement was
    refused (inconsistent, disagreeing with the filtered pose, under-determined or not
    converging); they are bridged like the steps without features."""
    set_aside: int
    """Observations set aside as inconsistent in the placements that were kept."""
    bridged: int = 0
    """Steps before the match without a placement of their own, placed instead from
    the nearest placed step through the logged odometry."""
    placed: np.ndarray | None = None
    """(N,) bool: the steps placed from their own features (reused by a run with
    ``exclude_known``)."""
    tied_known: frozenset[int] = frozenset()
    """Known ids whose ties entered a kept placement."""


@dataclass(frozen=True, eq=False)
class _Tie:
    kind: FeatureKind
    z: FloatArray
    cov_z: FloatArray
    known: FloatArray
    known_cov: FloatArray
    known_id: int


class _DegenerateError(Exception):
    """A tie's covariance stopped being positive definite during the solve."""


def _linearize(tie: _Tie, x: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Residual of the observation placed through ``x`` from its known feature, its
    Jacobian in ``x`` and its covariance (observation noise and known feature)."""
    f, Jx, Jz = transform_feature(tie.kind, x, tie.z)
    r, Jk, Jf = feature_residual(tie.kind, tie.known, f)
    rows = _POSE_ROWS
    H = (Jf @ Jx)[rows]
    A = (Jf @ Jz)[rows]
    B = Jk[rows]
    S = A @ tie.cov_z @ A.T + B @ tie.known_cov @ B.T
    return r[rows], H, 0.5 * (S + S.T)


def _weight(S: FloatArray) -> FloatArray:
    """``S⁻¹`` through its Cholesky factor; :class:`_DegenerateError` when ``S`` is not
    positive definite."""
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError as e:
        raise _DegenerateError from e
    Li = np.linalg.inv(L)
    return np.asarray(Li.T @ Li, dtype=float)


def _normal_equations(
    ties: list[_Tie], x: FloatArray
) -> tuple[FloatArray, FloatArray, list[float]]:
    info = np.zeros((3, 3))
    g = np.zeros(3)
    nis = []
    for t in ties:
        r, H, S = _linearize(t, x)
        W = _weight(S)
        info += H.T @ W @ H
        g += H.T @ W @ r
        nis.append(float(r @ W @ r))
    return info, g, nis


def _weighable(tie: _Tie, x: FloatArray) -> bool:
    """Whether ``tie``'s covariance at ``x`` is positive definite."""
    try:
        _weight(_linearize(tie, x)[2])
    except _DegenerateError:
        return False
    return True


def _determined(info: FloatArray) -> bool:
    return bool(np.linalg.eigvalsh(info)[0] > _MIN_EIG * max(1.0, float(np.trace(info))))


def _solve(ties: list[_Tie], x0: FloatArray) -> tuple[FloatArray, FloatArray, list[float]] | None:
    """Gauss–Newton placement from the ties alone: the pose, its information and each
    tie's χ² at the solution; ``None`` when the ties leave a direction free, a tie's
    covariance degenerates, or the iteration does not converge."""
    x = np.asarray(x0, dtype=float).copy()
    try:
        for _ in range(_MAX_ITER):
            info, g, _ = _normal_equations(ties, x)
            if not _determined(info):
                return None
            dx = -np.linalg.solve(info, g)
            x = x + dx
            x[2] = wrap_scalar(float(x[2]))
            if float(np.max(np.abs(dx))) < _STEP_TOL:
                break
        else:
            return None
        info, _, nis = _normal_equations(ties, x)
    except _DegenerateError:
        return None
    if not _determined(info):
        return None
    return x, info, nis


def _place(
    ties: list[_Tie], x0: FloatArray, level: float
) -> tuple[FloatArray, FloatArray, list[_Tie]] | None:
    """The consistent placement: the worst tie set aside until the χ² passes, while
    :data:`_MIN_TIES` remain.  Returns the pose, its information and the ties kept."""
    ties = list(ties)
    while len(ties) >= _MIN_TIES:
        sol = _solve(ties, x0)
        if sol is None:
            return None
        x, info, nis = sol
        dof = 2 * len(ties) - 3
        if sum(nis) <= float(chi2.ppf(level, dof)):
            return x, info, ties
        ties.pop(int(np.argmax(nis)))
    return None


def _with_prior(
    x0: FloatArray, P0: FloatArray, x: FloatArray, P: FloatArray, gate: float
) -> tuple[FloatArray, FloatArray] | None:
    """The placement ``(x, P)`` fused with the filtered pose ``(x0, P0)`` in covariance
    form (a zero ``P0`` keeps ``x0``); ``None`` when the two disagree beyond ``gate``.
    A non-finite ``P0`` is no prior: the placement stands alone."""
    if not np.all(np.isfinite(P0)):
        return x, P
    d = x - x0
    d[2] = wrap_scalar(float(d[2]))
    Sinv = np.linalg.pinv(P0 + P, hermitian=True)
    if float(d @ Sinv @ d) > gate:
        return None
    K = P0 @ Sinv
    xf = x0 + K @ d
    xf[2] = wrap_scalar(float(xf[2]))
    Pf = P0 - K @ P0
    return xf, 0.5 * (Pf + Pf.T)


def relocalize_before_match(
    log: MeasurementLog,
    obs_landmark: np.ndarray,
    obs_known_id: np.ndarray,
    poses_known: FloatArray,
    pose_covs_known: FloatArray,
    until_step: int,
    level: float,
    *,
    exclude_known: int | None = None,
    base: Relocalization | None = None,
) -> Relocalization:
    """Re-place the poses of steps ``0 … until_step − 1`` on the known map.

    ``poses_known``/``pose_covs_known``: the run's poses in ``Wknown`` with their
    covariances, the anchor's included for the steps before the match
    (:func:`~mapfuse_core.changes.evidence.poses_in_known`).
    ``obs_landmark``/``obs_known_id``: the run's decisions; an observation ties its
    step to a known feature when its landmark was merged with one.  ``level``: the
    probability of the placement's χ² tests.  ``exclude_known``: a known id whose ties
    are left out; ``base``: this function's result on the same inputs without
    exclusion, whose placements are reused at the steps without that feature's ties.
    See the module docstring.
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    poses = np.asarray(poses_known, dtype=float).copy()
    covs = np.asarray(pose_covs_known, dtype=float).copy()
    if poses.ndim != 2 or poses.shape[1] != 3 or covs.shape != (poses.shape[0], 3, 3):
        raise ValueError(
            f"poses must be (N, 3) and their covariances (N, 3, 3), got {poses.shape} "
            f"and {covs.shape}"
        )
    lm = np.asarray(obs_landmark, dtype=np.int64)
    kn = np.asarray(obs_known_id, dtype=np.int64)
    if lm.shape != (log.n_features,) or kn.shape != lm.shape:
        raise ValueError(f"the decisions hold {lm.shape[0]} observations, the log {log.n_features}")
    reused = base.placed if base is not None and exclude_known is not None else None
    known = log.known_map
    row_of = {int(k): r for r, k in enumerate(known.ids.tolist())}
    n = min(poses.shape[0], log.n_steps)
    last = max(0, min(int(until_step), n))
    done = refused = aside_total = 0
    placed_at = np.zeros(poses.shape[0], dtype=bool)
    tied: set[int] = set()
    gate3 = float(chi2.ppf(level, 3))
    for k in range(last):
        if not np.all(np.isfinite(poses[k])):
            continue
        ties = _ties_at(log, k, lm, kn, known, row_of)
        if exclude_known is not None:
            if reused is not None and not any(t.known_id == exclude_known for t in ties):
                if reused[k] and base is not None:
                    poses[k], covs[k] = base.poses[k], base.covs[k]
                    placed_at[k] = True
                continue
            ties = [t for t in ties if t.known_id != exclude_known]
        ties = [t for t in ties if _weighable(t, poses[k])]
        if len(ties) < _MIN_TIES:
            continue
        placed = _place(ties, poses[k], level)
        fused = None
        if placed is not None:
            x, info, kept = placed
            fused = _with_prior(poses[k], covs[k], x, np.asarray(np.linalg.inv(info), float), gate3)
        if placed is None or fused is None:
            refused += 1
            continue
        poses[k], covs[k] = fused
        placed_at[k] = True
        done += 1
        aside_total += len(ties) - len(kept)
        tied.update(t.known_id for t in kept)
    if last < n and np.all(np.isfinite(poses[last])) and np.all(np.isfinite(covs[last])):
        # The first pose from the match on is the filter's, anchored: a source too.
        placed_at[last] = True
    bridged = _bridge(log, poses, covs, placed_at, last, gate3) if placed_at.any() else 0
    if last < n:
        placed_at[last] = False
    return Relocalization(
        poses=poses,
        covs=covs,
        relocalized=done,
        refused=refused,
        set_aside=aside_total,
        bridged=bridged,
        placed=placed_at,
        tied_known=frozenset(tied),
    )


def _bridge(
    log: MeasurementLog,
    poses: FloatArray,
    covs: FloatArray,
    placed_at: np.ndarray,
    last: int,
    gate: float,
) -> int:
    """Place the steps before ``last`` that are not placed from the nearest placed step
    (step ``last`` itself, the first from the match on, counts as placed when marked),
    forwards or backwards through the logged odometry: the candidate with the smaller
    position covariance first, the other when that one disagrees with the pose; kept
    where it is tighter than the pose's own covariance and the two agree within
    ``gate``.  Modifies ``poses``/``covs``; returns the count."""
    end = min(last + 1, poses.shape[0], log.n_steps)
    fwd = _sweep(log, poses, covs, placed_at, range(end), forward=True)
    bwd = _sweep(log, poses, covs, placed_at, range(end - 1, -1, -1), forward=False)
    count = 0
    for k in range(last):
        if placed_at[k] or not np.all(np.isfinite(poses[k])):
            continue
        cands = sorted(
            (c for c in (fwd.get(k), bwd.get(k)) if c is not None),
            key=lambda c: float(np.trace(c[1][:2, :2])),
        )
        own = covs[k]
        for x, P in cands:
            if np.all(np.isfinite(own)):
                if float(np.trace(P[:2, :2])) >= float(np.trace(own[:2, :2])):
                    continue
                d = x - poses[k]
                d[2] = wrap_scalar(float(d[2]))
                if float(d @ np.linalg.pinv(own + P, hermitian=True) @ d) > gate:
                    continue
            poses[k] = x
            covs[k] = 0.5 * (P + P.T)
            count += 1
            break
    return count


def _sweep(
    log: MeasurementLog,
    poses: FloatArray,
    covs: FloatArray,
    placed_at: np.ndarray,
    order: range,
    forward: bool,
) -> dict[int, tuple[FloatArray, FloatArray]]:
    """Dead reckoning from the last placed step met along ``order``: each unplaced step's
    pose and covariance, reset at every placed step and lost at an odometry row that
    is not finite."""
    out: dict[int, tuple[FloatArray, FloatArray]] = {}
    x: FloatArray | None = None
    P = np.zeros((3, 3))
    prev = -1
    for k in order:
        if x is not None:
            # The increment between steps prev and k: row k forwards, row prev inverted
            # backwards.
            row = k if forward else prev
            u = np.asarray(log.odometry[row], dtype=float)
            Q = np.asarray(log.odometry_cov[row], dtype=float)
            if not (np.all(np.isfinite(u)) and np.all(np.isfinite(Q))):
                x = None
            else:
                if not forward:
                    u, Ji = inverse_jacobian(u)
                    Q = Ji @ Q @ Ji.T
                x, Ja, Jb = compose_jacobians(x, u)
                P = Ja @ P @ Ja.T + Jb @ Q @ Jb.T
        if placed_at[k]:
            x, P = poses[k].copy(), covs[k].copy()
        elif x is not None:
            out[k] = (x.copy(), P.copy())
        prev = k
    return out


def _ties_at(
    log: MeasurementLog,
    k: int,
    lm: np.ndarray,
    kn: np.ndarray,
    known: KnownMapArrays,
    row_of: dict[int, int],
) -> list[_Tie]:
    """Step ``k``'s observations of landmarks merged with a known feature of their kind,
    those with a finite covariance."""
    ties = []
    sl = log.feature_slice(k)
    for j in range(sl.start, sl.stop):
        if lm[j] < 0 or kn[j] < 0:
            continue
        r = row_of.get(int(kn[j]))
        if r is None or int(known.kinds[r]) != int(log.feat_kind[j]):
            continue
        cz = np.asarray(log.feat_cov[j], dtype=float)
        ck = np.asarray(known.covs[r], dtype=float)
        if not (np.all(np.isfinite(cz)) and np.all(np.isfinite(ck))):
            continue
        ties.append(
            _Tie(
                kind=FeatureKind(int(log.feat_kind[j])),
                z=np.asarray(log.feat_params[j], dtype=float),
                cov_z=cz,
                known=np.asarray(known.params[r], dtype=float),
                known_cov=ck,
                known_id=int(kn[j]),
            )
        )
    return ties
