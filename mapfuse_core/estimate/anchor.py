"""Where the SLAM frame lies in the known map: :class:`Anchor`."""

from __future__ import annotations

from dataclasses import dataclass

from mapfuse_core.geometry.se2 import FloatArray

__all__ = ["Anchor"]


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
    source: str | None = None
    """Where the anchor's value came from when the estimator can take it from elsewhere
    (a graph backend: ``"given"`` the anchor of the decisions it was given, ``"fit"`` a
    fit to truth pairings, ``"ccda"`` its own match); ``None`` when it always makes its
    own."""
