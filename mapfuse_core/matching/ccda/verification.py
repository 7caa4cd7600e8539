"""Hypotheses: a clique's fit, leave-one-out verification, one-to-one re-association."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mapfuse_core.geometry.se2 import FloatArray, wrap_angle
from mapfuse_core.matching.ccda.params import _Gates
from mapfuse_core.matching.ccda.prepare import _INFO_FLOOR, BoolArray, IntArray, _Prep
from mapfuse_core.matching.ccda.residuals import _residuals
from mapfuse_core.matching.ccda.transform import _estimate


@dataclass(frozen=True)
class _Hypothesis:
    """A fitted maximum clique, refined by nearest-neighbour re-association."""

    ii: IntArray
    """Features of ``A`` of the final pairings."""
    jj: IntArray
    """Their partners in ``B``."""
    T: FloatArray
    """Estimated ``x_A_B``."""
    cov: FloatArray
    """Its covariance."""
    clique: int
    """Inliers of the maximum clique the hypothesis grew from."""
    nodes: IntArray
    """All graph nodes passing the gate under :attr:`T` (before one-to-one)."""
    support: int
    """Features of ``A`` the transform explains one-to-one (ambiguous ones included):
    what hypotheses are ranked and compared by."""


def _gate_ratio(
    A: _Prep,
    B: _Prep,
    T: FloatArray,
    ii: IntArray,
    jj: IntArray,
    gates: _Gates,
    P: FloatArray | None = None,
) -> FloatArray:
    """χ² of each pairing under ``T`` divided by its gate: ≤ 1 passes.

    With ``P`` (the covariance of ``T``) the residual covariance includes
    ``J P Jᵀ``: the test of a pairing that did not take part in the fit.
    """
    r, J, S, dof = _residuals(A, B, T, ii, jj)
    if P is not None:
        S = S + J @ P @ J.transpose(0, 2, 1)
    c2 = np.einsum("mi,mi->m", r, np.linalg.solve(S, r[:, :, None])[:, :, 0])
    ratio: FloatArray = c2 / np.where(dof == 2, gates.g2, gates.g3)
    return ratio


def _deleted_covs(J: FloatArray, W: np.ndarray) -> FloatArray:
    """(m, 3, 3) covariance of the transform fitted without each pairing in turn:
    ``(H − H_k)⁻¹`` with ``H_k = J_kᵀ W_k J_k``, free directions given variance
    ``1 / _INFO_FLOOR``."""
    Jt = J.transpose(0, 2, 1)
    Hk = Jt @ W @ J
    Hm = Hk.sum(axis=0)[None] - Hk
    w, V = np.linalg.eigh(0.5 * (Hm + Hm.transpose(0, 2, 1)))
    P: FloatArray = (V / np.maximum(w, _INFO_FLOOR)[:, None, :]) @ V.transpose(0, 2, 1)
    return P


def _deleted_ratio(
    A: _Prep, B: _Prep, T: FloatArray, ii: IntArray, jj: IntArray, gates: _Gates
) -> FloatArray:
    """Leave-one-out χ² of each pairing divided by its gate (≤ 1 passes).

    Each pairing is tested against the transform fitted to the *other* pairings
    (one linearised Gauss–Newton downdate from the joint fit ``T``):
    ``δ_k = (H − H_k)⁻¹ J_kᵀ S_k⁻¹ r_k``, residual ``r_k + J_k δ_k`` with covariance
    ``S_k + J_k (H − H_k)⁻¹ J_kᵀ``.  The in-sample residual would hide an outlier
    that the joint fit has bent towards (a wrong line pairing moves a fit of eight
    pairings by metres and then passes its own gate); the deleted one does not.
    A pairing the others cannot fix without (free directions of ``H − H_k``) gets
    a huge predictive variance and passes.
    """
    r, J, S, dof = _residuals(A, B, T, ii, jj)
    W = np.linalg.inv(S)
    Jt = J.transpose(0, 2, 1)
    gk = (Jt @ W @ r[:, :, None])[:, :, 0]
    Pm = _deleted_covs(J, W)
    delta = (Pm @ gk[:, :, None])[:, :, 0]
    rt = r + (J @ delta[:, :, None])[:, :, 0]
    St = S + J @ Pm @ Jt
    c2 = np.einsum("mi,mi->m", rt, np.linalg.solve(St, rt[:, :, None])[:, :, 0])
    ratio: FloatArray = c2 / np.where(dof == 2, gates.g2, gates.g3)
    return ratio


def _fit_inliers(
    A: _Prep,
    B: _Prep,
    ii: IntArray,
    jj: IntArray,
    gates: _Gates,
    x0: FloatArray | None = None,
) -> tuple[IntArray, IntArray, FloatArray, FloatArray]:
    """Fit, drop the pairing whose leave-one-out χ² most exceeds its gate, refit,
    until all pass."""
    T, cov = _estimate(A, B, ii, jj, x0)
    while ii.size > 1:
        ratio = _deleted_ratio(A, B, T, ii, jj, gates)
        worst = int(np.argmax(ratio))
        if ratio[worst] <= 1.0:
            break
        ii, jj = np.delete(ii, worst), np.delete(jj, worst)
        # Restart from scratch: an outlier may have pulled the fit onto a wrong branch.
        T, cov = _estimate(A, B, ii, jj, None)
    return ii, jj, T, cov


def _segments_overlap(
    A: _Prep,
    B: _Prep,
    T: FloatArray,
    ii: IntArray,
    jj: IntArray,
    margin: float,
    within: bool = False,
) -> BoolArray:
    """Whether each line pairing's segments agree along ``A``'s line under ``T``
    (within ``margin``): overlap, or with ``within`` the ``A`` segment inside the
    ``B`` one (``CCDAParams.extent_rule``); circles and lines without extents pass."""
    out = np.ones(ii.size, dtype=bool)
    known = np.all(np.isfinite(A.ext[ii]), axis=1) & np.all(np.isfinite(B.ext[jj]), axis=1)
    if not np.any(known):
        return out
    i, j = ii[known], jj[known]
    c, s = math.cos(float(T[2])), math.sin(float(T[2]))
    thb = B.th[j] + float(T[2])
    qb = np.stack([c * B.p[j, 0] - s * B.p[j, 1], s * B.p[j, 0] + c * B.p[j, 1]], axis=1) + T[:2]
    ta = np.stack([np.cos(A.th[i]), np.sin(A.th[i])], axis=1)
    tb = np.stack([np.cos(thb), np.sin(thb)], axis=1)
    base = np.einsum("mi,mi->m", qb - A.p[i], ta)
    slope = np.einsum("mi,mi->m", tb, ta)
    e0 = base + slope * B.ext[j, 0]
    e1 = base + slope * B.ext[j, 1]
    lo, hi = np.minimum(e0, e1), np.maximum(e0, e1)
    if within:
        out[known] = (lo - margin <= A.ext[i, 0]) & (A.ext[i, 1] <= hi + margin)
    else:
        out[known] = (lo <= A.ext[i, 1] + margin) & (A.ext[i, 0] <= hi + margin)
    return out


def _one_to_one(
    A: _Prep,
    B: _Prep,
    T: FloatArray,
    P: FloatArray,
    ni: IntArray,
    nj: IntArray,
    gates: _Gates,
    margin: float,
    unique: bool,
    within: bool = False,
) -> tuple[IntArray, IntArray, IntArray]:
    """Greedy one-to-one assignment of the nodes passing the gate under ``T`` (whose
    covariance ``P`` widens the gate) whose segments overlap (``margin``); with
    ``unique``, only of the ``A`` features that have a single such partner.

    Returns the chosen ``(ii, jj)`` and the indices of every passing node.
    """
    ratio = _gate_ratio(A, B, T, ni, nj, gates, P)
    ratio[~_segments_overlap(A, B, T, ni, nj, margin, within)] = np.inf
    passing = np.nonzero(ratio <= 1.0)[0].astype(np.int64)
    used_a: set[int] = set()
    used_b: set[int] = set()
    if unique:
        # A feature with two partners inside the gate (parallel walls a door width
        # apart, trees of a grid) is ambiguous under this transform: leave it out.
        u, cnt = np.unique(ni[passing], return_counts=True)
        used_a |= set(u[cnt > 1].tolist())
    chosen: list[int] = []
    # Best residual first, so a feature goes to its nearest compatible partner.
    for n in passing[np.argsort(ratio[passing], kind="stable")].tolist():
        i, j = int(ni[n]), int(nj[n])
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            chosen.append(n)
    c = np.array(sorted(chosen), dtype=np.int64)
    return ni[c], nj[c], passing


def _hypothesis(
    A: _Prep,
    B: _Prep,
    clique: IntArray,
    ni: IntArray,
    nj: IntArray,
    gates: _Gates,
    margin: float = math.inf,
    unique: bool = False,
    within: bool = False,
) -> _Hypothesis:
    """Fit a clique, then re-associate every node with the fitted transform."""
    ii, jj, T, cov = _fit_inliers(A, B, ni[clique], nj[clique], gates)
    n_clique = int(ii.size)
    passing = np.zeros(0, dtype=np.int64)
    # The clique picks one of several partners a feature may have within the gate
    # (collinear walls); the transform then tells which one is nearest.  A few
    # rounds: the refit moves the transform, which can change the assignment.
    for _ in range(3):
        ri, rj, passing = _one_to_one(A, B, T, cov, ni, nj, gates, margin, False, within)
        if ri.size == 0:
            break
        same = ri.size == ii.size and np.array_equal(ri, ii) and np.array_equal(rj, jj)
        ii, jj = ri, rj
        if same:
            break
        ii, jj, T, cov = _fit_inliers(A, B, ii, jj, gates, T)
        passing = np.zeros(0, dtype=np.int64)
    if passing.size == 0:
        # The nodes this transform explains (removed before the search for rivals).
        ratio = _gate_ratio(A, B, T, ni, nj, gates, cov)
        ratio[~_segments_overlap(A, B, T, ni, nj, margin, within)] = np.inf
        passing = np.nonzero(ratio <= 1.0)[0].astype(np.int64)
    support = int(ii.size)
    if unique and ii.size:
        # Support counts every feature the transform explains; the pairings handed
        # on are those without a rival partner inside the gate.
        feats, cnt = np.unique(ni[passing], return_counts=True)
        keep = ~np.isin(ii, feats[cnt > 1])
        if not keep.all():
            ii, jj = ii[keep], jj[keep]
            if ii.size:
                # The transform handed on is the one its pairings give.
                T, cov = _estimate(A, B, ii, jj, T)
    return _Hypothesis(ii=ii, jj=jj, T=T, cov=cov, clique=n_clique, nodes=passing, support=support)


def _compatible(h1: _Hypothesis, h2: _Hypothesis, gates: _Gates) -> bool:
    d = h2.T - h1.T
    d[2] = float(wrap_angle(d[2]))
    q = float(d @ np.linalg.solve(h1.cov + h2.cov, d))
    return q <= gates.g3
