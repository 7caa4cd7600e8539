"""Cached loop600 logs and EKF results for the slow acceptance tests.

Each is computed once per test run: in this process (``functools.lru_cache``) and,
under ``pytest -n``, across the workers through pickles in the run's shared temporary
directory (``SHARED_DIR_ENV``, set by ``tests/conftest.py``).  A lock per entry makes a
worker that needs an entry another worker is computing wait for it instead of
computing it again.
"""

from __future__ import annotations

import fcntl
import functools
import os
import pickle
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from ekf_reference import EKFConfig, run_ekf
from mapfuse.metrics import run_metrics
from mapfuse_core.estimate import EstimatorResult
from mapfuse_core.measlog import MeasurementLog
from mapfuse_core.sim.scenario import load_scenario
from mapfuse_core.sim.simulate import simulate

SEEDS = (0, 1, 2, 3, 4)

#: Environment variable naming the directory the ``pytest -n`` workers share.
SHARED_DIR_ENV = "MAPFUSE_TEST_SHARED_DIR"

T = TypeVar("T")


def _shared(key: str, compute: Callable[[], T]) -> T:
    """``compute()``, or the value another worker of this run stored under ``key``."""
    root = os.environ.get(SHARED_DIR_ENV)
    if not root:
        return compute()
    directory = Path(root)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{key}.pickle"
    with open(directory / f"{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if path.exists():
            value: T = pickle.loads(path.read_bytes())
            return value
        value = compute()
        part = path.with_suffix(".part")
        part.write_bytes(pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL))
        part.replace(path)
        return value


# One more than SEEDS: tests/test_loop600_graph.py also reads seed 12.
@functools.lru_cache(maxsize=6)
def loop600_log(seed: int) -> MeasurementLog:
    """The loop600 measurement log of ``seed``.

    Extracted in this process (``workers=1``): the log is the same bit for bit with any
    number of workers (``tests/test_simulate.py``), and under ``pytest -n`` every core
    already runs a test, so a worker pool only adds its start-up and traffic.
    """
    return _shared(
        f"log-{seed}", lambda: simulate(load_scenario("loop600"), seed=seed, workers=1).log
    )


@functools.lru_cache(maxsize=10)
def loop600_ekf(seed: int, fusion: bool) -> EstimatorResult:
    """The EKF reference on the loop600 log of ``seed``."""
    return _shared(
        f"ekf-{seed}-{fusion}", lambda: run_ekf(loop600_log(seed), EKFConfig(), fusion=fusion)
    )


@functools.lru_cache(maxsize=5)
def loop600_ekf_carry(seed: int) -> EstimatorResult:
    """The fused EKF with ``carry_seen_steps=1`` on the loop600 log of ``seed``."""
    return _shared(
        f"ekf-carry-{seed}",
        lambda: run_ekf(loop600_log(seed), EKFConfig(carry_seen_steps=1), fusion=True),
    )


def ekf_metrics(result: EstimatorResult, log: MeasurementLog) -> dict[str, Any]:
    """``metrics.json`` of an EKF result on ``log``."""
    return run_metrics(result, log).to_json()
