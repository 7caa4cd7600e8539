"""Run a backend on a measurement log and write the standard outputs.

The library side of ``mapfuse run``: a log in, a :class:`RunOutput` out, and
:func:`write_outputs` for ``metrics.json``, ``trajectory.tum`` and ``errors.png``.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ekf_reference import EKFConfig, ekf_metrics, run_ekf, save_associations
from ekf_reference.loops import LoopClosureParams
from ekf_reference.result import EKFResult
from mapfuse_core.evaluation import pose_errors, truth_in_global, write_tum
from mapfuse_core.measlog import MeasurementLog, load_log
from mapfuse_core.scenario import load_scenario
from mapfuse_core.se2 import FloatArray
from mapfuse_core.simulate import simulate
from mapfuse_graph.graph import GraphOptions, centre_radius_correlated
from mapfuse_graph.solvers import GraphResult, ISAM2Options, graph_metrics, run_graph

__all__ = [
    "BACKENDS",
    "RunOutput",
    "default_ekf_config",
    "default_graph_options",
    "default_isam2_options",
    "prepare_log",
    "run_backend",
    "write_outputs",
]

BACKENDS = ("ekf", "batch", "isam2")
ASSOCIATIONS = ("ekf", "truth", "own")


@dataclass(frozen=True)
class RunOutput:
    """What any backend returns: the metrics and the per-step estimates."""

    metrics: dict[str, Any]
    """The ``metrics.json`` object."""
    timestamps: FloatArray
    """(N,) step times (s)."""
    poses: FloatArray
    """(N, 3) vehicle pose in ``Wglobal``."""
    covs: FloatArray
    """(N, 3, 3) its covariance."""
    log: MeasurementLog
    """The log the run consumed."""
    ekf: EKFResult | None = None
    """The full EKF result (EKF backend, and graph runs that used its decisions)."""
    graph: GraphResult | None = None
    """The full graph result (batch and isam2 backends)."""


DATASETS = ("carpark", "victoria-park")


def prepare_log(
    source: str,
    seed: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    data_dir: str | None = None,
) -> MeasurementLog:
    """A log from a ``.npz`` file, a real dataset (``carpark``, ``victoria-park``, needs
    ``data_dir``), or by simulating a scenario (built-in name or TOML)."""
    if source.endswith(".npz"):
        return load_log(source)
    if source in DATASETS:
        if data_dir is None:
            raise ValueError(f"dataset {source!r} needs a data directory (--data DIR)")
        from mapfuse_core.datasets import load_carpark, load_victoria_park

        loader = load_carpark if source == "carpark" else load_victoria_park
        return loader(data_dir)
    return simulate(load_scenario(source), seed=seed, progress=progress).log


def default_ekf_config(log: MeasurementLog, fusion: bool = True) -> EKFConfig:
    """The EKF configuration ``mapfuse`` uses for ``log``: the defaults, except on
    Victoria Park.

    Victoria Park's 7,230 scans hold 53k tree detections, a quarter of which are seen
    once (trunks far away or behind others), so the global map grows to well over a
    thousand features and every join costs O(F²).  Local maps of 200 scans (43 s of
    driving) make 5× fewer joins than the default 40, and features seen in a single scan
    of their local map are dropped before the join (``min_obs_to_join=2``): with the
    first calibration and no loop closure the whole run kept 1,689 features instead of
    2,976 and took 76 s of CPU instead of 237 s.

    Loops are closed at the joins by registering the local map's trees to the global
    map's (``loop_closure``, :mod:`ekf_reference.loops`), and every local tree gets
    0.1 m of viewpoint error at its join (``join_circle_sigma_m``).  With the first
    calibration's laser yaw (−0.0235 rad) and without them, the filter's relative pose
    between a local map and the global map was up to 4° and 10 m off (σ 0.5°) when the
    car came back from the park's western arm; the trees it saw became a second copy of
    the park that the rest of the run followed (10–20 m off GPS after t ≈ 1,150 s).
    With them: median 1.76 m (RMSE 3.86 m) against GPS instead of 2.97 m (6.49 m).  With
    the odometry's sideways slip (``VICTORIA_PARK_ODOMETRY_NOISE``, chosen where these
    closures stop turning one way) the GPS error hardly depends on them (median 0.82 m,
    RMSE 2.48 m; without them 0.84 m, 2.48 m; every RMSE here includes one GPS fix about
    130 m off, at t ≈ 1,222 s), but without them revisited trees get more second copies:
    964 features of which 287 pairs lie within 1 m of each other, against 940 and 247.
    """
    from mapfuse_core.datasets import VICTORIA_PARK_NAME

    if log.scenario == VICTORIA_PARK_NAME:
        return EKFConfig(
            fusion=fusion,
            local_map_steps=200,
            min_obs_to_join=2,
            loop_closure=LoopClosureParams(),
            join_circle_sigma_m=0.1,
        )
    return EKFConfig(fusion=fusion)


def default_graph_options(
    log: MeasurementLog, association: str = "ekf", robust: str | None = None
) -> GraphOptions:
    """The graph options ``mapfuse`` uses for ``log``: the defaults, except on Victoria
    Park with a fixed association and no robust kernel, where circle landmarks are split
    into a centre and a radius variable (:attr:`GraphOptions.split_circles`; its
    detections' diameter noise is independent of the centre's, so the model is the same):
    8–13 % less iSAM2 CPU over the whole run.  ``fusion`` and ``association`` themselves are
    set by :func:`~mapfuse_graph.solvers.run_graph`."""
    from mapfuse_core.datasets import VICTORIA_PARK_NAME

    if (
        log.scenario == VICTORIA_PARK_NAME
        and association != "own"
        and robust is None
        and centre_radius_correlated(log) is None
    ):
        return GraphOptions(split_circles=True)
    return GraphOptions()


def default_isam2_options(log: MeasurementLog) -> ISAM2Options:
    """The iSAM2 settings ``mapfuse`` uses for ``log``: the defaults, except on Victoria
    Park, where relinearisation is checked every 10 updates instead of every one (GTSAM's
    own default): on its first 800 scans the estimates agree to the millimetre and the
    CPU time halves (15.2 s → 7.5 s)."""
    from mapfuse_core.datasets import VICTORIA_PARK_NAME

    if log.scenario == VICTORIA_PARK_NAME:
        return ISAM2Options(relinearize_skip=10)
    return ISAM2Options()


def run_backend(
    log: MeasurementLog,
    backend: str,
    fusion: bool = True,
    association: str = "ekf",
    robust: str | None = None,
    ekf_result: EKFResult | None = None,
    progress: Callable[[int, int], None] | None = None,
    joint_stride: int | None = None,
) -> RunOutput:
    """Run ``backend`` on ``log``.

    ``joint_stride`` (batch) also keeps the joint covariance of every
    ``joint_stride``-th pose (``run.graph.joint_pose_cov``).

    Graph backends with ``association="ekf"`` consume the EKF's saved decisions: the
    EKF (same ``fusion``) is run first unless ``ekf_result`` is given.  On a log without
    a known map there is nothing to fuse: the run is made, and reported, without fusion.
    """
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    if association not in ASSOCIATIONS:
        raise ValueError(
            f"unknown association {association!r}; choose one of {', '.join(ASSOCIATIONS)}"
        )
    fusion = log.fuses(fusion)
    if backend == "ekf":
        res = run_ekf(log, default_ekf_config(log, fusion), progress=progress)
        return RunOutput(
            metrics=ekf_metrics(res, log),
            timestamps=log.timestamps,
            poses=res.poses,
            covs=res.covs,
            log=log,
            ekf=res,
        )
    if association == "ekf" and ekf_result is None:
        ekf_result = run_ekf(log, default_ekf_config(log, fusion))
    g = run_graph(
        log,
        backend=backend,
        fusion=fusion,
        association=association,
        ekf_result=ekf_result,
        robust=robust,
        progress=progress,
        options=default_graph_options(log, association, robust),
        isam2=default_isam2_options(log),
        joint_stride=joint_stride,
    )
    return RunOutput(
        metrics=graph_metrics(g, log),
        timestamps=log.timestamps[: g.poses.shape[0]],
        poses=g.poses,
        covs=g.covs,
        log=log,
        ekf=ekf_result,
        graph=g,
    )


def write_outputs(run: RunOutput, out: str | Path) -> dict[str, str]:
    """Write ``metrics.json``, ``trajectory.tum``, ``errors.png`` (and EKF associations).

    Real data with GPS gets ``gps_errors.png`` and ``gps_trajectory.png`` instead of
    ``errors.png``, which needs true poses.
    """
    from mapfuse_core.plotting import errors_figure

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"metrics": out / "metrics.json", "trajectory": out / "trajectory.tum"}
    paths["metrics"].write_text(json.dumps(run.metrics, indent=2) + "\n")
    write_tum(paths["trajectory"], run.timestamps, run.poses)
    if run.log.true_poses is not None:
        err = pose_errors(run.poses, truth_in_global(run.log.true_poses))
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
        from mapfuse_graph.figures import gps_error_figure, gps_trajectory_figure

        paths["gps_errors"] = out / "gps_errors.png"
        gps_error_figure([run]).savefig(paths["gps_errors"], dpi=110)
        paths["gps_trajectory"] = out / "gps_trajectory.png"
        gps_trajectory_figure([run]).savefig(paths["gps_trajectory"], dpi=110)
    if run.ekf is not None and run.graph is None:
        paths["associations"] = save_associations(run.ekf, out / "associations.npz")
    return {k: str(v) for k, v in paths.items()}
