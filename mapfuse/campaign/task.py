"""One campaign run on a worker: :func:`run_seed` simulates one seed and runs every
estimator of the spec on that log, for each fusion setting.

It returns plain data (:class:`RunOutcome`: table rows and per-step arrays), never
writes files, so a worker on another machine needs no access to the campaign
directory.  An estimator that consumes another's result (the graph backends, the
EKF's association decisions) gets that estimator's run of the same fusion setting,
as in :func:`mapfuse.comparison.compare` (both plan through :mod:`mapfuse.plan`).  An
estimator that raises is recorded with its error (so are its consumers), and the others
go on; a log that cannot be made fails every row of the run.
"""

from __future__ import annotations

import math
import time
import traceback
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import Any

import numpy as np

from mapfuse import registry
from mapfuse.campaign.spec import CampaignSpec
from mapfuse.metrics import run_metrics
from mapfuse.plan import RunRequest, RunResult, execute, plan_runs
from mapfuse.runner import Run, simulate
from mapfuse_core.measlog import MeasurementLog
from mapfuse_core.sim.scenario import Scenario, load_scenario

__all__ = [
    "ARRAY_FIELDS",
    "RunOutcome",
    "array_key",
    "make_log",
    "plugins_registered",
    "run_seed",
]

#: Per-step arrays of every (estimator, fusion) of a run, in its ``.npz``.
ARRAY_FIELDS = ("dx", "nees", "sigma", "position_error")


def array_key(estimator: str, fusion: bool, name: str) -> str:
    """Name of one array in a run's ``.npz``, e.g. ``ekf/fused/nees``."""
    return f"{estimator}/{'fused' if fusion else 'plain'}/{name}"


@dataclass(frozen=True)
class RunOutcome:
    """What one run hands back to the campaign."""

    seed: int
    """The run's seed."""
    rows: tuple[dict[str, Any], ...]
    """One table row per estimator × fusion setting (:func:`run_seed` documents the
    columns)."""
    arrays: dict[str, np.ndarray]
    """Per-step arrays by :func:`array_key` (``dx`` (N, 3) estimate − truth, ``nees``
    (N,), ``sigma`` (N, 3) standard deviations, ``position_error`` (N,) m), and
    ``timestamps`` (the log's step times, s)."""
    wall_time_s: float
    """Wall time of the whole run (simulation included), s."""


def plugins_registered(plugins: tuple[str, ...]) -> AbstractContextManager[object]:
    """The spec's ``module:attribute`` estimators registered for the duration of one run
    (:func:`mapfuse.registry.registered_plugins`: a serial campaign leaves the registry
    of its process as it found it)."""
    return registry.registered_plugins(plugins)


def run_scenario(spec: CampaignSpec, seed: int) -> Scenario:
    """The scenario of run ``seed``: the spec's, or a world generated from the seed."""
    if spec.world is None:
        return load_scenario(spec.scenario)
    from mapfuse_core.sim.worldgen import WorldParams, generate_scenario

    base = load_scenario(spec.scenario)
    return generate_scenario(WorldParams(seed=seed, **dict(spec.world)), base=base)


def make_log(spec: CampaignSpec, seed: int) -> MeasurementLog:
    """The log of run ``seed``, made in this process, of its first ``spec.steps``
    steps (more than it has: :class:`ValueError`): a CARMEN log (``carmen:PATH``)
    loaded with ``seed`` drawing its simulated odometry, else a simulation
    (:func:`mapfuse.runner.simulate`)."""
    from mapfuse.carmen_input import is_carmen, load_carmen_input

    if is_carmen(spec.scenario):
        log = load_carmen_input(spec.scenario, seed=seed)
        if spec.steps is not None and spec.steps > log.n_steps:
            raise ValueError(f"steps={spec.steps} is more than the log holds ({log.n_steps})")
        return log if spec.steps is None else log.head(spec.steps)
    # More steps than the scenario drives is an error (a generated world's length
    # depends on its seed: that run fails with this message).
    return simulate(run_scenario(spec, seed), seed, steps=spec.steps, workers=1)


def _error_text(exc: BaseException) -> str:
    tb = traceback.format_exception(type(exc), exc, exc.__traceback__)
    return f"{type(exc).__name__}: {exc}\n{''.join(tb[-3:])}".strip()


def _finite(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def _row_and_arrays(run: Run) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The table row and per-step arrays of one finished estimator run."""
    result, log, metrics = run.result, run.log, run.metrics
    assert log.true_poses is not None
    err = run.errors
    if err.dx is None or err.nees is None or err.sigma is None:
        raise ValueError(f"{result.estimator}: a campaign run needs errors against truth")
    pe, nm, head, a = metrics.position_error, metrics.nees, metrics.heading_error, metrics.anchor
    if pe is None or nm is None or head is None:
        raise ValueError(f"{result.estimator}: a campaign run needs errors against truth")
    row: dict[str, Any] = {
        "status": "ok",
        "error": None,
        "estimate": result.estimate,
        "steps": result.n_steps,
        "rmse_m": pe.rmse,
        "max_m": pe.max,
        "final_m": pe.final,
        "heading_rmse_rad": head.rmse,
        "nees_mean": _finite(nm.mean),
        "nees_within": _finite(nm.fraction_within_chi2_95),
        "anchor": a is not None,
        "anchor_m": None if a is None else a.position_error_m,
        "anchor_rad": None if a is None else a.heading_error_rad,
        "anchor_nees": None if a is None else _finite(a.nees),
        "accepted_at_step": None if a is None else a.accepted_at_step,
        "pairings": None if a is None else a.pairings,
        "wrong_pairings": None if a is None else a.pairings - a.correct_pairings,
        "ccda_reasons": None
        if metrics.matching.ccda_reasons is None
        else dict(metrics.matching.ccda_reasons),
        "map_features": metrics.map.features,
        "matched_known": metrics.map.matched_known,
        "runtime_s": metrics.runtime.total,
    }
    arrays = {"dx": err.dx, "nees": err.nees, "sigma": err.sigma, "position_error": err.position}
    return row, arrays


def _failed_row(error: str) -> dict[str, Any]:
    return {"status": "error", "error": error}


def run_seed(
    spec: CampaignSpec, seed: int, clock: Callable[[], float] = time.perf_counter
) -> RunOutcome:
    """Run ``seed`` of ``spec``: simulate once, then every estimator × fusion setting.

    Row columns: ``seed``, ``estimator``, ``fusion``, ``status`` (``"ok"`` or
    ``"error"``), ``error`` (message and the end of the traceback), ``estimate``
    (``filtered``/``smoothed``), ``steps``, ``rmse_m``, ``max_m``, ``final_m``,
    ``heading_rmse_rad``, ``nees_mean``, ``nees_within`` (fraction of steps with NEES ≤
    χ²(3, 0.95)), ``anchor`` (whether one was accepted), ``anchor_m``, ``anchor_rad``,
    ``anchor_nees``, ``accepted_at_step``, ``pairings``, ``wrong_pairings``,
    ``ccda_reasons`` (the map matchings behind the anchor, calls per outcome, as in
    ``metrics.json``; ``None`` without), ``map_features``, ``matched_known``,
    ``runtime_s`` (the estimator's summed step times), ``scenario`` (the log's).  Every
    value but ``runtime_s`` depends on the spec and the seed alone.
    """
    t0 = clock()
    with plugins_registered(spec.plugins):
        return _run(spec, seed, clock, t0)


def _run(spec: CampaignSpec, seed: int, clock: Callable[[], float], t0: float) -> RunOutcome:
    keys = [(e, f) for f in spec.fusions for e in spec.estimators]
    rows: dict[tuple[str, bool], dict[str, Any]] = {}
    arrays: dict[str, np.ndarray] = {}
    try:
        log = make_log(spec, seed)
        if log.true_poses is None:
            raise ValueError(f"scenario {spec.scenario!r} gave a log without true poses")
    except Exception as exc:
        text = _error_text(exc)
        rows = {k: _failed_row(f"simulation failed: {text}") for k in keys}
        return _outcome(seed, keys, rows, arrays, "", clock() - t0)
    requests = [RunRequest(e, f) for f in spec.fusions for e in spec.estimators]
    plan = plan_runs(requests, len(log.known_map) > 0)
    done = execute(plan, log, errors="record")
    for req in requests:
        d = _made(done, req, log)
        key = (req.estimator, req.fusion)
        if d.result is None:
            rows[key] = _failed_row(d.error or "failed")
            continue
        try:
            row, arr = _row_and_arrays(Run(d.result, log, run_metrics(d.result, log)))
        except Exception as exc:
            rows[key] = _failed_row(_error_text(exc))
            continue
        rows[key] = row
        for k, v in arr.items():
            arrays[array_key(req.estimator, req.fusion, k)] = v
    arrays["timestamps"] = np.asarray(log.timestamps, dtype=float)
    return _outcome(seed, keys, rows, arrays, log.scenario, clock() - t0)


def _made(done: tuple[RunResult, ...], req: RunRequest, log: MeasurementLog) -> RunResult:
    """The run of the plan that made ``req`` (the one without fusion where nothing can
    be fused)."""
    for fusion in (req.fusion and len(log.known_map) > 0, False):
        for d in done:
            p = d.planned
            if p.estimator == req.estimator and p.fusion is fusion and p.reported:
                return d
    raise AssertionError(f"the plan has no run of {req}")


def _outcome(
    seed: int,
    keys: list[tuple[str, bool]],
    rows: dict[tuple[str, bool], dict[str, Any]],
    arrays: dict[str, np.ndarray],
    scenario: str,
    wall: float,
) -> RunOutcome:
    out = tuple(
        {"seed": seed, "estimator": e, "fusion": f, "scenario": scenario, **rows[(e, f)]}
        for e, f in keys
    )
    return RunOutcome(seed=seed, rows=out, arrays=arrays, wall_time_s=wall)
