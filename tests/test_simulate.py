"""`mapfuse simulate loop600` gives the paper's loop, reproducibly."""

from __future__ import annotations

import dataclasses
import importlib
import json
import math
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from mapfuse.cli import main
from mapfuse_core.evaluation import path_length
from mapfuse_core.measlog import load_log, save_log
from mapfuse_core.sensor import LaserParams
from mapfuse_core.sim.laser import simulate_scan
from mapfuse_core.sim.scenario import Scenario, load_scenario
from mapfuse_core.sim.simulate import (
    _MIN_PARALLEL_STEPS,
    default_workers,
    extraction_workers,
    simulate,
)
from mapfuse_core.sim.world import World
from tests.loop600 import loop600_log


@pytest.mark.slow
def test_cli_simulate_loop600_is_the_papers_loop_and_bit_identical(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["simulate", "loop600", "--seed", "0", "--out", str(tmp_path), "--quiet"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["steps"] == 2400
    log = load_log(tmp_path / "log.npz")
    assert log.true_poses is not None
    assert log.true_poses.shape == (2400, 3)
    np.testing.assert_allclose(log.true_poses[0], [-29.0, -11.0, math.pi / 3], atol=1e-12)
    assert abs(path_length(log.true_poses) - 600.0) <= 12.0
    # A closed loop: back within a few metres of the start.
    assert np.hypot(*(log.true_poses[-1, :2] - log.true_poses[0, :2])) < 5.0
    assert (tmp_path / "world.png").stat().st_size > 10_000
    # Same seed, independent run in this process: the very same bytes.
    again = save_log(loop600_log(0), tmp_path / "again.npz")
    assert again.read_bytes() == (tmp_path / "log.npz").read_bytes()


def test_cli_reports_a_bad_scenario_clearly(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[scenario]\nname = 3\n")
    # An input error (3), not a usage error: the command line is right, the file is not.
    assert main(["simulate", str(bad), "--out", str(tmp_path / "o"), "--quiet"]) == 3
    err = capsys.readouterr().err
    assert "bad.toml" in err


# --------------------------------------------------------------------------- workers


@pytest.fixture(scope="module")
def short_loop() -> Scenario:
    """loop600 cut to the shortest run that is extracted in parallel."""
    return dataclasses.replace(load_scenario("loop600"), steps=_MIN_PARALLEL_STEPS)


@pytest.fixture(scope="module")
def in_process_bytes(short_loop: Scenario, tmp_path_factory: pytest.TempPathFactory) -> bytes:
    path = tmp_path_factory.mktemp("serial") / "log.npz"
    return save_log(simulate(short_loop, seed=1, workers=1).log, path).read_bytes()


def test_worker_processes_give_the_same_log_bit_for_bit(
    short_loop: Scenario, in_process_bytes: bytes, tmp_path: Path
) -> None:
    calls: list[tuple[int, int]] = []
    result = simulate(short_loop, seed=1, workers=2, progress=lambda k, n: calls.append((k, n)))
    assert save_log(result.log, tmp_path / "log.npz").read_bytes() == in_process_bytes
    assert len(result.scans) == short_loop.steps
    # Progress still reports every step once, in order.
    assert calls == [(k, short_loop.steps) for k in range(1, short_loop.steps + 1)]


def test_a_broken_pool_falls_back_to_the_same_log(
    short_loop: Scenario,
    in_process_bytes: bytes,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A pool that breaks part-way (its laser draws already made) changes nothing."""

    def broken(
        pool: object,
        world: World,
        poses: np.ndarray,
        laser: LaserParams,
        rng: np.random.Generator,
        *args: object,
    ) -> None:
        for pose in poses[:50]:
            simulate_scan(world, pose, laser, rng)
        return None

    # The package re-exports the function simulate under the module's name.
    module = importlib.import_module("mapfuse_core.sim.simulate")
    monkeypatch.setattr(module, "_parallel_extraction", broken)
    with pytest.warns(RuntimeWarning, match="worker pool broke"):
        result = simulate(short_loop, seed=1, workers=2)
    assert save_log(result.log, tmp_path / "log.npz").read_bytes() == in_process_bytes


def test_extraction_workers_default_and_small_runs(monkeypatch: pytest.MonkeyPatch) -> None:
    main_module = sys.modules["__main__"]
    # A notebook's or a session's main module has no file: the default pool.
    monkeypatch.delattr(main_module, "__file__", raising=False)
    assert default_workers() == min(2, os.cpu_count() or 1)
    assert extraction_workers(None, 10_000) == default_workers()
    # A script's would be run again by every worker: in-process unless asked.
    monkeypatch.setattr(main_module, "__file__", "script.py", raising=False)
    assert extraction_workers(None, 10_000) == 1
    assert extraction_workers(2, 10_000) == 2
    assert extraction_workers(3, 10_000) == 3
    assert extraction_workers(1, 10_000) == 1
    # A short run is not worth starting processes for.
    assert extraction_workers(4, _MIN_PARALLEL_STEPS - 1) == 1
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ValueError, match="workers"):
            extraction_workers(bad, 10_000)  # type: ignore[arg-type]
