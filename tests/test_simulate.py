"""Issue 2 acceptance: `mapfuse simulate loop600` gives the paper's loop, reproducibly."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from mapfuse_core.evaluation import path_length
from mapfuse_core.measlog import load_log, save_log
from mapfuse_graph.cli import main
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
    assert main(["simulate", str(bad), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "bad.toml" in err
