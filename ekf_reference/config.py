"""Configuration of the EKF reference pipeline (every *(choice)* of docs/method.md)."""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Literal

from ekf_reference.anchor_watch import AnchorWatchParams
from ekf_reference.known_gating import KnownGatingParams
from ekf_reference.loops import LoopClosureParams
from mapfuse_core.matching import AssociationConfig

__all__ = ["PAPER_FIELDS", "EKFConfig", "PaperField"]


@dataclass(frozen=True)
class EKFConfig:
    """Parameters of :func:`ekf_reference.run_ekf`."""

    local_map_steps: int = 40
    """*(choice)* Steps per local map before it is joined.  40 steps (10 m of travel in
    loop600) balances the per-step cost (larger maps) against the join cost and
    linearisation (more joins): ``benchmarks/bench_ekf.py`` measures it."""
    local_map_heading_sigma_rad: float | None = None
    """*(choice, beyond the paper)* Also join a local map once the heading σ its
    odometry has accumulated since the map started exceeds this (rad): the square root of
    the sum of its increments' heading variances, dead reckoning before any observation.
    On logs whose odometry is rough for their step length the filter's own excess over
    a smoother grows with what a local map accumulates; this bounds it whatever a
    step's length and noise, at the cost of more joins.  ``None`` (default): steps
    alone (:attr:`local_map_steps`), as the paper (``docs/results/carmen.md``, the
    EKF's own part)."""
    odometry_linearisation: Literal["measured", "iterated"] = "iterated"
    """*(choice, beyond the paper)* Where a step's update linearises the motion by its
    odometry increment.  ``"iterated"`` (default): the update holds the map before the
    prediction and the increment as a state, relinearises the motion at the updated
    increment (Gauss–Newton, :mod:`ekf_reference.increment`) and then moves the map by
    it; a step without pairings is the prediction alone.  ``"measured"``: the paper's
    EKF, linearised at the measured increment; the update then corrects the heading
    change through cross-covariances tangent to the rotation, which pushes every
    feature off its arc by about ``d·δ²/2`` (``d`` its distance, ``δ`` the heading
    correction) in the same direction at every step.  The two agree where a step's
    heading σ is small (loop600: 0.0009 rad); with 0.02–0.03 rad a step (laser logs,
    rough odometry) the measured linearisation leaves the EKF one to two orders
    overconfident where a smoother on its decisions is not; iterated, it costs about
    twice the time (``docs/results/carmen.md``, the EKF's own part)."""
    data_association: AssociationConfig = field(default_factory=AssociationConfig)
    """Gates, search (``method``: nearest neighbour or JCBB), one-to-one rules, CCDA
    match and anchor prior: the settings shared with the factor graph
    (:class:`~mapfuse_core.matching.AssociationConfig`)."""
    min_obs_to_join: int = 1
    """*(choice)* Local-map features seen fewer times than this when their local map is
    joined are dropped (marginalised out) instead of joining the global map, and their
    observations become unassociated (−1).  1 keeps every feature; 2 drops the trunks
    seen in a single scan, which keeps the global map (and every join's O(F²) cost) to
    the trees that were tracked (``docs/results/ekf-options.md``)."""
    tentative_min_sightings: int = 1
    """*(choice, beyond the paper)* A new feature joins the map only once seen on this
    many distinct steps within :attr:`tentative_window_steps` of its birth; until then
    it is tentative (not paired with the known map) and it is dropped (marginalised
    out, its observations unassociated) when it is not (:mod:`ekf_reference.tentative`).
    1 (default) is the paper's method: every new feature is permanent, spurious
    detections (clutter) too."""
    tentative_window_steps: int = 10
    """Steps, from its birth, within which a tentative feature must reach
    :attr:`tentative_min_sightings` (cut short by its local map's join)."""

    carry_seen_steps: int = 0
    """*(choice, beyond the paper)* Start every local map with the global features seen
    in the last this many steps of the one before, shared the way the known map is
    (conditionally independent local maps, Piniés & Tardós 2008), so that a feature
    seen across a join keeps constraining the vehicle.  0 (default) is the paper's
    local map, which starts empty and links a re-seen feature only at its join.  A
    carried feature is shared, so it is not tested against the known map while it is
    carried (new local features are, at every step); an estimated duplicate of a known
    feature then keeps its observations.  With fusion it bounds the maximum error more
    often at about the same consistency; without fusion it makes the EKF less
    consistent, towards one local map for the whole run (``docs/results/ekf-options.md``,
    ``benchmarks/mc_loop600.py``).  Not combinable with :attr:`loop_closure`."""

    loop_closure: LoopClosureParams | None = None
    """*(choice)* Before the join's association, register the local map's circles to
    the global map's (:mod:`ekf_reference.loops`); when that finds a loop closure the
    filtered relative pose of the two maps missed, widen that relative pose by the
    correction found and apply the registered pairings that then pass their gates.
    ``None`` (default) is the paper's join."""
    join_circle_sigma_m: float = 0.0
    """*(choice)* σ (m) added to the centre and the radius of every local circle when its
    local map is joined: the part of a trunk's detection error that depends on the side
    it is seen from is common to the scans of one local map and does not average out."""

    known_map_gating: bool = True
    """*(choice, beyond the paper)* Watch every known feature's pairings and stop fusing
    one that keeps failing its χ² tests (:mod:`ekf_reference.known_gating`); ``False``
    fuses every pairing the association's gate lets through (the paper's fusion, the
    baseline of ``docs/results/changes.md``)."""
    known_gating: KnownGatingParams = field(default_factory=KnownGatingParams)
    """Level, window and counts of that gate."""
    anchor_watch: AnchorWatchParams | None = None
    """*(choice, beyond the paper)* After a match is fused, test the known features'
    innovations against it and undo an anchor they contradict: filtering goes back to
    just before the fusion and runs again without that match, which CCDA may replace at
    a later join (:mod:`ekf_reference.anchor_watch`).  ``None`` (default) keeps every
    anchor fused, as the paper's Algorithm 1.  Off by default: on the generated worlds
    the joint test (``data_association.match_joint_test``) already refuses the wrong
    matches and the watch redid none, while on real logs (Intel, seeds 0–1) it undid
    right anchors, 0.2–0.3 m off, whose known walls the floor plan states more tightly
    than the anchor holds them (``docs/gaps.md``)."""

    anchor_entry: Literal["pairings", "ccda_estimate"] = "pairings"
    """*(choice, beyond the paper)* How an accepted CCDA match enters the global map.
    ``"pairings"`` (default): the anchor ``x^Wlocal_Wknown`` enters at CCDA's value under
    the flat prior ``data_association.anchor_prior_sigma``, with the known map, and the
    match's pairings tie the matched features to their known features by an iterated
    update (:func:`ekf_reference.anchoring.fuse_match`): what the matched features know
    of the transform enters once, with the EKF's correlations between them.
    ``"ccda_estimate"``: the paper's insertion (§3.2–3.3.1, eqs. 12–16).  CCDA matches
    the global map expressed in ``Wglobal``, and its estimate ``x^Wglobal_Wknown`` enters
    as ``x^Wlocal_Wknown = x^Wlocal_Wglobal ⊕ x^Wglobal_Wknown`` with covariance
    ``G diag(C_CCDA, C_global) Gᵀ`` (eq. 15), independent of the map's features; no
    pairing is fused, and the matched features stay in the map (their tracks join the
    known features').  CCDA's covariance comes from the same features, which keep
    their information, and ignores their correlations: the transform's information
    is counted twice.  ``docs/results/ekf-paper-preset.md`` measures the two."""
    known_map_in_local_maps: Literal["shared", "copied"] = "shared"
    """*(choice, beyond the paper)* How the anchor and the known map reach the local
    maps once the map is matched.  ``"shared"`` (default): they are shared between the
    global map and the local map started from it (conditionally independent local
    maps, Piniés and Tardós 2008; :func:`ekf_reference.maps.new_local_map`): a local map
    starts with their global marginal and the join corrects the global-only elements
    through their correlation with them, so their information is counted once.
    ``"copied"``: the paper's (§3.3.1–3.3.3, eqs. 14, 17–24).  The global map holds the
    anchor and no known feature (eq. 14); every local map starts with a copy of the
    anchor (its global mean and marginal covariance, uncorrelated with the vehicle,
    eqs. 17–18) and of the known map (its surveyed covariance, uncorrelated, eq. 19),
    :func:`ekf_reference.maps.copied_local_map`.  Observations update the local
    features only; a local feature is then tied to a known feature (eq. 20) and kept.
    At the join the copies of the known features are dropped, the local features join
    the global ones (eq. 5) and the local anchor is tied to the global one (eqs.
    22–24).  The copies are treated as independent of what they were copied from, so
    the anchor's and the known features' information is counted again at every join,
    and during a local map the vehicle's pose in ``Wglobal`` is the global map's base
    (as of the last join) with the local map's motion, uncorrected by what the local
    map learns of the anchor.  Not combinable with :attr:`carry_seen_steps` (a carried
    feature is shared)."""
    line_tie_residual_at: Literal["observed", "target"] = "observed"
    """*(choice, beyond the paper)* Where the lateral residual of a hard tie between two
    map lines is measured (:func:`mapfuse_core.models.line.line_residual`'s ``at``): a
    local line with a global one at a join, a local line with a known wall, a matched
    line with its known wall.  ``"observed"`` (default): at the reference point of the
    line being tied (near the segments it was observed at), from the line it is tied
    to, as every measurement is (``docs/method.md``): the residual does not depend on
    where the target's reference point lies along its line.  ``"target"``: the paper's
    ``B · x^F_G`` (eqs. 5 and 20): at the reference point of the line it is tied to.
    A known wall's reference point reaches the working frame through the anchor, whose
    translation along the wall is uncertain; measured there, the lateral residual
    depends on it through the sine of the (noisy) angle between the lines, and the
    ties pile up anchor information along the wall that no wall holds.  A
    measurement's residual is always measured at the measured segment."""

    def __post_init__(self) -> None:
        for name, allowed in (
            ("anchor_entry", ("pairings", "ccda_estimate")),
            ("known_map_in_local_maps", ("shared", "copied")),
            ("line_tie_residual_at", ("observed", "target")),
            ("odometry_linearisation", ("measured", "iterated")),
        ):
            if getattr(self, name) not in allowed:
                raise ValueError(
                    f"{name} must be one of {', '.join(map(repr, allowed))}; "
                    f"got {getattr(self, name)!r}"
                )
        if self.known_map_in_local_maps == "copied" and self.carry_seen_steps:
            raise ValueError(
                "carry_seen_steps shares features between the global and the local map; "
                "known_map_in_local_maps='copied' shares none (use 'shared')"
            )
        if self.anchor_watch is not None and not isinstance(self.anchor_watch, AnchorWatchParams):
            raise ValueError(
                "anchor_watch must be an AnchorWatchParams or None, got "
                f"{type(self.anchor_watch).__name__}"
            )
        if not isinstance(self.known_gating, KnownGatingParams):
            raise ValueError(
                f"known_gating must be a KnownGatingParams, got {type(self.known_gating).__name__}"
            )
        if self.local_map_steps < 1:
            raise ValueError(f"local_map_steps must be >= 1, got {self.local_map_steps}")
        h = self.local_map_heading_sigma_rad
        if h is not None and not (isinstance(h, numbers.Real) and math.isfinite(h) and h > 0.0):
            raise ValueError(f"local_map_heading_sigma_rad must be None or > 0, got {h!r}")
        if (
            isinstance(self.carry_seen_steps, bool)
            or not isinstance(self.carry_seen_steps, numbers.Integral)
            or self.carry_seen_steps < 0
        ):
            raise ValueError(f"carry_seen_steps must be an int >= 0, got {self.carry_seen_steps!r}")
        if self.carry_seen_steps and self.loop_closure is not None:
            # The registration tells local from global circles by in_local; carried
            # circles are both, and that case is neither designed nor tested.
            raise ValueError("carry_seen_steps and loop_closure cannot be used together")
        for name in ("tentative_min_sightings", "tentative_window_steps"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < 1:
                raise ValueError(f"{name} must be an int >= 1, got {v!r}")
        if self.tentative_window_steps < self.tentative_min_sightings:
            raise ValueError(
                f"tentative_window_steps ({self.tentative_window_steps}) must be >= "
                f"tentative_min_sightings ({self.tentative_min_sightings})"
            )
        if self.min_obs_to_join < 1:
            raise ValueError(f"min_obs_to_join must be >= 1, got {self.min_obs_to_join}")
        if not isinstance(self.data_association, AssociationConfig):
            raise ValueError(
                "data_association must be an AssociationConfig, got "
                f"{type(self.data_association).__name__}"
            )
        if not (math.isfinite(self.join_circle_sigma_m) and self.join_circle_sigma_m >= 0.0):
            raise ValueError(f"join_circle_sigma_m must be >= 0, got {self.join_circle_sigma_m}")

    @classmethod
    def paper(cls) -> EKFConfig:
        """The paper's method exactly: every extension beyond it off, the paper's forms
        and values where it gives them, and the default wherever it is silent, each such
        setting or detail marked *(choice)* below.  :data:`PAPER_FIELDS` classifies every
        setting; :meth:`extensions` lists where the default differs, and why.  With
        :func:`~ekf_reference.run_ekf`'s ``fusion=True`` (its default) it is the paper's
        Algorithm 1 (§3); with ``fusion=False`` the paper's SLAM without the known map.

        From the paper (Chanier et al.; § are the paper's sections):

        * ``anchor_entry``: ``"ccda_estimate"``.  CCDA matches the global map in
          ``Wglobal`` and estimates ``x^Wglobal_Wknown`` and its covariance (§3.2, eq.
          12); the anchor enters as ``x^Wlocal_Wglobal ⊕ x^Wglobal_Wknown`` (eq. 13) with
          the covariance of eqs. 15–16, CCDA's estimate independent of the map; no
          pairing is fused.  *(choice)* The matched features' tracks join the known
          features' (bookkeeping: the labels of the decisions and the map).
        * ``known_map_in_local_maps``: ``"copied"``.  The global map holds the anchor and
          no known feature (eq. 14).  Every local map starts with a copy of the anchor
          (the global mean and marginal covariance, uncorrelated with the vehicle, eqs.
          17–18) and of the known map with its surveyed covariance (eqs. 11, 19).
          Observations update the local features; then each local feature paired with a
          known feature is tied to it by a hard constraint (§3.3.2, eqs. 20–21).  The
          join pairs the local features with the global ones (eq. 5) and then ties the
          local anchor to the global one (§3.3.3, eqs. 22–24; Algorithm 1's order).
          During a local map the vehicle's pose in ``Wglobal`` is the global map's base
          with the local map's motion (§2.1).  *(choice)* The known map is joined once,
          when the local map starts (eq. 19 joins it "to update the local map"; joined
          afresh at every step it would count its covariance at every step).
          *(choice)* A local feature tied to a known one is kept and tied once (the
          paper does not say whether a tie is repeated; repeated, a hard constraint
          already met is singular).  *(choice)* At the join the copies of the known
          features are dropped (the global map has none, eq. 14).  *(choice)* The noise
          ``w_known`` of eq. 22 is the local anchor's own uncertainty (a state of the
          stacked system, eq. 24), with nothing added.
        * ``line_tie_residual_at``: ``"target"``: a tie of two lines (eqs. 5 and 20,
          ``B · x^F_G``) measures the lateral offset at the reference point of the line
          the local feature is tied to.
        * ``data_association.ccda.min_pairings``: 4, "more than three" pairings (§3.2).
        * ``data_association.ccda.redundant_pairings``: off, and
          ``data_association.ccda.ambiguity_margin``: 0: the match is accepted on the
          size of the maximum clique (§3.2), with no check of each pairing by the others
          and no refusal for a smaller incompatible rival.  *(choice)* A rival of the
          same size still refuses it: a count cannot choose between the two.
        * ``data_association.min_obs_for_matching``: 1, the whole global map is matched
          (§3.2, Algorithm 1).
        * ``data_association.match_joint_test``, ``match_pairing_test``: off and
          ``match_exclusions``: 0: CCDA's accepted match is used as it is (§3.2–3.3).
        * ``anchor_watch``: ``None``: an accepted anchor stays (Algorithm 1).
        * ``local_map_heading_sigma_rad``: ``None``: a local map is bounded by its number
          of filter iterations alone (§1).
        * ``odometry_linearisation``: ``"measured"``: the EKF's prediction and update
          (§2.1), the motion linearised at the measured increment.
        * ``known_map_gating``: off: every pairing the association accepts is fused at
          every step (§3.3.2).
        * ``tentative_min_sightings``: 1, no condition on a new feature (§2.1.1);
          ``min_obs_to_join``: 1, the whole local map is joined (§2.1.2);
          ``carry_seen_steps``: 0, a local map starts with its base and the anchor only
          (§3.3.1, eq. 17); ``loop_closure``: ``None`` and ``join_circle_sigma_m``: 0,
          a join pairs local and global features by association alone, with the local
          map's own covariance (§2.1.2, eq. 4).

        Where the paper is silent the preset keeps the default, each a *(choice)*:

        * ``local_map_steps`` *(choice)*: 40; the paper bounds a local map by "a maximal
          number of filter iterations" without giving it (§1).
        * ``data_association.gate_prob``, ``prefilter_m``, ``prefilter_rad``, ``method``,
          ``map_method``, ``map_ambiguity``, ``ambiguity``, ``jcbb_max_nodes``,
          ``one_observation_per_circle``, ``one_observation_per_line`` *(choice)*: the
          association within the filter and at a join is not described (the paper
          defers to its reference [5]): individual χ² at 0.999, nearest neighbour for
          measurements and at joins, one observation per trunk and scan.  *(choice)* So is the
          observation model of a local feature ([5]): a measured segment's lateral
          residual is taken at the segment (``docs/method.md``).
        * ``data_association.line_gap_m``, ``data_association.known_wall_ends``,
          ``data_association.ccda.extent_margin_m``,
          ``data_association.ccda.extent_rule`` *(choice)*: the paper uses a line's
          along-line coordinate to disambiguate association (§2.2.1) and gives no
          threshold.
        * ``data_association.known_gap_m`` *(choice)*: read by the factor graph only.
        * ``data_association.ccda.gate_prob``, ``parallel_tol_rad``,
          ``parallel_along_std_m``, ``var_floor_m``, ``var_floor_rad``,
          ``unique_partners`` *(choice)*: the gates, invariants and re-association of
          CCDA, whose tests the paper names but does not specify (§3.2).
        * ``data_association.ccda.max_transform_std_xy_m``,
          ``max_transform_std_theta_rad`` *(choice)*: pairings that leave the transform
          unfixed give no estimate of it to insert (§3.2 estimates it).
        * ``data_association.ccda.max_hypotheses``, ``max_clique_work``, ``max_edges``
          *(choice)*: bounds on the search's work; the paper gives none.
        * ``data_association.ccda.rival_fraction`` *(choice)*: unused with
          ``ambiguity_margin`` set.
        * ``data_association.anchor_prior_sigma`` *(choice)*: unused with
          ``anchor_entry`` ``"ccda_estimate"``, whose anchor has CCDA's covariance.
        * ``tentative_window_steps`` *(choice)*: unused with ``tentative_min_sightings``
          1; ``known_gating`` *(choice)*: unused with ``known_map_gating`` off.
        """
        d = cls()
        assoc = d.data_association
        ccda = dataclasses.replace(
            assoc.ccda, min_pairings=4, redundant_pairings=False, ambiguity_margin=0
        )
        return dataclasses.replace(
            d,
            anchor_entry="ccda_estimate",
            known_map_in_local_maps="copied",
            line_tie_residual_at="target",
            anchor_watch=None,
            local_map_heading_sigma_rad=None,
            odometry_linearisation="measured",
            known_map_gating=False,
            tentative_min_sightings=1,
            min_obs_to_join=1,
            carry_seen_steps=0,
            loop_closure=None,
            join_circle_sigma_m=0.0,
            data_association=dataclasses.replace(
                assoc,
                ccda=ccda,
                min_obs_for_matching=1,
                match_joint_test=False,
                match_pairing_test=False,
                match_exclusions=0,
            ),
        )

    @staticmethod
    def extensions() -> dict[str, str]:
        """The settings whose default goes beyond the paper (``EKFConfig()`` differs
        from :meth:`paper` there and nowhere else): dotted name → one line saying what
        the default does and why."""
        return {name: f.why for name, f in PAPER_FIELDS.items() if f.role == "extension"}


@dataclass(frozen=True)
class PaperField:
    """How one setting of :class:`EKFConfig` relates to the paper."""

    role: Literal["paper", "choice", "extension"]
    """``"paper"``: the paper fixes the value and the default is it; ``"choice"``: the
    paper is silent and :meth:`EKFConfig.paper` keeps the default; ``"extension"``: the
    default goes beyond the paper and :meth:`EKFConfig.paper` sets the paper's value."""
    why: str
    """One line: the paper's section (``"paper"``), what the preset keeps and why
    (``"choice"``), or what the default adds and why (``"extension"``)."""


def _p(why: str) -> PaperField:
    return PaperField("paper", why)


def _c(why: str) -> PaperField:
    return PaperField("choice", why)


def _x(why: str) -> PaperField:
    return PaperField("extension", why)


_DA = "data_association."
_CCDA = "data_association.ccda."

PAPER_FIELDS: Mapping[str, PaperField] = MappingProxyType(
    {
        "local_map_steps": _c("40: the paper bounds a local map by iterations, not how many."),
        "local_map_heading_sigma_rad": _p("§1: a local map is bounded by iterations only (None)."),
        "odometry_linearisation": _x(
            "§2.1's EKF linearises at the measured odometry; iterated through it, beyond."
        ),
        _DA + "gate_prob": _c("0.999: the association's gate is not given (ref. [5])."),
        _DA + "prefilter_m": _c("3 m: a cheap pre-gate far wider than the χ² gate."),
        _DA + "prefilter_rad": _c("0.3 rad: a cheap pre-gate far wider than the χ² gate."),
        _DA + "line_gap_m": _c("4 m: §2.2.1 uses the along-line coordinate, no threshold."),
        _DA + "known_gap_m": _c("30 m: read by the factor graph's own association only."),
        _DA + "known_wall_ends": _c(
            "on: §2.2.1 uses the along-line coordinate; a segment lies within its wall."
        ),
        _DA + "method": _c("nearest neighbour: the search is not described (ref. [5])."),
        _DA + "jcbb_max_nodes": _c("unused with nearest neighbour."),
        _DA + "map_method": _c(
            "nearest neighbour: the join's association is not described (ref. [5])."
        ),
        _DA + "map_ambiguity": _c(
            "the nearest: the join's association is not described (ref. [5])."
        ),
        _DA + "ambiguity": _c("the nearest: the association is not described (ref. [5])."),
        _DA + "one_observation_per_circle": _c("a scan sees a trunk once; not described."),
        _DA + "one_observation_per_line": _c("an occluded wall gives several segments."),
        _DA + "min_obs_for_matching": _x(
            "2: features seen once (mostly spurious) stay out of CCDA's match; §3.2 "
            "matches the whole global map (1)."
        ),
        _DA + "anchor_prior_sigma": _c(
            "flat; unused with anchor_entry 'ccda_estimate' (eq. 15: CCDA's covariance)."
        ),
        _DA + "match_joint_test": _x(
            "on: an accepted match's pairings must pass a joint χ² test with the EKF's "
            "correlations before they are fused (CCDA ignores them); §3.2 fuses the match."
        ),
        _DA + "match_pairing_test": _x(
            "on: each pairing of the match must pass its own χ² test given the others "
            "(one moved feature among many right ones); §3.2 fuses the match."
        ),
        _DA + "match_exclusions": _x(
            "4: a refused match is searched again without its failing pairing's feature; "
            "the paper has no refusal (0)."
        ),
        _CCDA + "gate_prob": _c("0.999: CCDA's gates are not given."),
        _CCDA + "min_pairings": _x(
            "8: fewer lets wrong matches of a few collinear walls through; §3.2 asks for "
            "more than three (4)."
        ),
        _CCDA + "max_transform_std_xy_m": _c("1 m: pairings must fix the transform."),
        _CCDA + "max_transform_std_theta_rad": _c("0.05 rad: pairings must fix the transform."),
        _CCDA + "redundant_pairings": _x(
            "on: a match whose transform one pairing alone fixes is refused; §3.2 "
            "accepts on the clique's size (off)."
        ),
        _CCDA + "parallel_tol_rad": _c("0.1 rad: parallel-line invariant; not described."),
        _CCDA + "parallel_along_std_m": _c("10 m: nearly parallel lines' gate; not described."),
        _CCDA + "ambiguity_margin": _x(
            "None (rival_fraction 0.5): an incompatible rival with half the support refuses "
            "the match; §3.2 takes the maximum clique (0: only a tie refuses)."
        ),
        _CCDA + "rival_fraction": _c("unused with ambiguity_margin set."),
        _CCDA + "max_hypotheses": _c("30: a bound on the search; the paper gives none."),
        _CCDA + "max_clique_work": _c("2·10⁶: a bound on the search; the paper gives none."),
        _CCDA + "max_edges": _c("5·10⁶: a bound on the search; the paper gives none."),
        _CCDA + "extent_margin_m": _c("0.5 m: §2.2.1 uses the along-line coordinate."),
        _CCDA + "extent_rule": _c("overlap: §2.2.1 uses the along-line coordinate."),
        _CCDA + "unique_partners": _c("re-association under the fit; not described."),
        _CCDA + "var_floor_m": _c("1e-4 m: keeps zero-covariance maps' gates invertible."),
        _CCDA + "var_floor_rad": _c("1e-5 rad: keeps zero-covariance maps' gates invertible."),
        "min_obs_to_join": _p("§2.1.2: the whole local map is joined to the global map (1)."),
        "tentative_min_sightings": _p("§2.1.1 sets no condition on a new feature (1)."),
        "tentative_window_steps": _c("unused with tentative_min_sightings 1."),
        "carry_seen_steps": _p("§3.3.1, eq. 17: a local map starts with base and anchor (0)."),
        "loop_closure": _p("§2.1.2: a join pairs features by association alone (None)."),
        "join_circle_sigma_m": _p("§2.1.2, eq. 4: a local map joins with its own covariance (0)."),
        "known_map_gating": _x(
            "on: a known feature whose pairings keep failing their χ² tests stops being "
            "fused (a map out of date); §3.3.2 fuses every accepted pairing (off)."
        ),
        "known_gating": _c("unused with known_map_gating off."),
        "anchor_watch": _p("Algorithm 1 keeps the first anchor (None, the default too)."),
        "anchor_entry": _x(
            "pairings: the match's pairings fix the anchor, counted once with the EKF's "
            "correlations; eqs. 12–16 insert CCDA's estimate and covariance (ccda_estimate)."
        ),
        "known_map_in_local_maps": _x(
            "shared: each local map shares the anchor and known map, counted once; eqs. "
            "17–24 copy them into every local map and fuse the anchor back (copied)."
        ),
        "line_tie_residual_at": _x(
            "observed: a tie of two lines measures the offset at the tied line's reference "
            "point, blind to the anchor along a wall; eqs. 5 and 20 at the target's (target)."
        ),
    }
)
"""Every setting of :class:`EKFConfig` (a dotted name; a nested settings object named
whole covers all of its fields) classified against the paper: what
:meth:`EKFConfig.paper` sets and why."""
