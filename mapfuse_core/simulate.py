"""Simulation pipeline: scenario → motion → laser scans → extracted features → log.

Random streams are split from one :class:`numpy.random.SeedSequence` per purpose
(motion, laser, known map), so changing e.g. the laser parameters does not change
the trajectory noise of the same seed.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mapfuse_core.extraction import ExtractionParams, extract_features
from mapfuse_core.features import FeatureKind
from mapfuse_core.laser import Scan, simulate_scan
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog
from mapfuse_core.scenario import Scenario, build_known_map, check_visibility
from mapfuse_core.se2 import FloatArray
from mapfuse_core.vehicle import MotionResult, simulate_motion
from mapfuse_core.world import WallSegment, World

__all__ = ["SimulationResult", "simulate", "world_arrays"]


@dataclass(frozen=True)
class SimulationResult:
    """A simulated run: the log both backends consume, plus the raw scans for plots."""

    log: MeasurementLog
    """The measurement log."""
    motion: MotionResult
    """True controls and poses, and the odometry (also in :attr:`log`)."""
    scans: tuple[Scan, ...]
    """The raw scan of every step (sensor frame)."""


def world_arrays(world: World) -> KnownMapArrays:
    """The true world as map arrays (zero covariances), lines as SPmap at their midpoints."""
    ids, kinds, params = [], [], []
    for s in world.segments:
        ids.append(s.id)
        kinds.append(int(FeatureKind.LINE))
        params.append(s.spmap())
    for c in world.circles:
        ids.append(c.id)
        kinds.append(int(FeatureKind.CIRCLE))
        params.append(c.params())
    n = len(ids)
    extents = np.full((n, 2), np.nan)
    for r, s in enumerate(world.segments):
        extents[r] = (-0.5 * s.length, 0.5 * s.length)
    return KnownMapArrays(
        ids=np.array(ids, dtype=np.int64),
        kinds=np.array(kinds, dtype=np.int8),
        params=np.array(params, dtype=float).reshape(n, 3),
        covs=np.zeros((n, 3, 3)),
        extents=extents,
    )


def _known_extents(scenario: Scenario, ids: np.ndarray, kinds: np.ndarray) -> FloatArray:
    """Along-line extents of the known walls: ±half the surveyed wall length."""
    walls = {s.id: s for s in scenario.world.segments}
    walls.update({f.id: f for f in scenario.known_map.removed if isinstance(f, WallSegment)})
    out = np.full((ids.shape[0], 2), np.nan)
    for r, (fid, kind) in enumerate(zip(ids, kinds, strict=True)):
        if int(kind) == int(FeatureKind.LINE):
            half = 0.5 * walls[int(fid)].length
            out[r] = (-half, half)
    return out


def simulate(
    scenario: Scenario,
    seed: int | None = None,
    extraction: ExtractionParams | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> SimulationResult:
    """Simulate ``scenario`` with ``seed`` (default: the scenario's own seed).

    ``progress(k, n)`` is called after each step when given.
    """
    seed = scenario.seed if seed is None else int(seed)
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    motion_ss, laser_ss, map_ss = np.random.SeedSequence(seed).spawn(3)
    motion = simulate_motion(
        scenario.start,
        scenario.waypoints,
        scenario.steps,
        scenario.vehicle,
        np.random.default_rng(motion_ss),
    )
    check_visibility(scenario, motion)
    known = build_known_map(scenario, np.random.default_rng(map_ss))
    laser_rng = np.random.default_rng(laser_ss)
    params = extraction if extraction is not None else ExtractionParams()

    n = motion.true_poses.shape[0]
    scans: list[Scan] = []
    rejected: Counter[str] = Counter()
    steps: list[int] = []
    kinds: list[int] = []
    fparams: list[FloatArray] = []
    covs: list[FloatArray] = []
    true_ids: list[int] = []
    n_points: list[int] = []
    extents: list[tuple[float, float]] = []
    for k in range(n):
        scan = simulate_scan(scenario.world, motion.true_poses[k], scenario.laser, laser_rng)
        scans.append(scan)
        result = extract_features(scan, scenario.laser, params)
        rejected.update(result.rejected)
        for f in result.features:
            steps.append(k)
            kinds.append(int(f.kind))
            fparams.append(f.params)
            covs.append(f.cov)
            true_ids.append(f.true_id)
            n_points.append(f.n_points)
            extents.append(f.extent)
        if progress is not None:
            progress(k + 1, n)

    m = len(steps)
    log = MeasurementLog(
        scenario=scenario.name,
        seed=seed,
        timestamps=np.arange(n, dtype=float) * scenario.vehicle.dt_s,
        odometry=motion.odometry,
        odometry_cov=motion.odometry_cov,
        feat_step=np.array(steps, dtype=np.int64),
        feat_kind=np.array(kinds, dtype=np.int8),
        feat_params=np.array(fparams, dtype=float).reshape(m, 3),
        feat_cov=np.array(covs, dtype=float).reshape(m, 3, 3),
        feat_true_id=np.array(true_ids, dtype=np.int64),
        feat_n_points=np.array(n_points, dtype=np.int64),
        feat_extent=np.array(extents, dtype=float).reshape(m, 2),
        known_map=KnownMapArrays(
            ids=known.ids,
            kinds=known.kinds,
            params=known.params,
            covs=known.covs,
            extents=_known_extents(scenario, known.ids, known.kinds),
        ),
        world=world_arrays(scenario.world),
        true_poses=motion.true_poses,
        rejected={k: int(v) for k, v in sorted(rejected.items())},
    )
    return SimulationResult(log=log, motion=motion, scans=tuple(scans))
