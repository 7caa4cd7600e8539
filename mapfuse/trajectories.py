"""The TUM trajectory files of a run, named by what they hold and in which frame.

TUM format (``t x y z qx qy qz qw``, one pose per line, ``#`` comments), readable by
evo and most SLAM evaluation tools; planar poses are written with ``z = 0`` and the
heading as a rotation about ``z`` (:func:`mapfuse_core.evaluation.write_tum`).

* ``trajectory.tum`` — the run's main estimate (smoothed when it has one) in
  ``Wglobal`` (the vehicle at step 0);
* ``trajectory_known.tum`` — the same poses in the known map's frame ``Wknown``,
  through the run's anchor ``x^Wknown_Wglobal`` (only when the run has an anchor);
* ``trajectory_filtered.tum`` and ``trajectory_smoothed.tum`` — both estimates, when
  the run has both (iSAM2: per-step filtered and final smoothed poses);
* ``truth.tum`` (``Wglobal``) and ``truth_known.tum`` (``Wknown``, which is the
  simulator's world frame) — the true poses, in simulation;
* ``reference.tum`` — real data: the GPS fixes in the GPS frame (= ``Wknown`` for the
  car park's surveyed beacons).  GPS has no orientation: it is written as the
  identity, which the file's header says, so compare positions only (evo:
  ``--pose_relation trans_part``).

``truth.tum`` against ``trajectory.tum`` is exactly what ``metrics.json``'s
``position_error_m`` scores (evo's APE without alignment gives the same RMSE).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapfuse.runner import Run
from mapfuse_core.evaluation import truth_in_global, write_tum
from mapfuse_core.geometry.se2 import FloatArray, compose

__all__ = ["TRAJECTORY_FILES", "Trajectory", "run_trajectories", "write_trajectories"]

#: Every file name :func:`write_trajectories` may write, and what it holds.
TRAJECTORY_FILES: dict[str, str] = {
    "trajectory.tum": "main estimate (smoothed when there is one) in Wglobal",
    "trajectory_known.tum": "main estimate in Wknown, through the run's anchor",
    "trajectory_filtered.tum": "filtered estimate (steps 0..k only) in Wglobal",
    "trajectory_smoothed.tum": "smoothed estimate (whole log) in Wglobal",
    "truth.tum": "true poses in Wglobal (simulation)",
    "truth_known.tum": "true poses in Wknown = the simulator's world frame (simulation)",
    "reference.tum": "GPS fixes in the GPS frame, orientation unknown (identity) (real data)",
}


@dataclass(frozen=True, eq=False)
class Trajectory:
    """One timed pose sequence to write as a TUM file."""

    timestamps: FloatArray
    """(N,) times (s)."""
    poses: FloatArray
    """(N, 3) planar poses ``(x, y, θ)``."""
    comment: str
    """What the poses are and in which frame (the file's first header line)."""


def _in_known(anchor: FloatArray, poses: FloatArray) -> FloatArray:
    return np.array([compose(anchor, p) for p in poses]).reshape(poses.shape)


def run_trajectories(run: Run) -> dict[str, Trajectory]:
    """The trajectories of ``run`` by file name (those of :data:`TRAJECTORY_FILES` it has)."""
    res, log = run.result, run.log
    t = np.asarray(run.timestamps, dtype=float)
    n = t.shape[0]
    out = {"trajectory.tum": Trajectory(t, run.poses, TRAJECTORY_FILES["trajectory.tum"])}
    if res.anchor is not None:
        a = np.asarray(res.anchor.x_Wknown_Wglobal, dtype=float)
        out["trajectory_known.tum"] = Trajectory(
            t, _in_known(a, run.poses), TRAJECTORY_FILES["trajectory_known.tum"]
        )
    if res.filtered is not None and res.smoothed is not None:
        out["trajectory_filtered.tum"] = Trajectory(
            t, res.filtered.poses, TRAJECTORY_FILES["trajectory_filtered.tum"]
        )
        out["trajectory_smoothed.tum"] = Trajectory(
            t, res.smoothed.poses, TRAJECTORY_FILES["trajectory_smoothed.tum"]
        )
    if log.true_poses is not None:
        truth = np.asarray(log.true_poses[:n], dtype=float)
        out["truth.tum"] = Trajectory(t, truth_in_global(truth), TRAJECTORY_FILES["truth.tum"])
        if len(log.known_map) > 0:
            out["truth_known.tum"] = Trajectory(t, truth, TRAJECTORY_FILES["truth_known.tum"])
    elif log.gps is not None:
        gt, gxy = (np.asarray(a, dtype=float) for a in log.gps)
        poses = np.column_stack([gxy, np.zeros(gt.shape[0])])
        out["reference.tum"] = Trajectory(gt, poses, TRAJECTORY_FILES["reference.tum"])
    return out


def write_trajectories(run: Run, out: str | Path) -> dict[str, Path]:
    """Write the TUM files of ``run`` into the folder ``out``; ``{file name: path}``."""
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    for name, tr in run_trajectories(run).items():
        paths[name] = write_tum(folder / name, tr.timestamps, tr.poses, comment=tr.comment)
    return paths
