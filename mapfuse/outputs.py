"""The files of one run: ``metrics.json``, ``trajectory.tum``, the error figures and
the association decisions."""

from __future__ import annotations

import json
from pathlib import Path

from mapfuse.run import Run
from mapfuse_core.evaluation import pose_errors, truth_in_global, write_tum

__all__ = ["write_outputs"]


def write_outputs(run: Run, out: str | Path) -> dict[str, str]:
    """Write ``metrics.json``, ``trajectory.tum``, ``errors.png`` and, when the run
    decided its own associations, ``associations.npz``.

    Real data with GPS gets ``gps_errors.png`` and ``gps_trajectory.png`` instead of
    ``errors.png``, which needs true poses.
    """
    from mapfuse.figures import gps_error_figure, gps_trajectory_figure
    from mapfuse.plotting import errors_figure

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"metrics": out / "metrics.json", "trajectory": out / "trajectory.tum"}
    paths["metrics"].write_text(json.dumps(run.metrics, indent=2) + "\n")
    write_tum(paths["trajectory"], run.timestamps, run.poses)
    if run.log.true_poses is not None:
        n = run.poses.shape[0]
        err = pose_errors(run.poses, truth_in_global(run.log.true_poses[:n]))
        m = run.metrics
        title = (
            f"{m['backend']} ({'with' if m['fusion'] else 'without'} map fusion), "
            f"{m['scenario']} seed {m['seed']}: errors and 2σ bounds"
        )
        fig = errors_figure(run.timestamps, err.dx, run.covs, title)
        paths["errors"] = out / "errors.png"
        fig.savefig(paths["errors"], dpi=110)
    elif isinstance(run.metrics.get("position_error_m"), dict):
        # Real data: no truth for errors.png; the GPS comparison stands in for it.
        paths["gps_errors"] = out / "gps_errors.png"
        gps_error_figure([run]).savefig(paths["gps_errors"], dpi=110)
        paths["gps_trajectory"] = out / "gps_trajectory.png"
        gps_trajectory_figure([run]).savefig(paths["gps_trajectory"], dpi=110)
    decisions = run.result.decisions
    if decisions is not None and run.result.association is None:
        paths["associations"] = decisions.save(out / "associations.npz")
    return {k: str(v) for k, v in paths.items()}
