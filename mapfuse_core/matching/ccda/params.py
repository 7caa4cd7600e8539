"""Parameters and result of CCDA, and the χ² gates derived from the parameters.

Every default of :class:`CCDAParams` is a *(choice)* explained in the package
docstring of :mod:`mapfuse_core.matching.ccda` and in ``docs/method.md`` §5.1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.stats import chi2

from mapfuse_core.geometry.se2 import FloatArray


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
    redundant_pairings: bool = True
    """*(choice)* Accept only a match whose transform stays fixed (by the two limits
    above) without any one of its pairings, so that every pairing is checked by the
    others.  Otherwise the match is refused as ``"unverifiable"``: one wrong pairing
    that alone fixes a direction (a tree beside parallel walls) would slide the whole
    match along that direction, and its leave-one-out test cannot see it."""
    parallel_tol_rad: float = 0.1
    """Two lines are parallel (their distance becomes an invariant too) when the angle
    between them is at most this in both maps.  Should exceed a few σ of the angle
    noise, or truly parallel lines only get the weaker angle test."""
    parallel_along_std_m: float = 10.0
    """Spread of the along-line origins of one wall between the maps, used to widen
    the distance gate of nearly (not exactly) parallel lines."""
    ambiguity_margin: int | None = None
    """``None``: the rivals that count are set by :attr:`rival_fraction`.  An integer
    ``m``: a hypothesis incompatible with the best one counts as a rival when it has
    at least ``max(min_pairings, best − m)`` pairings.  That rule accepts the larger
    of two well-supported hypotheses (10 against 8 with ``m = 1``), which is the
    wrong one in a periodic world whenever the local map reaches past the known
    map's edge; use it only on maps known not to repeat."""
    rival_fraction: float = 0.5
    """With ``ambiguity_margin = None``, a hypothesis incompatible with the best one
    makes the match ambiguous when it has at least
    ``max(min_pairings, ⌈rival_fraction · best⌉)`` pairings.  A shift by one period
    of a periodic world keeps ``(k − 1)/k`` of the pairings of a local map spanning
    ``k`` periods inside the known map (all of them for ``k ≤ 1``), so such rivals
    have at least half the support of the right match; chance cliques of unrelated
    features stay near ``min_pairings`` whatever the overlap."""
    max_hypotheses: int = 30
    """Most maximum-clique searches (best plus competitors) per call.  When the last
    one still finds a clique that could compete, the search is incomplete and the
    call returns ``"search_limit"``."""
    max_clique_work: int = 2_000_000
    """Budget of the exact clique search over all searches of one call, in work units:
    one per branch-and-bound node plus one per candidate vertex it colours or prunes
    (so units follow time; rates in ``docs/results/ccda.md``).  Exhausting it returns
    ``"search_limit"``, never a guess.  It counts work, not seconds, so the outcome
    is the same on every machine."""
    max_edges: int = 5_000_000
    """Largest correspondence graph searched.  The exact search costs about
    ``edges × nodes / 64`` word operations (timings in ``docs/method.md`` §5.1): beyond
    this the call returns ``"graph too large"`` instead of running for minutes; match
    a cropped map."""
    extent_margin_m: float = 0.5
    """Slack (m) of the segment tests (:attr:`extent_rule`), on top of the propagated
    position noise.  Where both maps give a line's extent, a pairing needs the two
    segments to agree along the line (the observed part of a wall lies on the known
    wall, not on its extension past a door or a corridor's end): in the unary length
    test, in the binary test of two non-parallel line pairings, whose intersection
    fixes where along each line the segments are, and in the re-association under a
    fitted transform.  An extent's ends move by a few beams' spacing with the view,
    and a landmark's grow by the drift along the wall between its observations, so
    the tests refuse only segments that disagree by more than this."""
    extent_rule: Literal["within", "overlap"] = "overlap"
    """How a line pairing's segments must lie, where both maps give extents.
    ``"overlap"``: the segments overlap along the line (within
    :attr:`extent_margin_m` plus noise).  ``"within"``: ``map_a``'s segment lies
    within ``map_b``'s, for a ``map_b`` that holds every wall whole and a ``map_a``
    whose landmarks never outgrow their wall: a wall of ``map_a`` is then never
    longer than its partner (a unary test on the nodes) and never reaches past its
    partner's ends (the binary test of non-parallel pairings and the
    re-association).  *(choice)* ``"overlap"``: an EKF landmark outgrows its wall by
    the drift along it between its observations and by the collinear pieces its
    association joins across doorways (``docs/results/ccda.md``)."""
    unique_partners: bool = True
    """Re-association pairs a feature of ``map_a`` only when it has a single partner
    inside the gate under the fitted transform.  A feature with two (a wall between
    two parallel walls a door width apart, a tree of a regular grid) says nothing
    about which is right, and counting it would let repetition add support to a
    wrong transform; it stays unpaired, for the estimator's own association later.
    Hypotheses are still ranked by all the features they explain; a match is
    accepted only when at least ``min_pairings`` of its pairings are unambiguous."""
    var_floor_m: float = 1e-4
    """Standard deviation (m) added in quadrature to every positional variance."""
    var_floor_rad: float = 1e-5
    """Standard deviation (rad) added in quadrature to every angular variance."""


#: Every :attr:`CCDAParams.extent_rule`.
EXTENT_RULES = ("within", "overlap")

#: Every :attr:`CCDAResult.reason`.
REASONS = (
    "accepted",
    "empty map",
    "too few features",
    "too few pairings",
    "degenerate geometry",
    "unverifiable",
    "ambiguous",
    "graph too large",
    "search_limit",
)


@dataclass(frozen=True)
class CCDAResult:
    """Outcome of :func:`ccda_match`; diagnostics are filled even when rejected."""

    accepted: bool
    """True when the pairings fix an unambiguous transform."""
    reason: str
    """One of :data:`REASONS`: ``"accepted"``; ``"empty map"``, ``"too few features"``
    (inputs); ``"too few pairings"`` (best hypothesis below ``min_pairings``);
    ``"degenerate geometry"`` (its pairings do not fix the transform);
    ``"unverifiable"`` (they do, but not without one of them:
    :attr:`CCDAParams.redundant_pairings`);
    ``"ambiguous"`` (an incompatible rival has comparable support, see
    :attr:`CCDAParams.rival_fraction`); ``"graph too large"`` (``max_edges``);
    ``"search_limit"`` (the clique search exhausted ``max_clique_work``, or
    ``max_hypotheses`` ran out before every competitor was ruled out)."""
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
    search_work: int = 0
    """Work units the exact clique searches spent (see
    :attr:`CCDAParams.max_clique_work`)."""


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


def _check_params(p: CCDAParams) -> None:
    if not 0.0 < p.gate_prob < 1.0:
        raise ValueError(f"gate_prob must be in (0, 1), got {p.gate_prob}")
    if p.min_pairings < 2:
        raise ValueError(f"min_pairings must be >= 2, got {p.min_pairings}")
    if p.max_hypotheses < 1:
        raise ValueError(f"max_hypotheses must be >= 1, got {p.max_hypotheses}")
    if p.max_edges < 0:
        raise ValueError(f"max_edges must be >= 0, got {p.max_edges}")
    if p.ambiguity_margin is not None and p.ambiguity_margin < 0:
        raise ValueError(f"ambiguity_margin must be None or >= 0, got {p.ambiguity_margin}")
    if p.extent_rule not in EXTENT_RULES:
        raise ValueError(
            f"extent_rule must be one of {', '.join(EXTENT_RULES)}, got {p.extent_rule!r}"
        )
    if not 0.0 < p.rival_fraction <= 1.0:
        raise ValueError(f"rival_fraction must be in (0, 1], got {p.rival_fraction}")
    if p.max_clique_work < 1:
        raise ValueError(f"max_clique_work must be >= 1, got {p.max_clique_work}")
    for name in (
        "max_transform_std_xy_m",
        "max_transform_std_theta_rad",
        "parallel_tol_rad",
        "parallel_along_std_m",
        "extent_margin_m",
        "var_floor_m",
        "var_floor_rad",
    ):
        v = getattr(p, name)
        if not (math.isfinite(v) and v >= 0.0):
            raise ValueError(f"{name} must be finite and >= 0, got {v}")
