"""CCDA's correspondence graph as arrays and as a networkx graph, checked against the
matcher's own counts and against invariants computed here from the maps."""

from __future__ import annotations

import math

import networkx as nx
import numpy as np
import pytest
from scipy.stats import chi2

from mapfuse.interop.networkx import correspondence_nx
from mapfuse_core.geometry.se2 import wrap_angle_half
from mapfuse_core.matching.ccda import ccda_match
from mapfuse_core.matching.ccda.inspect import EDGE_INVARIANTS, correspondence_graph
from tests.ccda_helpers import random_overlap

G1 = float(chi2.ppf(0.999, 1))  # the default gate_prob's 1-dof gate


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_graph_matches_the_matcher_and_the_maps(seed: int) -> None:
    case = random_overlap(seed)
    A, B = case.map_a, case.map_b
    res = ccda_match(A, B)
    G = correspondence_nx(A, B, result=res)
    assert isinstance(G, nx.Graph)
    # The very graph the matcher searched: same node and edge counts.
    assert G.number_of_nodes() == res.n_nodes
    assert G.number_of_edges() == res.n_edges
    assert G.graph["accepted"] is res.accepted
    paired = {n for n, d in G.nodes(data=True) if d["paired"]}
    assert paired == set(res.pairings)
    # The true pairings are candidate nodes of the graph.
    for i, j in case.truth.items():
        assert G.has_node((i, j))
        assert G.nodes[(i, j)]["kind"] == ("circle" if int(A.kinds[i]) == 1 else "line")
    for (i, j), d in G.nodes(data=True):
        assert (d["a_id"], d["b_id"]) == (int(A.ids[i]), int(B.ids[j]))
        if d["kind"] == "circle":
            assert d["chi2"] <= G1 * (1 + 1e-12)
        else:
            assert math.isnan(d["chi2"])

    def invariant(m: object, p: int, q: int) -> float:
        kinds, params = m.kinds, m.params  # type: ignore[attr-defined]
        fp, fq = params[p], params[q]
        if kinds[p] == 1 and kinds[q] == 1:
            return float(math.hypot(*(fq[:2] - fp[:2])))
        if kinds[p] != kinds[q]:
            c, ln = (fp, fq) if kinds[p] == 1 else (fq, fp)
            n = np.array([-math.sin(ln[2]), math.cos(ln[2])])
            return float(abs(n @ (c[:2] - ln[:2])))
        return float(wrap_angle_half(fq[2] - fp[2]))

    for u, v, d in G.edges(data=True):
        # networkx may hand the two ends either way round: the angle then flips sign.
        ga, gb = invariant(A, u[0], v[0]), invariant(B, u[1], v[1])
        if d["invariant"] == EDGE_INVARIANTS[2]:
            assert abs(abs(d["invariant_a"]) - abs(ga)) < 1e-9
            assert abs(abs(d["invariant_b"]) - abs(gb)) < 1e-9
        else:
            assert d["invariant_a"] == pytest.approx(ga, abs=1e-9)
            assert d["invariant_b"] == pytest.approx(gb, abs=1e-9)
        # Every edge passed its 1-dof gate.
        assert 0.0 <= d["chi2"] <= G1 * (1 + 1e-9)


def test_arrays_and_errors() -> None:
    case = random_overlap(3)
    cg = correspondence_graph(case.map_a, case.map_b)
    assert cg.edge_u.shape == cg.edge_v.shape == cg.chi2.shape == cg.edge_kind.shape
    assert set(np.unique(cg.edge_kind).tolist()) <= {0, 1, 2}
    from mapfuse_core.matching.ccda import CCDAParams

    with pytest.raises(ValueError, match="max_edges"):
        correspondence_graph(case.map_a, case.map_b, CCDAParams(max_edges=1))
