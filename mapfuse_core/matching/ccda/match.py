"""The CCDA driver: centring, graph, cliques, hypotheses, competitors and acceptance."""

from __future__ import annotations

import math

import numpy as np

from mapfuse_core.geometry.se2 import FloatArray, rot2, wrap_angle
from mapfuse_core.matching.ccda.clique import _CliqueGraph, _SearchBudget, _SearchLimitError
from mapfuse_core.matching.ccda.graph import _build_graph, _GraphTooLargeError, _k_core
from mapfuse_core.matching.ccda.params import CCDAParams, CCDAResult, _check_params, _Gates
from mapfuse_core.matching.ccda.prepare import IntArray, _centred, _Prep, _prepare
from mapfuse_core.matching.ccda.residuals import _residuals
from mapfuse_core.matching.ccda.verification import (
    _compatible,
    _deleted_covs,
    _Hypothesis,
    _hypothesis,
)
from mapfuse_core.measlog import KnownMapArrays

_DEFAULT_PARAMS = CCDAParams()
"""The default tuning (a frozen dataclass, shared safely as a default argument)."""


def _uncentre(
    T: FloatArray, P: FloatArray, ca: FloatArray, cb: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """``x_A_B = (ca, 0) ⊕ T ⊕ (−cb, 0)`` from the transform ``T`` between the centred
    frames, and its covariance ``J P Jᵀ`` (``J = ∂x_A_B/∂T``)."""
    th = float(T[2])
    R = rot2(th)
    dR = np.array([[-math.sin(th), -math.cos(th)], [math.cos(th), -math.sin(th)]])
    x = np.empty(3)
    x[:2] = ca + T[:2] - R @ cb
    x[2] = float(wrap_angle(th))
    J = np.eye(3)
    J[:2, 2] = -dR @ cb
    cov = J @ P @ J.T
    return x, 0.5 * (cov + cov.T)


def _overlap_std(B: _Prep, h: _Hypothesis, cov: FloatArray | None = None) -> tuple[float, float]:
    """Largest standard deviation (worst direction) of the position, in ``A``, of the
    centroid of ``h``'s paired ``B`` features, and that of the angle (under ``cov``,
    default the hypothesis's own covariance).

    The position of the frame origin is as uncertain as the lever arm of the angle
    from the pairings to wherever that origin happens to be; the centroid of the
    pairings is where the match is judged, whatever the maps' origins.
    """
    P = h.cov if cov is None else cov
    c = B.p[h.jj].mean(axis=0) if h.jj.size else np.zeros(2)
    th = float(h.T[2])
    dR = np.array([[-math.sin(th), -math.cos(th)], [math.cos(th), -math.sin(th)]])
    J = np.zeros((2, 3))
    J[:, :2] = np.eye(2)
    J[:, 2] = dR @ c
    w = np.linalg.eigvalsh(J @ P @ J.T)
    return math.sqrt(max(float(w.max()), 0.0)), math.sqrt(max(float(P[2, 2]), 0.0))


def _fixed_without_each(A: _Prep, B: _Prep, h: _Hypothesis, params: CCDAParams) -> bool:
    """Whether the transform stays fixed (:attr:`CCDAParams.max_transform_std_xy_m`,
    ``max_transform_std_theta_rad``) without any one of ``h``'s pairings.

    A pairing that alone fixes a direction of the transform (the one tree beside a
    row of parallel walls, which fixes the position along them) cannot be checked by
    the others: its leave-one-out test has nothing to test it against and passes
    whatever it is, and if it is wrong the whole match slides with it.
    """
    _, J, S, _ = _residuals(A, B, h.T, h.ii, h.jj)
    for P in _deleted_covs(J, np.linalg.inv(S)):
        std_xy, std_th = _overlap_std(B, h, P)
        if std_xy > params.max_transform_std_xy_m or std_th > params.max_transform_std_theta_rad:
            return False
    return True


def _result(
    accepted: bool,
    reason: str,
    h: _Hypothesis | None,
    centres: tuple[FloatArray, FloatArray],
    n_nodes: int = 0,
    n_edges: int = 0,
    runner_up: int = 0,
    n_hyp: int = 0,
    search_work: int = 0,
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
            search_work=search_work,
        )
    pairs = tuple(sorted(zip(h.ii.tolist(), h.jj.tolist(), strict=True)))
    x, cov = _uncentre(h.T, h.cov, *centres)
    return CCDAResult(
        accepted=accepted,
        reason=reason,
        pairings=tuple((int(i), int(j)) for i, j in pairs),
        x_A_B=x,
        cov=cov,
        n_nodes=n_nodes,
        n_edges=n_edges,
        clique_size=h.clique,
        runner_up_size=runner_up,
        n_hypotheses=n_hyp,
        search_work=search_work,
    )


def _rival_floor(params: CCDAParams, best_support: int) -> int:
    """Fewest pairings with which an incompatible hypothesis makes the match ambiguous."""
    if params.ambiguity_margin is None:
        return max(params.min_pairings, math.ceil(params.rival_fraction * best_support - 1e-9))
    return max(params.min_pairings, best_support - params.ambiguity_margin)


def _best_and_runner_up(hyps: list[_Hypothesis], gates: _Gates) -> tuple[_Hypothesis, int]:
    """The best-supported hypothesis and the support of its strongest incompatible rival."""
    best = max(hyps, key=lambda h: (h.support, h.clique))
    rivals = [h for h in hyps if h is not best and not _compatible(best, h, gates)]
    return best, max((h.support for h in rivals), default=0)


def _ambiguous(hyps: list[_Hypothesis], params: CCDAParams, gates: _Gates) -> bool:
    best, runner_up = _best_and_runner_up(hyps, gates)
    return runner_up >= _rival_floor(params, best.support)


def _clique_hypothesis(
    A: _Prep,
    B: _Prep,
    c: IntArray,
    ni: IntArray,
    nj: IntArray,
    gates: _Gates,
    params: CCDAParams,
) -> _Hypothesis:
    """The hypothesis of clique ``c`` (node ids) with ``params``' re-association rules."""
    return _hypothesis(
        A,
        B,
        c,
        ni,
        nj,
        gates,
        params.extent_margin_m,
        params.unique_partners,
        params.extent_rule == "within",
    )


def _partial(
    A: _Prep,
    B: _Prep,
    ni: IntArray,
    nj: IntArray,
    eu: IntArray,
    ev: IntArray,
    gates: _Gates,
    params: CCDAParams,
) -> _Hypothesis | None:
    """The best partial match for a refusal's diagnostics: the hypothesis of a greedy
    clique of the whole graph (not proven maximum: no budget is spent on a match that
    cannot be accepted), or ``None`` without nodes."""
    if ni.size == 0:
        return None
    G = _CliqueGraph(np.arange(ni.size, dtype=np.int64), eu, ev, ni, nj)
    c = G.max_clique(at_least=1, maximum=False)  # the greedy clique: no exact search
    return _clique_hypothesis(A, B, c, ni, nj, gates, params)


def ccda_match(
    map_a: KnownMapArrays, map_b: KnownMapArrays, params: CCDAParams = _DEFAULT_PARAMS
) -> CCDAResult:
    """Match ``map_b`` into ``map_a`` by CCDA (the package docstring explains how).

    ``map_a`` features are expected at ``x_A_B ⊕ b`` for their partners ``b`` of
    ``map_b``.  Returns a :class:`CCDAResult`; raises :class:`ValueError` only for
    malformed input (non-finite values, wrong shapes, unknown kinds, bad params).
    """
    _check_params(params)
    A, ca = _centred(_prepare(map_a, "map_a", params))
    B, cb = _centred(_prepare(map_b, "map_b", params))
    centres = (ca, cb)
    if A.n == 0 or B.n == 0:
        return _result(False, "empty map", None, centres)
    if min(A.n, B.n) < params.min_pairings:
        return _result(False, "too few features", None, centres)
    gates = _Gates.of(params.gate_prob)
    try:
        ni, nj, eu, ev = _build_graph(A, B, params, gates)
    except _GraphTooLargeError as err:
        return _result(False, "graph too large", None, centres, err.n_nodes, params.max_edges + 1)
    n_nodes, n_edges = int(ni.size), int(eu.size)

    # Only cliques that can lead to an accepted match are searched for: min_pairings
    # nodes, less one of slack (re-association adds a pairing the clique missed by an
    # edge that failed its gate by chance).  Proving the maximum of a smaller clique
    # is what exhausts the budget on dense graphs, and it decides nothing.
    first = max(params.min_pairings - 1, 1)
    alive = _k_core(n_nodes, eu, ev, first - 1)
    keep = alive[eu] & alive[ev]
    G = _CliqueGraph(np.nonzero(alive)[0].astype(np.int64), eu[keep], ev[keep], ni, nj)
    budget = _SearchBudget(params.max_clique_work)

    hyps: list[_Hypothesis] = []
    complete = True  # every clique that could compete was searched
    try:
        for n_search in range(params.max_hypotheses + 1):
            needed = first
            if hyps:
                # A feature shared by two hypotheses (the centre of a rotational
                # symmetry) went with the first one's nodes: one pairing of slack.
                needed = _rival_floor(params, max(h.support for h in hyps)) - 1
            c = G.max_clique(at_least=needed, budget=budget, maximum=False)
            if c.size == 0:
                break
            if n_search == params.max_hypotheses:
                # One more candidate than the hypotheses allowed: unresolved.
                complete = False
                break
            h = _clique_hypothesis(A, B, c, ni, nj, gates, params)
            hyps.append(h)
            # Remove what this transform explains, not the whole clique: with distance
            # invariants a mirror image of a symmetric map is a clique too, and its
            # fit keeps only a few inliers; the other nodes may belong to a genuine
            # rival (the 180° rotation of a rectangular grid shares a row with a
            # mirror).  The clique's own final pairings go too, and the whole clique
            # if none of it did: every search must remove something of the clique.
            in_final = np.isin(ni[c] * B.n + nj[c], h.ii * B.n + h.jj)
            gone = np.concatenate([h.nodes, c[in_final]])
            G.remove(gone if np.isin(c, gone).any() else c)
            if _ambiguous(hyps, params, gates):
                break  # refusing needs no further search (a periodic world has many)
    except _SearchLimitError:
        complete = False

    n_hyp = len(hyps)
    if not hyps:
        reason = "search_limit" if not complete else "too few pairings"
        partial = _partial(A, B, ni, nj, eu, ev, gates, params)
        return _result(False, reason, partial, centres, n_nodes, n_edges, 0, 0, budget.used)
    best, runner_up = _best_and_runner_up(hyps, gates)

    def out(ok: bool, reason: str) -> CCDAResult:
        return _result(ok, reason, best, centres, n_nodes, n_edges, runner_up, n_hyp, budget.used)

    if best.support < params.min_pairings:
        # Complete or not, nothing found reaches min_pairings; an unfinished search
        # may have missed a larger clique, so say so.
        return out(False, "too few pairings" if complete else "search_limit")
    std_xy, std_th = _overlap_std(B, best)
    if std_xy > params.max_transform_std_xy_m or std_th > params.max_transform_std_theta_rad:
        return out(False, "degenerate geometry")
    if params.redundant_pairings and not _fixed_without_each(A, B, best, params):
        return out(False, "unverifiable")
    if _ambiguous(hyps, params, gates):
        return out(False, "ambiguous")
    if not complete:
        return out(False, "search_limit")
    if best.ii.size < params.min_pairings:
        # Enough support, but too few of its pairings are unambiguous to be fused.
        return out(False, "too few pairings")
    return out(True, "accepted")
