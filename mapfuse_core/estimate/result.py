"""What every estimator returns: :class:`EstimatorResult`.

Metrics, figures, the comparison and the baselines read only this type, never a
backend's own, so a new estimator plugs in by returning one (``docs/plugins.md``).  It
lives in the core, below every estimator, so that the EKF reference and the graph
backends return it directly.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from mapfuse_core.estimate.anchor import Anchor
from mapfuse_core.estimate.decisions import AssociationDecisions
from mapfuse_core.estimate.map import MapEstimate
from mapfuse_core.estimate.matching import MatchAttempts
from mapfuse_core.estimate.track import PoseTrack
from mapfuse_core.geometry.se2 import FloatArray

__all__ = ["EstimatorResult"]


@dataclass(frozen=True, eq=False)
class EstimatorResult:
    """One estimator's run on one log: everything metrics and figures need."""

    estimator: str
    """Registered name of the estimator (``metrics.json``'s ``backend``)."""
    scenario: str
    """Scenario name of the log."""
    seed: int
    """Seed of the log."""
    fusion: bool
    """Whether the known map was fused (never on a log without one)."""
    timestamps: FloatArray
    """(N,) time of each estimated step (s); N may be below the log's step count."""
    step_time_s: FloatArray
    """(N,) wall time of each step (s); a batch solver shares its solve among the steps."""
    map: MapEstimate
    """The final map."""
    filtered: PoseTrack | None = None
    """Per-step estimate using steps ``0..k`` only (a filter's, iSAM2's), or ``None``."""
    smoothed: PoseTrack | None = None
    """Estimate of every step using the whole log (batch, iSAM2's final), or ``None``."""
    anchor: Anchor | None = None
    """The anchor, or ``None`` (no fusion, or no map match accepted)."""
    decisions: AssociationDecisions | None = None
    """Association decisions of the run (consumable by another estimator), if any."""
    association: str | None = None
    """Where the decisions came from when the estimator takes them as an input (the
    graph backends: ``"ekf"``, ``"truth"``, ``"own"``, ``"given"``); ``None`` when it
    has no such choice (reported in ``metrics.json`` only when set)."""
    upstream: EstimatorResult | None = None
    """The run whose decisions this one consumed (the EKF's for graph backends), if any."""
    matching: MatchAttempts | None = None
    """The map matchings the run made itself; ``None`` when it made none by design
    (it took its anchor from :attr:`upstream`, or matches no map)."""
    tentative_dropped: int = 0
    """New features dropped as tentative before entering the map (the EKF's
    ``tentative_min_sightings`` above 1), with their observations left unassociated."""
    details: Any = None
    """What only this estimator has, for power users: the EKF's
    :class:`~ekf_reference.result.EKFDetails`, a graph backend's
    :class:`~mapfuse_graph.results.GraphDetails` (its GTSAM graph and values among
    them); never read by the harness."""

    def __post_init__(self) -> None:
        if self.filtered is None and self.smoothed is None:
            raise ValueError(f"{self.estimator}: a result needs a filtered or a smoothed estimate")
        n = np.asarray(self.timestamps).shape
        for name in ("filtered", "smoothed"):
            track = getattr(self, name)
            if track is not None and np.asarray(track.poses).shape[0] != n[0]:
                raise ValueError(
                    f"{self.estimator}: {name} has {np.asarray(track.poses).shape[0]} poses "
                    f"for {n[0]} timestamps"
                )
        if np.asarray(self.step_time_s).shape != n:
            raise ValueError(
                f"{self.estimator}: step_time_s has shape {np.asarray(self.step_time_s).shape}, "
                f"timestamps {n}"
            )

    @property
    def estimate(self) -> Literal["filtered", "smoothed"]:
        """Which track :attr:`poses` is: the smoothed one when there is one."""
        return "smoothed" if self.smoothed is not None else "filtered"

    @property
    def track(self) -> PoseTrack:
        """The main estimate: :attr:`smoothed` when there is one, else :attr:`filtered`."""
        track = self.smoothed if self.smoothed is not None else self.filtered
        assert track is not None  # __post_init__ requires one
        return track

    @property
    def poses(self) -> FloatArray:
        """(N, 3) poses of :attr:`track`."""
        return self.track.poses

    @property
    def covs(self) -> FloatArray:
        """(N, 3, 3) covariances of :attr:`track`."""
        return self.track.covs

    @property
    def n_steps(self) -> int:
        """Number of estimated steps."""
        return int(np.asarray(self.timestamps).shape[0])
