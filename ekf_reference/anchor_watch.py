"""The anchor watch: after a map match is fused, the known features' innovations are
tested against it, and an anchor they contradict is undone.

A CCDA match passes its joint test (``AssociationConfig.match_joint_test``) against
the map as it is when it is fused.  What comes after can still contradict it: a match
whose pairings fit the matched region but whose transform is wrong elsewhere (a small
rotation about that region, a shift along a repeated structure) shows in the known
features met later, first as biased innovations, then, once the error exceeds the χ²
gate, as known features the observations pass by.  From the fusion on, the watch
applies three tests, in this order, at the end of every step:

* **Innovations.**  Every association with the known map (observations, local
  landmarks at each step, the joins) gives the normalised innovation squared of its
  known pairings jointly, ``NIS = νᵀ S⁻¹ ν`` with ``S = H P Hᵀ + R`` on the state
  before the update and the stacked dimension as degrees of freedom.  Under the
  hypothesis "the anchor and the known map are right" the innovations of a consistent
  filter are white, so their sum over the last :attr:`AnchorWatchParams.window_steps`
  steps is χ² with the summed degrees of freedom.  Model error inflates it on real
  scans whatever the anchor, so the test divides it by the NIS rate of the pairings
  with features that are not known (at least one): the anchor is contradicted when
  the ratio exceeds the :attr:`AnchorWatchParams.level` quantile of its F
  distribution (:meth:`AnchorWatch.innovation_threshold`).  (The pairings passed the
  individual gate, which truncates each NIS: the test is conservative.)
* **The match's own pairings** (with the known-map gate,
  :mod:`ekf_reference.known_gating`): more than half of the match's known features
  un-fused by the gate's per-feature tests
  (:attr:`~mapfuse_core.estimate.decisions.KnownMapGating.anchor_refuted`).
* **The known features met since** (with the gate): the known features outside the
  match that the gate has un-fused since the fusion (each failed its running χ² test
  or was passed by more often than paired) are at least
  :attr:`AnchorWatchParams.min_unfused` and more than
  :attr:`AnchorWatchParams.majority` times those paired and still fused.  A known
  feature moved since the survey fails alone and the rest confirm the anchor; under a
  wrong anchor every known feature met away from the matched region fails.

The pipeline (:mod:`ekf_reference.pipeline`) undoes a contradicted anchor by going
back to the state it kept from just before the fusion and filtering the steps since
again, without that match; CCDA tries again at the following joins, and refuses a
match whose anchor is compatible with an undone one.
"""

from __future__ import annotations

import math
import numbers
from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.stats import f as f_dist

from ekf_reference.association import Candidate, stack
from ekf_reference.state import GaussianMap, Role
from mapfuse_core.matching import chi2_gate

__all__ = [
    "CONTRADICTIONS",
    "AnchorWatch",
    "AnchorWatchParams",
    "Contradiction",
    "GateState",
    "Verdict",
    "joint_nis",
]

Contradiction = Literal["innovations", "pairings un-fused", "known features un-fused"]
"""Which test contradicted an anchor."""
CONTRADICTIONS: tuple[Contradiction, ...] = (
    "innovations",
    "pairings un-fused",
    "known features un-fused",
)
"""Every :data:`Contradiction`, in the order the watch tries them."""


@dataclass(frozen=True)
class AnchorWatchParams:
    """Settings of the anchor watch (:class:`AnchorWatch`)."""

    window_steps: int = 40
    """*(choice)* Steps the innovation test looks back on: one local map of the default
    ``EKFConfig.local_map_steps``, long enough for a few hundred degrees of freedom of
    known pairings on loop600, short enough that a bias growing along the drive is not
    diluted by the steps near the matched region."""
    level: float = 0.99999
    """*(choice)* χ² level of the innovation test.  It is made at every step on
    overlapping windows; a false alarm rate of 10⁻⁵ per test (the known-map gate's) is
    small over a run's few thousand steps, and a false alarm costs the run its
    anchor."""
    min_unfused: int = 3
    """Known features outside the match un-fused since the fusion that can contradict
    the anchor (with :attr:`majority`): the known-map gate's ``max_rejections``,
    counted over features instead of one feature's steps."""
    majority: float = 2.0
    """*(choice)* The known features un-fused since the fusion contradict the anchor
    when they are more than this many times those paired since and still fused (the
    match's included).  Twice, as CCDA's rival rule (``CCDAParams.rival_fraction``):
    a few known features moved together since the survey, met before any other, stay
    a minority of the features the anchor explains."""

    def __post_init__(self) -> None:
        if not (isinstance(self.level, numbers.Real) and 0.0 < self.level < 1.0):
            raise ValueError(f"anchor watch level must be in (0, 1), got {self.level!r}")
        for name in ("window_steps", "min_unfused"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < 1:
                raise ValueError(f"anchor watch {name} must be an int >= 1, got {v!r}")
        m = self.majority
        if isinstance(m, bool) or not (isinstance(m, numbers.Real) and 1.0 <= m < math.inf):
            raise ValueError(f"anchor watch majority must be a finite number >= 1, got {m!r}")


@dataclass(frozen=True)
class Verdict:
    """Why the watch finds an anchor contradicted."""

    test: Contradiction
    """Which test."""
    statistic: float
    """Its value: the window's summed NIS, the match's known features un-fused, or the
    other known features un-fused."""
    threshold: float
    """What it exceeded: the χ² quantile, half the match's pairings, or ``majority``
    times the known features paired and still fused."""
    dof: int
    """Degrees of freedom of the summed NIS (0 for the counts)."""


@dataclass(frozen=True)
class GateState:
    """What the known-map gate has decided since the fusion (its counts start there)."""

    paired: frozenset[int]
    """Known ids paired at least once."""
    unfused: frozenset[int]
    """Known ids un-fused."""
    match: frozenset[int]
    """Known ids of the fused match's pairings."""


def joint_nis(state: GaussianMap, chosen: list[Candidate]) -> tuple[float, int] | None:
    """``(νᵀ S⁻¹ ν, dim ν)`` of ``chosen`` stacked, on ``state`` before their update;
    ``None`` without pairings or when ``S`` is not positive definite.  ``S`` holds the
    covariances the update weighs with (:attr:`~ekf_reference.association.Candidate.R`):
    the watch compares the run's updates with what they promise."""
    if not chosen:
        return None
    r, H, R, idx = stack(state, chosen)
    S = H @ state.cov[np.ix_(idx, idx)] @ H.T + R
    try:
        L = np.linalg.cholesky(0.5 * (S + S.T))
    except np.linalg.LinAlgError:
        return None
    y = np.linalg.solve(L, r)
    return float(y @ y), int(r.size)


@dataclass
class _Step:
    """The known pairings' innovations of one step."""

    step: int
    nis: float = 0.0
    dof: int = 0


class AnchorWatch:
    """The known map's innovations since the anchor was fused, over a window of steps,
    and the verdict of the three tests (see the module docstring)."""

    def __init__(self, params: AnchorWatchParams) -> None:
        self.params = params
        self.steps: deque[_Step] = deque()
        self.singular = 0
        """Associations whose joint innovation covariance was not positive definite
        (their NIS is left out)."""
        self.local_nis = 0.0
        """Summed NIS of the pairings with features that are not known, since the
        fusion: the reference rate of the innovation test."""
        self.local_dof = 0
        """Their degrees of freedom."""

    def record(self, step: int, state: GaussianMap, chosen: list[Candidate | None]) -> None:
        """Record the pairings ``chosen`` by one association at ``step``, before they are
        applied: those with known features in the window, the others in the reference
        rate."""
        paired = [c for c in chosen if c is not None]
        known = [c for c in paired if state.elements[c.target].role == Role.KNOWN]
        local = joint_nis(state, [c for c in paired if state.elements[c.target].role != Role.KNOWN])
        if local is not None:
            self.local_nis += local[0]
            self.local_dof += local[1]
        if not known:
            return
        nis = joint_nis(state, known)
        if nis is None:
            self.singular += 1
            return
        if not self.steps or self.steps[-1].step != step:
            self.steps.append(_Step(step))
        self.steps[-1].nis += nis[0]
        self.steps[-1].dof += nis[1]

    def innovations(self, step: int) -> tuple[float, int]:
        """Summed NIS and degrees of freedom of the window ending at ``step``."""
        while self.steps and self.steps[0].step <= step - self.params.window_steps:
            self.steps.popleft()
        return sum(s.nis for s in self.steps), sum(s.dof for s in self.steps)

    def innovation_threshold(self, dof: int) -> float:
        """What the window's summed NIS of ``dof`` degrees of freedom may reach.

        The sensor's model error (walls not straight, trunks not round) inflates every
        innovation, the known pairings' too, whatever the anchor; a wrong anchor
        inflates the known pairings' only.  The test therefore compares the window's
        NIS per degree of freedom with that of the pairings with features that are not
        known, since the fusion, taken as at least one: their ratio is F-distributed
        with ``(dof, local dof)`` degrees of freedom, and the threshold is its
        :attr:`AnchorWatchParams.level` quantile.  Before any such pairing, the χ²
        quantile (the limit of many local degrees of freedom at a rate of one)."""
        if self.local_dof == 0:
            return chi2_gate(self.params.level, dof)
        rate = max(1.0, self.local_nis / self.local_dof)
        return float(dof * rate * f_dist.ppf(self.params.level, dof, self.local_dof))

    def verdict(self, step: int, gate: GateState | None) -> Verdict | None:
        """The first test that contradicts the anchor at the end of ``step`` (the last
        two only with the known-map gate's ``gate``), or ``None``."""
        nis, dof = self.innovations(step)
        if dof > 0:
            threshold = self.innovation_threshold(dof)
            if nis > threshold:
                return Verdict("innovations", nis, threshold, dof)
        if gate is None:
            return None
        n_match = len(gate.match)
        own = len(gate.unfused & gate.match)
        if n_match > 0 and 2 * own > n_match:
            return Verdict("pairings un-fused", float(own), n_match / 2, 0)
        others = len(gate.unfused - gate.match)
        still = self.params.majority * len(gate.paired - gate.unfused)
        if others >= self.params.min_unfused and others > still:
            return Verdict("known features un-fused", float(others), still, 0)
        return None
