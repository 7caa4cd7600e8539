"""Configuration of the EKF reference pipeline (every *(choice)* of method.md)."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from typing import Literal

from ekf_reference.loops import LoopClosureParams
from mapfuse_core.ccda import CCDAParams

__all__ = ["EKFConfig"]


@dataclass(frozen=True)
class EKFConfig:
    """Parameters of :func:`ekf_reference.run_ekf`."""

    fusion: bool = True
    """Fuse the known map (the paper's method); ``False`` is "SLAM without map fusion"."""
    local_map_steps: int = 40
    """*(choice)* Steps per local map before it is joined.  40 steps (10 m of travel in
    loop600) was measured as the best trade-off between per-step cost (larger maps)
    and join cost/linearisation (more joins): see ``benchmarks/bench_ekf.py``."""
    gate_prob: float = 0.999
    """χ² gate probability of individual compatibility (observation ↔ map feature)."""
    association: Literal["nn", "jcbb"] = "nn"
    """Nearest neighbour with individual compatibility, or joint compatibility (JCBB).
    Either way a circle takes at most one observation per scan and a line any number
    (the segments of one wall split by an occluder): see
    :func:`ekf_reference.association.exclusive`."""
    line_overlap_gap_m: float = 4.0
    """Two collinear line observations are one wall only if their extents overlap or the
    gap between them is below this (m): SPmap's along-line coordinate at work."""
    prefilter_m: float = 3.0
    """Cheap pre-gate before χ² tests: centre distance (circles) and lateral offset
    (lines) in metres.  Far larger than any 99.9 % gate at the loop600 noise."""
    prefilter_rad: float = 0.3
    """Cheap pre-gate on line angle differences (rad, modulo π)."""
    anchor_prior_sigma: tuple[float, float, float] = (100.0, 100.0, math.pi)
    """*(choice)* Prior σ of the anchor when CCDA accepts a match.  The anchor is then
    constrained by the CCDA pairings themselves (hard constraints through the known
    features, an iterated update since this prior is flat:
    :func:`ekf_reference.association.apply_iterated`), so the information of the
    matched features is counted once.  The paper instead inserts CCDA's own
    covariance, which counts it twice."""
    ccda: CCDAParams = field(default_factory=lambda: CCDAParams(min_pairings=8))
    """CCDA matching parameters.  *(choice)* At least 8 pairings (the paper: more than
    three): on loop600 seed 3 a 6-pairing, all-line match 97 m off passed every gate at
    step 119, while every correct match had 8 or more pairings."""
    min_obs_for_matching: int = 2
    """Global features seen fewer times than this are left out of CCDA (spurious ones)."""
    min_obs_to_join: int = 1
    """*(choice)* Local-map features seen fewer times than this when their local map is
    joined are dropped (marginalised out) instead of joining the global map, and their
    observations become unassociated (−1).  1 keeps every feature.  On Victoria Park a
    third of the features are trunks seen in a single scan: 2 drops them, which keeps
    the global map (and every join's O(F²) cost) to the trees that were tracked."""

    carry_seen_steps: int = 0
    """*(choice, beyond the paper)* Start every local map with the global features seen
    in the last this many steps of the one before, shared the way the known map is
    (conditionally independent local maps, Piniés & Tardós 2008), so that a feature
    seen across a join keeps constraining the vehicle.  0 (default) is the paper's
    local map, which starts empty and links a re-seen feature only at its join.  A
    carried feature is shared, so it is not tested against the known map while it is
    carried (new local features are, at every step); an estimated duplicate of a known
    feature then keeps its observations (loop600 seed 2: 6 duplicates, 4 without).  On
    loop600 (40 seeds, ``benchmarks/mc_loop600.py``), 1 keeps the fused maximum error
    within 0.15 m on 37 seeds instead of 32 (iSAM2's filter: 37), about as consistent
    with fusion as before (NEES within the χ² bound on ≥ 90 % of the steps on 35 seeds
    instead of 33); without fusion it makes the EKF less consistent (NEES
    within the χ² bound on ≥ 90 % of the steps on 29 seeds instead of 34), towards
    one local map for the whole run (seed 4: 11 % of the steps within).  Not
    combinable with :attr:`loop_closure`."""

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

    def __post_init__(self) -> None:
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
        if self.min_obs_to_join < 1:
            raise ValueError(f"min_obs_to_join must be >= 1, got {self.min_obs_to_join}")
        if not 0.0 < self.gate_prob < 1.0:
            raise ValueError(f"gate_prob must be in (0, 1), got {self.gate_prob}")
        if self.association not in ("nn", "jcbb"):
            raise ValueError(f"association must be 'nn' or 'jcbb', got {self.association!r}")
        if not (math.isfinite(self.join_circle_sigma_m) and self.join_circle_sigma_m >= 0.0):
            raise ValueError(f"join_circle_sigma_m must be >= 0, got {self.join_circle_sigma_m}")
        for name in ("line_overlap_gap_m", "prefilter_m", "prefilter_rad"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be > 0")
        if any(not s > 0.0 for s in self.anchor_prior_sigma):
            raise ValueError("anchor_prior_sigma must be positive")
