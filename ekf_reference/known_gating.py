"""The known-map gate: a known feature that keeps failing its tests is no longer fused.

Every pairing with a known feature (an observation, or a local landmark at a step or a
join, with the feature seen through the anchor) already passes the association's
individual χ² gate (``AssociationConfig.gate_prob``).  A feature moved by less than
the gate width passes it too, and is then fused as if right.  The gate here watches
each known feature over time and takes it out of the fusion once it is found
inconsistent (``docs/change-detection.md`` says why this mechanism):

* **Running test of the accepted pairings.**  Under the hypothesis "the feature is
  where the map says", the Mahalanobis distances ``d²`` of its accepted pairings are
  χ²-distributed with ``m`` dof (2 for a line, 3 for a circle).  The sum of the last
  ``window`` of them is tested against ``χ²_{n·m}(level)`` once ``n ≥ min_pairings``.
  A feature moved by a fraction of the gate biases every pairing the same way, so the
  sum grows linearly with ``n`` and the test fires after a few scans.
* **Rejections.**  At a step where a known feature received no pairing, it is
  *rejected* (counted once per step) when, inside the association's pre-gate of it
  (:func:`~ekf_reference.association.prefilter`), an observation of its kind failed
  its χ² test with it and was not paired with a known feature, or a landmark of its
  kind was not paired with it.  Each landmark counts once against a known feature:
  its failed ties at later steps repeat the same evidence (the same observations, a
  few more each step).  Counted per step, a local landmark of a wall lying 2 cm (four
  of its σ) from the known wall would un-fuse that wall while the wall's own
  observations pass their tests (dense world 42).  An observation that passes the
  test but goes to an estimated landmark nearer still is no evidence against the
  known feature.  When, among its last ``window`` outcomes, there are at least
  ``max_rejections`` rejections and more rejections than acceptances, it is un-fused.

An un-fused feature is removed from every target list from then on: its later
observations build an ordinary landmark (and a new feature in the map); what it had
already contributed stays in the estimate.  The un-fused ids travel with the run's
:class:`~mapfuse_core.estimate.decisions.AssociationDecisions`, so a graph backend
consuming them adds no tie for those features.
"""

from __future__ import annotations

import math
import numbers
from collections import deque
from dataclasses import dataclass

from ekf_reference.association import Candidate, Query, evaluate, prefilter, weighed_d2
from ekf_reference.state import ElementKind, GaussianMap, Role
from mapfuse_core.estimate.decisions import KnownMapGating
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.matching import AssociationConfig, chi2_gate

__all__ = ["KnownGate", "KnownGatingParams", "KnownOutcomes", "known_outcomes"]

Targets = dict[ElementKind, tuple[list[int], FloatArray]]


@dataclass(frozen=True)
class KnownGatingParams:
    """Settings of the known-map gate (:class:`KnownGate`)."""

    level: float = 0.99999
    """*(choice)* χ² level of the running test of a known feature's accepted pairings.
    The test is repeated at every pairing of every known feature, and the d² of one
    feature's consecutive pairings are correlated through the vehicle's error, so a
    false alarm rate of 10⁻⁵ per test (rather than the association's 10⁻³) keeps the
    features of an unchanged map fused."""
    window: int = 20
    """*(choice)* Outcomes (accepted pairings and rejected steps) of one known feature
    the tests look back on: long enough to accumulate a small bias, short enough that
    the feature's own correction by its first pairings does not hide it."""
    min_pairings: int = 5
    """Accepted pairings needed before the running test is made (one pairing is the
    association's own gate already)."""
    max_rejections: int = 3
    """Rejected steps within the window (and more than the acceptances) that un-fuse a
    known feature."""

    def __post_init__(self) -> None:
        if not (isinstance(self.level, numbers.Real) and 0.0 < self.level < 1.0):
            raise ValueError(f"known gating level must be in (0, 1), got {self.level!r}")
        for name in ("window", "min_pairings", "max_rejections"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < 1:
                raise ValueError(f"known gating {name} must be an int >= 1, got {v!r}")


@dataclass(frozen=True, eq=False)
class KnownOutcomes:
    """What one association did with the known features among its targets."""

    accepted: list[tuple[int, Candidate]]
    """``(known id, pairing)`` of every pairing with a known feature, in query order."""
    refused: list[tuple[int, int]]
    """``(known id, source)`` of every refused pairing: the known feature lay inside the
    pre-gate of a query of its kind that was not paired with a known feature and, for
    an observation, failed its χ² test with it.  ``source`` is the landmark's track for
    a map element's query, −1 for an observation; observations' refusals come first,
    then the landmarks', each in query order."""


def known_outcomes(
    state: GaussianMap,
    queries: list[Query],
    chosen: list[Candidate | None],
    targets: Targets,
    association: AssociationConfig,
) -> KnownOutcomes:
    """The pairings with known features of one association, and the known features it
    passed by (:class:`KnownOutcomes`), from ``state`` before the pairings are applied."""
    els = state.elements
    accepted = [
        (els[c.target].true_id, c)
        for c in chosen
        if c is not None and els[c.target].role == Role.KNOWN
    ]
    refused: list[tuple[int, int]] = []
    for q, c in zip(queries, chosen, strict=True):
        if c is not None and els[c.target].role == Role.KNOWN:
            continue
        idx, preds = targets[q.kind]
        known_rows = [r for r, t in enumerate(idx) if els[t].role == Role.KNOWN]
        if not known_rows:
            continue
        known_t = [idx[r] for r in known_rows]
        source = -1 if q.element < 0 else els[q.element].track
        gate = chi2_gate(association.gate_prob, 2 if q.kind == ElementKind.LINE else 3)
        for t in prefilter(q, preds[known_rows], known_t, state, association):
            if source < 0 and evaluate(state, q, t).d2 <= gate:
                continue  # compatible: no evidence against the known feature
            refused.append((els[t].true_id, source))
    refused.sort(key=lambda r: r[1] >= 0)  # stable: observations first
    return KnownOutcomes(accepted, refused)


class KnownGate:
    """Per-known-feature bookkeeping of one EKF run (see the module docstring)."""

    def __init__(self, params: KnownGatingParams, association: AssociationConfig) -> None:
        self.params = params
        self.association = association
        self.history: dict[int, deque[float]] = {}
        """Known id → last outcomes: an accepted pairing's d², or NaN for a rejection."""
        self.rejected: dict[int, int] = {}
        self.accepted: dict[int, int] = {}
        self.unfused: dict[int, int] = {}
        self.anchor_known: list[int] = []
        self._dofs: dict[int, int] = {}
        self._step = -1
        self._touched: set[int] = set()
        self._rejected_now: set[int] = set()
        self._landmarks_refused: set[tuple[int, int]] = set()
        """``(known id, landmark track)`` already counted as a rejection."""

    # ------------------------------------------------------------------ targets

    def filter(self, state: GaussianMap, targets: Targets) -> Targets:
        """``targets`` without the known features already un-fused."""
        if not self.unfused:
            return targets
        out: Targets = {}
        for kind, (idx, preds) in targets.items():
            keep = [
                r
                for r, t in enumerate(idx)
                if not (
                    state.elements[t].role == Role.KNOWN
                    and state.elements[t].true_id in self.unfused
                )
            ]
            out[kind] = ([idx[r] for r in keep], preds[keep])
        return out

    # ------------------------------------------------------------------ outcomes

    def record(
        self,
        step: int,
        state: GaussianMap,
        queries: list[Query],
        chosen: list[Candidate | None],
        targets: Targets,
    ) -> None:
        """Record the outcome of one association against ``targets`` (already filtered)
        at ``step``, before its pairings are applied, and un-fuse what fails."""
        if step != self._step:
            self._step, self._touched, self._rejected_now = step, set(), set()
        out = known_outcomes(state, queries, chosen, targets, self.association)
        for kid, c in out.accepted:
            self._dofs[kid] = c.residual.size
            self._touched.add(kid)
            # The running sum spans consecutive scans: their shared errors count once.
            self._push(kid, weighed_d2(state, c))
            self.accepted[kid] = self.accepted.get(kid, 0) + 1
        for kid, source in out.refused:
            if kid in self._touched or kid in self._rejected_now:
                continue
            if source >= 0:
                if (kid, source) in self._landmarks_refused:
                    continue
                self._landmarks_refused.add((kid, source))
            self._rejected_now.add(kid)
            self.rejected[kid] = self.rejected.get(kid, 0) + 1
            self._push(kid, math.nan)
        for kid in self._touched | self._rejected_now:
            if kid not in self.unfused and self._fails(kid):
                self.unfused[kid] = step

    def _push(self, kid: int, value: float) -> None:
        h = self.history.get(kid)
        if h is None:
            h = self.history[kid] = deque(maxlen=self.params.window)
        h.append(value)

    def _fails(self, kid: int) -> bool:
        h = self.history.get(kid, ())
        d2 = [v for v in h if not math.isnan(v)]
        n_rej = len(h) - len(d2)
        p = self.params
        if n_rej >= p.max_rejections and n_rej > len(d2):
            return True
        if len(d2) < p.min_pairings:
            return False
        return sum(d2) > chi2_gate(p.level, len(d2) * self._dofs[kid])

    # ------------------------------------------------------------------ report

    def report(self) -> KnownMapGating:
        """The frozen summary handed to the run's decisions."""
        bad = sum(1 for k in self.anchor_known if k in self.unfused)
        return KnownMapGating(
            level=self.params.level,
            rejected=dict(self.rejected),
            accepted=dict(self.accepted),
            unfused=dict(self.unfused),
            anchor_pairings_unfused=bad,
            anchor_pairings=len(self.anchor_known),
        )
