"""The planar laser scanner as data: its geometry and noise (:class:`LaserParams`) and
one scan (:class:`Scan`).

Bottom-layer types: the simulator casts rays into a :class:`Scan`, extraction reads
one, real datasets build one from a log's ranges.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mapfuse_core.geometry.se2 import FloatArray

__all__ = ["MAX_ANGLE_SIGMA", "MAX_BEAMS", "LaserParams", "Scan"]

MAX_ANGLE_SIGMA = math.pi
"""Largest standard deviation of an angle (rad): beyond π the angle is as good as
uniform, which no linearised filter can represent (its innovation covariances stop
being positive definite)."""

MAX_BEAMS = 10_000
"""Most beams of a simulated laser (real planar scanners give at most a few thousand):
a scan's ray casting then holds a few beams × features arrays of 80 kB per feature."""


@dataclass(frozen=True)
class LaserParams:
    """Geometry and noise of a planar range–bearing laser scanner."""

    fov_rad: float = math.pi
    """Field of view (rad), centred on the sensor x axis; in ``(0, 2π]``."""
    max_range_m: float = 80.0
    """Maximum range (m); farther surfaces give no return."""
    n_beams: int = 361
    """Number of beams, evenly spaced over the field of view (361 → 0.5° spacing);
    2 … :data:`~mapfuse_core.sim.limits.MAX_BEAMS`."""
    sigma_range_m: float = 0.05
    """Standard deviation σρ of the range noise (m), ≥ 0."""
    sigma_bearing_rad: float = math.pi / 720
    """Standard deviation σβ of the bearing (pointing) noise (rad), in ``[0, π]``."""

    def __post_init__(self) -> None:
        for name in ("fov_rad", "max_range_m", "sigma_range_m", "sigma_bearing_rad"):
            value = getattr(self, name)
            if not isinstance(value, int | float) or not math.isfinite(value):
                raise ValueError(f"LaserParams.{name} must be a finite number, got {value!r}")
        if not 0.0 < self.fov_rad <= 2.0 * math.pi:
            raise ValueError(f"LaserParams.fov_rad must be in (0, 2π], got {self.fov_rad}")
        if self.max_range_m <= 0.0:
            raise ValueError(f"LaserParams.max_range_m must be > 0, got {self.max_range_m}")
        if isinstance(self.n_beams, bool) or not isinstance(self.n_beams, int | np.integer):
            raise ValueError(f"LaserParams.n_beams must be an integer, got {self.n_beams!r}")
        if self.n_beams < 2:
            raise ValueError(f"LaserParams.n_beams must be >= 2, got {self.n_beams}")
        if self.n_beams > MAX_BEAMS:
            raise ValueError(
                f"LaserParams.n_beams must be <= {MAX_BEAMS:,} (the documented maximum), "
                f"got {self.n_beams}"
            )
        if self.sigma_range_m < 0.0:
            raise ValueError(f"LaserParams.sigma_range_m must be >= 0, got {self.sigma_range_m}")
        if self.sigma_bearing_rad < 0.0:
            raise ValueError(
                f"LaserParams.sigma_bearing_rad must be >= 0, got {self.sigma_bearing_rad}"
            )
        if self.sigma_bearing_rad > MAX_ANGLE_SIGMA:
            raise ValueError(
                f"LaserParams.sigma_bearing_rad must be <= π, got {self.sigma_bearing_rad}"
            )

    @property
    def beam_spacing_rad(self) -> float:
        """Angle between consecutive beams (rad)."""
        return self.fov_rad / (self.n_beams - 1)

    def bearings(self) -> FloatArray:
        """(n_beams,) nominal bearings from ``−fov/2`` to ``+fov/2`` inclusive.

        With ``fov = 2π`` the first and last beams point the same way.
        """
        half = 0.5 * self.fov_rad
        return np.linspace(-half, half, int(self.n_beams), dtype=np.float64)


@dataclass(frozen=True)
class Scan:
    """One laser scan in the sensor frame."""

    bearings: FloatArray
    """(n,) nominal beam bearings in the sensor frame (rad), increasing."""
    ranges: FloatArray
    """(n,) measured ranges (m); ``np.inf`` where there is no return."""
    hit_ids: np.ndarray
    """(n,) int64 id of the world feature each beam hit, −1 for none (simulation truth)."""

    def __post_init__(self) -> None:
        b = np.asarray(self.bearings, dtype=np.float64)
        r = np.asarray(self.ranges, dtype=np.float64)
        h = np.asarray(self.hit_ids)
        if b.ndim != 1:
            raise ValueError(f"Scan.bearings must be 1-D, got shape {b.shape}")
        if r.shape != b.shape or h.shape != b.shape:
            raise ValueError(
                "Scan.bearings, ranges and hit_ids must have the same shape, got "
                f"{b.shape}, {r.shape}, {h.shape}"
            )
        if not np.all(np.isfinite(b)):
            raise ValueError("Scan.bearings has a non-finite entry")
        if np.any(np.isnan(r)):
            raise ValueError("Scan.ranges has a NaN entry (use np.inf for no return)")
        if np.any(r <= 0.0):
            raise ValueError("Scan.ranges must be > 0 (use np.inf for no return)")
        if h.size and not np.issubdtype(h.dtype, np.integer):
            raise ValueError(f"Scan.hit_ids must be integers, got dtype {h.dtype}")
        object.__setattr__(self, "bearings", b)
        object.__setattr__(self, "ranges", r)
        object.__setattr__(self, "hit_ids", h.astype(np.int64))

    def valid(self) -> np.ndarray:
        """(n,) bool mask of beams with a return."""
        return np.asarray(np.isfinite(self.ranges))

    def points(self) -> FloatArray:
        """(k, 2) sensor-frame ``(x, y)`` of the valid returns, in beam order."""
        m = self.valid()
        r, b = self.ranges[m], self.bearings[m]
        return np.column_stack((r * np.cos(b), r * np.sin(b)))
