"""A third-party estimator plugs into the harness: registered in-process with
``register()`` or through a ``mapfuse.estimators`` entry point, it runs through
``run``, ``compare`` (report row and every figure) and the baselines."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from mapfuse import registry
from mapfuse.baseline import check_log_against_baseline, record_baselines
from mapfuse.comparison import FIGURE_FILES, compare, write_comparison
from mapfuse.runner import run
from mapfuse_core.evaluation import pose_errors, truth_in_global
from mapfuse_core.measlog import MeasurementLog, save_log
from tests.synthetic import synthetic_log
from tests.toy_estimator import DeadReckoning

ROOT = Path(__file__).resolve().parents[1]
PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def log() -> MeasurementLog:
    return synthetic_log(120, 3)


@pytest.fixture
def toy() -> Iterator[DeadReckoning]:
    est = registry.register(DeadReckoning)
    assert isinstance(est, DeadReckoning)
    yield est
    registry.unregister("toy")


def test_registered_estimator_runs_and_is_scored(log: MeasurementLog, toy: DeadReckoning) -> None:
    assert "toy" in registry.available()
    assert registry.get("toy") is toy
    done = run(log, "toy", fusion=True)
    m = done.metrics
    assert (m.estimator, m.fusion, m.steps) == ("toy", False, log.n_steps)
    assert m.anchor is None
    assert m.to_json()["map"] == {
        "features": 0,
        "matched_known": 0,
        "seen_once": 0,
        "tentative_dropped": 0,
    }
    assert "association" not in m.to_json()
    assert "estimate" not in m.to_json()
    # Dead reckoning from the true start: its error is the odometry's drift, which the
    # metrics report exactly as computed from the poses.
    assert log.true_poses is not None
    err = pose_errors(done.poses, truth_in_global(log.true_poses)).position
    assert m.position_error is not None
    assert m.position_error.max == pytest.approx(float(err.max()), rel=1e-12)
    assert float(err[0]) < 1e-12  # truth_in_global's round-off at the start
    # Options come from the estimator's own type and can be overridden by field.
    wide = run(log, "toy", noise_scale=4.0)
    np.testing.assert_allclose(wide.covs[1:], 4.0 * done.covs[1:], rtol=1e-9)
    with pytest.raises(ValueError, match="has no option association"):
        run(log, "toy", association="truth")
    with pytest.raises(TypeError, match="takes DeadReckoningOptions"):
        run(log, "toy", options=object())


def test_register_refuses_a_taken_name_and_a_non_estimator(toy: DeadReckoning) -> None:
    with pytest.raises(ValueError, match="exists already"):
        registry.register(DeadReckoning())
    assert registry.register(DeadReckoning(), replace=True) is not toy
    with pytest.raises(TypeError, match="not a mapfuse estimator"):
        registry.register(lambda: object())  # type: ignore[arg-type, return-value]
    with pytest.raises(ValueError, match="unknown estimator 'nope'; choose one of ekf"):
        registry.get("nope")


def test_compare_reports_and_draws_the_plugin(
    log: MeasurementLog, toy: DeadReckoning, tmp_path: Path
) -> None:
    c = compare(log, ("ekf", "isam2", "toy"))
    # The toy cannot fuse: one run of it, reported without fusion.
    got = [(m.estimator, m.fusion) for m in c.metrics]
    assert got == [("ekf", True), ("isam2", True), ("ekf", False), ("isam2", False), ("toy", False)]
    paths = write_comparison(c, tmp_path)
    report = (tmp_path / "report.md").read_text()
    assert "| toy without fusion |" in report
    drawn = [n for n in FIGURE_FILES if not n.startswith("gps_")]
    for name in drawn:
        assert (tmp_path / name).read_bytes()[:8] == PNG, name
        assert paths[name.removesuffix(".png")] == str(tmp_path / name)
    # Without the EKF the toy alone still gets every figure that does not need it.
    alone = compare(log, ("toy",), fusions=(False,))
    write_comparison(alone, tmp_path / "alone")
    for name in drawn:
        if name != "fig6_errors_bounds.png":  # the EKF with fusion's own figure
            assert (tmp_path / "alone" / name).is_file(), name


def test_baseline_records_and_checks_the_plugin(log: MeasurementLog, toy: DeadReckoning) -> None:
    entries = record_baselines(log, estimators=("toy",))
    assert [(e.metrics.estimator, e.metrics.fusion) for e in entries] == [("toy", False)]
    reports = check_log_against_baseline(log, entries)
    assert [r.passed for r in reports] == [True]
    assert any(c.status == "pass" for c in reports[0].checks)
    # A worse toy fails its baseline: 3× the odometry drift is not within 10 %.
    worse = registry.register(_ScaledToy(), replace=True)
    assert worse.name == "toy"
    failed = check_log_against_baseline(log, entries)
    assert not failed[0].passed
    assert "position_error_m.rmse" in {c.metric for c in failed[0].failures}


class _ScaledToy(DeadReckoning):
    """The toy with every odometry increment tripled (a broken estimator)."""

    def run(self, log, options, *, fusion, upstream=None, progress=None):  # type: ignore[no-untyped-def]
        import dataclasses

        odo = log.odometry.copy()
        odo[:, :2] *= 3.0
        return super().run(dataclasses.replace(log, odometry=odo), options, fusion=fusion)


def _plugin_env(tmp_path: Path) -> dict[str, str]:
    """A PYTHONPATH whose only new distribution declares the toy as an entry point."""
    site = tmp_path / "site"
    info = site / "toy_plugin-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: toy-plugin\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        "[mapfuse.estimators]\ntoy = tests.toy_estimator:DeadReckoning\n"
    )
    return {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(site), str(ROOT)]),
        "OPENBLAS_NUM_THREADS": "1",
    }


def _mapfuse(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    code = "import sys; from mapfuse.cli import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, env=env
    )


@pytest.mark.slow
def test_entry_point_plugin_runs_from_the_command_line(log: MeasurementLog, tmp_path: Path) -> None:
    env = _plugin_env(tmp_path)
    path = str(save_log(log, tmp_path / "log.npz"))
    run_out = str(tmp_path / "run")
    done = _mapfuse(env, "run", path, "--estimator", "toy", "--out", run_out, "--quiet")
    assert done.returncode == 0, done.stderr
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert (metrics["backend"], metrics["steps"]) == ("toy", log.n_steps)
    assert (tmp_path / "run" / "errors.png").read_bytes()[:8] == PNG
    out = tmp_path / "cmp"
    cmp_ = _mapfuse(env, "compare", path, "--estimators", "ekf,toy", "--out", str(out), "--quiet")
    assert cmp_.returncode == 0, cmp_.stderr
    rows = json.loads((out / "comparison.json").read_text())
    assert [(m["backend"], m["fusion"]) for m in rows] == [
        ("ekf", True),
        ("ekf", False),
        ("toy", False),
    ]
    assert "| toy without fusion |" in (out / "report.md").read_text()
    bad = _mapfuse(env, "compare", path, "--estimators", "ekf,nope", "--out", str(out), "--quiet")
    assert bad.returncode == 2
    assert "unknown estimator 'nope'" in bad.stderr
