"""Map-to-map matching by Combined Constraint Data Association (method.md §5.1).

CCDA (Bailey, Nebot, Rosenblatt, Durrant-Whyte, ICRA 2000) finds which features of
map ``A`` are the same physical features as features of map ``B`` when the rigid
motion between the two frames is unknown.  In mapfuse ``A`` is the SLAM global map
(frame ``Wglobal``) and ``B`` the a-priori known map (frame ``Wknown``); the result
is ``x^Wglobal_Wknown`` (the paper's eq. 12) with its covariance.

The method, step by step:

1. **Nodes (unary test).**  A node of the correspondence graph is a pair
   ``(i in A, j in B)`` of the same kind.  Circles must also have compatible radii:
   ``(r_a − r_b)² ≤ χ²₁(p) · (σ²_ra + σ²_rb)``.  Lines have no frame-free unary
   property (their offset and angle change with the frame), so every line pair is
   a node.
2. **Edges (binary test).**  Two nodes ``(i, j)`` and ``(k, l)`` with ``i ≠ k`` and
   ``j ≠ l`` are joined when the rigid-motion invariants of the pair ``(i, k)`` in
   ``A`` agree with those of ``(j, l)`` in ``B`` within a χ² gate computed from
   the first-order propagated covariances of the four features:

   * circle–circle: distance between the centres (1 dof);
   * circle–line: unsigned distance from the centre to the line (1 dof);
   * line–line: signed angle from the first line to the second, modulo π (1 dof);
     when both pairs are parallel (``|angle| ≤ parallel_tol_rad`` in both maps) also
     the unsigned lateral distance of the second line's origin from the first line,
     tested jointly with the angle (2 dof, with their correlation).

   Lines enter only through their lateral offset and angle: every line covariance
   is first reduced to the 2×2 covariance of ``(e_lat, e_θ)``, the SPmap
   perturbation ``L ⊕ (0, e_lat, e_θ)``, so the along-line pseudo-variance is never
   used.  The invariants are computed with numpy for all feature pairs of each map;
   the pairs of ``A`` are joined to those of ``B`` by sorting ``B``'s values and
   searching a window around each value of ``A`` (so the cost grows with the number
   of edges, not with ``|A|²·|B|²``), and each candidate is then tested exactly.
3. **Maximum clique.**  Nodes that cannot be in a clique of ``min_pairings`` nodes
   are pruned (k-core), then an exact maximum clique is searched by
   :class:`_CliqueGraph` (networkx's ``max_weight_clique`` takes seconds on the
   ~300,000-edge graphs of 200 × 60 feature maps; see that class for the method).
4. **Transform and verification.**  The transform is estimated from the clique's
   pairings by weighted least squares (:func:`estimate_transform`).  Every pairing
   is then tested *leave-one-out*: its residual against the transform fitted to
   the other pairings, with that fit's covariance added (a wrong line pairing can
   bend a fit of eight pairings by a metre and then pass its own in-sample gate).
   The worst failure is dropped and the fit repeated until all pass.  Finally
   every node is re-associated with the fitted transform (one-to-one, nearest
   first, gate widened by the transform's covariance) and refitted: the clique
   may have picked the wrong one of two collinear walls, or missed a pairing
   whose edge to one member failed its gate by chance.
5. **Acceptance.**  The match is accepted only with at least ``min_pairings``
   pairings (the paper: "more than three"), a covariance showing that the
   pairings fix the transform, and no competing hypothesis: the nodes that agree
   with the transform are removed, the next maximum clique is searched and
   fitted, and so on while a clique large enough to compete remains; if a
   hypothesis whose transform is incompatible with the best one has nearly as
   many pairings (within ``ambiguity_margin``), the map is symmetric or repetitive
   at the scale of the noise and the match is rejected as ``"ambiguous"`` rather
   than chosen at random.

Choices the paper leaves open (all configurable in :class:`CCDAParams`):

* *(choice)* One gate probability, ``gate_prob = 0.999``, for the unary, binary
  and pairing tests.  A true pair of features fails one test with probability
  ``1 − p``; a clique of ``n`` true pairings needs ``n(n−1)/2`` edges, so a strict
  gate is needed for large overlaps to stay a single clique (and step 4 recovers
  the few true pairings the clique still misses).
* *(choice)* Correlations between features of one map are ignored (a
  :class:`KnownMapArrays` only holds marginal covariances).  In a SLAM map nearby
  features are positively correlated, so their relative geometry is better known
  than the marginals say: ignoring the correlation makes the gates looser, which
  can add spurious edges but does not cut true ones.
* *(choice)* Distances are unsigned (circle–line and parallel line–line) because a
  line has no direction; the line–line angle keeps its sign (a rotation preserves
  it, a reflection would not).  Circle–circle distances cannot tell a map from
  its mirror image: mirror cliques of symmetric maps are found and then fail the
  transform fit of step 4.
* *(choice)* Two lines are parallel for the distance test when the angle between
  them is at most ``parallel_tol_rad`` in both maps.  For lines that are only
  nearly parallel the distance depends on where along the lines it is measured,
  and SPmap origins sit at segment midpoints that differ between maps; the
  variance of the distance is therefore increased by
  ``(sin(max |angle|) · parallel_along_std_m)²``.
* *(choice)* A line's covariance is read in its own frame: lateral variance
  ``nᵀ Σ_xy n`` with ``n`` the normal of the line's *own* angle, as extraction
  (pseudo-variance along the fitted direction) and the EKF (along-line component
  projected out) state it.  A pseudo-variance ``L²`` along some other direction
  would leak ``L² sin²δ`` into the lateral one.
* *(choice)* Every variance gets a small floor (``var_floor_m``,
  ``var_floor_rad``) so that noise-free maps (e.g. the true world, whose
  covariances are zero) still give invertible gates.
* *(choice)* The transform is "fixed" when the largest standard deviation of its
  position (worst direction) is at most ``max_transform_std_xy_m`` and that of its
  angle at most ``max_transform_std_theta_rad``.  Degenerate sets (only parallel
  lines, a single circle with lines through it, …) have a rank-deficient
  information matrix; its null directions get a variance of ``1 / 1e-12``.
* *(choice)* A competing hypothesis counts when its transform differs from the
  best one beyond the χ²₃ gate of their summed covariances and it has at least
  ``max(min_pairings, best − ambiguity_margin)`` pairings after re-association
  (step 4).  Pairings are counted after re-association, not as clique sizes,
  because removing the best hypothesis' nodes also removes a feature both share
  (the centre of a rotational symmetry) from the rival's clique; the search for
  rivals continues down to cliques one node smaller than needed for that reason.
* *(choice)* The returned pairings are those of step 4: consistent with the
  estimated transform leave-one-out, one-to-one, each feature with its nearest
  compatible partner.  ``clique_size`` reports the maximum clique's inliers.
* *(choice)* Graphs beyond ``max_edges`` edges are not searched (the exact search
  costs about ``edges × nodes / 64`` word operations); the call returns
  ``"graph too large"`` after bounded time and memory.

Everything fails cleanly: empty or too small maps and every rejection give a
:class:`CCDAResult` with ``accepted=False`` and a reason; only malformed input
(non-finite numbers, wrong shapes, unknown kinds, bad parameters) raises
:class:`ValueError`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from mapfuse_core.features import FeatureKind
from mapfuse_core.measlog import KnownMapArrays
from mapfuse_core.se2 import FloatArray, as_pose, rot2, wrap_angle, wrap_angle_half

__all__ = [
    "CCDAParams",
    "CCDAResult",
    "ccda_match",
    "estimate_transform",
    "pairing_chi2",
]

IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

#: Information below this (1/m², 1/rad²) is treated as none: the direction is free.
_INFO_FLOOR = 1e-12

#: The shortest step (fraction of the Gauss–Newton step) the line search tries.
_MIN_STEP = 2.0**-20
#: Below this step the line search first checks that the shortest step helps at all.
_PROBE_BELOW = 2.0**-4

_LINE = int(FeatureKind.LINE)
_CIRCLE = int(FeatureKind.CIRCLE)


@dataclass(frozen=True)
class CCDAParams:
    """Tuning of :func:`ccda_match`; every default is a documented *(choice)*."""

    gate_prob: float = 0.999
    """χ² gate probability of the unary (radius), binary (invariant), pairing
    (leave-one-out residual under the estimated transform) and transform
    compatibility tests."""
    min_pairings: int = 4
    """Fewest pairings accepted; the paper requires "more than three"."""
    max_transform_std_xy_m: float = 1.0
    """Largest standard deviation (worst direction) of the transform's position for
    the pairings to count as fixing it; larger means degenerate geometry."""
    max_transform_std_theta_rad: float = 0.05
    """Largest standard deviation of the transform's angle for it to count as fixed."""
    parallel_tol_rad: float = 0.1
    """Two lines are parallel (their distance becomes an invariant too) when the angle
    between them is at most this in both maps.  Should exceed a few σ of the angle
    noise, or truly parallel lines only get the weaker angle test."""
    parallel_along_std_m: float = 10.0
    """Spread of the along-line origins of one wall between the maps, used to widen
    the distance gate of nearly (not exactly) parallel lines."""
    ambiguity_margin: int = 1
    """A hypothesis incompatible with the best one and supported by at least
    ``best − ambiguity_margin`` pairings makes the match ambiguous."""
    max_hypotheses: int = 10
    """Most maximum-clique searches (best plus competitors) per call."""
    max_edges: int = 5_000_000
    """Largest correspondence graph searched.  The exact search costs about
    ``edges × nodes / 64`` word operations (0.25 s for 200 × 60 features and 3·10⁵
    edges, 3 s for 200 × 200 and 3·10⁶): beyond this the call returns
    ``"graph too large"`` instead of running for minutes; match a cropped map."""
    var_floor_m: float = 1e-4
    """Standard deviation (m) added in quadrature to every positional variance."""
    var_floor_rad: float = 1e-5
    """Standard deviation (rad) added in quadrature to every angular variance."""


@dataclass(frozen=True)
class CCDAResult:
    """Outcome of :func:`ccda_match`; diagnostics are filled even when rejected."""

    accepted: bool
    """True when the pairings fix an unambiguous transform."""
    reason: str
    """``"accepted"``, ``"empty map"``, ``"too few features"``, ``"too few pairings"``,
    ``"degenerate geometry"``, ``"ambiguous"`` or ``"graph too large"``."""
    pairings: tuple[tuple[int, int], ...]
    """``(index into map_a, index into map_b)``, sorted, of the best hypothesis: its
    maximum clique's inliers, re-associated one-to-one to the nearest partner within
    the gate under the fitted transform (which can swap a clique pairing for a closer
    collinear wall and add pairings the clique missed).  Also filled when rejected,
    for diagnostics."""
    x_A_B: FloatArray
    """(3,) pose of frame ``B`` in frame ``A`` estimated from :attr:`pairings` (NaN
    when no hypothesis was fitted: empty, too small or too large inputs)."""
    cov: FloatArray
    """(3, 3) covariance of :attr:`x_A_B` (NaN if no estimate)."""
    n_nodes: int
    """Nodes of the correspondence graph (type- and radius-compatible pairs)."""
    n_edges: int
    """Edges of the correspondence graph, before pruning (``max_edges + 1`` when the
    graph was too large: building stopped there)."""
    clique_size: int
    """Inliers of the maximum clique the best hypothesis grew from (``len(pairings)``
    is this after re-association)."""
    runner_up_size: int
    """Pairings of the strongest hypothesis whose transform is incompatible with the
    best one (0 if none)."""
    n_hypotheses: int = 0
    """Hypotheses (maximum cliques) fitted."""


# --------------------------------------------------------------------------- preparation


@dataclass(frozen=True)
class _Prep:
    """One map reduced to what matching needs, in its own frame."""

    kinds: NDArray[np.int8]
    """(n,) feature kinds."""
    params: FloatArray
    """(n, 3) raw parameters."""
    covs: FloatArray
    """(n, 3, 3) covariances, with the variance floor added (circles only)."""
    circ: IntArray
    """Indices of the circles."""
    line: IntArray
    """Indices of the lines."""
    p: FloatArray
    """(n, 2) circle centres / line origins."""
    Sp: FloatArray
    """(n, 2, 2) covariance of the circle centres (unused for lines)."""
    vr: FloatArray
    """(n,) variance of the circle radii (unused for lines)."""
    th: FloatArray
    """(n,) line angles (unused for circles)."""
    C: FloatArray
    """(n, 2, 2) covariance of a line's ``(e_lat, e_θ)`` perturbation (unused for
    circles)."""

    @property
    def n(self) -> int:
        """Number of features."""
        return int(self.kinds.shape[0])


def _check_finite(name: str, a: FloatArray) -> None:
    bad = np.argwhere(~np.isfinite(a))
    if bad.size:
        idx = tuple(int(v) for v in bad[0])
        where = ", ".join(str(v) for v in idx)
        raise ValueError(f"{name}[{where}] is not finite ({a[idx]})")


def _prepare(m: KnownMapArrays, name: str, params: CCDAParams) -> _Prep:
    """Validate a map (errors name ``name``) and reduce it to :class:`_Prep`."""
    kinds = np.asarray(m.kinds)
    n = int(kinds.shape[0]) if kinds.ndim == 1 else -1
    if n < 0:
        raise ValueError(f"{name}.kinds must be one-dimensional, got shape {kinds.shape}")
    P = np.asarray(m.params, dtype=np.float64)
    S = np.asarray(m.covs, dtype=np.float64)
    if P.shape != (n, 3):
        raise ValueError(f"{name}.params has shape {P.shape}, expected ({n}, 3)")
    if S.shape != (n, 3, 3):
        raise ValueError(f"{name}.covs has shape {S.shape}, expected ({n}, 3, 3)")
    bad_kind = np.nonzero((kinds != _LINE) & (kinds != _CIRCLE))[0]
    if bad_kind.size:
        i = int(bad_kind[0])
        raise ValueError(f"{name}.kinds[{i}] = {kinds[i]} is not a feature kind")
    _check_finite(f"{name}.params", P)
    _check_finite(f"{name}.covs", S)
    kinds = kinds.astype(np.int8)
    circ = np.nonzero(kinds == _CIRCLE)[0].astype(np.int64)
    line = np.nonzero(kinds == _LINE)[0].astype(np.int64)
    vm, va = params.var_floor_m**2, params.var_floor_rad**2

    covs = S.copy()
    covs[circ] += np.diag([vm, vm, vm])
    p = P[:, :2].copy()
    Sp = covs[:, :2, :2].copy()
    vr = covs[:, 2, 2].copy()
    th = P[:, 2].copy()
    # (e_lat, e_θ) covariance of a line: project the position block on the normal
    # only, so the along-line pseudo-variance never enters.
    nrm = np.stack([-np.sin(th), np.cos(th)], axis=1)
    C = np.zeros((n, 2, 2))
    C[:, 0, 0] = np.einsum("ni,nij,nj->n", nrm, S[:, :2, :2], nrm) + vm
    C[:, 0, 1] = C[:, 1, 0] = np.einsum("ni,ni->n", nrm, S[:, :2, 2])
    C[:, 1, 1] = S[:, 2, 2] + va
    return _Prep(
        kinds=kinds, params=P, covs=covs, circ=circ, line=line, p=p, Sp=Sp, vr=vr, th=th, C=C
    )


# --------------------------------------------------------------------------- invariants


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
    return _Pairs(i=i, k=k, g=g, S=S)


@dataclass(frozen=True)
class _Gates:
    """χ² thresholds by degrees of freedom."""

    g1: float
    """1 dof."""
    g2: float
    """2 dof."""
    g3: float
    """3 dof."""

    @staticmethod
    def of(p: float) -> _Gates:
        v = np.asarray(chi2.ppf(p, [1, 2, 3]), dtype=np.float64)
        return _Gates(float(v[0]), float(v[1]), float(v[2]))


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


def _line_filter(pa: _Pairs, pb: _Pairs, gates: _Gates, params: CCDAParams, emit: _Emit) -> _Emit:
    """Wrap ``emit`` with the test of parallel line pairs: angle and distance jointly."""

    def parallel_test(ia: IntArray, ib: IntArray) -> None:
        dang = wrap_angle_half(pa.g[ia, 0] - pb.g[ib, 0])
        abs_a, abs_b = np.abs(pa.g[ia, 0]), np.abs(pb.g[ib, 0])
        par = (abs_a <= params.parallel_tol_rad) & (abs_b <= params.parallel_tol_rad)
        ok = np.ones(ia.size, dtype=bool)
        if np.any(par):
            ja, jb, da = ia[par], ib[par], dang[par]
            dd = pa.g[ja, 1] - pb.g[jb, 1]
            S = pa.S[ja] + pb.S[jb]
            # Nearly parallel lines: their distance depends on where it is measured.
            sin_max = np.sin(np.maximum(abs_a[par], abs_b[par]))
            S[:, 1, 1] += (sin_max * params.parallel_along_std_m) ** 2
            det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] ** 2
            q = (S[:, 1, 1] * da * da - 2.0 * S[:, 0, 1] * da * dd + S[:, 0, 0] * dd * dd) / det
            ok[par] = q <= gates.g2
        emit(ia[ok], ib[ok])

    return parallel_test


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
    la, lb = np.meshgrid(A.line, B.line, indexing="ij")
    ni = np.concatenate([ca[okr], la.ravel()]).astype(np.int64)
    nj = np.concatenate([cb[okr], lb.ravel()]).astype(np.int64)
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


# --------------------------------------------------------------------------- residuals


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


def _pairing_arrays(
    A: _Prep, B: _Prep, pairings: Sequence[tuple[int, int]]
) -> tuple[IntArray, IntArray]:
    arr = np.asarray(list(pairings), dtype=np.int64).reshape(-1, 2)
    ii, jj = arr[:, 0], arr[:, 1]
    for name, idx, n in (("map_a", ii, A.n), ("map_b", jj, B.n)):
        bad = np.nonzero((idx < 0) | (idx >= n))[0]
        if bad.size:
            raise ValueError(
                f"pairing {int(bad[0])} indexes {name}[{int(idx[bad[0]])}], outside 0..{n - 1}"
            )
    mism = np.nonzero(A.kinds[ii] != B.kinds[jj])[0]
    if mism.size:
        m = int(mism[0])
        raise ValueError(
            f"pairing {m} pairs map_a[{int(ii[m])}] and map_b[{int(jj[m])}] of different kinds"
        )
    return ii, jj


# --------------------------------------------------------------------------- transform


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
        # halving it to 2^-20 each time took most of the matching time.  So after
        # the first few halvings the shortest step is tried: if that fails too, the
        # cost rises along dx at both ends of the lengths left and the fit stops (a
        # cost that dipped only between 1/16 and 2^-20 would be missed; loop600's
        # seeds 0-6 give the results of the full halving to 1e-8).
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


# --------------------------------------------------------------------------- matching


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
    Hk = Jt @ W @ J
    gk = (Jt @ W @ r[:, :, None])[:, :, 0]
    Hm = Hk.sum(axis=0)[None] - Hk
    w, V = np.linalg.eigh(0.5 * (Hm + Hm.transpose(0, 2, 1)))
    Pm = (V / np.maximum(w, _INFO_FLOOR)[:, None, :]) @ V.transpose(0, 2, 1)
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


def _one_to_one(
    A: _Prep,
    B: _Prep,
    T: FloatArray,
    P: FloatArray,
    ni: IntArray,
    nj: IntArray,
    gates: _Gates,
) -> tuple[IntArray, IntArray, IntArray]:
    """Greedy one-to-one assignment of the nodes passing the gate under ``T`` (whose
    covariance ``P`` widens the gate).

    Returns the chosen ``(ii, jj)`` and the indices of every passing node.
    """
    ratio = _gate_ratio(A, B, T, ni, nj, gates, P)
    passing = np.nonzero(ratio <= 1.0)[0].astype(np.int64)
    used_a: set[int] = set()
    used_b: set[int] = set()
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
    A: _Prep, B: _Prep, clique: IntArray, ni: IntArray, nj: IntArray, gates: _Gates
) -> _Hypothesis:
    """Fit a clique, then re-associate every node with the fitted transform."""
    ii, jj, T, cov = _fit_inliers(A, B, ni[clique], nj[clique], gates)
    n_clique = int(ii.size)
    passing = np.zeros(0, dtype=np.int64)
    # The clique picks one of several partners a feature may have within the gate
    # (collinear walls); the transform then tells which one is nearest.  A few
    # rounds: the refit moves the transform, which can change the assignment.
    for _ in range(3):
        ri, rj, passing = _one_to_one(A, B, T, cov, ni, nj, gates)
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
        passing = np.nonzero(ratio <= 1.0)[0].astype(np.int64)
    return _Hypothesis(ii=ii, jj=jj, T=T, cov=cov, clique=n_clique, nodes=passing)


def _compatible(h1: _Hypothesis, h2: _Hypothesis, gates: _Gates) -> bool:
    d = h2.T - h1.T
    d[2] = float(wrap_angle(d[2]))
    q = float(d @ np.linalg.solve(h1.cov + h2.cov, d))
    return q <= gates.g3


# --------------------------------------------------------------------------- max clique


class _CliqueGraph:
    """Maximum-clique search on the correspondence graph.

    networkx's ``max_weight_clique`` takes seconds on the ~5,000-node,
    ~300,000-edge graphs of 200 × 60 feature maps, so the search is written here
    around one observation: chance edges are spread thinly, so a random edge has
    few common neighbours, whereas every edge inside a clique of ``k`` nodes has at
    least ``k − 2``.  The search therefore

    1. counts the common neighbours of every edge at once (rows of the adjacency
       matrix as packed 64-bit words, ``AND`` and population count in numpy);
    2. grows cliques greedily from the nodes in the most triangles, which gives a
       lower bound ``L`` (usually the answer);
    3. peels the graph down to the edges that could lie in a clique of more than
       ``L`` nodes (≥ ``L − 1`` common neighbours, endpoints with neighbours on
       ≥ ``L`` distinct features of each map), repeating until stable (a k-truss);
    4. runs an exact branch and bound on whatever is left (usually nothing): for
       each node, its later neighbours in a degree order, with a k-core prune and
       Tomita's greedy-colouring bound (MCQ), Python integers as bitsets.

    Memory is ``n² / 8`` bytes for ``n`` nodes (2.7 MB for 4,600 nodes).
    """

    def __init__(
        self, nodes: IntArray, eu: IntArray, ev: IntArray, fa: IntArray, fb: IntArray
    ) -> None:
        self.fa = fa
        """Feature of ``A`` of every graph node (all nodes, alive or not)."""
        self.fb = fb
        """Feature of ``B`` of every graph node."""
        self.eu = eu
        """Edge endpoints (graph node ids)."""
        self.ev = ev
        """Other endpoints."""
        self.alive = np.zeros(fa.size, dtype=bool)
        """Nodes (by graph node id) not removed."""
        self.alive[nodes] = True
        self._common: IntArray | None = None

    def remove(self, graph_nodes: IntArray) -> None:
        """Remove nodes (graph node ids) from later searches."""
        self.alive[graph_nodes] = False

    def max_clique(self, at_least: int = 1) -> IntArray:
        """Graph node ids of a maximum clique among the alive nodes, or an empty array
        when none has ``at_least`` nodes."""
        keep = self.alive[self.eu] & self.alive[self.ev]
        if self._common is not None:
            # Common-neighbour counts only fall as nodes are removed, so the counts
            # of the first search bound those of later ones.
            keep &= self._common >= at_least - 2
        eu, ev = self.eu[keep], self.ev[keep]
        alive_ids = np.nonzero(self.alive)[0].astype(np.int64)
        if eu.size == 0:
            return alive_ids[:1] if alive_ids.size and at_least <= 1 else alive_ids[:0]
        ids, (u, v) = _compact(self.alive.size, eu, ev)
        W = _packed_adjacency(ids.size, u, v)
        common = _common_neighbours(W, u, v)
        if self._common is None:
            self._common = np.zeros(self.eu.size, dtype=np.int64)
            self._common[keep] = common
        tri = np.bincount(u, common, ids.size) + np.bincount(v, common, ids.size)
        best: list[int] = []
        for seed in np.argsort(-tri, kind="stable")[:8].tolist():
            c = _greedy_clique(W, int(seed))
            if len(c) > len(best):
                best = c
        floor = max(len(best), at_least - 1)  # only larger cliques are of interest now
        u, v, common = _truss(ids.size, u, v, common, floor + 1, self.fa[ids], self.fb[ids])
        if u.size:
            sub, (su, sv) = _compact(ids.size, u, v)
            found = _Bitsets(_packed_adjacency(sub.size, su, sv)).exact(floor)
            if len(found) > floor:
                best = sub[np.array(found, dtype=np.int64)].tolist()
        if len(best) < at_least:
            return alive_ids[:0]
        return ids[np.array(sorted(best), dtype=np.int64)]


def _greedy_clique(W: NDArray[np.uint64], seed: int) -> list[int]:
    """A maximal clique grown from ``seed``, adding each time the candidate with the
    most candidate neighbours (vectorised over the candidates' packed rows)."""
    clique = [seed]
    cand = W[seed].copy()
    while True:
        idx = np.flatnonzero(np.unpackbits(cand.astype("<u8").view(np.uint8), bitorder="little"))
        if idx.size == 0:
            return clique
        score = np.bitwise_count(W[idx] & cand).sum(axis=1, dtype=np.int64)
        u = int(idx[int(np.argmax(score))])
        clique.append(u)
        cand &= W[u]


def _compact(n: int, u: IntArray, v: IntArray) -> tuple[IntArray, tuple[IntArray, IntArray]]:
    """Ids (< ``n``) used by the edges, and the edges renumbered 0, 1, … in that order."""
    used = np.zeros(n, dtype=bool)
    used[u] = True
    used[v] = True
    ids = np.nonzero(used)[0].astype(np.int64)
    local = np.cumsum(used, dtype=np.int64) - 1
    return ids, (local[u], local[v])


def _packed_adjacency(n: int, u: IntArray, v: IntArray) -> NDArray[np.uint64]:
    """Symmetric adjacency as rows of little-endian 64-bit words (n, ⌈n/64⌉)."""
    words = (n + 63) // 64
    W = np.zeros(n * words, dtype=np.uint64)
    for a, b in ((u, v), (v, u)):
        np.bitwise_or.at(
            W, a * words + (b >> 6), np.left_shift(np.uint64(1), (b & 63).astype(np.uint64))
        )
    return W.reshape(n, words)


def _common_neighbours(W: NDArray[np.uint64], u: IntArray, v: IntArray) -> IntArray:
    """Number of common neighbours of each edge ``(u, v)``."""
    words = W.shape[1]
    step = max(1, 2**16 // max(words, 1))  # ~0.5 MB buffers: stay in cache
    out = np.empty(u.size, dtype=np.int64)
    bu = np.empty((step, words), dtype=np.uint64)
    bv = np.empty((step, words), dtype=np.uint64)
    bc = np.empty((step, words), dtype=np.uint8)
    # Preallocated buffers and out= halve the time of the naive expression.
    for k in range(0, u.size, step):
        m = min(step, u.size - k)
        np.take(W, u[k : k + m], axis=0, out=bu[:m])
        np.take(W, v[k : k + m], axis=0, out=bv[:m])
        np.bitwise_and(bu[:m], bv[:m], out=bu[:m])
        np.bitwise_count(bu[:m], out=bc[:m])
        out[k : k + m] = bc[:m].sum(axis=1, dtype=np.int64)
    return out


def _truss(
    n: int, u: IntArray, v: IntArray, common: IntArray, k: int, fa: IntArray, fb: IntArray
) -> tuple[IntArray, IntArray, IntArray]:
    """Edges that can lie in a clique of ``k`` nodes.

    Peels until every edge has ``≥ k − 2`` common neighbours and every node has
    neighbours on ``≥ k − 1`` distinct features of each map (a clique pairs each
    feature once, so nodes sharing a feature are never adjacent: this bound cuts
    the dense line–line regions that angle-only edges create).  Counts from before
    a peel are upper bounds afterwards (removing edges only lowers them), so peeling
    goes on with them until stable and they are recounted, on the renumbered
    remainder, only then.
    """
    while u.size:
        while u.size:
            deg = np.bincount(u, minlength=n) + np.bincount(v, minlength=n)
            ok = (common >= k - 2) & (deg[u] >= k - 1) & (deg[v] >= k - 1)
            if ok.all():
                reach = np.minimum(_distinct_partners(n, u, v, fa), _distinct_partners(n, u, v, fb))
                ok = (reach[u] >= k - 1) & (reach[v] >= k - 1)
                if ok.all():
                    break
            u, v, common = u[ok], v[ok], common[ok]
        if not u.size:
            break
        ids, (cu, cv) = _compact(n, u, v)
        fresh = _common_neighbours(_packed_adjacency(ids.size, cu, cv), cu, cv)
        if np.array_equal(fresh, common):
            break
        common = fresh
    return u, v, common


def _distinct_partners(n: int, u: IntArray, v: IntArray, feat: IntArray) -> IntArray:
    """For each node, the number of distinct ``feat`` values among its neighbours."""
    m = int(feat.max(initial=0)) + 1
    keys = np.unique(np.concatenate([u * m + feat[v], v * m + feat[u]]))
    return np.bincount(keys // m, minlength=n)


def _bits(x: int) -> list[int]:
    """Indices of the set bits of ``x``, lowest first."""
    out = []
    while x:
        low = x & -x
        out.append(low.bit_length() - 1)
        x ^= low
    return out


class _Bitsets:
    """Adjacency as one Python integer per node, for the branch and bound."""

    def __init__(self, W: NDArray[np.uint64]) -> None:
        self.adj = [int.from_bytes(row.astype("<u8").tobytes(), "little") for row in W]
        """Neighbour bitset of each node."""
        self._best: list[int] = []
        self._floor = 0

    def _size(self) -> int:
        """Size a new clique must exceed: the best so far, or the floor."""
        return max(len(self._best), self._floor)

    def _colour_sort(self, P: int) -> tuple[list[int], list[int]]:
        order: list[int] = []
        bound: list[int] = []
        colour = 0
        uncoloured = P
        while uncoloured:
            colour += 1
            Q = uncoloured
            while Q:
                low = Q & -Q
                v = low.bit_length() - 1
                Q &= ~self.adj[v]
                Q &= ~low
                uncoloured ^= low
                order.append(v)
                bound.append(colour)
        return order, bound

    def _expand(self, R: list[int], P: int) -> None:
        order, bound = self._colour_sort(P)
        for idx in range(len(order) - 1, -1, -1):
            # The colours of the remaining candidates bound the clique size.
            if len(R) + bound[idx] <= self._size():
                return
            v = order[idx]
            R.append(v)
            NP = P & self.adj[v]
            if NP:
                self._expand(R, NP)
            elif len(R) > self._size():
                self._best = list(R)
            R.pop()
            P &= ~(1 << v)

    def exact(self, floor: int) -> list[int]:
        """A maximum clique if it has more than ``floor`` nodes, else ``[]``."""
        self._best, self._floor = [], floor
        n = len(self.adj)
        # Degree order approximates a degeneracy order: each clique is searched from
        # its first node, among that node's later neighbours only.
        order = sorted(range(n), key=lambda w: self.adj[w].bit_count())
        later_mask = [0] * n
        acc = 0
        for w in reversed(order):
            later_mask[w] = acc
            acc |= 1 << w
        for v in order:
            need = self._size()  # nodes besides v for a strictly larger clique
            P = self.adj[v] & later_mask[v]
            # k-core of the later neighbours: in a clique of need + 1 nodes with v,
            # every other member has need − 1 neighbours among them.
            while P.bit_count() >= need:
                drop = 0
                for u in _bits(P):
                    if (self.adj[u] & P).bit_count() < need - 1:
                        drop |= 1 << u
                if not drop:
                    break
                P &= ~drop
            if P.bit_count() < need:
                continue
            if not P:
                self._best = [v]
                continue
            self._expand([v], P)
        return self._best


def _result(
    accepted: bool,
    reason: str,
    h: _Hypothesis | None,
    n_nodes: int = 0,
    n_edges: int = 0,
    runner_up: int = 0,
    n_hyp: int = 0,
) -> CCDAResult:
    if h is None:
        return CCDAResult(
            accepted=accepted,
            reason=reason,
            pairings=(),
            x_A_B=np.full(3, np.nan),
            cov=np.full((3, 3), np.nan),
            n_nodes=n_nodes,
            n_edges=n_edges,
            clique_size=0,
            runner_up_size=runner_up,
            n_hypotheses=n_hyp,
        )
    pairs = tuple(sorted(zip(h.ii.tolist(), h.jj.tolist(), strict=True)))
    return CCDAResult(
        accepted=accepted,
        reason=reason,
        pairings=tuple((int(i), int(j)) for i, j in pairs),
        x_A_B=h.T.copy(),
        cov=h.cov.copy(),
        n_nodes=n_nodes,
        n_edges=n_edges,
        clique_size=h.clique,
        runner_up_size=runner_up,
        n_hypotheses=n_hyp,
    )


def _check_params(p: CCDAParams) -> None:
    if not 0.0 < p.gate_prob < 1.0:
        raise ValueError(f"gate_prob must be in (0, 1), got {p.gate_prob}")
    if p.min_pairings < 2:
        raise ValueError(f"min_pairings must be >= 2, got {p.min_pairings}")
    if p.max_hypotheses < 1:
        raise ValueError(f"max_hypotheses must be >= 1, got {p.max_hypotheses}")
    if p.max_edges < 0:
        raise ValueError(f"max_edges must be >= 0, got {p.max_edges}")
    if p.ambiguity_margin < 0:
        raise ValueError(f"ambiguity_margin must be >= 0, got {p.ambiguity_margin}")
    for name in (
        "max_transform_std_xy_m",
        "max_transform_std_theta_rad",
        "parallel_tol_rad",
        "parallel_along_std_m",
        "var_floor_m",
        "var_floor_rad",
    ):
        v = getattr(p, name)
        if not (math.isfinite(v) and v >= 0.0):
            raise ValueError(f"{name} must be finite and >= 0, got {v}")


def ccda_match(
    map_a: KnownMapArrays, map_b: KnownMapArrays, params: CCDAParams = CCDAParams()
) -> CCDAResult:
    """Match ``map_b`` into ``map_a`` by CCDA; see the module docstring.

    ``map_a`` features are expected at ``x_A_B ⊕ b`` for their partners ``b`` of
    ``map_b``.  Returns a :class:`CCDAResult`; raises :class:`ValueError` only for
    malformed input (non-finite values, wrong shapes, unknown kinds, bad params).
    """
    _check_params(params)
    A, B = _prepare(map_a, "map_a", params), _prepare(map_b, "map_b", params)
    if A.n == 0 or B.n == 0:
        return _result(False, "empty map", None)
    if min(A.n, B.n) < params.min_pairings:
        return _result(False, "too few features", None)
    gates = _Gates.of(params.gate_prob)
    try:
        ni, nj, eu, ev = _build_graph(A, B, params, gates)
    except _GraphTooLargeError as err:
        return _result(False, "graph too large", None, err.n_nodes, params.max_edges + 1)
    n_nodes, n_edges = int(ni.size), int(eu.size)

    alive = _k_core(n_nodes, eu, ev, params.min_pairings - 1)
    if not np.any(alive):
        # No clique can reach min_pairings; search the whole (then very sparse)
        # graph anyway so that the rejection reports the best partial match.
        alive[:] = True
    keep = alive[eu] & alive[ev]
    G = _CliqueGraph(np.nonzero(alive)[0].astype(np.int64), eu[keep], ev[keep], ni, nj)

    hyps: list[_Hypothesis] = []
    for _ in range(params.max_hypotheses):
        needed = 1
        if hyps:
            best_support = max(int(h.ii.size) for h in hyps)
            # A feature shared by two hypotheses (the centre of a rotational
            # symmetry) went with the first one's nodes: one pairing of slack.
            needed = max(params.min_pairings, best_support - params.ambiguity_margin) - 1
        c = G.max_clique(at_least=needed)
        if c.size == 0:
            break
        h = _hypothesis(A, B, c, ni, nj, gates)
        hyps.append(h)
        # Remove what this transform explains, not the whole clique: with distance
        # invariants a mirror image of a symmetric map is a clique too, and its
        # fit keeps only a few inliers; the other nodes may belong to a genuine
        # rival (the 180° rotation of a rectangular grid shares a row with a mirror).
        # The clique's own final pairings go too, and the whole clique if none of it
        # did: every search must remove something of the clique it found.
        in_final = np.isin(ni[c] * B.n + nj[c], h.ii * B.n + h.jj)
        gone = np.concatenate([h.nodes, c[in_final]])
        G.remove(gone if np.isin(c, gone).any() else c)

    if not hyps:
        return _result(False, "too few pairings", None, n_nodes, n_edges)
    best = max(hyps, key=lambda h: (h.ii.size, h.clique))
    rivals = [h for h in hyps if h is not best and not _compatible(best, h, gates)]
    runner_up = max((int(h.ii.size) for h in rivals), default=0)
    n_hyp = len(hyps)

    def out(ok: bool, reason: str) -> CCDAResult:
        return _result(ok, reason, best, n_nodes, n_edges, runner_up, n_hyp)

    if best.ii.size < params.min_pairings:
        return out(False, "too few pairings")
    w = np.linalg.eigvalsh(best.cov[:2, :2])
    if (
        math.sqrt(max(float(w.max()), 0.0)) > params.max_transform_std_xy_m
        or math.sqrt(max(float(best.cov[2, 2]), 0.0)) > params.max_transform_std_theta_rad
    ):
        return out(False, "degenerate geometry")
    if runner_up >= max(params.min_pairings, int(best.ii.size) - params.ambiguity_margin):
        return out(False, "ambiguous")
    return out(True, "accepted")
