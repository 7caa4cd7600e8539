"""CCDA's correspondence graph as a ``networkx.Graph``, to inspect, analyse or draw.

Nodes are the candidate pairings ``(i, j)`` (feature ``i`` of map A, the SLAM map,
with feature ``j`` of map B, the known map); an edge joins two pairings whose
rigid-motion invariants agree within the χ² gate
(:mod:`mapfuse_core.matching.ccda.inspect`).  Attributes:

* node: ``a``, ``b`` (indices into the maps), ``a_id``, ``b_id`` (their ids),
  ``kind`` (``"line"`` or ``"circle"``), ``chi2`` (circles: the radius test; NaN for
  lines), ``paired`` (in the match's final pairings, when a result is given);
* edge: ``invariant`` (what is compared), ``invariant_a``, ``invariant_b``, ``chi2``.

Example (notebook 04)::

    G = correspondence_nx(map_a, map_b, result=ccda_match(map_a, map_b))
    best = G.subgraph(n for n, d in G.nodes(data=True) if d["paired"])
"""

from __future__ import annotations

import math

import networkx as nx
import numpy as np

from mapfuse_core.matching.ccda import CCDAParams, CCDAResult
from mapfuse_core.matching.ccda.inspect import EDGE_INVARIANTS, correspondence_graph
from mapfuse_core.measlog import KnownMapArrays

__all__ = ["correspondence_nx"]


def correspondence_nx(
    map_a: KnownMapArrays,
    map_b: KnownMapArrays,
    params: CCDAParams | None = None,
    result: CCDAResult | None = None,
) -> nx.Graph:
    """The correspondence graph of ``map_a`` and ``map_b`` under ``params`` as a
    ``networkx.Graph`` whose nodes are the pairings ``(i, j)``.

    ``result`` (the :func:`~mapfuse_core.matching.ccda.ccda_match` of the same maps and
    params) marks its final pairings (node attribute ``paired``) and is stored with
    its transform in ``G.graph`` (``accepted``, ``reason``, ``x_A_B``).
    """
    cg = correspondence_graph(map_a, map_b, params)
    paired = set(result.pairings) if result is not None else set()
    G = nx.Graph()
    kinds_a = np.asarray(map_a.kinds)
    nodes = list(zip(cg.node_a.tolist(), cg.node_b.tolist(), strict=True))
    for (i, j), c in zip(nodes, cg.node_chi2.tolist(), strict=True):
        G.add_node(
            (i, j),
            a=i,
            b=j,
            a_id=int(map_a.ids[i]),
            b_id=int(map_b.ids[j]),
            kind="circle" if int(kinds_a[i]) == 1 else "line",
            chi2=float(c) if math.isfinite(c) else math.nan,
            paired=(i, j) in paired,
        )
    for u, v, k, ga, gb, c in zip(
        cg.edge_u.tolist(),
        cg.edge_v.tolist(),
        cg.edge_kind.tolist(),
        cg.invariant_a.tolist(),
        cg.invariant_b.tolist(),
        cg.chi2.tolist(),
        strict=True,
    ):
        G.add_edge(
            nodes[u], nodes[v], invariant=EDGE_INVARIANTS[k], invariant_a=ga, invariant_b=gb, chi2=c
        )
    if result is not None:
        G.graph.update(
            accepted=result.accepted,
            reason=result.reason,
            x_A_B=[float(v) for v in result.x_A_B],
        )
    return G
