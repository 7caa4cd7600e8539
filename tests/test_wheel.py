"""The wheel: carries the scenarios, the README and the licence, and its quick start
works from a fresh virtual environment outside the repository."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_wheel_installs_and_simulates_outside_the_repository(tmp_path: Path) -> None:
    dist = tmp_path / "dist"
    build = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "-q",
            "-w",
            str(dist),
            str(ROOT),
        ],
        capture_output=True,
        text=True,
        check=False,
        timeout=600,
    )
    assert build.returncode == 0, build.stderr
    (wheel,) = dist.glob("mapfuse-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert "mapfuse_core/sim/scenarios/loop600.toml" in names
    assert any(n.endswith(".dist-info/licenses/LICENSE") for n in names)
    meta = next(n for n in names if n.endswith(".dist-info/METADATA"))
    readme_title = (ROOT / "README.md").read_text().splitlines()[0]
    assert readme_title in zipfile.ZipFile(wheel).read(meta).decode()
    assert not any(n.startswith(("tests/", "notebooks/", "benchmarks/")) for n in names)

    # A fresh venv; the dependencies come from this interpreter's site-packages through
    # a .pth file (offline and fast), after the venv's own, so the wheel's mapfuse wins.
    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=True)
    py = env_dir / "bin" / "python"
    site = subprocess.run(
        [str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    (Path(site) / "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    inst = subprocess.run(
        [str(py), "-m", "pip", "install", "--no-deps", "--no-index", "-q", str(wheel)],
        capture_output=True,
        text=True,
        check=False,
        timeout=600,
    )
    assert inst.returncode == 0, inst.stderr
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env["OPENBLAS_NUM_THREADS"] = "1"
    where = subprocess.run(
        [str(py), "-c", "import mapfuse_core, mapfuse; print(mapfuse_core.__file__)"],
        capture_output=True,
        text=True,
        check=True,
        cwd=work,
        env=env,
    ).stdout.strip()
    assert Path(where).is_relative_to(env_dir), where  # the wheel's copy, not the repo's
    mapfuse = env_dir / "bin" / "mapfuse"
    version = subprocess.run(
        [str(mapfuse), "--version"], capture_output=True, text=True, check=True, env=env
    )
    assert version.stdout.startswith("mapfuse ")
    sim = subprocess.run(
        [str(mapfuse), "simulate", "loop600", "--out", "out", "--quiet"],
        capture_output=True,
        text=True,
        check=False,
        cwd=work,
        env=env,
        timeout=900,
    )
    assert sim.returncode == 0, sim.stderr
    summary = json.loads(sim.stdout)
    assert summary["steps"] == 2400
    assert (work / "out" / "log.npz").is_file()
