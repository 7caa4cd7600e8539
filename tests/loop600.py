"""Cached loop600 logs and EKF results for the slow acceptance tests (one per process).

The caches live in one process; under ``pytest -n`` (``--dist loadgroup``, set in
``pyproject.toml``) every test marked with :data:`LOOP600_GROUP` runs on the same
worker, so each log and each EKF run is computed once per suite rather than on every
worker that draws one of its tests.
"""

from __future__ import annotations

import functools
from typing import Any

import pytest

from ekf_reference import EKFConfig, EKFResult, run_ekf
from mapfuse.estimators.ekf import to_result
from mapfuse.metrics import run_metrics
from mapfuse_core.data.measlog import MeasurementLog
from mapfuse_core.sim.scenario import load_scenario
from mapfuse_core.sim.simulate import simulate

SEEDS = (0, 1, 2, 3, 4)

#: The xdist group of the tests that read these caches (see the module docstring).
LOOP600_GROUP = pytest.mark.xdist_group("loop600")


# One more than SEEDS: tests/test_loop600_graph.py also reads seed 12.
@functools.lru_cache(maxsize=6)
def loop600_log(seed: int) -> MeasurementLog:
    """The loop600 measurement log of ``seed``.

    Extracted in this process (``workers=1``): the log is the same bit for bit with any
    number of workers (``tests/test_simulate.py``), and under ``pytest -n`` every core
    already runs a test, so a worker pool only adds its start-up and traffic.
    """
    return simulate(load_scenario("loop600"), seed=seed, workers=1).log


@functools.lru_cache(maxsize=10)
def loop600_ekf(seed: int, fusion: bool) -> EKFResult:
    """The EKF reference on the loop600 log of ``seed``."""
    return run_ekf(loop600_log(seed), EKFConfig(fusion=fusion))


@functools.lru_cache(maxsize=5)
def loop600_ekf_carry(seed: int) -> EKFResult:
    """The fused EKF with ``carry_seen_steps=1`` on the loop600 log of ``seed``."""
    return run_ekf(loop600_log(seed), EKFConfig(fusion=True, carry_seen_steps=1))


def ekf_metrics(result: EKFResult, log: MeasurementLog) -> dict[str, Any]:
    """``metrics.json`` of an EKF result on ``log``."""
    return run_metrics(to_result(result, log), log)
