"""The files of one run: ``metrics.json``, the TUM trajectories
(:mod:`mapfuse.trajectories`), the error figures and the association decisions."""

from __future__ import annotations

import json
from pathlib import Path

from mapfuse.runner import Run
from mapfuse.trajectories import write_trajectories

__all__ = ["write_outputs"]


def write_outputs(run: Run, out: str | Path, figures: bool = True) -> dict[str, str]:
    """Write ``metrics.json``, the TUM trajectories (``trajectory.tum`` and the others
    of :data:`mapfuse.trajectories.TRAJECTORY_FILES` the run has), ``errors.png`` and,
    when the run decided its own associations, ``associations.npz``.

    Real data with GPS gets ``gps_errors.png`` and ``gps_trajectory.png`` instead of
    ``errors.png``, which needs true poses.  ``figures=False`` writes no figure.
    Returns ``{name: path}``; trajectory entries are keyed by file name without
    ``.tum`` (``trajectory``, ``truth_known``, ...).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"metrics": out / "metrics.json"}
    paths["metrics"].write_text(json.dumps(run.metrics.to_json(), indent=2) + "\n")
    for name, p in write_trajectories(run, out).items():
        paths[name.removesuffix(".tum")] = p
    if figures:
        paths.update(_figures(run, out))
    decisions = run.result.decisions
    if decisions is not None and run.result.association is None:
        paths["associations"] = decisions.save(out / "associations.npz")
    return {k: str(v) for k, v in paths.items()}


def _figures(run: Run, out: Path) -> dict[str, Path]:
    """``errors.png`` (simulation) or the GPS figures (real data)."""
    from mapfuse.figures import gps_error_figure, gps_trajectory_figure
    from mapfuse.plotting import errors_figure

    paths: dict[str, Path] = {}
    errors = run.errors if run.truth is not None else None
    if errors is not None and errors.dx is not None:
        m = run.metrics
        title = (
            f"{m.estimator} ({'with' if m.fusion else 'without'} map fusion), "
            f"{m.scenario} seed {m.seed}: errors and 2σ bounds"
        )
        fig = errors_figure(run.timestamps, errors.dx, run.covs, title)
        paths["errors"] = out / "errors.png"
        fig.savefig(paths["errors"], dpi=110)
    elif run.metrics.position_error is not None:
        # Real data: no truth for errors.png; the GPS comparison stands in for it.
        paths["gps_errors"] = out / "gps_errors.png"
        gps_error_figure([run]).savefig(paths["gps_errors"], dpi=110)
        paths["gps_trajectory"] = out / "gps_trajectory.png"
        gps_trajectory_figure([run]).savefig(paths["gps_trajectory"], dpi=110)
    return paths
