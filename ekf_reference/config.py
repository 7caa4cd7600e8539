"""Configuration of the EKF reference pipeline (every *(choice)* of docs/method.md)."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field

from ekf_reference.anchor_watch import AnchorWatchParams
from ekf_reference.known_gating import KnownGatingParams
from ekf_reference.loops import LoopClosureParams
from mapfuse_core.matching import AssociationConfig

__all__ = ["EKFConfig"]


@dataclass(frozen=True)
class EKFConfig:
    """Parameters of :func:`ekf_reference.run_ekf`."""

    local_map_steps: int = 40
    """*(choice)* Steps per local map before it is joined.  40 steps (10 m of travel in
    loop600) balances the per-step cost (larger maps) against the join cost and
    linearisation (more joins): ``benchmarks/bench_ekf.py`` measures it."""
    data_association: AssociationConfig = field(default_factory=AssociationConfig)
    """Gates, search (``method``: nearest neighbour or JCBB), one-to-one rules, CCDA
    match and anchor prior: the settings shared with the factor graph
    (:class:`~mapfuse_core.matching.AssociationConfig`)."""
    min_obs_to_join: int = 1
    """*(choice)* Local-map features seen fewer times than this when their local map is
    joined are dropped (marginalised out) instead of joining the global map, and their
    observations become unassociated (−1).  1 keeps every feature; 2 drops the trunks
    seen in a single scan, which keeps the global map (and every join's O(F²) cost) to
    the trees that were tracked (``docs/configuration.md``)."""
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
    consistent, towards one local map for the whole run (``docs/configuration.md``,
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
    baseline of ``docs/changes.md``)."""
    known_gating: KnownGatingParams = field(default_factory=KnownGatingParams)
    """Level, window and counts of that gate."""
    anchor_watch: AnchorWatchParams | None = field(default_factory=AnchorWatchParams)
    """*(choice, beyond the paper)* After a match is fused, test the known features'
    innovations against it and undo an anchor they contradict: filtering goes back to
    just before the fusion and runs again without that match, which CCDA may replace at
    a later join (:mod:`ekf_reference.anchor_watch`).  ``None`` keeps every anchor
    fused (the paper's method)."""

    def __post_init__(self) -> None:
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
