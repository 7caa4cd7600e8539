"""The estimators run BLAS on one thread, whatever the environment says, and give the
caller's setting back when they return or raise (docs/results/performance.md)."""

from __future__ import annotations

from collections.abc import Callable

import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from ekf_reference.config import EKFConfig
from ekf_reference.pipeline import run_ekf
from mapfuse_core.measlog import MeasurementLog
from mapfuse_graph.solvers import run_graph
from tests.synthetic import synthetic_log

#: The callers' setting around the runs: more than one thread, so that a run that
#: leaves BLAS alone is seen.
OUTSIDE = 2


def _blas_threads() -> list[int]:
    """Thread count of every BLAS library loaded in this process."""
    return [int(lib["num_threads"]) for lib in threadpool_info() if lib["user_api"] == "blas"]


@pytest.fixture(scope="module")
def log() -> MeasurementLog:
    return synthetic_log(30, 0)


RUNS: dict[str, Callable[[MeasurementLog, Callable[[int, int], None]], object]] = {
    "ekf": lambda log, progress: run_ekf(log, EKFConfig(), progress=progress),
    "isam2": lambda log, progress: run_graph(
        log, "isam2", fusion=False, association="truth", marginals=False, progress=progress
    ),
    "batch": lambda log, progress: run_graph(
        log, "batch", fusion=False, association="truth", marginals=False, progress=progress
    ),
}


@pytest.mark.parametrize("name", sorted(RUNS))
def test_blas_runs_on_one_thread_during_a_run(log: MeasurementLog, name: str) -> None:
    seen: list[list[int]] = []
    with threadpool_limits(limits=OUTSIDE, user_api="blas"):
        assert _blas_threads()
        assert set(_blas_threads()) == {OUTSIDE}
        RUNS[name](log, lambda k, n: seen.append(_blas_threads()))
        after = _blas_threads()
    assert seen
    assert all(threads == [1] * len(threads) for threads in seen)
    assert set(after) == {OUTSIDE}


@pytest.mark.parametrize("name", sorted(RUNS))
def test_the_callers_setting_comes_back_when_a_run_raises(log: MeasurementLog, name: str) -> None:
    def stop(k: int, n: int) -> None:
        raise KeyboardInterrupt

    with threadpool_limits(limits=OUTSIDE, user_api="blas"):
        with pytest.raises(KeyboardInterrupt):
            RUNS[name](log, stop)
        assert set(_blas_threads()) == {OUTSIDE}
