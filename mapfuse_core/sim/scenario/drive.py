"""Driving a scenario: the true controls, the simulated motion and the check that the
features are seen along it."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.sensor import LaserParams
from mapfuse_core.sim.laser import cast_rays
from mapfuse_core.sim.scenario.types import ControlSegment, IntArray, Scenario, ScenarioError
from mapfuse_core.sim.vehicle import MotionResult, simulate_controls, simulate_motion
from mapfuse_core.sim.world import World


def control_table(controls: Sequence[ControlSegment]) -> FloatArray:
    """(Σ n, 2) true controls ``(v, φ)`` step by step: each segment repeated ``steps`` times."""
    if not controls:
        return np.zeros((0, 2))
    vphi = np.array([(c.speed_mps, c.steer_rad) for c in controls], dtype=np.float64)
    return np.repeat(vphi, [c.steps for c in controls], axis=0)


def simulate_drive(scenario: Scenario, rng: np.random.Generator) -> MotionResult:
    """The scenario's true drive and odometry over ``scenario.steps`` poses.

    Pure pursuit through :attr:`Scenario.waypoints`
    (:func:`~mapfuse_core.sim.vehicle.simulate_motion`), or the first ``steps − 1`` rows of
    the :attr:`Scenario.controls` table (:func:`~mapfuse_core.sim.vehicle.simulate_controls`);
    the noise is drawn from ``rng`` the same way for both.
    """
    if not scenario.controls:
        return simulate_motion(
            scenario.start, scenario.waypoints, scenario.steps, scenario.vehicle, rng
        )
    table = control_table(scenario.controls)
    if not 2 <= scenario.steps <= table.shape[0] + 1:
        raise ValueError(
            f"steps must be in [2, {table.shape[0] + 1}] for these controls, got {scenario.steps}"
        )
    return simulate_controls(scenario.start, table[: scenario.steps - 1], scenario.vehicle, rng)


# --------------------------------------------------------------------------- visibility


def features_in_view(world: World, poses: FloatArray, laser: LaserParams) -> IntArray:
    """Number of distinct features hit by the noise-free beams of ``laser`` from each pose.

    ``poses`` is (P, 3), the sensor at each pose; returns (P,) int64 counts.
    """
    P = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    bearings = laser.bearings()
    out = np.zeros(P.shape[0], dtype=np.int64)
    for k in range(P.shape[0]):
        _, ids = cast_rays(world, P[k], P[k, 2] + bearings, laser.max_range_m)
        out[k] = np.unique(ids[ids >= 0]).size
    return out


def check_visibility(scenario: Scenario, motion: MotionResult, stride: int = 8) -> IntArray:
    """Check that the drive sees the world; return the feature counts at the sampled steps.

    Every ``stride``-th true pose (and the last) is checked with noise-free rays.
    Raises :class:`ScenarioError` (key ``trajectory``) when no sampled pose sees any
    feature: such a scenario cannot exercise anything.
    """
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    n = motion.true_poses.shape[0]
    steps = np.unique(np.append(np.arange(0, n, stride), n - 1))
    counts = features_in_view(scenario.world, motion.true_poses[steps], scenario.laser)
    if counts.max(initial=0) == 0:
        raise ScenarioError(
            scenario.source,
            "trajectory",
            f"no feature is within {scenario.laser.max_range_m} m in the field of view at any "
            f"of {steps.size} sampled poses: the trajectory never sees the world",
        )
    return counts
