"""Logs in, runs out: :func:`load`, :func:`simulate`, :func:`run` and :class:`Run`.

The library side of ``mapfuse run`` and of ``import mapfuse as mf``.  :func:`run`
plans the runs an estimator needs (:mod:`mapfuse.plan`: the EKF first for a graph
backend that consumes its decisions), makes them, and returns a :class:`Run`: the
estimator's :class:`~mapfuse_core.estimate.EstimatorResult`, the log, its typed
:class:`~mapfuse_core.estimate.RunMetrics`, and its errors and truth in the
estimate's own frame ``Wglobal``.  A log without a known map has nothing to fuse
(:func:`fusion_for`), whatever a run asks.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from mapfuse.carmen_input import is_carmen, load_carmen_input
from mapfuse.datadir import data_dir
from mapfuse.estimator import Estimator, Progress
from mapfuse.execution import estimate, fusion_for
from mapfuse.metrics import run_metrics
from mapfuse.plan import RunRequest, execute, plan_runs
from mapfuse.registry import resolve
from mapfuse_core.estimate import EstimatorResult, RunMetrics
from mapfuse_core.evaluation import gps_error_series, nees_series, pose_errors, truth_in_global
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.measlog import MeasurementLog, load_log
from mapfuse_core.sim.scenario import Scenario, load_scenario

if TYPE_CHECKING:
    from matplotlib.axes import Axes

__all__ = [
    "DATASETS",
    "Run",
    "RunErrors",
    "estimate",
    "fusion_for",
    "labelled",
    "load",
    "prepare_log",
    "run",
    "simulate",
]

#: Real datasets :func:`load` reads by name (they need a data directory).
DATASETS = ("carpark", "victoria-park")


def simulate(
    scenario: str | Path | Scenario,
    seed: int | None = None,
    *,
    steps: int | None = None,
    progress: Progress | None = None,
    workers: int | None = None,
) -> MeasurementLog:
    """The measurement log of ``scenario`` (a built-in name such as ``"loop600"``, a
    TOML file, or a :class:`~mapfuse_core.sim.scenario.Scenario`) simulated with
    ``seed`` (default: the scenario's own).

    ``steps`` keeps the first ``steps`` steps: a drive through waypoints is simulated
    for those steps only (its draws come step by step, so the log is the head of the
    full one, bit for bit); a drive by a table of controls is simulated whole and cut.
    ``workers``: processes extracting the features (default
    :func:`~mapfuse_core.sim.simulate.extraction_workers`: none in a script, whose
    workers would run the script again); the log is the same bit for bit whatever
    their number.
    """
    from mapfuse_core.sim.simulate import simulate as simulate_scenario

    sc = scenario if isinstance(scenario, Scenario) else load_scenario(str(scenario))
    if steps is not None:
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
            raise ValueError(f"steps must be a positive integer, got {steps!r}")
        if steps > sc.steps:
            raise ValueError(
                f"steps={steps} is more than scenario {sc.name!r} drives ({sc.steps} steps)"
            )
        if not sc.controls:
            sc = dataclasses.replace(sc, steps=steps)
    log = simulate_scenario(sc, seed=seed, progress=progress, workers=workers).log
    return log if steps is None or log.n_steps == steps else log.head(steps)


def load(
    source: str | Path,
    *,
    seed: int | None = None,
    steps: int | None = None,
    data: str | Path | None = None,
    known_map: str | None = None,
    progress: Progress | None = None,
    workers: int | None = None,
) -> MeasurementLog:
    """A measurement log from ``source``: a saved ``.npz`` log, a real dataset
    (``"carpark"``, ``"victoria-park"``; in the data directory ``data``, else in
    ``$MAPFUSE_DATA``), a CARMEN log (``"carmen:PATH"``; ``seed`` of its simulated
    odometry, ``known_map`` ``"floorplan"`` or ``"none"``, :mod:`mapfuse.carmen_input`),
    or a scenario to simulate (a built-in name or a TOML file; :func:`simulate`).

    ``seed`` applies to a simulation and to a CARMEN log's simulated odometry only, and
    ``data`` to a dataset only: given elsewhere they are errors (they would change
    nothing).  ``steps`` keeps the first ``steps`` steps of any log.  ``workers``:
    extraction processes of a simulation (:func:`simulate`).  ``progress(k, n)``: the
    steps of a simulation, the scans of a CARMEN log read.
    """
    src = str(source)
    if data is not None and src not in DATASETS:
        raise ValueError(f"a data directory applies to {', '.join(DATASETS)} only, not {src!r}")
    if is_carmen(src):
        log = load_carmen_input(src, seed=seed, known_map=known_map, progress=progress)
        return log if steps is None else _head(log, steps)
    if known_map is not None:
        raise ValueError(f"a known-map choice applies to CARMEN logs only, not {src!r}")
    if seed is not None and (src.endswith(".npz") or src in DATASETS):
        what = "a saved log" if src.endswith(".npz") else "the real dataset"
        raise ValueError(f"seed does not apply to {what} {src!r}: only a simulation has one")
    if src.endswith(".npz"):
        return _head(load_log(src), steps) if steps is not None else load_log(src)
    if src in DATASETS:
        from mapfuse_core.data.datasets import load_carpark, load_victoria_park

        loader = load_carpark if src == "carpark" else load_victoria_park
        log = loader(data_dir(data, src, "data"))
        return log if steps is None else _head(log, steps)
    return simulate(src, seed, steps=steps, progress=progress, workers=workers)


def _head(log: MeasurementLog, steps: int) -> MeasurementLog:
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    if steps > log.n_steps:
        raise ValueError(f"steps={steps} is more than the log holds ({log.n_steps} steps)")
    return log.head(steps)


def prepare_log(
    source: str,
    seed: int | None = None,
    progress: Progress | None = None,
    data_dir: str | None = None,
    known_map: str | None = None,
    workers: int | None = None,
) -> MeasurementLog:
    """:func:`load` under the command line's argument names."""
    return load(
        source, seed=seed, data=data_dir, known_map=known_map, progress=progress, workers=workers
    )


@dataclass(frozen=True, eq=False)
class RunErrors:
    """A run's errors against its reference, step by step, in the estimate's frame."""

    reference: Literal["truth", "gps"]
    """What the errors are measured against: the true poses (simulation, corrected
    CARMEN logs) or GPS fixes (real data; position only, at the fixes)."""
    timestamps: FloatArray
    """(N,) times of the errors (s): every step against truth, the fixes against GPS."""
    position: FloatArray
    """(N,) position error (m)."""
    heading: FloatArray | None
    """(N,) absolute heading error (rad); ``None`` against GPS."""
    dx: FloatArray | None
    """(N, 3) estimate − truth ``(x, y, θ)``, θ wrapped; ``None`` against GPS."""
    nees: FloatArray | None
    """(N,) 3-dof NEES of each step; ``None`` against GPS."""
    sigma: FloatArray | None
    """(N, 3) the estimate's standard deviations of ``(x, y, θ)``; ``None`` against GPS."""

    @property
    def rmse(self) -> float:
        """Root mean square of :attr:`position` (m)."""
        return float(np.sqrt(np.mean(np.square(self.position))))


@dataclass(frozen=True, eq=False)
class Run:
    """One estimator's run on one log: its result, its metrics, and its errors and
    truth in the estimate's frame ``Wglobal`` (the vehicle at step 0)."""

    result: EstimatorResult
    """What the estimator returned."""
    log: MeasurementLog
    """The log the run consumed."""
    metrics: RunMetrics
    """What the run's numbers say (``metrics.json`` is :meth:`RunMetrics.to_json`)."""

    @property
    def estimator(self) -> str:
        """Name of the estimator."""
        return self.result.estimator

    @property
    def fusion(self) -> bool:
        """Whether the known map was fused."""
        return self.result.fusion

    @property
    def timestamps(self) -> FloatArray:
        """(N,) step times (s)."""
        return self.result.timestamps

    @property
    def poses(self) -> FloatArray:
        """(N, 3) the main pose estimate in ``Wglobal``."""
        return self.result.poses

    @property
    def covs(self) -> FloatArray:
        """(N, 3, 3) its covariance."""
        return self.result.covs

    @property
    def truth(self) -> FloatArray | None:
        """(N, 3) the true poses of the run's steps in ``Wglobal``, the frame of
        :attr:`poses` (the log's ``true_poses`` are in the world frame), or ``None``
        without truth."""
        if self.log.true_poses is None:
            return None
        return truth_in_global(self.log.true_poses[: self.result.n_steps])

    @cached_property
    def errors(self) -> RunErrors:
        """The errors of :attr:`poses` against truth, or against GPS on real data
        (through the anchor, or the best fit without one, as
        :attr:`RunMetrics.position_error` says); :class:`ValueError` for a log with
        neither."""
        truth = self.truth
        if truth is not None:
            err = pose_errors(self.poses, truth)
            sigma = np.sqrt(np.clip(np.diagonal(self.covs, axis1=1, axis2=2), 0.0, None))
            return RunErrors(
                reference="truth",
                timestamps=self.timestamps,
                position=err.position,
                heading=err.heading,
                dx=err.dx,
                nees=nees_series(err.dx, self.covs),
                sigma=sigma,
            )
        pe = self.metrics.position_error
        if self.log.gps is None or pe is None or pe.x_gps_Wglobal is None:
            raise ValueError(
                f"{self.log.scenario}: the log has no truth and no GPS reference, so the "
                "run has no errors"
            )
        t, pos = gps_error_series(
            self.timestamps, self.poses, *self.log.gps, np.asarray(pe.x_gps_Wglobal)
        )
        return RunErrors("gps", t, pos, None, None, None, None)

    def plot(self, ax: Axes | None = None) -> Axes:
        """Draw the position error against time, with the estimate's 2σ position bound
        when measured against truth, on ``ax`` (a new figure's when ``None``)."""
        from mapfuse.plotting import run_error_axes

        out: Axes = run_error_axes(self, ax)
        return out


def labelled(progress: Callable[[str, int, int], None] | None, label: str) -> Progress | None:
    """``progress(k, n)`` from a labelled ``progress(label, k, n)``."""
    if progress is None:
        return None

    def report(k: int, n: int) -> None:
        progress(label, k, n)

    return report


def run(
    log: MeasurementLog | str | Path,
    estimator: str | Estimator = "ekf",
    *,
    fusion: bool = True,
    options: Any = None,
    upstream: EstimatorResult | None = None,
    progress: Progress | None = None,
    **overrides: Any,
) -> Run:
    """Run ``estimator`` (a registered name or an estimator) on ``log`` (a log, or a
    source for :func:`load`).

    ``options``: the estimator's options (default: its defaults for the log,
    :mod:`mapfuse.profiles`), with ``overrides`` of their fields (e.g.
    ``association="truth"`` for a graph backend; a mapping changes only the fields it
    names: ``graph={"robust": "huber"}``).  An estimator that consumes another's result
    (:attr:`~mapfuse.estimator.Capabilities.consumes`) gets ``upstream`` when given,
    else that estimator is run first with its defaults.  On a log without a known map
    the run is made without fusion, whatever ``fusion`` asks.  ``progress(k, n)`` is
    called as the estimator advances.
    """
    if not isinstance(log, MeasurementLog):
        log = load(log)
    est = resolve(estimator)
    consumed = est.capabilities.consumes
    if consumed is not None and upstream is None:
        plan = plan_runs([RunRequest(consumed, fusion)], len(log.known_map) > 0)
        (made,) = execute(plan, log)
        upstream = made.result
    result = estimate(
        log, est, fusion=fusion, options=options, upstream=upstream, progress=progress, **overrides
    )
    return Run(result=result, log=log, metrics=run_metrics(result, log))
