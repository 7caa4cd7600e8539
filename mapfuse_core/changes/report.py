"""The outcome of change detection: :class:`FeatureChange`, :class:`NewFeature`,
:class:`ChangeReport`."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import TYPE_CHECKING, Any

import numpy as np

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray

if TYPE_CHECKING:
    from mapfuse_core.changes.consistency import RunConsistency

__all__ = ["ChangeReport", "ChangeStatus", "FeatureChange", "NewFeature"]


class ChangeStatus(StrEnum):
    """Class of a known feature after a run."""

    CONFIRMED = "confirmed"
    """Observed, and the observations agree with the known map (χ² test passed)."""
    MOVED = "moved"
    """Observed, and the observations disagree with the known map."""
    MISSING = "missing"
    """Predicted in view for at least ``K`` scans and never observed."""
    UNOBSERVED = "unobserved"
    """Never observed, and not predicted in view long enough to call it missing."""
    INCONCLUSIVE = "inconclusive"
    """Its tests call it moved or missing, but the run is not consistent enough to be
    trusted with that (:mod:`mapfuse_core.changes.consistency`)."""


@dataclass(frozen=True, eq=False)
class FeatureChange:
    """The class of one known feature, with the evidence behind it."""

    known_id: int
    """Known-map id."""
    kind: FeatureKind
    """Feature kind."""
    status: ChangeStatus
    """Its class."""
    displacement: FloatArray
    """(3,) estimated ``(dx, dy, dθ)`` (line: lateral displacement of its reference point
    and turn) or ``(dx, dy, dr)`` (circle), in ``Wknown``; NaN when not observed."""
    residual: FloatArray
    """The tested residual (line: lateral offset (m), angle (rad); circle: dx, dy, dr);
    empty when not observed."""
    residual_cov: FloatArray
    """Its covariance (evidence plus the known feature's), the test's ``S``."""
    statistic: float
    """χ² statistic ``rᵀS⁻¹r`` (NaN when not observed)."""
    dof: int
    """Degrees of freedom of the test."""
    threshold: float
    """χ² threshold at the stated level."""
    n_obs: int
    """Observations of the landmark tested against it (0 if none)."""
    scans_in_view: int
    """Scans in which the known map predicts the feature in view."""
    associated: bool
    """Whether the estimator associated a landmark with it (else the landmark, if any,
    was found near it afterwards: a move beyond the association gate)."""
    landmark: int
    """Landmark (track) id of the observations tested, −1 if none."""
    scans_seen_empty: int = 0
    """Scans whose raw beams went through the feature's surveyed place (circles of a
    log with raw scans; :mod:`mapfuse_core.changes.freespace`), 0 otherwise."""
    spread_factor: float = 1.0
    """Factor the evidence's measurement covariance was scaled by because its
    observations disagree beyond their noise (1: they agree; 1 when not observed)."""
    scans_seen_occupied: int = 0
    """Scans whose raw beams found a circle still standing at its surveyed place (read
    for circles without an associated landmark, in a log with raw scans), 0 otherwise."""

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "known_id": self.known_id,
            "kind": self.kind.name.lower(),
            "status": self.status.value,
            "displacement": [_num(v) for v in self.displacement],
            "residual": [_num(v) for v in self.residual],
            "residual_cov": [[_num(v) for v in row] for row in self.residual_cov],
            "statistic": _num(self.statistic),
            "dof": self.dof,
            "threshold": _num(self.threshold),
            "n_obs": self.n_obs,
            "scans_in_view": self.scans_in_view,
            "associated": self.associated,
            "landmark": self.landmark,
            "scans_seen_empty": self.scans_seen_empty,
            "scans_seen_occupied": self.scans_seen_occupied,
            "spread_factor": _num(self.spread_factor),
        }


@dataclass(frozen=True, eq=False)
class NewFeature:
    """A mapped landmark that no known feature accounts for."""

    landmark: int
    """Landmark (track) id."""
    kind: FeatureKind
    """Feature kind."""
    params: FloatArray
    """(3,) its observation-only estimate in ``Wknown``."""
    cov: FloatArray
    """(3, 3) its covariance."""
    n_obs: int
    """Observations."""
    true_id: int
    """Most frequent world id of its observations (simulation), −1 if unknown."""

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "landmark": self.landmark,
            "kind": self.kind.name.lower(),
            "params": [_num(v) for v in self.params],
            "n_obs": self.n_obs,
            "true_id": self.true_id,
        }


@dataclass(frozen=True, eq=False)
class ChangeReport:
    """Every known feature's class and the new features of one run."""

    known: tuple[FeatureChange, ...]
    """One entry per known feature, in known-map order."""
    new: tuple[NewFeature, ...]
    """Mapped landmarks not in the known map."""
    duplicates: int
    """Unassociated landmarks consistent with a known feature already observed (a
    landmark the estimator did not merge): neither new nor a change."""
    level: float
    """Probability of the χ² tests."""
    x_Wknown_Wglobal: FloatArray
    """(3,) the anchor the evidence was put in ``Wknown`` with."""
    relocalized_steps: int = 0
    """Steps before the run's map match whose pose was re-placed on the known map
    (:mod:`mapfuse_core.changes.relocalize`)."""
    bridged_steps: int = 0
    """Steps before the match placed from the nearest re-placed step through the
    logged odometry."""
    relocalize_refused: int = 0
    """Steps before the match with three or more merged features whose re-placement was
    refused; they are bridged like the steps without features, or enter as filtered."""
    consistency: RunConsistency | None = None
    """The run's consistency verdict (:mod:`mapfuse_core.changes.consistency`), or
    ``None`` when it was not judged."""
    withheld_new: int = 0
    """Landmarks the tests found new but that are not reported, the run not being
    trusted (0 on a trusted run)."""

    @property
    def conclusive(self) -> bool:
        """Whether the run was trusted (or not judged): its changes are reported."""
        return self.consistency is None or self.consistency.trusted

    def of(self, status: ChangeStatus) -> list[FeatureChange]:
        """Known features of one class."""
        return [c for c in self.known if c.status == status]

    def counts(self) -> dict[str, int]:
        """Number of known features per class, and of new features."""
        out = {s.value: len(self.of(s)) for s in ChangeStatus}
        out["new"] = len(self.new)
        out["duplicates"] = self.duplicates
        return out

    def status_of(self, known_id: int) -> ChangeStatus:
        """Class of known feature ``known_id``."""
        for c in self.known:
            if c.known_id == known_id:
                return c.status
        raise KeyError(f"known feature {known_id} is not in the report")

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready form (``changes.json``)."""
        return {
            "verdict": "conclusive" if self.conclusive else "inconclusive",
            "consistency": None if self.consistency is None else self.consistency.as_dict(),
            "withheld_new": self.withheld_new,
            "level": self.level,
            "x_Wknown_Wglobal": [float(v) for v in self.x_Wknown_Wglobal],
            "counts": self.counts(),
            "relocalized_steps": self.relocalized_steps,
            "bridged_steps": self.bridged_steps,
            "relocalize_refused": self.relocalize_refused,
            "known": [c.as_dict() for c in self.known],
            "new": [n.as_dict() for n in self.new],
        }


def _num(v: float) -> float | None:
    f = float(v)
    return f if np.isfinite(f) else None
