"""The TUM files of a run, read back with evo: frames, content, and evo's APE = our RMSE."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from evo.core import metrics as evo_metrics
from evo.core.trajectory import PoseTrajectory3D
from evo.tools import file_interface

from mapfuse.comparison import compare, write_comparison
from mapfuse.outputs import write_outputs
from mapfuse.runner import Run, run
from mapfuse.trajectories import TRAJECTORY_FILES
from mapfuse_core.evaluation import truth_in_global
from mapfuse_core.geometry.se2 import compose, wrap_angle
from mapfuse_core.measlog import MeasurementLog
from tests.synthetic import synthetic_log


@pytest.fixture(scope="module")
def log() -> MeasurementLog:
    return synthetic_log(120, 3)


@pytest.fixture(scope="module")
def isam2_run(log: MeasurementLog) -> Run:
    return run(log, "isam2", fusion=True)


def _read(path: Path) -> PoseTrajectory3D:
    traj = file_interface.read_tum_trajectory_file(str(path))
    assert isinstance(traj, PoseTrajectory3D)
    return traj


def _planar(traj: PoseTrajectory3D) -> np.ndarray:
    """(N, 3) ``(x, y, θ)`` of an evo trajectory (yaw from its quaternions, wxyz)."""
    q = traj.orientations_quat_wxyz
    yaw = 2.0 * np.arctan2(q[:, 3], q[:, 0])
    assert np.allclose(q[:, 1:3], 0.0)
    assert np.allclose(traj.positions_xyz[:, 2], 0.0)
    return np.column_stack([traj.positions_xyz[:, :2], wrap_angle(yaw)])


def _same_poses(a: np.ndarray, b: np.ndarray) -> None:
    # The files hold 9 decimals: 1e-8 covers the rounding.
    assert np.allclose(a[:, :2], b[:, :2], atol=1e-8, rtol=0)
    assert np.allclose(wrap_angle(a[:, 2] - b[:, 2]), 0.0, atol=1e-8)


def _ape(ref: PoseTrajectory3D, est: PoseTrajectory3D, relation: object) -> dict[str, float]:
    ape = evo_metrics.APE(relation)  # type: ignore[arg-type]
    ape.process_data((ref, est))
    return ape.get_all_statistics()  # type: ignore[no-any-return]


def test_every_isam2_trajectory_round_trips_through_evo(
    isam2_run: Run, log: MeasurementLog, tmp_path: Path
) -> None:
    paths = write_outputs(isam2_run, tmp_path, figures=False)
    res = isam2_run.result
    assert res.filtered is not None
    assert res.smoothed is not None
    assert res.anchor is not None
    n = res.n_steps
    truth = log.true_poses
    assert truth is not None
    anchor = res.anchor.x_Wknown_Wglobal
    expected = {
        "trajectory": res.smoothed.poses,
        "trajectory_smoothed": res.smoothed.poses,
        "trajectory_filtered": res.filtered.poses,
        "trajectory_known": np.array([compose(anchor, p) for p in res.smoothed.poses]),
        "truth": truth_in_global(truth[:n]),
        "truth_known": truth[:n],
    }
    assert {k for k in paths if k.startswith(("trajectory", "truth"))} == set(expected)
    assert "reference" not in paths  # simulation: truth, not GPS
    for name, poses in expected.items():
        assert paths[name] == str(tmp_path / f"{name}.tum")
        header = (tmp_path / f"{name}.tum").read_text().splitlines()[0]
        assert header == f"# {TRAJECTORY_FILES[name + '.tum']}"
        traj = _read(tmp_path / f"{name}.tum")
        assert np.allclose(traj.timestamps, isam2_run.timestamps, atol=1e-9, rtol=0)
        _same_poses(_planar(traj), poses)


def test_evo_ape_without_alignment_equals_our_rmse(isam2_run: Run, tmp_path: Path) -> None:
    write_outputs(isam2_run, tmp_path, figures=False)
    m = isam2_run.metrics
    ref = _read(tmp_path / "truth.tum")
    pos = _ape(ref, _read(tmp_path / "trajectory.tum"), evo_metrics.PoseRelation.translation_part)
    # 9-decimal files: the statistics agree far below a micrometre.
    assert m.position_error is not None
    for stat in ("rmse", "mean", "median", "max"):
        assert pos[stat] == pytest.approx(getattr(m.position_error, stat), abs=1e-8), stat
    head = _ape(
        ref, _read(tmp_path / "trajectory.tum"), evo_metrics.PoseRelation.rotation_angle_rad
    )
    assert m.heading_error is not None
    assert head["rmse"] == pytest.approx(m.heading_error.rmse, abs=1e-8)
    filt = _ape(
        ref,
        _read(tmp_path / "trajectory_filtered.tum"),
        evo_metrics.PoseRelation.translation_part,
    )
    assert m.position_error_filtered is not None
    assert filt["rmse"] == pytest.approx(m.position_error_filtered.rmse, abs=1e-8)
    # In the known-map frame, step 0 is the anchor itself (X_0 is held at the origin of
    # Wglobal by a tight prior) and its truth the true start pose: the error there is
    # the anchor's position error of metrics.json.
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data(
        (_read(tmp_path / "truth_known.tum"), _read(tmp_path / "trajectory_known.tum"))
    )
    assert m.anchor is not None
    assert ape.error[0] == pytest.approx(m.anchor.position_error_m, abs=1e-6)


def test_ekf_without_fusion_has_no_known_frame_nor_second_estimate(
    log: MeasurementLog, tmp_path: Path
) -> None:
    r = run(log, "ekf", fusion=False)
    paths = write_outputs(r, tmp_path, figures=False)
    tums = sorted(p.name for p in tmp_path.glob("*.tum"))
    assert tums == ["trajectory.tum", "truth.tum", "truth_known.tum"]
    assert "trajectory" in paths


def test_gps_reference_on_real_like_data(tmp_path: Path) -> None:
    base = synthetic_log(80, 4)
    assert base.true_poses is not None
    # A real-data-like log: GPS fixes at every other step.
    t = np.asarray(base.timestamps[::2], dtype=float)
    xy = np.array(base.true_poses[::2, :2], dtype=float)
    real = dataclasses.replace(base, true_poses=None, world=None, gps_times=t, gps_xy=xy)
    r = run(real, "ekf", fusion=False)
    write_outputs(r, tmp_path, figures=False)
    assert not (tmp_path / "truth.tum").exists()
    lines = (tmp_path / "reference.tum").read_text().splitlines()
    assert "orientation unknown" in lines[0]
    traj = _read(tmp_path / "reference.tum")
    assert np.allclose(traj.timestamps, t, atol=1e-9, rtol=0)
    assert np.allclose(traj.positions_xyz[:, :2], xy, atol=1e-8, rtol=0)
    assert np.allclose(traj.orientations_quat_wxyz, [1.0, 0.0, 0.0, 0.0])


def test_compare_writes_each_runs_files(log: MeasurementLog, tmp_path: Path) -> None:
    cmp_ = compare(log.head(60), ["ekf", "isam2"])
    paths = write_comparison(cmp_, tmp_path)
    for folder in ("ekf_fusion", "ekf_no_fusion", "isam2_fusion", "isam2_no_fusion"):
        d = tmp_path / "runs" / folder
        assert (d / "metrics.json").is_file()
        assert (d / "trajectory.tum").is_file()
        assert (d / "truth.tum").is_file()
        assert paths[f"runs/{folder}/trajectory"] == str(d / "trajectory.tum")
    assert (tmp_path / "runs" / "isam2_fusion" / "trajectory_filtered.tum").is_file()
    assert (tmp_path / "runs" / "ekf_fusion" / "trajectory_known.tum").is_file()
    assert not list((tmp_path / "runs").glob("*/*.png"))
    r = cmp_.get("isam2", True)
    traj = _read(tmp_path / "runs" / "isam2_fusion" / "trajectory.tum")
    _same_poses(_planar(traj), r.poses)
