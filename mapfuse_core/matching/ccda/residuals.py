"""Pairing residuals under a transform, their Jacobians and covariances, and their χ²."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mapfuse_core.geometry.se2 import FloatArray, as_pose, wrap_angle_half
from mapfuse_core.matching.ccda.params import CCDAParams
from mapfuse_core.matching.ccda.prepare import (
    _CIRCLE,
    BoolArray,
    IntArray,
    _pairing_arrays,
    _Prep,
    _prepare,
)
from mapfuse_core.measlog import KnownMapArrays


def pairing_chi2(
    map_a: KnownMapArrays,
    map_b: KnownMapArrays,
    x_A_B: FloatArray,
    pairings: Sequence[tuple[int, int]],
) -> tuple[FloatArray, IntArray]:
    """χ² of each pairing's residual under ``x_A_B`` and its degrees of freedom.

    The residual is ``pairing_residual(a_i, x_A_B ⊕ b_j)`` (2 for a line, 3 for a
    circle); its covariance propagates both features' covariances (lines through
    their ``(e_lat, e_θ)`` part only).  Vectorised; used for gating.
    """
    params = CCDAParams()
    A, B = _prepare(map_a, "map_a", params), _prepare(map_b, "map_b", params)
    ii, jj = _pairing_arrays(A, B, pairings)
    return _chi2(A, B, as_pose(x_A_B, "x_A_B"), ii, jj)


@dataclass(frozen=True)
class _PairSet:
    """The parts of :func:`_residuals` that do not depend on the transform.

    Gauss–Newton evaluates one pairing set under many transforms; gathering and
    rotating these once per set instead of once per evaluation gives the same
    numbers (the same operations on the same operands) in about half the time.
    """

    A: _Prep
    B: _Prep
    m: int
    bp: FloatArray
    """(m, 2) ``B.p[jj]``."""
    circ: BoolArray
    """(m,) which pairings are circles."""
    dof: IntArray
    """(m,) residual dimension."""
    ci: IntArray
    cj: IntArray
    """Circle pairings' indices into ``A`` and ``B``."""
    c_ap: FloatArray
    c_dr: FloatArray
    """``A.p`` and radius differences ``B.r − A.r`` of the circle pairings."""
    c_acov: FloatArray
    c_bcov: FloatArray
    """Their covariances in ``A`` and ``B``."""
    li: IntArray
    lj: IntArray
    """Line pairings' indices into ``A`` and ``B``."""
    l_ap: FloatArray
    """``A.p`` of the line pairings."""
    tha: FloatArray
    ta: FloatArray
    na: FloatArray
    """Angle, direction and normal of the ``A`` lines."""
    thb0: FloatArray
    """Angle of the ``B`` lines in their own frame."""
    l_ac: FloatArray
    l_bc: FloatArray
    """``(e_lat, e_θ)`` covariances of the ``A`` and ``B`` lines."""


def _pair_set(A: _Prep, B: _Prep, ii: IntArray, jj: IntArray) -> _PairSet:
    circ = A.kinds[ii] == _CIRCLE
    ci, cj = ii[circ], jj[circ]
    lin = ~circ
    li, lj = ii[lin], jj[lin]
    tha = A.th[li]
    return _PairSet(
        A=A,
        B=B,
        m=int(ii.size),
        bp=B.p[jj],
        circ=circ,
        dof=np.where(circ, 3, 2).astype(np.int64),
        ci=ci,
        cj=cj,
        c_ap=A.p[ci],
        c_dr=B.params[cj, 2] - A.params[ci, 2],
        c_acov=A.covs[ci],
        c_bcov=B.covs[cj],
        li=li,
        lj=lj,
        l_ap=A.p[li],
        tha=tha,
        ta=np.stack([np.cos(tha), np.sin(tha)], axis=1),
        na=np.stack([-np.sin(tha), np.cos(tha)], axis=1),
        thb0=B.th[lj],
        l_ac=A.C[li],
        l_bc=B.C[lj],
    )


def _residuals(
    A: _Prep, B: _Prep, T: FloatArray, ii: IntArray, jj: IntArray
) -> tuple[FloatArray, FloatArray, FloatArray, IntArray]:
    """Pairing residuals under ``T``, vectorised, padded to 3 rows.

    Returns ``r`` (m, 3), ``∂r/∂T`` (m, 3, 3), the residual covariance ``S``
    (m, 3, 3) and the residual dimension (3 for circles, 2 for lines).  Lines get
    ``r[2] = 0``, a zero third Jacobian row and ``S[2, 2] = 1``, so χ² and normal
    equations need no special case.  The values are those of
    ``features.pairing_residual(kind, a_i, features.transform_feature(kind, T, b_j))``
    (checked by the tests); ``S`` propagates both features' noise: ``(x, y, r)`` for
    circles and the SPmap ``(e_lat, e_θ)`` for lines, never the along-line variance.
    """
    return _residuals_of(_pair_set(A, B, ii, jj), T)


def _residuals_of(
    P: _PairSet, T: FloatArray, jacobian: bool = True
) -> tuple[FloatArray, FloatArray, FloatArray, IntArray]:
    """:func:`_residuals` of a prepared pairing set (``J`` left zero without ``jacobian``)."""
    m = P.m
    r = np.zeros((m, 3))
    J = np.zeros((m, 3, 3))
    S = np.zeros((m, 3, 3))
    c, s = math.cos(float(T[2])), math.sin(float(T[2]))
    R = np.array([[c, -s], [s, c]])
    qb = P.bp @ R.T + T[:2]  # b's centre / origin in frame A
    # ∂(R q)/∂θ = R' q with R' = [[−s, −c], [c, −s]].
    dq = np.stack([-s * P.bp[:, 0] - c * P.bp[:, 1], c * P.bp[:, 0] - s * P.bp[:, 1]], axis=1)
    circ = P.circ
    if P.ci.size:
        r[circ, :2] = qb[circ] - P.c_ap
        r[circ, 2] = P.c_dr
        if jacobian:
            Jc = np.zeros((P.ci.size, 3, 3))
            Jc[:, 0, 0] = Jc[:, 1, 1] = 1.0
            Jc[:, :2, 2] = dq[circ]
            J[circ] = Jc
        Rb = np.eye(3)
        Rb[:2, :2] = R
        S[circ] = P.c_acov + Rb @ P.c_bcov @ Rb.T
    lin = ~circ
    if P.li.size:
        na = P.na
        thb = P.thb0 + T[2]
        nb = np.stack([-np.sin(thb), np.cos(thb)], axis=1)
        rel = qb[lin] - P.l_ap
        # The line model measures the offset along a's normal oriented like b's.
        sign = np.where(np.cos(thb - P.tha) >= 0.0, 1.0, -1.0)
        r[lin, 0] = sign * np.einsum("mi,mi->m", na, rel)
        r[lin, 1] = wrap_angle_half(thb - P.tha)
        if jacobian:
            Jl = np.zeros((P.li.size, 3, 3))
            Jl[:, 0, :2] = sign[:, None] * na
            Jl[:, 0, 2] = sign * np.einsum("mi,mi->m", na, dq[lin])
            Jl[:, 1, 2] = 1.0
            J[lin] = Jl
        lx = np.einsum("mi,mi->m", P.ta, rel)
        # ∂r/∂(e_lat, e_θ) of a: [[−1, −lx], [0, −1]] (a rotates about its origin);
        # of b: [[n_a·n_b, 0], [0, 1]] (b's origin moves along b's normal).
        Ja = np.zeros((P.li.size, 2, 2))
        Ja[:, 0, 0] = -1.0
        Ja[:, 0, 1] = -lx
        Ja[:, 1, 1] = -1.0
        Jb = np.zeros((P.li.size, 2, 2))
        Jb[:, 0, 0] = np.einsum("mi,mi->m", na, nb)
        Jb[:, 1, 1] = 1.0
        Ja[:, 0, :] *= sign[:, None]
        Jb[:, 0, :] *= sign[:, None]
        Sl = np.zeros((P.li.size, 3, 3))
        Sl[:, :2, :2] = Ja @ P.l_ac @ Ja.transpose(0, 2, 1) + Jb @ P.l_bc @ Jb.transpose(0, 2, 1)
        Sl[:, 2, 2] = 1.0
        S[lin] = Sl
    return r, J, S, P.dof


def _chi2(
    A: _Prep, B: _Prep, T: FloatArray, ii: IntArray, jj: IntArray
) -> tuple[FloatArray, IntArray]:
    r, _, S, dof = _residuals(A, B, T, ii, jj)
    c2: FloatArray = np.einsum("mi,mi->m", r, np.linalg.solve(S, r[:, :, None])[:, :, 0])
    return c2, dof
