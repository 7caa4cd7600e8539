"""The scenario data model: the validated scenario, its known-map specification and
the known map drawn from it, and the error every invalid file raises."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.sensor import LaserParams
from mapfuse_core.sim.vehicle import VehicleParams
from mapfuse_core.sim.world import CircleObstacle, WallSegment, World

IntArray = NDArray[np.int64]


class ScenarioError(ValueError):
    """A scenario file is invalid: names the file, the dotted key and the reason."""

    def __init__(self, file: str, key: str, reason: str) -> None:
        self.file = file
        """The scenario file (or the name that was looked up)."""
        self.key = key
        """Dotted path of the offending key, e.g. ``world.circles[3].radius`` ("" for the file)."""
        self.reason = reason
        """What is wrong, in words."""
        where = f"{file}: {key}" if key else file
        super().__init__(f"{where}: {reason}")


# --------------------------------------------------------------------------- data model


@dataclass(frozen=True)
class FeatureMove:
    """A deliberate error of the known map: it holds feature ``id`` at a displaced place.

    Offsets are in the world frame; a line is rotated about its midpoint.
    """

    id: int
    """Feature id (must be held by the known map)."""
    dx: float
    """Displacement of the line midpoint or circle centre along x (m)."""
    dy: float
    """Displacement along y (m)."""
    dtheta: float
    """Rotation of a line about its midpoint (rad); 0 for circles."""
    dr: float
    """Change of a circle's radius (m); 0 for lines."""


@dataclass(frozen=True)
class ControlSegment:
    """A stretch of the drive at constant true controls (a ``trajectory.controls`` row)."""

    speed_mps: float
    """Speed ``v`` of the rear axle (m/s); negative reverses, 0 stands still."""
    steer_rad: float
    """Steering angle ``φ`` (rad), ``|φ| ≤ VehicleParams.max_steer_rad``; positive turns left."""
    steps: int
    """Number of steps ``n ≥ 1`` driven with these controls."""


# eq=False: the fields hold arrays, whose == is elementwise; compare by identity instead.
@dataclass(frozen=True, eq=False)
class KnownMapSpec:
    """What the a-priori known map holds and how uncertain it is (paper eq. 11).

    The map is block-diagonal: every feature has an independent diagonal covariance,
    ``diag(σxy², σxy², σθ²)`` for lines and ``diag(σxy², σxy², σr²)`` for circles.
    """

    world_ids: tuple[int, ...]
    """World feature ids the map holds (after ``ids = "all"`` and ``added`` are applied)."""
    sigma_xy_m: float
    """Standard deviation of feature coordinates (m): line midpoints and circle centres."""
    sigma_r_m: float
    """Standard deviation of circle radii (m)."""
    sigma_theta_rad: float
    """Standard deviation of line angles (rad)."""
    frame: FloatArray
    """``x^W_Wknown``: pose of the map's frame in the world (usually zero)."""
    moved: tuple[FeatureMove, ...]
    """Features the map holds at a displaced place."""
    removed: tuple[WallSegment | CircleObstacle, ...]
    """Features the map holds that the world no longer has (ids not in the world)."""
    added: tuple[int, ...]
    """World ids that are new since the map was made: never in the map."""

    @property
    def ids(self) -> tuple[int, ...]:
        """All ids the map holds, sorted: held world features and removed ones."""
        return tuple(sorted((*self.world_ids, *(f.id for f in self.removed))))


# eq=False: the fields hold arrays, whose == is elementwise; compare by identity instead.
@dataclass(frozen=True, eq=False)
class Scenario:
    """A validated scenario.  Arrays are read-only."""

    name: str
    """Scenario name (``[scenario].name``, else the file stem)."""
    description: str
    """Free text from the file."""
    source: str
    """Path of the TOML file it was loaded from."""
    seed: int
    """Default random seed of the simulation (≥ 0)."""
    world: World
    """The ground-truth world."""
    start: FloatArray
    """(3,) true start pose ``(x, y, θ)`` in ``W``."""
    steps: int
    """Number of poses to simulate (≥ 2), the start included; with :attr:`controls`, at
    most one more than the steps they drive (fewer shortens the drive)."""
    waypoints: FloatArray
    """(K, 2) path the pure-pursuit driver follows, K ≥ 2; (0, 2) when the drive is given
    by :attr:`controls` instead."""
    controls: tuple[ControlSegment, ...]
    """The true controls the car is driven with, stretch by stretch; empty when it
    follows :attr:`waypoints`."""
    vehicle: VehicleParams
    """Vehicle model, odometry noise and driver."""
    laser: LaserParams
    """Laser scanner geometry and noise."""
    known_map: KnownMapSpec
    """What the a-priori map holds."""


# eq=False: the fields hold arrays, whose == is elementwise; compare by identity instead.
@dataclass(frozen=True, eq=False)
class KnownMap:
    """A realisation of the known map: one noisy draw from its stated σ.

    ``true_params`` are the features as the map *should* hold them (the world's,
    or the removed ones, with the deliberate ``moved`` changes applied), expressed in
    the map frame.  ``params = true_params + n`` with ``n ~ N(0, covs)`` drawn once
    per map, so the map's covariance is honest: the estimator is told the σ the error
    really has.  Lines are SPmap frames at the wall midpoint, x axis from ``p1`` to
    ``p2``; circles are ``(x, y, r)``.  A noisy radius ≤ 0 (possible for thin poles
    with σr comparable to r) is redrawn, which truncates that one variable's tail.
    """

    ids: IntArray
    """(M,) int64 feature ids, sorted."""
    kinds: NDArray[np.int8]
    """(M,) int8 :class:`FeatureKind` codes."""
    params: FloatArray
    """(M, 3) noisy parameters in the map frame."""
    covs: FloatArray
    """(M, 3, 3) diagonal covariances of :attr:`params` in the map frame."""
    true_params: FloatArray
    """(M, 3) noise-free, change-applied parameters in the map frame."""
    frame: FloatArray
    """(3,) ``x^W_Wknown`` the map is expressed in."""

    def __len__(self) -> int:
        return int(self.ids.shape[0])


# --------------------------------------------------------------------------- loading
