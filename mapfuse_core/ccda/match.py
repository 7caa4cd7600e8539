"""The CCDA driver: graph, cliques, hypotheses, competitors and acceptance."""

from __future__ import annotations

import math

import numpy as np

from mapfuse_core.ccda.clique import _CliqueGraph
from mapfuse_core.ccda.graph import _build_graph, _GraphTooLargeError, _k_core
from mapfuse_core.ccda.params import CCDAParams, CCDAResult, _check_params, _Gates
from mapfuse_core.ccda.prepare import _prepare
from mapfuse_core.ccda.verification import _compatible, _Hypothesis, _hypothesis
from mapfuse_core.measlog import KnownMapArrays

_DEFAULT_PARAMS = CCDAParams()
"""The default tuning (a frozen dataclass, shared safely as a default argument)."""


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


def ccda_match(
    map_a: KnownMapArrays, map_b: KnownMapArrays, params: CCDAParams = _DEFAULT_PARAMS
) -> CCDAResult:
    """Match ``map_b`` into ``map_a`` by CCDA (the package docstring explains how).

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
