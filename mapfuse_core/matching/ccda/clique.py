"""Exact maximum-clique search on the correspondence graph (see :class:`_CliqueGraph`)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mapfuse_core.matching.ccda.prepare import IntArray


class _SearchLimitError(Exception):
    """The branch and bound exhausted its :class:`_SearchBudget`."""


class _SearchBudget:
    """Work units left for the branch and bound of one matching call.

    A unit is one search node or one candidate vertex it colours or prunes, so the
    units follow the time a search takes, and count the same on every machine.
    """

    def __init__(self, units: int) -> None:
        self.limit = units
        """Units allowed in total."""
        self.used = 0
        """Units spent so far."""

    def spend(self, n: int = 1) -> None:
        """Count ``n`` units; raise :class:`_SearchLimitError` beyond the limit."""
        self.used += n
        if self.used > self.limit:
            raise _SearchLimitError(self.used)


class _CliqueGraph:
    """Maximum-clique search on the correspondence graph.

    networkx's ``max_weight_clique`` takes seconds on the graphs of 200 × 60 feature
    maps (thousands of nodes, some 10⁵ edges), so the search is written here
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

    Memory is ``n² / 8`` bytes for ``n`` nodes.  Steps 1–3 are vectorised and
    polynomial; step 4 is exponential in the worst case (dense angle-only edges
    between perpendicular walls, noise-free maps), so it spends a
    :class:`_SearchBudget` and stops with :class:`_SearchLimitError` when that runs
    out.
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

    def max_clique(
        self, at_least: int = 1, budget: _SearchBudget | None = None, maximum: bool = True
    ) -> IntArray:
        """Graph node ids of a maximum clique among the alive nodes, or an empty array
        when none has ``at_least`` nodes.

        With ``maximum=False``, any clique of at least ``at_least`` nodes, the likely
        one first: the greedy clique (step 2) when it is that large, else the first
        the exact search finds.  The search then spends its budget only where the
        greedy growth fails, and proving that no clique of ``at_least`` nodes is
        left, not proving which one is largest.

        Raises :class:`_SearchLimitError` when the exact search exhausts ``budget``
        (unlimited without one).
        """
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
        best = _greedy_best(W, common, u, v)
        if not maximum and len(best) >= at_least:
            return ids[np.array(sorted(best), dtype=np.int64)]
        floor = max(len(best), at_least - 1)  # only larger cliques are of interest now
        u, v, common = _truss(ids.size, u, v, common, floor + 1, self.fa[ids], self.fb[ids])
        if u.size:
            sub, (su, sv) = _compact(ids.size, u, v)
            feats = (self.fa[ids[sub]], self.fb[ids[sub]])
            bits = _Bitsets(
                _packed_adjacency(sub.size, su, sv), budget or _SearchBudget(1 << 62), feats
            )
            found = bits.exact(floor, stop_at=None if maximum else at_least)
            if len(found) > floor:
                best = sub[np.array(found, dtype=np.int64)].tolist()
        if len(best) < at_least:
            return alive_ids[:0]
        return ids[np.array(sorted(best), dtype=np.int64)]


def _greedy_best(W: NDArray[np.uint64], common: IntArray, u: IntArray, v: IntArray) -> list[int]:
    """The largest of the cliques grown greedily from the 8 nodes in the most
    triangles (``common``: common neighbours of each edge ``(u, v)``)."""
    n = W.shape[0]
    tri = np.bincount(u, common, n) + np.bincount(v, common, n)
    best: list[int] = []
    for seed in np.argsort(-tri, kind="stable")[:8].tolist():
        c = _greedy_clique(W, int(seed))
        if len(c) > len(best):
            best = c
    return best


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
    acc = _row_sum_dtype(words)
    # Preallocated buffers and out= halve the time of the naive expression.
    for k in range(0, u.size, step):
        m = min(step, u.size - k)
        np.take(W, u[k : k + m], axis=0, out=bu[:m])
        np.take(W, v[k : k + m], axis=0, out=bv[:m])
        np.bitwise_and(bu[:m], bv[:m], out=bu[:m])
        np.bitwise_count(bu[:m], out=bc[:m])
        out[k : k + m] = bc[:m].sum(axis=1, dtype=acc)
    return out


def _row_sum_dtype(words: int) -> type[np.unsignedinteger] | type[np.signedinteger]:
    """Accumulator of a row's population counts: a row of ``words`` words counts at
    most ``64 · words``, summed in 16 bits where that fits (40 % faster than 64)."""
    return np.uint16 if 64 * words <= np.iinfo(np.uint16).max else np.int64


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
    remainder, only then.  Peeling is only pruning, so it stops after a fixed number
    of passes and rounds (each linear in the edges), or as soon as a pass removes
    under 1 % of the edges: the exact search handles what remains, within its
    budget, and the cost of this step stays bounded.
    """
    for _ in range(_TRUSS_ROUNDS):
        for _ in range(_TRUSS_PASSES):
            deg = np.bincount(u, minlength=n) + np.bincount(v, minlength=n)
            ok = (common >= k - 2) & (deg[u] >= k - 1) & (deg[v] >= k - 1)
            if ok.all():
                reach = np.minimum(_distinct_partners(n, u, v, fa), _distinct_partners(n, u, v, fb))
                ok = (reach[u] >= k - 1) & (reach[v] >= k - 1)
                if ok.all():
                    break
            dropped = u.size - int(ok.sum())
            u, v, common = u[ok], v[ok], common[ok]
            if dropped * _TRUSS_MIN_DROP < u.size:
                break  # diminishing returns: recount instead
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
    keys = np.concatenate([u * m + feat[v], v * m + feat[u]])
    if n * m <= _DENSE_CELLS:
        # A (node, feature) occupancy table: linear in edges, no sort or hash.
        seen = np.bincount(keys, minlength=n * m).reshape(n, m) > 0
        out: IntArray = seen.sum(axis=1, dtype=np.int64)
        return out
    keys = np.unique(keys)
    return np.bincount(keys // m, minlength=n)


#: Recounts of common neighbours in :func:`_truss`.
_TRUSS_ROUNDS = 8
#: Peeling passes between recounts.
_TRUSS_PASSES = 16
#: A pass removing fewer than 1/this of the edges ends the peeling between recounts.
_TRUSS_MIN_DROP = 100

#: Largest (node × feature) table :func:`_distinct_partners` counts in (64 MB of int64).
_DENSE_CELLS = 1 << 23


def _bits(x: int) -> list[int]:
    """Indices of the set bits of ``x``, lowest first."""
    out = []
    while x:
        low = x & -x
        out.append(low.bit_length() - 1)
        x ^= low
    return out


class _FoundError(Exception):
    """The branch and bound reached the clique size it was asked to stop at."""


class _Bitsets:
    """Adjacency as one Python integer per node, for the branch and bound.

    The bound on the clique a candidate set can still add is the number of colours
    of a colouring of it (classes of pairwise non-adjacent nodes).  Tomita's greedy
    colouring is one; the pairings of one feature are another, since a clique pairs
    each feature of either map once: nodes sharing a feature of ``A``, or of ``B``,
    are never adjacent.  Each expansion uses whichever of the three has the fewest
    colours.  Against a known map of a few dozen walls the feature classes bound
    far tighter than the greedy colouring of a dense angle-only graph.
    """

    def __init__(
        self,
        W: NDArray[np.uint64],
        budget: _SearchBudget,
        feats: tuple[IntArray, ...] = (),
    ) -> None:
        self.adj = [int.from_bytes(row.astype("<u8").tobytes(), "little") for row in W]
        """Neighbour bitset of each node."""
        self.feats = [f.tolist() for f in feats]
        """Per map, the feature of each node (classes of non-adjacent nodes)."""
        self.budget = budget
        """Work left: every expansion and start vertex spends one unit plus one per
        candidate vertex."""
        self._best: list[int] = []
        self._floor = 0
        self._stop: int | None = None

    def _size(self) -> int:
        """Size a new clique must exceed: the best so far, or the floor."""
        return max(len(self._best), self._floor)

    def _colour_sort(self, P: int) -> tuple[list[int], list[int]]:
        """The nodes of ``P`` in colour order and, for each, the number of colours up
        to its own: the fewest-colour colouring of the greedy one and the feature
        classes (class docstring)."""
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
        for feat in self.feats:
            classes: dict[int, list[int]] = {}
            for v in order:
                classes.setdefault(feat[v], []).append(v)
            if len(classes) < colour:
                colour = len(classes)
                order = [v for members in classes.values() for v in members]
                bound = [c for c, members in enumerate(classes.values(), 1) for _ in members]
        return order, bound

    def _expand(self, R: list[int], P: int) -> None:
        self.budget.spend(1 + P.bit_count())
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
                self._found(R)
            R.pop()
            P &= ~(1 << v)

    def _found(self, clique: list[int]) -> None:
        """Keep ``clique`` as the best so far; stop when it is as large as asked."""
        self._best = list(clique)
        if self._stop is not None and len(clique) >= self._stop:
            raise _FoundError

    def _reach(self, P: int) -> int:
        """Fewest distinct features of either map among the nodes of ``P``: a bound
        on the clique they hold (a clique pairs each feature once)."""
        nodes = _bits(P)
        return min((len({feat[v] for v in nodes}) for feat in self.feats), default=len(nodes))

    def exact(self, floor: int, stop_at: int | None = None) -> list[int]:
        """A maximum clique if it has more than ``floor`` nodes, else ``[]``; with
        ``stop_at``, the first clique found of at least that many nodes instead."""
        self._stop = stop_at
        try:
            return self._exact(floor)
        except _FoundError:
            return self._best

    def _exact(self, floor: int) -> list[int]:
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
            self.budget.spend(1 + P.bit_count())
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
                self.budget.spend(P.bit_count())
            if P.bit_count() < need or (need and self._reach(P) < need):
                continue
            if not P:
                self._found([v])
                continue
            self._expand([v], P)
        return self._best
