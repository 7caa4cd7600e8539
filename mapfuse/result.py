"""What every estimator returns to the harness: :class:`EstimatorResult`.

Metrics (:mod:`mapfuse.metrics`), figures (:mod:`mapfuse.figures`), the comparison
and the baselines read only this type, never a backend's own result, so a new
estimator plugs in by returning one (``docs/plugins.md``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from mapfuse_core.estimate.decisions import AssociationDecisions
from mapfuse_core.geometry.se2 import FloatArray

__all__ = ["Anchor", "EstimatorResult", "MapEstimate", "MatchAttempts", "PoseTrack"]


@dataclass(frozen=True, eq=False)
class PoseTrack:
    """One vehicle pose estimate per step, with its covariance."""

    poses: FloatArray
    """(N, 3) pose ``x^Wglobal_R`` of each step (``Wglobal``: the vehicle at step 0)."""
    covs: FloatArray
    """(N, 3, 3) covariance of the absolute ``(x, y, θ)`` error (NaN where not computed)."""

    def __post_init__(self) -> None:
        p, c = np.asarray(self.poses), np.asarray(self.covs)
        if p.ndim != 2 or p.shape[1] != 3 or c.shape != (p.shape[0], 3, 3):
            raise ValueError(
                f"a pose track needs (N, 3) poses and (N, 3, 3) covariances, got {p.shape} "
                f"and {c.shape}"
            )


@dataclass(frozen=True, eq=False)
class MapEstimate:
    """The final map, in ``Wglobal``."""

    kinds: np.ndarray
    """(F,) int8 feature kinds (0 line, 1 circle)."""
    params: FloatArray
    """(F, 3) feature parameters (SPmap lines, circles ``(x, y, r)``)."""
    covs: FloatArray
    """(F, 3, 3) their covariances (NaN where not computed)."""
    known_ids: np.ndarray
    """(F,) known-map id each feature is tied to or merged with, −1 if none."""
    true_ids: np.ndarray
    """(F,) world id of the feature's first observation (simulation), −1 if unknown."""
    n_obs: np.ndarray
    """(F,) observations of each feature (0: a known feature never observed)."""
    tracks: np.ndarray | None = None
    """(F,) landmark (track) id of each feature as the run's decisions name it, −1 for
    a known feature only carried; ``None`` when the estimator does not say."""
    params_known: FloatArray | None = None
    """(F, 3) the features kept apart from the known map, in ``Wknown`` (NaN elsewhere);
    ``None`` when the estimator does not give them."""
    covs_known: FloatArray | None = None
    """(F, 3, 3) their covariances in ``Wknown``, the anchor's uncertainty included
    jointly (NaN where :attr:`params_known` is)."""

    def __post_init__(self) -> None:
        f = np.asarray(self.kinds).shape[0]
        for name, shape in (
            ("tracks", (f,)),
            ("params_known", (f, 3)),
            ("covs_known", (f, 3, 3)),
        ):
            v = getattr(self, name)
            if v is not None and np.asarray(v).shape != shape:
                raise ValueError(
                    f"MapEstimate.{name} must have shape {shape}, got {np.asarray(v).shape}"
                )

    @classmethod
    def empty(cls) -> MapEstimate:
        """A map without features (an estimator that keeps none)."""
        return cls(
            kinds=np.zeros(0, np.int8),
            params=np.zeros((0, 3)),
            covs=np.zeros((0, 3, 3)),
            known_ids=np.zeros(0, np.int64),
            true_ids=np.zeros(0, np.int64),
            n_obs=np.zeros(0, np.int64),
        )

    @property
    def matched_known(self) -> int:
        """Known features paired with an observed feature: entries tied to a known id
        with at least one observation.  A known feature an estimator only carries (the
        EKF inserts the whole known map when it fuses) does not count."""
        return int(np.sum((np.asarray(self.known_ids) >= 0) & (np.asarray(self.n_obs) > 0)))

    @property
    def seen_once(self) -> int:
        """Estimated features (not tied to the known map) built from a single
        observation: where spurious detections (clutter) end up."""
        return int(np.sum((np.asarray(self.known_ids) < 0) & (np.asarray(self.n_obs) == 1)))


@dataclass(frozen=True, eq=False)
class Anchor:
    """The estimated pose of the SLAM frame ``Wglobal`` in the known map."""

    x_Wknown_Wglobal: FloatArray
    """(3,) pose of ``Wglobal`` in ``Wknown`` at the end of the run."""
    cov: FloatArray
    """(3, 3) its covariance."""
    accepted_at_step: int
    """Step at which the map match was accepted (or entered the estimate)."""
    pairings: tuple[tuple[int, int], ...]
    """(true world id of the estimated feature or −1, known-map id) per pairing, the id
    being the one most of the feature's observations carry
    (:func:`~mapfuse_core.evaluation.landmark_labels`).  The EKF gives the match's
    pairings, labelled by the observations up to the match; a graph backend gives every
    tie of a landmark to a known feature, labelled by all the landmark's observations."""


@dataclass(frozen=True)
class MatchAttempts:
    """The map matchings (CCDA calls) a run made and how each ended."""

    attempts: int
    """CCDA calls."""
    reasons: Mapping[str, int]
    """Calls per outcome: a :data:`mapfuse_core.matching.ccda.REASONS` entry
    (``"accepted"``, ``"ambiguous"``, ``"search_limit"``, ...), or ``"anchor refused"``
    for an accepted match the estimator's own anchor check turned down."""

    @property
    def search_limit(self) -> int:
        """Calls that ended at CCDA's search budget (``"search_limit"``)."""
        return int(self.reasons.get("search_limit", 0))


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
    extras: Mapping[str, Any] = field(default_factory=dict)
    """Backend-specific results for power users, e.g. ``extras["ekf"]`` the
    :class:`~ekf_reference.result.EKFResult`, ``extras["graph"]`` the
    :class:`~mapfuse_graph.solvers.GraphResult`; never read by the harness."""

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
