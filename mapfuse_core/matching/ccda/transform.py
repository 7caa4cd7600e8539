"""Weighted least-squares fit of the transform between two maps from pairings.

Gauss–Newton with a halving line search from closed-form starts (Procrustes on
circle centres, or the mean line angle on both branches of its π ambiguity).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from mapfuse_core.geometry.se2 import FloatArray, as_pose, rot2, wrap_angle
from mapfuse_core.matching.ccda.params import CCDAParams
from mapfuse_core.matching.ccda.prepare import (
    _CIRCLE,
    _INFO_FLOOR,
    IntArray,
    _pairing_arrays,
    _Prep,
    _prepare,
)
from mapfuse_core.matching.ccda.residuals import _pair_set, _PairSet, _residuals_of
from mapfuse_core.measlog import KnownMapArrays

#: The shortest step (fraction of the Gauss–Newton step) the line search tries.
_MIN_STEP = 2.0**-20
#: Below this step the line search first checks that the shortest step helps at all.
_PROBE_BELOW = 2.0**-4


def _normal_equations(P: _PairSet, T: FloatArray) -> tuple[FloatArray, FloatArray, float]:
    """Information ``H = Σ Jᵀ S⁻¹ J``, gradient ``Σ Jᵀ S⁻¹ r`` and cost ``Σ rᵀ S⁻¹ r``."""
    r, J, S, _ = _residuals_of(P, T)
    W = np.linalg.inv(S)
    WJ = W @ J
    H: FloatArray = np.einsum("mki,mkj->ij", J, WJ)
    g: FloatArray = np.einsum("mki,mk->i", WJ, r)
    cost = float(np.einsum("mi,mij,mj->", r, W, r))
    return 0.5 * (H + H.T), g, cost


def _cost(P: _PairSet, T: FloatArray) -> float:
    """The cost of :func:`_normal_equations` alone, computed the same way."""
    r, _, S, _ = _residuals_of(P, T, jacobian=False)
    W = np.linalg.inv(S)
    return float(np.einsum("mi,mij,mj->", r, W, r))


def _initial_guesses(A: _Prep, B: _Prep, ii: IntArray, jj: IntArray) -> list[FloatArray]:
    """Closed-form starting transforms: rotation from circles (Procrustes) or lines
    (mean angle, both branches of the π ambiguity), then least-squares translation."""
    circ = A.kinds[ii] == _CIRCLE
    thetas: list[float] = []
    if int(circ.sum()) >= 2:
        pa, pb = A.p[ii[circ]], B.p[jj[circ]]
        ca, cb = pa - pa.mean(axis=0), pb - pb.mean(axis=0)
        cross = float(np.sum(cb[:, 0] * ca[:, 1] - cb[:, 1] * ca[:, 0]))
        dot = float(np.sum(cb * ca))
        if math.hypot(cross, dot) > 1e-12:
            thetas.append(math.atan2(cross, dot))
    if not thetas and np.any(~circ):
        d = A.th[ii[~circ]] - B.th[jj[~circ]]
        # Line angles are modulo π: average the doubled angles.
        th0 = 0.5 * math.atan2(float(np.sin(2 * d).sum()), float(np.cos(2 * d).sum()))
        thetas += [th0, th0 + math.pi]
    if not thetas:
        thetas.append(0.0)
    guesses = []
    for th in thetas:
        R = rot2(th)
        rows: list[FloatArray] = []
        rhs: list[float] = []
        for i, j, is_c in zip(ii.tolist(), jj.tolist(), circ.tolist(), strict=True):
            pb_a = R @ B.p[j]
            if is_c:
                rows += [np.array([1.0, 0.0]), np.array([0.0, 1.0])]
                rhs += [float(A.p[i, 0] - pb_a[0]), float(A.p[i, 1] - pb_a[1])]
            else:
                n = np.array([-math.sin(A.th[i]), math.cos(A.th[i])])
                rows.append(n)
                rhs.append(float(n @ (A.p[i] - pb_a)))
        t = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]
        guesses.append(np.array([t[0], t[1], float(wrap_angle(th))]))
    return guesses


def _solve(H: FloatArray, g: FloatArray) -> FloatArray:
    """Gauss–Newton step ``−H⁻¹ g``, minimum-norm in the free directions of ``H``."""
    w, V = np.linalg.eigh(H)
    inv = np.where(
        w > _INFO_FLOOR * max(1.0, float(w.max(initial=0.0))), 1.0 / np.maximum(w, 1e-300), 0.0
    )
    return -(V * inv) @ (V.T @ g)


def _cov_of(H: FloatArray) -> FloatArray:
    """``H⁻¹`` with the free directions given variance ``1 / _INFO_FLOOR``."""
    w, V = np.linalg.eigh(0.5 * (H + H.T))
    cov: FloatArray = (V / np.maximum(w, _INFO_FLOOR)) @ V.T
    return cov


def _step(T: FloatArray, dx: FloatArray, step: float) -> FloatArray:
    Tn = T + step * dx
    Tn[2] = float(wrap_angle(Tn[2]))
    return Tn


def _gauss_newton(
    A: _Prep, B: _Prep, ii: IntArray, jj: IntArray, x0: FloatArray
) -> tuple[FloatArray, FloatArray, float]:
    T = x0.copy()
    P = _pair_set(A, B, ii, jj)
    H, g, cost = _normal_equations(P, T)
    for _ in range(100):
        dx = _solve(H, g)
        # −g·dx is the decrease the Gauss–Newton model predicts.  Once it is at
        # round-off level no step can be told from none.
        if -float(g @ dx) <= 1e-12 * max(cost, 1.0):
            break
        # Halve the step until the cost does not increase (the angle makes the
        # problem nonlinear far from the solution).  The trials compute the cost
        # alone.  S depends on T (a line's angle noise grows with the other
        # feature's distance along it), which the model ignores: on a wrong
        # hypothesis the step can increase the true cost at every length, and
        # halving all the way to _MIN_STEP every time would dominate the matching
        # time.  So after the first few halvings the shortest step is tried: if that
        # fails too, the cost rises along dx at both ends of the lengths left and the
        # fit stops (a cost that dips only between _PROBE_BELOW and _MIN_STEP is
        # missed; on loop600 this gives the results of the full halving).
        step = 1.0
        Tn = _step(T, dx, step)
        while not _cost(P, Tn) <= cost * (1.0 + 1e-12) + 1e-12:
            step *= 0.5
            if step < _MIN_STEP or (
                step == _PROBE_BELOW
                and not _cost(P, _step(T, dx, _MIN_STEP)) <= cost * (1.0 + 1e-12) + 1e-12
            ):
                step = 0.0
                break
            Tn = _step(T, dx, step)
        if step == 0.0:
            break
        Hn, gn, cn = _normal_equations(P, Tn)
        converged = np.max(np.abs(step * dx)) < 1e-12 or cost - cn <= 1e-14 * max(cost, 1.0)
        T, H, g, cost = Tn, Hn, gn, cn
        if converged:
            break
    return T, _cov_of(H), cost


def _estimate(
    A: _Prep, B: _Prep, ii: IntArray, jj: IntArray, x0: FloatArray | None
) -> tuple[FloatArray, FloatArray]:
    starts = [x0] if x0 is not None else _initial_guesses(A, B, ii, jj)
    best: tuple[FloatArray, FloatArray, float] | None = None
    for s in starts:
        sol = _gauss_newton(A, B, ii, jj, s)
        if best is None or sol[2] < best[2]:
            best = sol
    assert best is not None
    return best[0], best[1]


def estimate_transform(
    map_a: KnownMapArrays,
    map_b: KnownMapArrays,
    pairings: Sequence[tuple[int, int]],
    x0: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Weighted least-squares ``x_A_B`` (pose of frame ``B`` in frame ``A``) and covariance.

    Minimises ``Σ rᵀ S⁻¹ r`` over the pairings ``(i, j)``, with
    ``r = pairing_residual(a_i, transform_feature(x_A_B, b_j))`` and ``S`` the
    covariance of both features propagated through the residual Jacobians (lines
    through their ``(e_lat, e_θ)`` part only), by Gauss–Newton from ``x0`` or, when
    ``x0`` is ``None``, from closed-form starts (Procrustes on circle centres, or
    the mean line angle on both branches of its π ambiguity).  The covariance is
    the inverse information ``(Σ Jᵀ S⁻¹ J)⁻¹``; directions the pairings do not fix
    get a variance of ``1e12``.

    Raises :class:`ValueError` for no pairings, out-of-range indices, pairings of
    different kinds and non-finite input.
    """
    params = CCDAParams()
    A, B = _prepare(map_a, "map_a", params), _prepare(map_b, "map_b", params)
    ii, jj = _pairing_arrays(A, B, pairings)
    if ii.size == 0:
        raise ValueError("estimate_transform needs at least one pairing")
    start = None if x0 is None else as_pose(x0, "x0")
    return _estimate(A, B, ii, jj, start)
