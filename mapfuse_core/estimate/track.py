"""A vehicle trajectory estimate with its per-step covariance: :class:`PoseTrack`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapfuse_core.geometry.se2 import FloatArray

__all__ = ["PoseTrack"]


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
