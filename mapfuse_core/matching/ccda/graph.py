"""The correspondence graph: nodes (unary test), rigid-motion invariants, edges (binary test).

Invariants are computed for all feature pairs of each map at once; the pairs of ``A``
are joined to those of ``B`` by a sorted-window search (cost grows with the number of
edges, not ``|A|²·|B|²``), each candidate then tested exactly.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mapfuse_core.geometry.se2 import FloatArray, wrap_angle_half
from mapfuse_core.matching.ccda.params import CCDAParams, _Gates
from mapfuse_core.matching.ccda.prepare import BoolArray, IntArray, _Prep


@dataclass(frozen=True)
class _Pairs:
    """Invariants of pairs ``(i, k)`` of one map (global feature indices)."""

    i: IntArray
    """First feature of each pair."""
    k: IntArray
    """Second feature of each pair."""
    g: FloatArray
    """(m, 2) invariants: (distance, unused) or (angle, distance) for line pairs."""
    S: FloatArray
    """(m, 2, 2) covariance of :attr:`g`."""
    corner: FloatArray | None = None
    """Line pairs: (m, 6) segment intervals along each line measured from the lines'
    intersection, ``(lo_i, hi_i, lo_k, hi_k)``, and the variances of the
    intersection's position along ``i`` and along ``k``; NaN where an extent is
    unknown or the lines are parallel."""
    directed: FloatArray | None = None
    """Line pairs: (m,) directed angle ``θ_k − θ_i`` (not modulo π)."""
    along: FloatArray | None = None
    """Line pairs: (m, 5) segment intervals of ``i`` and ``k`` along ``i``'s direction
    from ``i``'s origin, ``(lo_i, hi_i, lo_k, hi_k)``, and the largest distance of
    ``k``'s segment from line ``i`` (its lever arm on ``i``'s angle); NaN where an
    extent is unknown.  Used only for parallel pairs, whose intersection is at
    infinity (:func:`_parallel_overlap`)."""


def _pairs_cc(P: _Prep) -> _Pairs:
    """Circle–circle pairs ``i < k``: centre distance."""
    a, b = np.triu_indices(P.circ.size, 1)
    i, k = P.circ[a], P.circ[b]
    diff = P.p[k] - P.p[i]
    d = np.hypot(diff[:, 0], diff[:, 1])
    # Coincident centres have no direction; any unit vector gives a fair variance.
    u = np.where(d[:, None] > 1e-9, diff / np.maximum(d, 1e-300)[:, None], [1.0, 0.0])
    var = np.einsum("mi,mij,mj->m", u, P.Sp[i] + P.Sp[k], u)
    g = np.zeros((i.size, 2))
    g[:, 0] = d
    S = np.zeros((i.size, 2, 2))
    S[:, 0, 0] = var
    S[:, 1, 1] = 1.0
    return _Pairs(i=i, k=k, g=g, S=S)


def _pairs_cl(P: _Prep) -> _Pairs:
    """Every (circle, line) pair: unsigned distance from the centre to the line."""
    ii, kk = np.meshgrid(P.circ, P.line, indexing="ij")
    i, k = ii.ravel(), kk.ravel()
    th = P.th[k]
    t = np.stack([np.cos(th), np.sin(th)], axis=1)
    nrm = np.stack([-np.sin(th), np.cos(th)], axis=1)
    rel = P.p[i] - P.p[k]
    s = np.einsum("mi,mi->m", nrm, rel)
    a = np.einsum("mi,mi->m", t, rel)
    # s = n·(p − q) moves by n·δp − e_lat − a·e_θ (rotation of the line about q).
    J = np.stack([-np.ones_like(a), -a], axis=1)
    var = np.einsum("mi,mij,mj->m", nrm, P.Sp[i], nrm) + np.einsum("mi,mij,mj->m", J, P.C[k], J)
    g = np.zeros((i.size, 2))
    g[:, 0] = np.abs(s)
    S = np.zeros((i.size, 2, 2))
    S[:, 0, 0] = var
    S[:, 1, 1] = 1.0
    return _Pairs(i=i, k=k, g=g, S=S)


def _pairs_ll(P: _Prep, ordered: bool) -> _Pairs:
    """Line pairs (``i < k``, or all ``i ≠ k`` when ``ordered``): signed angle from
    ``i`` to ``k`` modulo π, and unsigned lateral distance of ``k``'s origin from
    ``i`` (used only when the lines are parallel)."""
    ln = P.line
    if ordered:
        ii, kk = np.meshgrid(ln, ln, indexing="ij")
        mask = ii != kk
        i, k = ii[mask], kk[mask]
    else:
        a_, b_ = np.triu_indices(ln.size, 1)
        i, k = ln[a_], ln[b_]
    thi, thk = P.th[i], P.th[k]
    ti = np.stack([np.cos(thi), np.sin(thi)], axis=1)
    ni = np.stack([-np.sin(thi), np.cos(thi)], axis=1)
    nk = np.stack([-np.sin(thk), np.cos(thk)], axis=1)
    rel = P.p[k] - P.p[i]
    delta = wrap_angle_half(thk - thi)
    s = np.einsum("mi,mi->m", ni, rel)
    a = np.einsum("mi,mi->m", ti, rel)
    m = np.einsum("mi,mi->m", ni, nk)
    Ci, Ck = P.C[i], P.C[k]
    # Δ = θk − θi;  s = n_i·(q_k − q_i) moves by −e_lat_i − a·e_θi + (n_i·n_k)·e_lat_k.
    var_d = Ci[:, 1, 1] + Ck[:, 1, 1]
    var_s = Ci[:, 0, 0] + 2.0 * a * Ci[:, 0, 1] + a * a * Ci[:, 1, 1] + m * m * Ck[:, 0, 0]
    cov_ds = (Ci[:, 0, 1] + a * Ci[:, 1, 1] + m * Ck[:, 0, 1]) * np.where(s >= 0.0, 1.0, -1.0)
    g = np.stack([delta, np.abs(s)], axis=1)
    S = np.empty((i.size, 2, 2))
    S[:, 0, 0] = var_d
    S[:, 1, 1] = var_s
    S[:, 0, 1] = S[:, 1, 0] = cov_ds
    corner = _corners(P, i, k, ti, ni, nk, rel)
    along = _along(P, i, k, ti, ni, rel)
    return _Pairs(i=i, k=k, g=g, S=S, corner=corner, directed=thk - thi, along=along)


def _along(
    P: _Prep, i: IntArray, k: IntArray, ti: FloatArray, ni: FloatArray, rel: FloatArray
) -> FloatArray:
    """Segment intervals of line pairs along the first line (see :attr:`_Pairs.along`)."""
    out = np.full((i.size, 5), np.nan)
    ok = np.all(np.isfinite(P.ext[i]), axis=1) & np.all(np.isfinite(P.ext[k]), axis=1)
    if not np.any(ok):
        return out
    i, k, ti, ni, rel = i[ok], k[ok], ti[ok], ni[ok], rel[ok]
    tk = np.stack([np.cos(P.th[k]), np.sin(P.th[k])], axis=1)
    ends = rel[:, None, :] + P.ext[k][:, :, None] * tk[:, None, :]  # (m, 2 ends, xy)
    proj = np.einsum("mei,mi->me", ends, ti)
    out[ok, 0:2] = P.ext[i]
    out[ok, 2] = proj.min(axis=1)
    out[ok, 3] = proj.max(axis=1)
    out[ok, 4] = np.abs(np.einsum("mei,mi->me", ends, ni)).max(axis=1)
    return out


def _corners(
    P: _Prep,
    i: IntArray,
    k: IntArray,
    ti: FloatArray,
    ni: FloatArray,
    nk: FloatArray,
    rel: FloatArray,
) -> FloatArray:
    """Segment intervals of line pairs measured from their intersection (see
    :attr:`_Pairs.corner`).

    With ``c = q_i + s_i t_i = q_k + s_k t_k`` the intersection, ``s_i = n_k·(q_k −
    q_i) / (n_k·t_i)`` and ``s_k = n_i·(q_i − q_k) / (n_i·t_k)``; a rigid motion
    keeps ``c`` on both lines, so the intervals ``extent − s`` are invariants (up
    to the sign of each line's direction).  The intersection moves along ``i`` by
    ``(δ_lat_k + s_k δθ_k − cos Δ (δ_lat_i + s_i δθ_i)) / sin Δ``, whose variance
    is bounded by the sum of the four terms' variances over ``sin² Δ``.
    """
    out = np.full((i.size, 6), np.nan)
    sin_d = np.einsum("mi,mi->m", nk, ti)  # n_k·t_i = sin(θ_k − θ_i) up to sign
    tk = np.stack([nk[:, 1], -nk[:, 0]], axis=1)
    ok = (np.abs(sin_d) > 1e-6) & np.all(np.isfinite(P.ext[i]), axis=1)
    ok &= np.all(np.isfinite(P.ext[k]), axis=1)
    if not np.any(ok):
        return out
    sd = sin_d[ok]
    s_i = np.einsum("mi,mi->m", nk[ok], rel[ok]) / sd
    s_k = np.einsum("mi,mi->m", ni[ok], -rel[ok]) / np.einsum("mi,mi->m", ni[ok], tk[ok])
    Ci, Ck = P.C[i[ok]], P.C[k[ok]]
    lat = Ci[:, 0, 0] + Ck[:, 0, 0]
    var_i = (lat + s_k**2 * Ck[:, 1, 1] + s_i**2 * Ci[:, 1, 1]) / sd**2
    var_k = (lat + s_i**2 * Ci[:, 1, 1] + s_k**2 * Ck[:, 1, 1]) / sd**2
    out[ok, 0:2] = P.ext[i[ok]] - s_i[:, None]
    out[ok, 2:4] = P.ext[k[ok]] - s_k[:, None]
    out[ok, 4] = var_i
    out[ok, 5] = var_k
    return out


#: Candidate pairs materialised at once by the window join (bounds its memory).
_CHUNK = 1 << 20

_Emit = Callable[[IntArray, IntArray], None]


class _GraphTooLargeError(Exception):
    """The correspondence graph exceeds ``CCDAParams.max_edges``."""

    def __init__(self, n_nodes: int) -> None:
        super().__init__(n_nodes)
        self.n_nodes = n_nodes


def _gated_join(
    va: FloatArray,
    var_a: FloatArray,
    vb: FloatArray,
    var_b: FloatArray,
    gate: float,
    emit: _Emit,
    period: float | None = None,
) -> None:
    """Emit, in chunks, all ``(a, b)`` with ``(va[a] − vb[b])² ≤ gate · (var_a[a] + var_b[b])``.

    ``B`` is sorted and each ``a`` searches a window around its value, so the cost
    follows the number of matches, not ``|A|·|B|``.  ``B`` is split into groups
    whose variances are within a factor of 4, each searched with a window sized for
    its largest variance, so one very uncertain pair does not widen every window.
    With a ``period`` the difference is taken modulo it (line angles, period π).
    """
    if va.size == 0 or vb.size == 0:
        return
    group = np.floor(np.log(np.maximum(var_b, 1e-300)) / math.log(4.0)).astype(np.int64)
    for key in np.unique(group).tolist():
        members = np.nonzero(group == key)[0].astype(np.int64)
        # Widen slightly: the window only preselects; the exact test follows.
        h = np.sqrt(gate * (var_a + float(var_b[members].max()))) * (1.0 + 1e-9)
        vals = vb[members]
        if period is not None:
            h = np.minimum(h, 0.49 * period)
            vals = np.concatenate([vals - period, vals, vals + period])
        order = np.argsort(vals, kind="stable")
        sb = vals[order]
        lo = np.searchsorted(sb, va - h, side="left")
        cnt = np.maximum(np.searchsorted(sb, va + h, side="right") - lo, 0)
        ends = np.cumsum(cnt)
        a0 = 0
        while a0 < va.size:
            base = int(ends[a0 - 1]) if a0 else 0
            a1 = min(va.size, max(a0 + 1, int(np.searchsorted(ends, base + _CHUNK, "right"))))
            c = cnt[a0:a1]
            total = int(c.sum())
            if total:
                ia = np.repeat(np.arange(a0, a1, dtype=np.int64), c)
                start = np.repeat(lo[a0:a1] - (np.cumsum(c) - c), c)
                ib = members[order[np.arange(total, dtype=np.int64) + start] % members.size]
                d = va[ia] - vb[ib]
                if period is not None:
                    d = d - period * np.round(d / period)
                ok = d * d <= gate * (var_a[ia] + var_b[ib])
                emit(ia[ok], ib[ok])
            a0 = a1


def _corners_overlap(
    ca: FloatArray, cb: FloatArray, sign: FloatArray, gates: _Gates, params: CCDAParams
) -> BoolArray:
    """Whether the segments of two non-parallel line pairings can agree, pair by pair:
    each ``A`` segment within its ``B`` partner (``params.extent_rule`` ``"within"``)
    or overlapping it (``"overlap"``), along the line from the lines' intersection.

    ``ca``, ``cb``: :attr:`_Pairs.corner` rows of the ``A`` pair ``(i, k)`` and the
    ``B`` pair ``(j, l)``; ``sign`` from the directed angles.  The rotation is known
    only modulo π from the lines, so both are tried: line ``i``'s direction maps to
    ``j``'s (and ``k``'s to ``sign`` times ``l``'s), or both reversed.  Rows with an
    unknown extent pass.
    """
    known = np.isfinite(ca[:, :4]).all(axis=1) & np.isfinite(cb[:, :4]).all(axis=1)
    if not known.any():
        return np.ones(ca.shape[0], dtype=bool)
    if not known.all():
        ca, cb, sign = ca[known], cb[known], sign[known]
    within = params.extent_rule == "within"

    def both(
        lo: FloatArray, hi: FloatArray, blo: FloatArray, bhi: FloatArray, var: FloatArray
    ) -> tuple[BoolArray, BoolArray]:
        # Whether [lo, hi] agrees with [blo, bhi] as measured, and reversed along its
        # line ([−hi, −lo]): each candidate's rotation picks one per line.
        m = params.extent_margin_m + np.sqrt(gates.g1 * var)
        top = bhi + m
        if within:
            bottom = blo - m
            return (bottom <= lo) & (hi <= top), (bottom <= -hi) & (-lo <= top)
        return (lo <= top) & (blo <= hi + m), (-hi <= top) & (blo <= m - lo)

    i_fwd, i_rev = both(ca[:, 0], ca[:, 1], cb[:, 0], cb[:, 1], ca[:, 4] + cb[:, 4])
    k_same, k_flip = both(ca[:, 2], ca[:, 3], cb[:, 2], cb[:, 3], ca[:, 5] + cb[:, 5])
    # Line k's direction maps to ``sign`` times l's when i's maps to j's, and to
    # ``−sign`` times l's when i's is reversed (``sign`` is ±1).
    ok: BoolArray = (i_fwd & np.where(sign > 0, k_same, k_flip)) | (
        i_rev & np.where(sign < 0, k_same, k_flip)
    )
    if ok.size == known.size:
        return ok
    out = np.ones(known.size, dtype=bool)
    out[known] = ok
    return out


def _parallel_overlap(
    pa: _Pairs, pb: _Pairs, ia: IntArray, ib: IntArray, gates: _Gates, params: CCDAParams
) -> BoolArray:
    """Whether the segments of two parallel line pairings can agree under one motion.

    Parallel lines do not fix where along them the motion puts ``B``'s segments, but
    it is one offset ``c`` for both pairings: along ``i``'s direction, an ``A``
    coordinate is ``σ·b + c`` for a ``B`` coordinate ``b`` along ``j``'s direction
    (``σ = ±1``: the rotation is known only modulo π from the lines).  Each pairing
    allows an interval of ``c`` (its segments overlap, or with ``"within"`` the ``A``
    one lies within the ``B`` one, within :attr:`CCDAParams.extent_margin_m` plus the
    lever arm of each map's angle noise and the foreshortening an angle error within
    the gate gives ``B``'s coordinates); the pairings can both hold when their
    intervals meet, for either ``σ``.  Without this test, pairings of walls along a
    corridor shifted by any length form large chance cliques.  Rows with an unknown
    extent pass.
    """
    out = np.ones(ia.size, dtype=bool)
    if pa.along is None or pb.along is None:
        return out
    a, b = pa.along[ia], pb.along[ib]
    known = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1)
    if not np.any(known):
        return out
    a, b = a[known], b[known]
    # The pair's angle variance (both lines') bounds that of line i's direction.
    sd_a = np.sqrt(pa.S[ia[known], 0, 0])
    sd_b = np.sqrt(pb.S[ib[known], 0, 0])
    lever = np.sqrt(gates.g1) * (a[:, 4] * sd_a + b[:, 4] * sd_b)
    # An angle error ε between the maps foreshortens B's coordinates by 1 − cos ε ≈ ε²/2,
    # which the one offset cannot absorb across the span of B's two segments.
    span = b[:, 0:4].max(axis=1) - b[:, 0:4].min(axis=1)
    foreshortening = 0.5 * gates.g2 * (sd_a**2 + sd_b**2) * span
    m_first = params.extent_margin_m + foreshortening
    m_second = params.extent_margin_m + lever + foreshortening
    within = params.extent_rule == "within"

    def offsets(
        alo: FloatArray, ahi: FloatArray, blo: FloatArray, bhi: FloatArray, m: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        # Offsets c for which [alo, ahi] and [blo + c, bhi + c] agree.
        if within:
            return ahi - bhi - m, alo - blo + m
        return alo - bhi - m, ahi - blo + m

    ok = np.zeros(a.shape[0], dtype=bool)
    for sg in (1.0, -1.0):
        b1 = np.sort(sg * b[:, 0:2], axis=1)
        b2 = np.sort(sg * b[:, 2:4], axis=1)
        lo1, hi1 = offsets(a[:, 0], a[:, 1], b1[:, 0], b1[:, 1], m_first)
        lo2, hi2 = offsets(a[:, 2], a[:, 3], b2[:, 0], b2[:, 1], m_second)
        ok |= np.maximum(lo1, lo2) <= np.minimum(hi1, hi2)
    out[known] = ok
    return out


def _line_filter(pa: _Pairs, pb: _Pairs, gates: _Gates, params: CCDAParams, emit: _Emit) -> _Emit:
    """Wrap ``emit`` with the test of parallel line pairs: angle and distance jointly."""

    def parallel_test(ia: IntArray, ib: IntArray) -> None:
        ang_a, ang_b = pa.g[ia, 0], pb.g[ib, 0]
        abs_a, abs_b = np.abs(ang_a), np.abs(ang_b)
        par = (abs_a <= params.parallel_tol_rad) & (abs_b <= params.parallel_tol_rad)
        ok = np.ones(ia.size, dtype=bool)
        rows = np.flatnonzero(par)
        if rows.size:
            ja, jb = ia[rows], ib[rows]
            da = wrap_angle_half(ang_a[rows] - ang_b[rows])
            dd = pa.g[ja, 1] - pb.g[jb, 1]
            S = pa.S[ja] + pb.S[jb]
            # Nearly parallel lines: their distance depends on where it is measured.
            sin_max = np.sin(np.maximum(abs_a[rows], abs_b[rows]))
            S[:, 1, 1] += (sin_max * params.parallel_along_std_m) ** 2
            det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] ** 2
            q = (S[:, 1, 1] * da * da - 2.0 * S[:, 0, 1] * da * dd + S[:, 0, 0] * dd * dd) / det
            ok[rows] = q <= gates.g2
            test = rows[ok[rows]]
            ok[test] = _parallel_overlap(pa, pb, ia[test], ib[test], gates, params)
        rows = np.flatnonzero(~par)
        if pa.corner is not None and pb.corner is not None and rows.size:
            na, nb = ia[rows], ib[rows]
            ok[rows] = _corners_overlap(
                pa.corner[na], pb.corner[nb], dang_sign(na, nb), gates, params
            )
        emit(ia[ok], ib[ok])

    def dang_sign(ia: IntArray, ib: IntArray) -> FloatArray:
        # +1 when the directed angles from i to k agree in both maps, −1 when they
        # differ by π (one line's direction is reversed relative to the other).
        assert pa.directed is not None
        assert pb.directed is not None
        sign: FloatArray = np.where(np.cos(pa.directed[ia] - pb.directed[ib]) >= 0.0, 1.0, -1.0)
        return sign

    return parallel_test


def _lengths_fit(A: _Prep, B: _Prep, la: IntArray, lb: IntArray, params: CCDAParams) -> BoolArray:
    """Unary test of line nodes ``(la, lb)`` under ``params.extent_rule`` ``"within"``:
    the ``A`` segment is at most ``2 · extent_margin_m`` longer than its ``B``
    partner (a length is frame-free: the part of a wall a run saw is no longer than
    the wall).  Every node passes under ``"overlap"``, and where an extent is unknown.
    """
    ok = np.ones(la.size, dtype=bool)
    if params.extent_rule != "within" or la.size == 0:
        return ok
    len_a = A.ext[la, 1] - A.ext[la, 0]
    len_b = B.ext[lb, 1] - B.ext[lb, 0]
    known = np.isfinite(len_a) & np.isfinite(len_b)
    ok[known] = len_a[known] <= len_b[known] + 2.0 * params.extent_margin_m
    return ok


def _build_graph(
    A: _Prep, B: _Prep, params: CCDAParams, gates: _Gates
) -> tuple[IntArray, IntArray, IntArray, IntArray]:
    """Nodes ``(ni, nj)`` and edges ``(eu, ev)`` (node indices) of the correspondence graph.

    Raises :class:`_GraphTooLargeError` as soon as the edges exceed ``params.max_edges``.
    """
    node_of = np.full((A.n, B.n), -1, dtype=np.int64)
    # Circles: unary radius test.
    cag, cbg = np.meshgrid(A.circ, B.circ, indexing="ij")
    ca, cb = cag.ravel(), cbg.ravel()
    dr = A.params[ca, 2] - B.params[cb, 2]
    okr = dr * dr <= gates.g1 * (A.vr[ca] + B.vr[cb])
    lag, lbg = np.meshgrid(A.line, B.line, indexing="ij")
    la, lb = lag.ravel(), lbg.ravel()
    okl = _lengths_fit(A, B, la, lb, params)
    ni = np.concatenate([ca[okr], la[okl]]).astype(np.int64)
    nj = np.concatenate([cb[okr], lb[okl]]).astype(np.int64)
    node_of[ni, nj] = np.arange(ni.size, dtype=np.int64)

    us: list[IntArray] = []
    vs: list[IntArray] = []
    count = [0]

    def add(ai: IntArray, ak: IntArray, bj: IntArray, bl: IntArray) -> None:
        u, v = node_of[ai, bj], node_of[ak, bl]
        keep = (u >= 0) & (v >= 0)
        us.append(u[keep])
        vs.append(v[keep])
        count[0] += int(keep.sum())
        if count[0] > params.max_edges:
            raise _GraphTooLargeError(int(ni.size))

    # Circle–circle: distances are symmetric, so unordered pairs on both sides and
    # both orientations of the B pair.
    cc_a, cc_b = _pairs_cc(A), _pairs_cc(B)

    def emit_cc(ia: IntArray, ib: IntArray) -> None:
        add(cc_a.i[ia], cc_a.k[ia], cc_b.i[ib], cc_b.k[ib])
        add(cc_a.i[ia], cc_a.k[ia], cc_b.k[ib], cc_b.i[ib])

    _gated_join(cc_a.g[:, 0], cc_a.S[:, 0, 0], cc_b.g[:, 0], cc_b.S[:, 0, 0], gates.g1, emit_cc)
    # Circle–line: (circle, line) on both sides, one orientation.
    cl_a, cl_b = _pairs_cl(A), _pairs_cl(B)

    def emit_cl(ia: IntArray, ib: IntArray) -> None:
        add(cl_a.i[ia], cl_a.k[ia], cl_b.i[ib], cl_b.k[ib])

    _gated_join(cl_a.g[:, 0], cl_a.S[:, 0, 0], cl_b.g[:, 0], cl_b.S[:, 0, 0], gates.g1, emit_cl)
    # Line–line: the angle is signed, so unordered in A against ordered in B.
    ll_a, ll_b = _pairs_ll(A, ordered=False), _pairs_ll(B, ordered=True)

    def emit_ll(ia: IntArray, ib: IntArray) -> None:
        add(ll_a.i[ia], ll_a.k[ia], ll_b.i[ib], ll_b.k[ib])

    _gated_join(
        ll_a.g[:, 0],
        ll_a.S[:, 0, 0],
        ll_b.g[:, 0],
        ll_b.S[:, 0, 0],
        gates.g1,
        _line_filter(ll_a, ll_b, gates, params, emit_ll),
        period=math.pi,
    )
    eu = np.concatenate(us) if us else np.zeros(0, np.int64)
    ev = np.concatenate(vs) if vs else np.zeros(0, np.int64)
    return ni, nj, eu, ev


def _k_core(n: int, eu: IntArray, ev: IntArray, k: int) -> BoolArray:
    """Mask of the nodes of the ``k``-core (every node has ≥ ``k`` neighbours in it)."""
    alive = np.ones(n, dtype=bool)
    if k <= 0:
        return alive
    while True:
        keep = alive[eu] & alive[ev]
        deg = np.bincount(eu[keep], minlength=n) + np.bincount(ev[keep], minlength=n)
        new = alive & (deg >= k)
        if np.array_equal(new, alive):
            return alive
        alive = new
