"""Simulation pipeline: scenario → motion → laser scans → extracted features → log.

Random streams are split from one :class:`numpy.random.SeedSequence` per purpose
(motion, laser, known map), so changing e.g. the laser parameters does not change
the trajectory noise of the same seed.

Feature extraction is most of the cost and needs no random numbers, so scans are
extracted in a pool of worker processes while this process keeps casting rays: the
scans themselves must be made in step order, from one generator.  The log does not
depend on the number of workers, bit for bit: every scan is extracted by the same
deterministic code on the same arrays, and the results are gathered in step order.

The pool uses the ``spawn`` start method on every platform.  ``fork`` would start
faster, but forking a process that runs threads (a Jupyter kernel, a pytest-xdist
worker driven by execnet, a threaded BLAS) can deadlock the child on a lock copied
while held.  A spawned worker imports numpy and scipy afresh (about a second, paid
while this process simulates the drive and casts the first rays) and shares no state
with its parent.  It also runs the parent's main module again when that is a script,
to find what the script defines: without an ``if __name__ == "__main__":`` guard, every
worker would run the whole script and fail with a traceback when it comes to start a
pool of its own.  So by default the pool is used only where the main module is not a
file (a notebook, an interactive session, ``python -c``) and a script extracts in its
own process; a guarded script, like the ``mapfuse`` command, asks for workers by number
(:func:`default_workers`).
"""

from __future__ import annotations

import multiprocessing
import os
import sys
import threading
import time
import warnings
from collections import Counter
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass

import numpy as np

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog, MeasurementLogError
from mapfuse_core.perception.extraction import ExtractionParams, ExtractionResult, extract_features
from mapfuse_core.sensor import LaserParams, Scan
from mapfuse_core.sim.clutter import ClutterParams, add_clutter
from mapfuse_core.sim.laser import simulate_scan
from mapfuse_core.sim.limits import check_seed, check_steps
from mapfuse_core.sim.scenario import (
    Scenario,
    ScenarioError,
    build_known_map,
    check_visibility,
    simulate_drive,
)
from mapfuse_core.sim.vehicle import MotionResult
from mapfuse_core.sim.world import WallSegment, World

__all__ = ["SimulationResult", "default_workers", "extraction_workers", "simulate", "world_arrays"]

# Below this many steps a pool costs more than it saves: a spawned worker is ready only
# after its imports (the package, numpy, scipy: seconds), while a scan is extracted in
# milliseconds, so two workers gain half of n scans' extraction against that wait.
_MIN_PARALLEL_STEPS = 600
# Scans per task: enough to make the inter-process traffic negligible against a task's
# work, few enough that the workers start early and share the
# tail of the run evenly.
_CHUNK_STEPS = 64


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


def default_workers() -> int:
    """Size of the extraction pool: two processes (the project's machines have two
    cores), one on a single core."""
    return min(2, os.cpu_count() or 1)


def _main_is_a_file() -> bool:
    """Whether this process's main module is a file (a script, ``python -m``), which a
    spawned process may run again, rather than a notebook, a session or ``python -c``."""
    return getattr(sys.modules.get("__main__"), "__file__", None) is not None


def extraction_workers(workers: int | None, steps: int) -> int:
    """Number of processes :func:`simulate` extracts features with; 1 means in-process.

    ``workers=None`` asks for the default: :func:`default_workers` where the main module
    is not a file, 1 in a script (see the module's docstring).  Runs of fewer than 600
    steps (where starting the workers costs more than they save) and daemonic processes
    (which may not start children) use 1 whatever is asked.
    """
    if workers is None:
        workers = 1 if _main_is_a_file() else default_workers()
    elif isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be an integer >= 1 or None, got {workers!r}")
    if steps < _MIN_PARALLEL_STEPS or multiprocessing.current_process().daemon:
        return 1
    return workers


def _extract_chunk(
    scans: Sequence[Scan], laser: LaserParams, params: ExtractionParams
) -> list[ExtractionResult]:
    """Worker task: the extraction of consecutive scans, in order."""
    return [extract_features(scan, laser, params) for scan in scans]


def _exit_with_parent(parent: int) -> None:
    """Worker initializer: end the worker once the process that started it is gone.

    A parent killed without shutting its pool down (SIGKILL, a test runner's timeout)
    would otherwise leave the workers waiting on the task queue forever, since each
    holds both ends of its pipe.
    """

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def _start_pool(workers: int, laser: LaserParams, params: ExtractionParams) -> ProcessPoolExecutor:
    """A ``spawn`` pool whose ``workers`` processes are already starting.

    The executor starts a process per task waiting for one: an empty task each starts
    them all at once, so that their imports overlap the simulation of the drive.
    """
    pool = ProcessPoolExecutor(
        workers,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_exit_with_parent,
        initargs=(os.getpid(),),
    )
    try:
        for _ in range(workers):
            pool.submit(_extract_chunk, [], laser, params)
    except BrokenProcessPool:
        pass  # reported by the first real task
    return pool


def _parallel_extraction(
    pool: ProcessPoolExecutor,
    world: World,
    poses: FloatArray,
    laser: LaserParams,
    rng: np.random.Generator,
    params: ExtractionParams,
    progress: Callable[[int, int], None] | None,
) -> tuple[list[Scan], list[ExtractionResult]] | None:
    """Scans made here in step order, extracted by the processes of ``pool``.

    ``None`` when the pool broke (a worker could not start, e.g. one asked for by a
    script without a ``__main__`` guard): the caller then starts again in-process.
    """
    n = poses.shape[0]
    scans: list[Scan] = []
    results: list[ExtractionResult] = []
    futures: list[Future[list[ExtractionResult]]] = []
    try:
        for lo in range(0, n, _CHUNK_STEPS):
            chunk = [simulate_scan(world, x, laser, rng) for x in poses[lo : lo + _CHUNK_STEPS]]
            scans.extend(chunk)
            futures.append(pool.submit(_extract_chunk, chunk, laser, params))
        for f in futures:
            for result in f.result():
                results.append(result)
                if progress is not None:
                    progress(len(results), n)
    except BrokenProcessPool:
        return None
    return scans, results


def simulate(
    scenario: Scenario,
    seed: int | None = None,
    extraction: ExtractionParams | None = None,
    progress: Callable[[int, int], None] | None = None,
    workers: int | None = None,
    clutter: ClutterParams | None = None,
) -> SimulationResult:
    """Simulate ``scenario`` with ``seed`` (default: the scenario's own seed).

    ``seed`` is an integer in ``0 … 2**63 - 1`` and the scenario within the limits of
    :mod:`mapfuse_core.sim.limits`; :class:`ValueError` before any work otherwise.

    ``progress(k, n)`` is called after each step when given (with workers, in step
    order as the extracted scans come back).  ``workers`` processes extract the
    features (see :func:`extraction_workers`: by default none in a script, so that it
    needs no ``__main__`` guard; ``workers=1`` keeps everything in this process); the
    result is the same bit for bit whatever their number.  ``clutter``
    adds spurious features and gross outliers to the extracted features
    (:mod:`mapfuse_core.sim.clutter`, from a stream of their own: the rest of the log
    is that of the same seed without them).
    """
    seed = check_seed(scenario.seed if seed is None else seed)
    check_steps(scenario.steps, scenario.laser.n_beams, f"scenario {scenario.name!r}: steps")
    params = extraction if extraction is not None else ExtractionParams()
    n_workers = extraction_workers(workers, scenario.steps)
    pool = _start_pool(n_workers, scenario.laser, params) if n_workers > 1 else None
    scans: list[Scan] = []
    results: list[ExtractionResult] = []
    try:
        # Children are numbered: the fourth leaves the first three (and the logs of
        # runs without clutter) unchanged.
        motion_ss, laser_ss, map_ss, clutter_ss = np.random.SeedSequence(seed).spawn(4)
        motion = simulate_drive(scenario, np.random.default_rng(motion_ss))
        check_visibility(scenario, motion)
        known = build_known_map(scenario, np.random.default_rng(map_ss))
        laser_rng = np.random.default_rng(laser_ss)
        if pool is not None:
            state = laser_rng.bit_generator.state
            done = _parallel_extraction(
                pool,
                scenario.world,
                motion.true_poses,
                scenario.laser,
                laser_rng,
                params,
                progress,
            )
            if done is None:
                warnings.warn(
                    "the extraction worker pool broke (a script asking simulate() for workers "
                    'needs an `if __name__ == "__main__":` guard); extracting in this process',
                    RuntimeWarning,
                    stacklevel=2,
                )
                # Rewind the laser stream to where the pool started: the scans are made
                # again.
                laser_rng.bit_generator.state = state
            else:
                scans, results = done
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)

    n = motion.true_poses.shape[0]
    if not results:
        for k in range(n):
            scan = simulate_scan(scenario.world, motion.true_poses[k], scenario.laser, laser_rng)
            scans.append(scan)
            results.append(extract_features(scan, scenario.laser, params))
            if progress is not None:
                progress(k + 1, n)

    if clutter is not None and clutter.active:
        results = add_clutter(results, scenario.laser, clutter, np.random.default_rng(clutter_ss))

    rejected: Counter[str] = Counter()
    steps: list[int] = []
    kinds: list[int] = []
    fparams: list[FloatArray] = []
    covs: list[FloatArray] = []
    true_ids: list[int] = []
    n_points: list[int] = []
    extents: list[tuple[float, float]] = []
    for k, result in enumerate(results):
        rejected.update(result.rejected)
        for f in result.features:
            steps.append(k)
            kinds.append(int(f.kind))
            fparams.append(f.params)
            covs.append(f.cov)
            true_ids.append(f.true_id)
            n_points.append(f.n_points)
            extents.append(f.extent)

    m = len(steps)
    try:
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
            known_frame=np.array(known.frame, dtype=float),
            rejected={k: int(v) for k, v in sorted(rejected.items())},
            scan_bearings=scenario.laser.bearings(),
            scan_ranges=np.array([s.ranges for s in scans], dtype=np.float32).reshape(
                n, int(scenario.laser.n_beams)
            ),
        )
    except MeasurementLogError as exc:
        # Extreme but valid parameters (e.g. a control noise that dwarfs the slip) can
        # give covariances the log refuses: report them against the scenario file.
        raise ScenarioError(
            scenario.source, "", f"the simulated log is invalid (check the noise): {exc}"
        ) from None
    return SimulationResult(log=log, motion=motion, scans=tuple(scans))
