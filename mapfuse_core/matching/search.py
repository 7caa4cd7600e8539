"""Choosing pairings among individually compatible candidates: greedy nearest
neighbour and joint compatibility branch and bound (JCBB).

Each *query* (an observation, or a map feature paired with another map) has a list of
candidates, each naming a *target* and its Mahalanobis distance ``d2``.  A query takes
at most one target; an *exclusive* target takes at most one query (the one-to-one
rules of :class:`~mapfuse_core.matching.config.AssociationConfig`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol, TypeVar

__all__ = ["Scored", "ScoredPair", "drop_ambiguous", "jcbb", "nearest_neighbour"]


class Scored(Protocol):
    """What the searches read of a candidate."""

    @property
    def target(self) -> int:
        """Index of the target."""
        ...

    @property
    def d2(self) -> float:
        """Mahalanobis distance of the pairing."""
        ...


@dataclass(frozen=True)
class ScoredPair:
    """A plain candidate, for callers with no linearisation to carry along."""

    target: int
    """Index of the target."""
    d2: float
    """Mahalanobis distance of the pairing."""


C = TypeVar("C", bound=Scored)


def drop_ambiguous(
    cands: Sequence[Sequence[C]], distinct: Callable[[int, int], bool]
) -> list[list[C]]:
    """``cands`` without the candidates of ambiguous queries: those whose best
    candidate's target and another candidate's target are ``distinct`` (not
    compatible with each other, so not one feature).  Candidates are best first; a
    query whose candidates all name one feature (duplicates of it) keeps them."""
    out: list[list[C]] = []
    for cs in cands:
        best = cs[0].target if cs else -1
        ambiguous = any(c.target != best and distinct(best, c.target) for c in cs[1:])
        out.append([] if ambiguous else list(cs))
    return out


def nearest_neighbour(
    cands: Sequence[Sequence[C]], exclusive: Callable[[C], bool]
) -> list[C | None]:
    """Greedy nearest neighbour: the globally best pairs first, one target per query,
    and a target for which ``exclusive(candidate)`` holds taken by one query only.

    Equal distances go to the lower query index, then to the earlier candidate.
    """
    flat = sorted(
        ((c.d2, qi, c) for qi, cs in enumerate(cands) for c in cs), key=lambda x: (x[0], x[1])
    )
    chosen: list[C | None] = [None] * len(cands)
    used: set[int] = set()
    for _, qi, c in flat:
        if chosen[qi] is None and c.target not in used:
            chosen[qi] = c
            if exclusive(c):
                used.add(c.target)
    return chosen


def jcbb(
    cands: Sequence[Sequence[C]],
    compatible: Callable[[list[C]], bool],
    exclusive: Callable[[C], bool],
    max_nodes: int,
) -> list[C | None]:
    """Joint compatibility branch and bound (Neira & Tardós 2001): the largest set of
    pairings, at most one per query, that ``compatible`` accepts as a whole.

    Queries are taken in order, each query's candidates in the order given (callers
    pass them best first), a pairing tried before leaving the query unpaired; a branch
    is pruned when even pairing every remaining query could not beat the best set.  Of
    equally large sets the first found is kept.  ``compatible(pairs)`` is asked of every
    set the search extends and must be monotone (a subset of a compatible set is
    compatible) for the result to be the largest.  The search stops after ``max_nodes``
    nodes and returns the best set found by then.
    """
    n = len(cands)
    best: list[C | None] = [None] * n
    best_count = 0
    nodes = 0

    def rec(i: int, current: list[C | None], used: set[int], count: int) -> None:
        nonlocal best, best_count, nodes
        nodes += 1
        if nodes > max_nodes:
            return
        if i == n:
            if count > best_count:
                best, best_count = list(current), count
            return
        remaining = sum(1 for cs in cands[i:] if cs)
        if count + remaining <= best_count:
            return
        for c in cands[i]:
            if c.target in used:
                continue
            trial = [x for x in current if x is not None] + [c]
            if compatible(trial):
                current[i] = c
                taken = exclusive(c)
                if taken:
                    used.add(c.target)
                rec(i + 1, current, used, count + 1)
                if taken:
                    used.discard(c.target)
                current[i] = None
        rec(i + 1, current, used, count)

    rec(0, [None] * n, set(), 0)
    return best
