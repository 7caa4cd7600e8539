"""The final map an estimator returns: :class:`MapEstimate`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapfuse_core.geometry.se2 import FloatArray

__all__ = ["MapEstimate"]


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
