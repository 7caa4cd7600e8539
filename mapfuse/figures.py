"""Figures of a backend comparison, after the paper's Figs. 6, 7 and 10.

Every function builds and returns a matplotlib :class:`~matplotlib.figure.Figure`
from finished results (never ``pyplot``, never ``show()``), with labelled axes in
units, a legend and a title; the caller saves or displays it.  Runs are the
:class:`mapfuse.runner.Run` of :func:`mapfuse.runner.run`; every figure reads only their
:class:`~mapfuse_core.estimate.EstimatorResult`, their log and their metrics, so any
registered estimator can be drawn.

Figures that compare against truth raise :class:`ValueError` for a log without true
poses (real data); :func:`fig10_maps` and :func:`timing_figure` work without truth.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from mapfuse.execution import fusion_for
from mapfuse.plotting import (
    draw_circle,
    draw_line_feature,
    plot_errors_with_bounds,
    plot_trajectory,
    plot_world,
)
from mapfuse.runner import Run
from mapfuse_core.evaluation import (
    CHI2_3_95,
    gps_error_series,
    nees_series,
    pose_errors,
    truth_in_global,
)
from mapfuse_core.geometry.features import FeatureKind, transform_feature
from mapfuse_core.geometry.se2 import FloatArray, compose, inverse
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog
from mapfuse_core.sim.world import World

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from mapfuse_core.matching.ccda import CCDAResult

__all__ = [
    "PAPER_ANCHOR_ESTIMATE",
    "PAPER_ANCHOR_TRUTH",
    "PAPER_FUSED_MAX_ERROR_M",
    "PAPER_UNFUSED_ERROR_M",
    "anchor_of",
    "ccda_figure",
    "fig6_errors_bounds",
    "fig7_error_fusion",
    "fig10_maps",
    "gps_error_figure",
    "gps_errors",
    "gps_trajectory_figure",
    "map_of",
    "nees_figure",
    "plot_map_arrays",
    "run_errors",
    "run_label",
    "step_times",
    "timing_figure",
]

#: Paper, Sect. 4.2: the fused vehicle position error stays below this along the loop (m).
PAPER_FUSED_MAX_ERROR_M = 0.15
#: Paper, Sect. 4.2: the unfused position error reaches about this far from the start (m).
PAPER_UNFUSED_ERROR_M = 0.50
#: Paper, Sect. 4.2: estimated pose of the start (``Wglobal``) in the known map.
PAPER_ANCHOR_ESTIMATE = (-28.968, -10.980, 1.0472)
#: Paper, Sect. 4.2: its true value.
PAPER_ANCHOR_TRUTH = (-29.0, -11.0, math.pi / 3)

# One colour per backend, one line style per fusion setting, in every figure.
_COLOURS = {"ekf": "tab:blue", "batch": "tab:orange", "isam2": "tab:green"}
_STYLES = {True: "-", False: "--"}


def run_label(run: Run) -> str:
    """``"ekf with fusion"``-style label of a run; just the backend on a log without a
    known map (Victoria Park), where there is nothing to fuse either way."""
    if not fusion_for(run.log, True):
        return run.estimator
    return f"{run.estimator} {'with' if run.fusion else 'without'} fusion"


def _colour(run: Run) -> str:
    return _COLOURS.get(run.estimator, "tab:gray")


def _style(run: Run) -> str:
    return _STYLES[run.fusion]


def _truth(log: MeasurementLog, n: int) -> FloatArray:
    if log.true_poses is None:
        raise ValueError(f"log {log.scenario!r} has no true poses: this figure needs truth")
    return truth_in_global(log.true_poses[:n])


def run_errors(run: Run) -> tuple[FloatArray, FloatArray]:
    """Per-step ``(dx (N, 3), NEES (N,))`` of a run against truth in ``Wglobal``."""
    err = pose_errors(run.poses, _truth(run.log, run.poses.shape[0]))
    return err.dx, nees_series(err.dx, run.covs)


def step_times(run: Run) -> FloatArray:
    """(N,) wall time of each step of a run (s)."""
    return run.result.step_time_s


def anchor_of(run: Run) -> FloatArray | None:
    """The run's estimated ``x^Wknown_Wglobal``, or ``None`` (no fusion, no match)."""
    anchor = run.result.anchor
    return None if anchor is None else np.asarray(anchor.x_Wknown_Wglobal, dtype=float)


def map_of(run: Run) -> tuple[np.ndarray, FloatArray, np.ndarray, np.ndarray]:
    """The run's final map in ``Wglobal``: ``(kinds, params, known_ids, n_obs)``."""
    mp = run.result.map
    return mp.kinds, mp.params, mp.known_ids, mp.n_obs


def _finish(ax: Axes, xlabel: str, ylabel: str, title: str, legend: bool = True) -> None:
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if legend:
        ax.legend(loc="best", fontsize=8)


# --------------------------------------------------------------------------- Fig. 6


def fig6_errors_bounds(run: Run) -> Figure:
    """x, y, θ errors of one run (the paper: EKF with fusion) with ±2σ bounds."""
    from matplotlib.figure import Figure

    dx, _ = run_errors(run)
    fig = Figure(figsize=(9, 7), layout="constrained")
    axes = list(fig.subplots(3, 1, sharex=True))
    t = run.timestamps
    plot_errors_with_bounds(axes, t, dx, run.covs, label=run_label(run), color=_colour(run))
    anchor = run.metrics.anchor
    if anchor is not None:
        # Where CCDA accepted the match: the bounds shrink there.
        ta = float(t[min(anchor.accepted_at_step, t.shape[0] - 1)])
        for i, ax in enumerate(axes):
            ax.axvline(ta, color="tab:red", lw=0.8, ls=":", label="map matched" if i == 0 else None)
        axes[0].legend(loc="upper right", fontsize=8)
    m = run.metrics
    fig.suptitle(
        f"Fig. 6: vehicle errors and 2σ bounds, {run_label(run)} "
        f"({m.scenario}, seed {m.seed}, {m.steps} steps)"
    )
    return fig


# --------------------------------------------------------------------------- Fig. 7


def fig7_error_fusion(runs: Sequence[Run], paper_reference: bool = True) -> Figure:
    """Position error against time of several runs (with and without fusion).

    ``paper_reference`` draws the paper's two levels (fused < 0.15 m, unfused ≈ 0.5 m).
    """
    from matplotlib.figure import Figure

    if not runs:
        raise ValueError("fig7_error_fusion needs at least one run")
    fig = Figure(figsize=(10, 5), layout="constrained")
    ax = fig.subplots()
    for run in runs:
        dx, _ = run_errors(run)
        ax.plot(
            run.timestamps,
            np.hypot(dx[:, 0], dx[:, 1]),
            color=_colour(run),
            ls=_style(run),
            lw=1.0,
            label=run_label(run),
        )
    if paper_reference:
        ax.axhline(
            PAPER_FUSED_MAX_ERROR_M, color="k", lw=0.8, ls=":", label="paper: fused max 0.15 m"
        )
        ax.axhline(
            PAPER_UNFUSED_ERROR_M, color="0.5", lw=0.8, ls=":", label="paper: unfused ≈ 0.50 m"
        )
    ax.set_ylim(bottom=0.0)
    m = runs[0].metrics
    _finish(
        ax,
        "time [s]",
        "position error [m]",
        f"Fig. 7: vehicle position error with and without map fusion ({m.scenario}, seed {m.seed})",
    )
    return fig


# --------------------------------------------------------------------------- Fig. 10


def plot_map_arrays(
    ax: Axes,
    kinds: np.ndarray,
    params: FloatArray,
    extents: FloatArray | None = None,
    default_extent: tuple[float, float] = (-4.0, 4.0),
    label: str | None = None,
    **style: object,
) -> None:
    """Map features: circles as outlines, lines over their extent (or ``default_extent``)."""
    first = True
    for i, (kind, p) in enumerate(zip(kinds, params, strict=True)):
        lab = label if first else None
        first = False
        if int(kind) == FeatureKind.LINE:
            ext = default_extent
            if extents is not None and np.all(np.isfinite(extents[i])):
                ext = (float(extents[i, 0]), float(extents[i, 1]))
            draw_line_feature(ax, p, ext, label=lab, **style)
        else:
            draw_circle(ax, p, label=lab, **style)


def _in_frame(T: FloatArray, kinds: np.ndarray, params: FloatArray) -> FloatArray:
    """Features given in frame ``T`` re-expressed in ``T``'s parent frame."""
    return np.array(
        [
            transform_feature(FeatureKind(int(k)), T, p)[0]
            for k, p in zip(kinds, params, strict=True)
        ]
    ).reshape(-1, 3)


def _display_frame(run: Run) -> tuple[FloatArray, str]:
    """Where Fig. 10 draws a run: its anchor, else the true start, the GPS fit, or none."""
    T = anchor_of(run)
    if T is not None:
        return T, "through its estimated anchor"
    if run.log.true_poses is not None:
        return np.asarray(run.log.true_poses[0], dtype=float), "through the true start pose"
    gps_fit = _gps_alignment(run)
    if gps_fit is not None:
        return gps_fit, "through its best fit to GPS"
    return np.zeros(3), "in Wglobal (no anchor, no truth)"


def fig10_maps(
    runs: Sequence[Run],
    world: World | None = None,
    line_extent_m: tuple[float, float] = (-4.0, 4.0),
) -> Figure:
    """Estimated map and trajectory of each run over the known map, in ``Wknown``.

    One panel per run; features never observed (the known features an EKF with fusion
    holds) are not drawn as estimates.  The estimates are moved into the known-map frame through the
    run's own anchor ``x^Wknown_Wglobal``; a run without an anchor (no fusion) is
    drawn through the true start pose when the log has truth (said in the title),
    else in ``Wglobal``.  The true world (``world``, else the log's world arrays) and
    the true trajectory (or the GPS track of real data) are drawn underneath.
    Estimated lines are drawn over ``line_extent_m`` along them (m from their reference
    point; short indoor walls want a shorter piece than the default).
    """
    from matplotlib.figure import Figure

    if not runs:
        raise ValueError("fig10_maps needs at least one run")
    fig = Figure(figsize=(7.5 * len(runs), 7.5), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(runs)))
    for ax, run in zip(axes, runs, strict=True):
        log = run.log
        T, how = _display_frame(run)
        if world is not None:
            plot_world(ax, world, color="0.75", label="true world")
        elif log.world is not None:
            plot_map_arrays(
                ax,
                log.world.kinds,
                log.world.params,
                log.world.extents,
                color="0.75",
                lw=1.0,
                label="true world",
            )
        known = log.known_map
        plot_map_arrays(
            ax,
            known.kinds,
            known.params,
            known.extents,
            color="tab:red",
            lw=1.0,
            ls="--",
            label="known map",
        )
        if log.true_poses is not None:
            plot_trajectory(ax, log.true_poses, label="true trajectory", color="k", lw=0.8)
        elif log.gps_xy is not None:
            ax.plot(log.gps_xy[:, 0], log.gps_xy[:, 1], ".", ms=2, color="k", label="GPS")
        kinds, params, _, n_obs = map_of(run)
        # With fusion the EKF's map also holds every known feature; those never observed
        # are the known map itself, drawn already.
        seen = n_obs > 0
        plot_map_arrays(
            ax,
            kinds[seen],
            _in_frame(T, kinds[seen], params[seen]),
            default_extent=line_extent_m,
            color=_colour(run),
            lw=1.6,
            label="estimated map",
        )
        est = np.array([compose(T, p) for p in run.poses])
        plot_trajectory(ax, est, label="estimated trajectory", color=_colour(run), lw=1.0, ls="-.")
        ax.set_aspect("equal", adjustable="datalim")
        _finish(ax, "x in Wknown [m]", "y in Wknown [m]", f"{run_label(run)}: map {how}")
    m = runs[0].metrics
    fig.suptitle(f"Fig. 10: estimated maps over the known map ({m.scenario}, seed {m.seed})")
    return fig


# --------------------------------------------------------------------------- real data


def _gps_alignment(run: Run) -> FloatArray | None:
    """``x^gps_Wglobal`` the run's GPS metrics used (anchor or best fit), if any."""
    block = run.metrics.position_error
    if block is None or block.x_gps_Wglobal is None:
        return None
    return np.asarray(block.x_gps_Wglobal, dtype=float)


def _alignment(run: Run) -> str | None:
    """How the run's GPS errors put the estimate in the GPS frame (``"anchor"`` or
    ``"best_fit"``)."""
    block = run.metrics.position_error
    return None if block is None else block.alignment


def gps_errors(run: Run) -> tuple[FloatArray, FloatArray]:
    """``(times (G,), position error (G,))`` of a run against GPS, as in its metrics.

    The estimate goes into the GPS frame through the transform the metrics used (the
    anchor with fusion, the best fit without); only fixes inside the run are kept.
    """
    T = _gps_alignment(run)
    gps = run.log.gps
    if T is None or gps is None:
        raise ValueError(f"run {run_label(run)!r} has no GPS-based position errors")
    return gps_error_series(run.timestamps, run.poses, *gps, T)


def gps_error_figure(runs: Sequence[Run]) -> Figure:
    """Position error against GPS over time, one curve per run (real data)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4.5), layout="constrained")
    ax = fig.subplots()
    for run in runs:
        t, e = gps_errors(run)
        how = str(_alignment(run)).replace("_", " ")
        ax.plot(
            t - run.timestamps[0],
            e,
            _style(run),
            color=_colour(run),
            lw=1.0,
            label=f"{run_label(run)} ({how}; median {np.median(e):.3f} m)",
        )
    scenario = runs[0].metrics.scenario if runs else "?"
    _finish(
        ax,
        "time since the first scan [s]",
        "position error against GPS [m]",
        f"Position error against GPS ({scenario}); GPS itself has errors",
    )
    return fig


def gps_trajectory_figure(runs: Sequence[Run]) -> Figure:
    """Estimated trajectories over the GPS track, in the GPS frame (real data)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 8), layout="constrained")
    ax = fig.subplots()
    gps = runs[0].log.gps if runs else None
    if gps is not None:
        ax.plot(gps[1][:, 0], gps[1][:, 1], ".", ms=2, color="k", label="GPS")
    for run in runs:
        T = _gps_alignment(run)
        if T is None:
            continue
        est = np.array([compose(T, p) for p in run.poses])
        how = str(_alignment(run)).replace("_", " ")
        ax.plot(
            est[:, 0],
            est[:, 1],
            _style(run),
            color=_colour(run),
            lw=1.0,
            label=f"{run_label(run)} ({how})",
        )
    known = runs[0].log.known_map if runs else None
    if known is not None and len(known) > 0:
        plot_map_arrays(
            ax,
            known.kinds,
            known.params,
            known.extents,
            color="tab:red",
            lw=1.0,
            label="known map",
        )
    ax.set_aspect("equal", adjustable="datalim")
    scenario = runs[0].metrics.scenario if runs else "?"
    _finish(ax, "East [m]", "North [m]", f"Trajectories over GPS ({scenario})")
    return fig


# --------------------------------------------------------------------------- NEES, timing


def _split_by_fusion(runs: Sequence[Run]) -> list[tuple[bool, list[Run]]]:
    out: list[tuple[bool, list[Run]]] = []
    for fusion in (True, False):
        sel = [r for r in runs if r.fusion is fusion]
        if sel:
            out.append((fusion, sel))
    return out


def nees_figure(runs: Sequence[Run]) -> Figure:
    """Vehicle NEES against time with the χ²(3, 0.95) bound; one panel per fusion setting.

    Graph runs show the smoothed estimate; iSAM2 also its filtered (per-step)
    estimate, the one comparable with the EKF's.
    """
    from matplotlib.figure import Figure

    groups = _split_by_fusion(runs)
    if not groups:
        raise ValueError("nees_figure needs at least one run")
    fig = Figure(figsize=(10, 3.8 * len(groups)), layout="constrained")
    axes = np.atleast_1d(fig.subplots(len(groups), 1, sharex=True))
    for ax, (fusion, sel) in zip(axes, groups, strict=True):
        for run in sel:
            _, nees = run_errors(run)
            smoothed = " (smoothed)" if run.result.smoothed is not None else ""
            ax.plot(
                run.timestamps,
                nees,
                color=_colour(run),
                lw=0.8,
                label=run.estimator + smoothed,
            )
            f = run.result.filtered
            if run.result.smoothed is not None and f is not None:
                n = f.poses.shape[0]
                err = pose_errors(f.poses, _truth(run.log, n))
                ax.plot(
                    run.timestamps[:n],
                    nees_series(err.dx, f.covs),
                    color=_colour(run),
                    lw=0.8,
                    ls=":",
                    label=f"{run.estimator} (filtered)",
                )
        ax.axhline(CHI2_3_95, color="k", lw=1.0, ls="--", label=f"χ²(3, 0.95) = {CHI2_3_95:.3f}")
        ax.set_yscale("log")
        # The first pose is fixed by a prior (graph) or known exactly (EKF): its NEES is
        # ~0 and would stretch the log axis over many decades.
        ax.set_ylim(bottom=1e-3)
        _finish(
            ax, "time [s]", "NEES (3 dof) [-]", f"NEES {'with' if fusion else 'without'} fusion"
        )
    m = runs[0].metrics
    fig.suptitle(f"Vehicle NEES against the 95 % bound ({m.scenario}, seed {m.seed})")
    return fig


def timing_figure(runs: Sequence[Run]) -> Figure:
    """Per-step wall time of each run (log scale); one panel per fusion setting.

    A smoother without per-step estimates (batch) has no per-step cost: its solve is
    shared equally among the steps (said in the legend).
    """
    from matplotlib.figure import Figure

    groups = _split_by_fusion(runs)
    if not groups:
        raise ValueError("timing_figure needs at least one run")
    fig = Figure(figsize=(10, 3.8 * len(groups)), layout="constrained")
    axes = np.atleast_1d(fig.subplots(len(groups), 1, sharex=True))
    for ax, (fusion, sel) in zip(axes, groups, strict=True):
        for run in sel:
            st = step_times(run)
            b = run.estimator
            # A smoother without per-step estimates (batch) shares its solve among the steps.
            shared = run.result.filtered is None
            label = f"{b} (solve shared equally over steps)" if shared else b
            label += f", total {float(np.sum(st)):.2f} s"
            ax.plot(
                run.timestamps[: st.shape[0]], 1e3 * st, color=_colour(run), lw=0.7, label=label
            )
        ax.set_yscale("log")
        _finish(
            ax,
            "time [s]",
            "wall time per step [ms]",
            f"run time per step {'with' if fusion else 'without'} fusion",
        )
    m = runs[0].metrics
    fig.suptitle(f"Per-step run time of each backend ({m.scenario}, seed {m.seed})")
    return fig


# --------------------------------------------------------------------------- CCDA


def ccda_figure(
    map_a: KnownMapArrays,
    map_b: KnownMapArrays,
    result: CCDAResult,
    x_B_A_true: FloatArray | None = None,
) -> Figure:
    """A CCDA match: map ``A`` (SLAM, in ``Wglobal``) drawn in map ``B``'s frame.

    Left: both maps in frame ``B`` through the estimated transform, pairings joined
    by segments.  Right: the same through the true transform ``x_B_A_true`` (when
    given), to show what a correct match looks like.
    """
    from matplotlib.figure import Figure

    panels: list[tuple[str, FloatArray]] = []
    if np.all(np.isfinite(result.x_A_B)):
        panels.append((f"CCDA estimate ({result.reason})", inverse(result.x_A_B)))
    if x_B_A_true is not None:
        panels.append(("true transform", np.asarray(x_B_A_true, dtype=float)))
    if not panels:
        raise ValueError("nothing to draw: CCDA fitted no transform and no truth was given")
    fig = Figure(figsize=(7.5 * len(panels), 7.5), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(panels)))
    for ax, (title, T) in zip(axes, panels, strict=True):
        a_in_b = _in_frame(T, map_a.kinds, map_a.params)
        plot_map_arrays(
            ax,
            map_b.kinds,
            map_b.params,
            map_b.extents,
            color="tab:red",
            lw=1.0,
            ls="--",
            label=f"map B: known map ({len(map_b)})",
        )
        plot_map_arrays(
            ax,
            map_a.kinds,
            a_in_b,
            map_a.extents,
            color="tab:blue",
            lw=1.4,
            label=f"map A: SLAM map ({len(map_a)})",
        )
        for n, (i, j) in enumerate(result.pairings):
            pa, pb = a_in_b[i, :2], map_b.params[j, :2]
            ax.plot(
                [pa[0], pb[0]],
                [pa[1], pb[1]],
                color="tab:green",
                lw=2.0,
                label=f"pairings ({len(result.pairings)})" if n == 0 else None,
            )
        ax.set_aspect("equal", adjustable="datalim")
        _finish(ax, "x in B [m]", "y in B [m]", title)
    fig.suptitle(
        f"CCDA: {result.n_nodes} nodes, {result.n_edges} edges, clique of {result.clique_size}, "
        f"{len(result.pairings)} pairings, runner-up {result.runner_up_size}"
    )
    return fig
