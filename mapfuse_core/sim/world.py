"""Ground-truth worlds: wall segments (line features) and circles (trees, poles).

Coordinates are metres in the world frame ``W`` (= ``Wknown`` in simulation).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray

__all__ = ["CircleObstacle", "WallSegment", "World"]


@dataclass(frozen=True)
class WallSegment:
    """A straight wall between two endpoints; observed as an SPmap line."""

    id: int
    """Unique feature id within the world (shared with circles)."""
    p1: tuple[float, float]
    """First endpoint ``(x, y)`` in metres."""
    p2: tuple[float, float]
    """Second endpoint ``(x, y)`` in metres."""

    @property
    def length(self) -> float:
        """Segment length in metres."""
        return math.hypot(self.p2[0] - self.p1[0], self.p2[1] - self.p1[1])

    def spmap(self) -> FloatArray:
        """SPmap frame: origin at the midpoint, x axis from ``p1`` towards ``p2``."""
        return np.array(
            [
                0.5 * (self.p1[0] + self.p2[0]),
                0.5 * (self.p1[1] + self.p2[1]),
                math.atan2(self.p2[1] - self.p1[1], self.p2[0] - self.p1[0]),
            ]
        )


@dataclass(frozen=True)
class CircleObstacle:
    """A circular obstacle (tree trunk, pole); observed as a circle feature."""

    id: int
    """Unique feature id within the world (shared with segments)."""
    centre: tuple[float, float]
    """Centre ``(x, y)`` in metres."""
    radius: float
    """Radius in metres (> 0)."""

    def params(self) -> FloatArray:
        """Circle feature parameters ``(x, y, r)``."""
        return np.array([self.centre[0], self.centre[1], self.radius])


@dataclass(frozen=True)
class World:
    """A 2D world of walls and circles, with vectorised views for ray casting."""

    segments: tuple[WallSegment, ...]
    """Wall segments."""
    circles: tuple[CircleObstacle, ...]
    """Circular obstacles."""
    seg_p1: FloatArray = field(init=False, repr=False, compare=False)
    """(S, 2) first endpoints, in the order of :attr:`segments`."""
    seg_p2: FloatArray = field(init=False, repr=False, compare=False)
    """(S, 2) second endpoints."""
    seg_ids: np.ndarray = field(init=False, repr=False, compare=False)
    """(S,) int64 ids of the segments."""
    circ_c: FloatArray = field(init=False, repr=False, compare=False)
    """(C, 2) circle centres."""
    circ_r: FloatArray = field(init=False, repr=False, compare=False)
    """(C,) circle radii."""
    circ_ids: np.ndarray = field(init=False, repr=False, compare=False)
    """(C,) int64 ids of the circles."""

    def __post_init__(self) -> None:
        ids = [s.id for s in self.segments] + [c.id for c in self.circles]
        if len(ids) == 0:
            raise ValueError("world is empty: it needs at least one segment or circle")
        dup = sorted({i for i in ids if ids.count(i) > 1})
        if dup:
            raise ValueError(f"world has duplicate feature ids: {dup}")
        for s in self.segments:
            if not all(math.isfinite(v) for v in (*s.p1, *s.p2)):
                raise ValueError(f"segment {s.id} has a non-finite endpoint")
            if s.length <= 1e-6:
                raise ValueError(f"segment {s.id} has zero length")
        for c in self.circles:
            if not all(math.isfinite(v) for v in (*c.centre, c.radius)):
                raise ValueError(f"circle {c.id} has a non-finite centre or radius")
            if c.radius <= 0.0:
                raise ValueError(f"circle {c.id} has radius {c.radius} <= 0")
        set_ = object.__setattr__
        set_(self, "seg_p1", np.array([s.p1 for s in self.segments], dtype=float).reshape(-1, 2))
        set_(self, "seg_p2", np.array([s.p2 for s in self.segments], dtype=float).reshape(-1, 2))
        set_(self, "seg_ids", np.array([s.id for s in self.segments], dtype=np.int64))
        set_(self, "circ_c", np.array([c.centre for c in self.circles], dtype=float).reshape(-1, 2))
        set_(self, "circ_r", np.array([c.radius for c in self.circles], dtype=float))
        set_(self, "circ_ids", np.array([c.id for c in self.circles], dtype=np.int64))

    @property
    def ids(self) -> list[int]:
        """All feature ids, segments first."""
        return [s.id for s in self.segments] + [c.id for c in self.circles]

    def feature(self, fid: int) -> tuple[FeatureKind, FloatArray]:
        """Kind and parameters (SPmap line or circle) of the feature with id ``fid``."""
        for s in self.segments:
            if s.id == fid:
                return FeatureKind.LINE, s.spmap()
        for c in self.circles:
            if c.id == fid:
                return FeatureKind.CIRCLE, c.params()
        raise KeyError(f"no feature with id {fid} in the world")
