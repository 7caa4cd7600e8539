"""A set of map features as parallel arrays: the known map, or the true world."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapfuse_core.geometry.se2 import FloatArray

__all__ = ["KnownMapArrays"]

IntArray = np.ndarray


@dataclass(frozen=True)
class KnownMapArrays:
    """A set of map features as parallel arrays (the known map, or the true world)."""

    ids: IntArray
    """(M,) int64 feature ids."""
    kinds: IntArray
    """(M,) int8 :class:`FeatureKind` codes."""
    params: FloatArray
    """(M, 3) SPmap line ``(x, y, θ)`` or circle ``(x, y, r)`` in the map frame."""
    covs: FloatArray
    """(M, 3, 3) covariances of :attr:`params` (zeros for the true world)."""
    extents: FloatArray | None = None
    """(M, 2) along-line interval of each line's wall relative to its reference point
    (NaN for circles); ``None`` when unknown.  Lets association tell collinear walls apart."""

    def __len__(self) -> int:
        return int(self.ids.shape[0])
