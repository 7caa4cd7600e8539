"""A script without an ``if __name__ == "__main__":`` guard simulates through the harness
and runs the estimators cleanly: the README's plug-in example, saved as a file."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from mapfuse_core.sim.simulate import _MIN_PARALLEL_STEPS, extraction_workers

ROOT = Path(__file__).resolve().parents[1]


def _readme_example() -> str:
    """The Python block of the README's section "Your own estimator"."""
    section = (ROOT / "README.md").read_text().split("## Your own estimator", 1)[1]
    return section.split("```python\n", 1)[1].split("```", 1)[0]


def _short_loop600(tmp_path: Path) -> Path:
    """loop600 cut to the shortest run that is long enough for an extraction pool."""
    toml = (ROOT / "mapfuse_core" / "sim" / "scenarios" / "loop600.toml").read_text()
    assert "\nsteps = 2400\n" in toml
    path = tmp_path / "loop600-short.toml"
    path.write_text(toml.replace("\nsteps = 2400\n", f"\nsteps = {_MIN_PARALLEL_STEPS}\n", 1))
    return path


def test_the_readme_plugin_example_runs_as_a_plain_script(tmp_path: Path) -> None:
    # The run is long enough that a pool would be started if asked for.
    assert extraction_workers(2, _MIN_PARALLEL_STEPS) == 2
    script = tmp_path / "example.py"
    script.write_text(
        "from mapfuse.run import prepare_log\n"
        f"log = prepare_log({str(_short_loop600(tmp_path))!r})\n"
        + _readme_example()
        + "print('example done', log.n_steps)\n"
    )
    proc = subprocess.run(
        [sys.executable, str(script)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    assert f"example done {_MIN_PARALLEL_STEPS}" in proc.stdout
    for bad in ("Traceback", "RuntimeError", "pool broke"):
        assert bad not in proc.stderr, proc.stderr
