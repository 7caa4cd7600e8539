"""Settings of data association, shared by every estimator (EKF and factor graph).

One :class:`AssociationConfig` decides how observations are paired with map features
and how a map is matched with the known map: the χ² gate, the cheap pre-gates before
it, when two collinear segments can be one wall, the search (nearest neighbour or
joint compatibility), the one-to-one rules, and the CCDA match that anchors the known
map.  The estimators hold one such object (``EKFConfig.data_association``,
``GraphOptions.data_association``) and keep only their backend-specific settings.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from typing import Literal

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.matching.ccda import CCDAParams

__all__ = ["AMBIGUITY", "MAP_AMBIGUITY", "METHODS", "AssociationConfig"]

METHODS: tuple[str, ...] = ("nn", "jcbb")
"""Names of the association searches: nearest neighbour, joint compatibility."""

MAP_AMBIGUITY: tuple[str, ...] = ("refuse", "nearest")
"""What an ambiguous map-to-map pairing does (:attr:`AssociationConfig.map_ambiguity`)."""
AMBIGUITY: tuple[str, ...] = ("refuse", "refuse_known", "skip", "nearest")
"""What an ambiguous measurement does (:attr:`AssociationConfig.ambiguity`)."""


def _default_ccda() -> CCDAParams:
    return CCDAParams(min_pairings=8)


@dataclass(frozen=True)
class AssociationConfig:
    """How observations are paired with map features and maps with the known map."""

    gate_prob: float = 0.999
    """χ² gate probability of individual compatibility (observation ↔ map feature, map
    feature ↔ known feature) and of the joint test of JCBB."""
    prefilter_m: float = 3.0
    """Cheap pre-gate before the χ² test (m): centre distance for circles, lateral
    offset for lines (either reference point from the other's line).  Far larger than
    any 99.9 % gate at simulated laser noise; it only saves χ² tests."""
    prefilter_rad: float = 0.3
    """Cheap pre-gate on the angle between two lines (rad, modulo π)."""
    line_gap_m: float = 4.0
    """Two collinear line segments can be one wall only if their extents along the
    wall overlap or the gap between them is at most this (m): without it, collinear
    walls far apart (two sides of a street) pair up."""
    known_wall_ends: bool = True
    """A segment pairs with a known wall whose extent is surveyed only if it lies within
    that extent: each of its ends at most the :attr:`gate_prob` quantile (one dof) of
    the along-wall σ of where the ends lie (the anchor's uncertainty along the wall,
    the survey's, and the segment's: a beam's footprint at its range) beyond it.  A
    segment of a wall lies within that wall.
    Without it, a wall that continues beyond a known one's end at a few degrees to it
    (two walls side by side) passes the χ² test of the known wall's infinite line,
    whose direction the survey knows only to its σ, and the known wall takes the other
    wall's observations for the rest of the run
    (``docs/results/association.md``).  Used by the EKF."""
    known_gap_m: float = 30.0
    """*(choice)* For a known wall with no extents: it can be a line landmark only if
    its reference point lies within this distance (m) of the segment the landmark was
    seen on.  30 m is half the longest loop600 wall (45 m) plus margin.  Used by the
    factor graph's own known-map pairing; the EKF takes a known wall without extents
    as overlapping every collinear segment."""
    method: Literal["nn", "jcbb"] = "nn"
    """``"nn"``: greedy nearest neighbour over individually compatible pairs, best
    (smallest d²) first.  ``"jcbb"``: joint compatibility branch and bound (Neira &
    Tardós 2001), the largest jointly compatible set.  The factor graph's own
    association supports ``"nn"`` only."""
    map_method: Literal["nn", "jcbb"] = "nn"
    """The search of map-to-map pairings (a local map's features at its join with the
    global map, map features with the known map), as :attr:`method` is that of
    measurements.  ``"jcbb"``: a local map's features pair with the global map only as
    a jointly compatible set.  They share the local map's drift relative to the global
    map, so a pairing that fits alone but not with the others (the parallel wall a
    metre off, once the drift allows a metre) is a wrong one.  ``"nn"``: each feature
    its nearest compatible target.  *(choice)* ``"nn"``: on loop600 (30 seeds)
    ``"jcbb"`` leaves more duplicate landmarks and raises the unfused NEES by 0.13; on
    the CARMEN logs, where walls come in parallel families, it cuts the joins' wrong
    pairings by 38–79 %, and the CARMEN profile sets it
    (``docs/results/association.md``).  Used by the EKF."""
    map_ambiguity: Literal["refuse", "nearest"] = "nearest"
    """What a map feature paired with another map (a local map's feature at its join
    with the global map, a map feature with the known map) does when it is
    individually compatible with two targets that are not compatible with each
    other: two walls a door or a corridor apart, a wall and the next one along a
    turn.  ``"refuse"``: it is not paired (it stays a landmark of its own, a
    duplicate at worst, and is paired at a later join once the maps have drifted
    less); which of the two it is would be a guess, and a wrong merge joins two
    walls for the rest of the run.  ``"nearest"``: the nearest of them.  Measurements
    follow :attr:`ambiguity`.  *(choice)* ``"nearest"``: on loop600 a refused
    feature becomes a duplicate landmark, and with ``map_method`` ``"jcbb"`` the
    duplicates double the line landmarks.  On the CARMEN logs, with ``"jcbb"``, refusing
    halves the joins' wrong pairings on three logs of six and leaves every judged pairing
    of CCDA's accepted matches right, and the CARMEN profile refuses
    (``docs/results/association.md``).  Used by the EKF."""
    ambiguity: Literal["refuse", "refuse_known", "skip", "nearest"] = "nearest"
    """What a measurement does when it is individually compatible with two targets that
    are not compatible with each other (two walls a door or a corridor apart), as
    :attr:`map_ambiguity` is for map features.  ``"refuse"``: it is not paired and
    starts a feature of its own (a duplicate at worst, which a join may pair later);
    ``"refuse_known"``: the same when both targets are known-map features, the nearest
    otherwise; ``"skip"``: it is neither paired nor a feature (it fits two features
    already in the map, so it adds no new one; counted in the EKF's
    ``details.ambiguous_skipped``); ``"nearest"``: the nearest of them.  *(choice)*
    ``"nearest"``: the paper's filter pairs every measurement it can.  On the CARMEN
    logs, once the pose has drifted a few decimetres, a short segment far off fits the
    plan wall beside its own as well as its own; refusing mends those runs, but before
    the match its duplicate landmarks let CCDA accept wrong pairings (Intel, Seattle),
    so the CARMEN profile refuses between known walls only, which acts after the match
    alone.  Skipping mends Seattle without the plan and Freiburg with it, but FHW loses
    its walls' observations and CCDA accepts wrong pairings on four runs in 48
    (``docs/results/carmen.md``).  Used by the EKF."""
    jcbb_max_nodes: int = 20_000
    """JCBB stops after visiting this many search nodes and returns the best set found
    so far (its cost is exponential in the worst case)."""
    one_observation_per_circle: bool = True
    """A circle (tree trunk) takes at most one observation per scan: a scan gives one
    return arc per trunk, so a second observation on it is another trunk."""
    one_observation_per_line: bool = False
    """``False``: a line may take several segments of one scan.  A wall occluded by a
    tree gives two segments in one scan, each a genuine, independent observation of
    one line; keeping only the best-fitting one both makes the other a duplicate
    landmark and biases the update towards the prediction (see
    ``docs/results/association.md``)."""
    ccda: CCDAParams = field(default_factory=_default_ccda)
    """CCDA parameters of the match with the known map.  *(choice)* At least 8
    pairings (the paper asks for more than three): with fewer, wrong matches made of a
    few collinear walls pass every other test (``docs/results/association.md``)."""
    min_obs_for_matching: int = 2
    """Map features observed fewer times than this are left out of the CCDA match and
    of the known-map pairing (most spurious features are seen once)."""
    anchor_prior_sigma: tuple[float, float, float] = (100.0, 100.0, math.pi)
    """*(choice)* σ (m, m, rad) of the loose prior on the anchor (the known map's pose)
    at the value CCDA accepts.  The pairings with the known features then fix the
    anchor, so the information of the matched features is counted once (CCDA's own
    covariance, inserted as the paper does, would count it twice)."""
    match_joint_test: bool = True
    """Test the pairings of an accepted CCDA match jointly, with the estimator's joint
    covariance of the matched features, before they are fused; refuse the match when
    their χ² (dimension less the anchor's 3) exceeds the :attr:`gate_prob` quantile.
    CCDA tests each pairing with marginal covariances and so cannot see that features
    drifted together: after metres of unfused drift its gates are loose enough for a
    wrong pairing among correct ones (``docs/results/ccda.md``).  Used by the EKF; its
    decisions carry the outcome to the factor graph."""
    match_pairing_test: bool = True
    """With :attr:`match_joint_test`, also test each pairing of the match against the
    others: the χ² it adds to the joint update of the rest, against the
    :attr:`gate_prob` quantile of its own dimension; refuse the match when one fails.
    One wrong pairing among many right ones can pass the joint test, its excess spread
    over the whole dimension (a wall moved since the survey, ``docs/results/changes-worlds.md``)."""
    match_exclusions: int = 4
    """When a test refuses a match and one pairing fails its own test, CCDA runs again
    at once without that pairing's map feature, up to this many times per attempt
    (0: refuse and wait for the next attempt).  A feature moved since the survey but
    still within CCDA's marginal gates otherwise keeps the same match refused at every
    attempt while the map grows.  The re-run passes every check of CCDA and both tests
    again on what is left; the bound only caps the cost of one attempt."""

    def __post_init__(self) -> None:
        if not (isinstance(self.gate_prob, numbers.Real) and 0.0 < self.gate_prob < 1.0):
            raise ValueError(f"gate_prob must be in (0, 1), got {self.gate_prob!r}")
        for name in ("prefilter_m", "prefilter_rad", "line_gap_m", "known_gap_m"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, numbers.Real) and v > 0.0):
                raise ValueError(f"{name} must be a number > 0 (inf: no limit), got {v!r}")
        for name, allowed in (("ambiguity", AMBIGUITY), ("map_ambiguity", MAP_AMBIGUITY)):
            if getattr(self, name) not in allowed:
                raise ValueError(
                    f"{name} must be one of {', '.join(allowed)}, got {getattr(self, name)!r}"
                )
        for name in ("method", "map_method"):
            if getattr(self, name) not in METHODS:
                raise ValueError(
                    f"{name} must be one of {', '.join(METHODS)}, got {getattr(self, name)!r}"
                )
        for name in ("jcbb_max_nodes", "min_obs_for_matching"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < 1:
                raise ValueError(f"{name} must be an int >= 1, got {v!r}")
        v = self.match_exclusions
        if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < 0:
            raise ValueError(f"match_exclusions must be an int >= 0, got {v!r}")
        for name in (
            "one_observation_per_circle",
            "one_observation_per_line",
            "match_joint_test",
            "match_pairing_test",
            "known_wall_ends",
        ):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be a bool, got {getattr(self, name)!r}")
        if not isinstance(self.ccda, CCDAParams):
            raise ValueError(f"ccda must be a CCDAParams, got {type(self.ccda).__name__}")
        sig = self.anchor_prior_sigma
        if not (
            isinstance(sig, tuple)
            and len(sig) == 3
            and all(isinstance(s, numbers.Real) and math.isfinite(s) and s > 0.0 for s in sig)
        ):
            raise ValueError(
                f"anchor_prior_sigma must be a tuple of 3 finite values > 0, got {sig!r}"
            )

    def one_observation_per(self, kind: FeatureKind) -> bool:
        """Whether a map feature of ``kind`` takes at most one observation per scan."""
        if kind == FeatureKind.CIRCLE:
            return self.one_observation_per_circle
        return self.one_observation_per_line
