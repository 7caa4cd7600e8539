"""The correspondence graph :func:`~mapfuse_core.matching.ccda.ccda_match` searches, as arrays.

:func:`correspondence_graph` rebuilds, with the same code and parameters, the graph
of type- and radius-compatible pairings (nodes) and pairwise-consistent pairs of
pairings (edges) that CCDA's maximum-clique search runs on, and adds what each edge
was accepted on: the rigid-motion invariant in each map and its χ² statistic
(``docs/method.md`` §5.1).  It is for inspection and plotting (the harness turns it
into a ``networkx.Graph``, :mod:`mapfuse.interop.networkx`); the matcher itself
keeps only node and edge indices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapfuse_core.geometry.se2 import FloatArray, wrap_angle_half
from mapfuse_core.matching.ccda.graph import (
    _build_graph,
    _GraphTooLargeError,
    _Pairs,
    _pairs_cc,
    _pairs_cl,
    _pairs_ll,
)
from mapfuse_core.matching.ccda.params import CCDAParams, _check_params, _Gates
from mapfuse_core.matching.ccda.prepare import IntArray, _prepare
from mapfuse_core.measlog import KnownMapArrays

__all__ = ["EDGE_INVARIANTS", "CorrespondenceGraph", "correspondence_graph"]

#: What the invariant of each edge kind is (``CorrespondenceGraph.edge_kind`` index).
EDGE_INVARIANTS: tuple[str, ...] = (
    "circle-circle: distance between the centres [m]",
    "circle-line: unsigned distance from the centre to the line [m]",
    "line-line: signed angle from the first line to the second, modulo π [rad]",
)


@dataclass(frozen=True, eq=False)
class CorrespondenceGraph:
    """Nodes and edges of CCDA's correspondence graph, with each edge's test."""

    node_a: IntArray
    """(n,) index into ``map_a`` of each node's feature."""
    node_b: IntArray
    """(n,) index into ``map_b`` of its partner."""
    node_chi2: FloatArray
    """(n,) unary χ² (1 dof) of circle nodes, the radius test; NaN for lines (no test)."""
    edge_u: IntArray
    """(m,) first node of each edge."""
    edge_v: IntArray
    """(m,) second node."""
    edge_kind: IntArray
    """(m,) index into :data:`EDGE_INVARIANTS`."""
    invariant_a: FloatArray
    """(m,) the invariant of the two ``map_a`` features of the edge."""
    invariant_b: FloatArray
    """(m,) the invariant of their two ``map_b`` partners."""
    chi2: FloatArray
    """(m,) ``(g_a − g_b)² / (σ²_a + σ²_b)`` of the invariant (1 dof; for parallel
    line pairs the matcher also tests their lateral distance jointly)."""


def _lookup(
    pairs: _Pairs, n: int, i: IntArray, k: IntArray, symmetric: bool
) -> tuple[FloatArray, FloatArray]:
    """Invariant and its variance of the pairs ``(i, k)`` in one pair table."""
    row = np.full(n * n, -1, dtype=np.int64)
    row[pairs.i * n + pairs.k] = np.arange(pairs.i.size)
    if symmetric:
        row[pairs.k * n + pairs.i] = np.arange(pairs.i.size)
    r = row[i * n + k]
    sign = np.ones(i.size)
    if not symmetric:
        # Unordered line pairs: the angle from k to i is minus that from i to k.
        back = r < 0
        rb = np.full(n * n, -1, dtype=np.int64)
        rb[pairs.k * n + pairs.i] = np.arange(pairs.i.size)
        r = np.where(back, rb[i * n + k], r)
        sign = np.where(back, -1.0, 1.0)
    if np.any(r < 0):
        raise AssertionError("an edge whose feature pair has no invariant")
    return sign * pairs.g[r, 0], pairs.S[r, 0, 0]


def correspondence_graph(
    map_a: KnownMapArrays, map_b: KnownMapArrays, params: CCDAParams | None = None
) -> CorrespondenceGraph:
    """The correspondence graph :func:`~mapfuse_core.matching.ccda.ccda_match` builds for these
    maps and ``params`` (before its k-core pruning): same nodes, same edges.

    :class:`ValueError` for malformed input, or when the graph exceeds
    ``params.max_edges`` (the matcher then reports ``"graph too large"``).
    """
    params = CCDAParams() if params is None else params
    _check_params(params)
    A, B = _prepare(map_a, "map_a", params), _prepare(map_b, "map_b", params)
    gates = _Gates.of(params.gate_prob)
    try:
        ni, nj, eu, ev = _build_graph(A, B, params, gates)
    except _GraphTooLargeError:
        raise ValueError(
            f"the correspondence graph has more than max_edges={params.max_edges} edges"
        ) from None
    circ_a = A.kinds[ni] == 1
    node_chi2 = np.full(ni.size, np.nan)
    dr = A.params[ni[circ_a], 2] - B.params[nj[circ_a], 2]
    node_chi2[circ_a] = dr * dr / (A.vr[ni[circ_a]] + B.vr[nj[circ_a]])
    ai, ak, bj, bl = ni[eu], ni[ev], nj[eu], nj[ev]
    ka, kk = A.kinds[ai] == 1, A.kinds[ak] == 1
    kind = np.where(ka & kk, 0, np.where(ka ^ kk, 1, 2)).astype(np.int64)
    ga, gb = np.zeros(eu.size), np.zeros(eu.size)
    va, vb = np.zeros(eu.size), np.zeros(eu.size)
    tables = (
        (0, _pairs_cc(A), _pairs_cc(B), True, True),
        (1, _pairs_cl(A), _pairs_cl(B), True, True),
        (2, _pairs_ll(A, ordered=False), _pairs_ll(B, ordered=True), False, True),
    )
    for k, pa, pb, sym_a, sym_b in tables:
        sel = kind == k
        if not np.any(sel):
            continue
        i1, i2, j1, j2 = ai[sel], ak[sel], bj[sel], bl[sel]
        if k == 1:
            # (circle, line) order on both sides.
            swap = A.kinds[i1] != 1
            i1, i2 = np.where(swap, i2, i1), np.where(swap, i1, i2)
            j1, j2 = np.where(swap, j2, j1), np.where(swap, j1, j2)
        ga[sel], va[sel] = _lookup(pa, A.n, i1, i2, sym_a)
        gb[sel], vb[sel] = _lookup(pb, B.n, j1, j2, sym_b and k != 2)
    diff = np.where(kind == 2, wrap_angle_half(ga - gb), ga - gb)
    return CorrespondenceGraph(
        node_a=ni,
        node_b=nj,
        node_chi2=node_chi2,
        edge_u=eu,
        edge_v=ev,
        edge_kind=kind,
        invariant_a=ga,
        invariant_b=gb,
        chi2=diff * diff / (va + vb),
    )
