"""Plot helpers.  Each draws on a given matplotlib ``Axes`` and never calls ``show()``.

Part of the harness: the numeric packages (``mapfuse_core``, ``ekf_reference``,
``mapfuse_graph``) never import matplotlib.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray, compose, transform_point
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog
from mapfuse_core.sim.world import World

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from mapfuse.runner import Run
    from mapfuse_core.sensor import Scan

__all__ = [
    "draw_circle",
    "draw_line_feature",
    "errors_figure",
    "plot_errors_with_bounds",
    "plot_known_map",
    "plot_scan",
    "plot_trajectory",
    "plot_world",
    "run_error_axes",
    "world_figure",
]


def draw_circle(ax: Axes, c: FloatArray, **kw: object) -> None:
    """Draw circle ``(x, y, r)`` as an outline."""
    from matplotlib.patches import Circle

    kw.setdefault("fill", False)
    ax.add_patch(Circle((float(c[0]), float(c[1])), float(c[2]), **kw))


def draw_line_feature(
    ax: Axes, line: FloatArray, extent: tuple[float, float] = (-5.0, 5.0), **kw: object
) -> None:
    """Draw an SPmap line ``(x, y, θ)`` from ``extent[0]`` to ``extent[1]`` along it."""
    c, s = math.cos(line[2]), math.sin(line[2])
    t = np.array(extent, dtype=float)
    ax.plot(line[0] + t * c, line[1] + t * s, **kw)  # type: ignore[arg-type]


def plot_world(ax: Axes, world: World, color: str = "0.35", label: str = "world") -> None:
    """Walls as segments, circles as outlines."""
    for i, s in enumerate(world.segments):
        ax.plot(
            [s.p1[0], s.p2[0]],
            [s.p1[1], s.p2[1]],
            color=color,
            lw=1.5,
            label=label if i == 0 else None,
        )
    for i, c in enumerate(world.circles):
        draw_circle(
            ax,
            c.params(),
            color=color,
            lw=1.0,
            label=label if not world.segments and i == 0 else None,
        )


def plot_known_map(
    ax: Axes, known: KnownMapArrays, world: World | None = None, color: str = "tab:red"
) -> None:
    """Known-map features; lines drawn with the length of the matching world wall."""
    lengths = {s.id: s.length for s in world.segments} if world is not None else {}
    first = True
    for fid, kind, p in zip(known.ids, known.kinds, known.params, strict=True):
        label = "known map" if first else None
        first = False
        if kind == FeatureKind.LINE:
            half = 0.5 * lengths.get(int(fid), 10.0)
            draw_line_feature(ax, p, (-half, half), color=color, lw=1.0, ls="--", label=label)
        else:
            draw_circle(ax, p, color=color, lw=1.0, ls="--", label=label)


def plot_trajectory(ax: Axes, poses: FloatArray, label: str = "trajectory", **kw: object) -> None:
    """Vehicle positions as a polyline, with a marker at the start."""
    ax.plot(poses[:, 0], poses[:, 1], label=label, **kw)  # type: ignore[arg-type]
    ax.plot(poses[0, 0], poses[0, 1], marker="o", color="k", ms=5, ls="none")


def plot_scan(
    ax: Axes,
    scan: Scan,
    x_W_S: FloatArray,
    log: MeasurementLog | None = None,
    step: int | None = None,
) -> None:
    """A scan's points in ``W`` and, from ``log`` at ``step``, its extracted features."""
    pts = scan.points()
    if pts.shape[0]:
        c, s = math.cos(x_W_S[2]), math.sin(x_W_S[2])
        w = pts @ np.array([[c, s], [-s, c]]) + x_W_S[:2]
        ax.plot(w[:, 0], w[:, 1], ".", ms=2, color="tab:blue", label="laser points")
    ax.plot(x_W_S[0], x_W_S[1], marker=(3, 0, math.degrees(x_W_S[2]) - 90), color="k", ms=9)
    if log is None or step is None:
        return
    sl = log.feature_slice(step)
    first_line = first_circle = True
    for kind, p, ext in zip(
        log.feat_kind[sl], log.feat_params[sl], log.feat_extent[sl], strict=True
    ):
        if kind == FeatureKind.LINE:
            pw = compose(x_W_S, p)
            draw_line_feature(
                ax,
                pw,
                (float(ext[0]), float(ext[1])),
                color="tab:green",
                lw=2.5,
                label="extracted line" if first_line else None,
            )
            first_line = False
        else:
            cw = np.array([*transform_point(x_W_S, p[:2]), p[2]])
            draw_circle(ax, cw, color="tab:orange", lw=2.0)
            if first_circle:
                ax.plot([], [], color="tab:orange", lw=2.0, label="extracted circle")
            first_circle = False


def world_figure(
    world: World,
    log: MeasurementLog,
    scan: Scan,
    step: int,
) -> Figure:
    """Two panels: world, known map and true trajectory; one scan with its features."""
    from matplotlib.figure import Figure

    if log.true_poses is None:
        raise ValueError("world_figure needs a simulated log with true poses")
    fig = Figure(figsize=(14, 6.5), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2)
    plot_world(ax1, world)
    plot_known_map(ax1, log.known_map, world)
    plot_trajectory(ax1, log.true_poses, color="tab:blue", lw=1.0, label="true trajectory")
    pose = log.true_poses[step]
    ax1.plot(
        pose[0], pose[1], marker="*", color="tab:green", ms=12, ls="none", label=f"step {step}"
    )
    ax1.set_title(f"{log.scenario}: world, known map ({len(log.known_map)} features), trajectory")
    plot_world(ax2, world)
    plot_scan(ax2, scan, pose, log, step)
    sl = log.feature_slice(step)
    ax2.set_title(f"scan at step {step}: {sl.stop - sl.start} features extracted")
    r = 45.0
    ax2.set_xlim(pose[0] - r, pose[0] + r)
    ax2.set_ylim(pose[1] - r, pose[1] + r)
    ax1.set_aspect("equal", adjustable="datalim")
    ax2.set_aspect("equal", adjustable="box")  # keeps the fixed zoom limits
    for ax in (ax1, ax2):
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    return fig


def plot_errors_with_bounds(
    axes: Sequence[Axes],
    t: FloatArray,
    dx: FloatArray,
    covs: FloatArray,
    label: str = "error",
    color: str = "tab:blue",
) -> None:
    """x, y, θ errors against time with ±2σ bounds (the paper's Fig. 6), one axis each."""
    names = ("x error [m]", "y error [m]", "θ error [rad]")
    for i, ax in enumerate(axes[:3]):
        sig = 2.0 * np.sqrt(np.maximum(covs[:, i, i], 0.0))
        ax.plot(t, dx[:, i], color=color, lw=1.0, label=label)
        ax.plot(t, sig, color="k", lw=0.8, label="±2σ" if i == 0 else None)
        ax.plot(t, -sig, color="k", lw=0.8)
        ax.set_ylabel(names[i])
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    axes[0].legend(loc="upper right", fontsize=8)


def errors_figure(t: FloatArray, dx: FloatArray, covs: FloatArray, title: str) -> Figure:
    """Three stacked panels of :func:`plot_errors_with_bounds`."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 7), layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)
    plot_errors_with_bounds(list(axes), t, dx, covs)
    fig.suptitle(title)
    return fig


def run_error_axes(run: Run, ax: Axes | None = None) -> Axes:
    """A run's position error against time on ``ax`` (a new figure's when ``None``):
    with the estimate's 2σ position bound (``2·√(σx² + σy²)``) against truth, at the
    fixes against GPS."""
    import matplotlib.pyplot as plt

    if ax is None:
        _, ax = plt.subplots(figsize=(8, 3.2), constrained_layout=True)
    err = run.errors
    label = f"{run.estimator} {'with' if run.fusion else 'without'} fusion"
    if err.reference == "truth":
        ax.plot(err.timestamps, err.position, lw=1.0, label=f"{label}: position error")
        if err.sigma is not None:
            bound = 2.0 * np.hypot(err.sigma[:, 0], err.sigma[:, 1])
            ax.plot(err.timestamps, bound, lw=0.8, ls="--", color="0.4", label="2σ bound")
    else:
        ax.plot(err.timestamps, err.position, ".", ms=3, label=f"{label}: error against GPS")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("position error [m]")
    ax.set_title(f"{run.log.scenario}, seed {run.log.seed}: RMSE {err.rmse:.3f} m")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    return ax
