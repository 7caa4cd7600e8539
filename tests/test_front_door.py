"""``import mapfuse as mf``: lazy, complete, and the README's scripts run as written.

The README's Python examples are extracted and run as plain scripts in a fresh
interpreter (no ``if __name__ == "__main__":`` guard), so a change that breaks them,
or makes a script print a traceback, fails here.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import mapfuse as mf
from mapfuse_core.measlog import MeasurementLog
from tests.loop600 import ekf_metrics, loop600_ekf, loop600_log

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "mapfuse.cli"]


def readme_script(name: str) -> str:
    """The code block after ``<!-- readme-script: NAME -->`` in the README."""
    text = (ROOT / "README.md").read_text()
    m = re.search(
        rf"<!-- readme-script: {re.escape(name)} -->\s*```python\n(.*?)```", text, re.DOTALL
    )
    assert m is not None, f"README has no script {name!r}"
    return m.group(1)


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    env["PYTHONPATH"] = str(ROOT)
    env["MPLBACKEND"] = "Agg"
    return env


def run_script(code: str, tmp_path: Path) -> subprocess.CompletedProcess[str]:
    """``code`` saved as a file and run as ``python script.py`` in ``tmp_path``."""
    script = tmp_path / "script.py"
    script.write_text(code)
    return subprocess.run(
        [sys.executable, str(script)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=_env(),
        timeout=600,
    )


@pytest.fixture(scope="module")
def loop_log_300() -> MeasurementLog:
    """The first 300 steps of loop600, seed 0 (two CCDA matches' worth of map)."""
    return mf.simulate("loop600", seed=0, steps=300)


def test_import_loads_neither_gtsam_nor_matplotlib() -> None:
    code = (
        "import sys, mapfuse as mf\n"
        "mf.run, mf.Run, mf.EstimatorResult, mf.Capabilities\n"
        "print(','.join(sorted({'gtsam', 'matplotlib'} & {m.split('.')[0] for m in sys.modules})))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=_env(), check=True
    )
    assert out.stdout.strip() == ""


def test_every_front_door_name_resolves() -> None:
    for name in mf.__all__:
        assert getattr(mf, name) is not None, name
    assert set(mf.__all__) <= set(dir(mf))
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        _ = mf.nope  # type: ignore[attr-defined]


def test_front_door_names_are_not_shadowed_by_submodules() -> None:
    # A submodule named like a front-door function would replace it on import.
    import importlib

    for module in ("mapfuse.comparison", "mapfuse.runner", "mapfuse.campaign.api"):
        importlib.import_module(module)
    assert callable(mf.run)
    assert callable(mf.compare)
    assert not (ROOT / "mapfuse" / "run.py").exists()
    assert not (ROOT / "mapfuse" / "compare.py").exists()


@pytest.mark.slow
def test_the_readme_front_door_script_reproduces_metrics_json(tmp_path: Path) -> None:
    code = readme_script("front-door")
    assert len([line for line in code.splitlines() if line.strip()]) <= 10
    proc = run_script(code, tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    rmse = re.search(r"^RMSE (\S+) m$", proc.stdout, re.MULTILINE)
    said = re.search(r"^metrics.json: (\S+) m, NEES (\S+)$", proc.stdout, re.MULTILINE)
    assert rmse is not None, proc.stdout
    assert said is not None, proc.stdout
    # The naive RMSE of the script is metrics.json's, printed to 4 decimals alike.
    assert rmse.group(1) == said.group(1)
    # And it is the number of the same run in this process (the cache the loop600 tests
    # share; the command line's metrics.json is this function's output, see
    # test_architecture.py::test_mapfuse_run_ekf_works_without_gtsam).
    metrics = ekf_metrics(loop600_ekf(0, True), loop600_log(0))
    assert f"{metrics['position_error_m']['rmse']:.4f}" == rmse.group(1)


@pytest.mark.slow
def test_the_readme_plug_in_script_runs_as_a_plain_script(tmp_path: Path) -> None:
    from mapfuse_core.sim.simulate import extraction_workers

    code = readme_script("plug-in")
    # Its log is long enough that an extraction pool would start if asked for: the
    # script has no main guard, and a pool's workers would run it again.
    steps = int(re.search(r"steps=(\d+)", code).group(1))  # type: ignore[union-attr]
    assert extraction_workers(2, steps) == 2
    proc = run_script(code, tmp_path)
    assert proc.returncode == 0, proc.stderr
    for bad in ("Traceback", "RuntimeError", "pool broke"):
        assert bad not in proc.stderr, proc.stderr
    rows = re.findall(r"^(\w+)\s+fusion=(True|False)\s+RMSE (\S+) m$", proc.stdout, re.MULTILINE)
    assert [(e, f) for e, f, _ in rows] == [
        ("ekf", "True"),
        ("ekf", "False"),
        ("toy", "False"),
    ]
    rmse = {(e, f): float(v) for e, f, v in rows}
    # Dead reckoning drifts; the EKF on the same 600 steps stays within decimetres.
    assert rmse[("toy", "False")] > 3 * rmse[("ekf", "True")]
    assert rmse[("ekf", "True")] < 0.2


def test_run_answers_in_the_estimate_frame(loop_log_300: MeasurementLog) -> None:
    from mapfuse.runner import Run

    run = mf.run(loop_log_300, "ekf")
    assert isinstance(run, Run)
    assert run.truth is not None
    assert run.truth.shape == run.poses.shape
    # The truth is in Wglobal: it starts at the origin, as the estimate does.
    np.testing.assert_allclose(run.truth[0], 0.0, atol=1e-12)
    err = run.errors
    assert err.reference == "truth"
    assert run.metrics.position_error is not None
    assert run.metrics.nees is not None
    assert err.rmse == pytest.approx(run.metrics.position_error.rmse, rel=1e-12)
    finite = np.isfinite(err.nees)
    assert float(np.mean(err.nees[finite])) == pytest.approx(run.metrics.nees.mean, rel=1e-12)
    ax = run.plot()
    assert ax.get_lines(), "the plot draws the error"
    import matplotlib.pyplot as plt

    plt.close("all")


def test_run_of_a_graph_backend_plans_its_upstream(loop_log_300: MeasurementLog) -> None:
    batch = mf.run(loop_log_300, "batch")
    up = batch.result.upstream
    assert up is not None
    assert up.estimator == "ekf"
    assert batch.metrics.association == "ekf"
    # Handing the upstream in gives the same result without running the EKF again.
    again = mf.run(loop_log_300, "batch", upstream=up)
    np.testing.assert_array_equal(again.poses, batch.poses)


def test_errors_without_a_reference_say_so(loop_log_300: MeasurementLog) -> None:
    import dataclasses

    log = dataclasses.replace(loop_log_300, true_poses=None)
    run = mf.run(log, "ekf")
    assert run.truth is None
    with pytest.raises(ValueError, match="no truth and no GPS"):
        _ = run.errors
