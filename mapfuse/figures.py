"""Figures of a backend comparison, after the paper's Figs. 6, 7 and 10.

Every function builds and returns a matplotlib :class:`~matplotlib.figure.Figure`
from finished results (never ``pyplot``, never ``show()``), with labelled axes in
units, a legend and a title; the caller saves or displays it.  Runs are the
:class:`mapfuse.runner.Run` of :func:`mapfuse.runner.run`; every figure reads only their
:class:`~mapfuse_core.estimate.EstimatorResult`, their log and their metrics, so any
registered estimator can be drawn.

Figures that compare against truth raise :class:`ValueError` for a log without true
poses (real data); :func:`fig10_maps` and :func:`timing_figure` work without truth.

Conventions (:mod:`mapfuse.plotting`): one colour per estimator, given in the order of
the runs (:func:`run_colours`; pass one mapping as ``colours`` to every figure of a
comparison); fusion settings in separate panels on one scale; curves identical to the
drawing's resolution drawn once and named together; y axes scaled to the data, the
paper's levels and χ² bounds annotated rather than stretching them; NEES from step 1;
known and estimated features told apart by marker.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from mapfuse.execution import fusion_for
from mapfuse.plotting import (
    ESTIMATOR_PALETTE,
    KNOWN_MAP_COLOUR,
    Curve,
    draw_circle,
    draw_curves,
    draw_features,
    draw_line_feature,
    estimator_colours,
    log_axis_ticks,
    log_name,
    outside_legend,
    plot_errors_with_bounds,
    plot_trajectory,
    plot_world,
    reference_line,
    running_mean,
    scale_to_data,
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
    "NEES_POINTS",
    "PAPER_ANCHOR_ESTIMATE",
    "PAPER_ANCHOR_TRUTH",
    "PAPER_FUSED_MAX_ERROR_M",
    "PAPER_SCENARIOS",
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
    "run_colours",
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

#: Built-in scenarios that drive the paper's 600 m loop from its start pose: the
#: paper's numbers (Sect. 4.2) are a reference for these and no other log.
PAPER_SCENARIOS: tuple[str, ...] = ("loop600", "loop600-sparse")
#: NEES curves are running means over ``steps // NEES_POINTS`` steps: about this many
#: independent values across the axis, few enough to read, many enough to show trends.
NEES_POINTS = 100

Colours = Mapping[str, str]


def run_label(run: Run) -> str:
    """``"ekf with fusion"``-style label of a run; just the backend on a log without a
    known map (Victoria Park), where there is nothing to fuse either way."""
    if not fusion_for(run.log, True):
        return run.estimator
    return f"{run.estimator} {'with' if run.fusion else 'without'} fusion"


def run_colours(runs: Sequence[Run]) -> dict[str, str]:
    """One colour per estimator of ``runs``, in their order
    (:func:`mapfuse.plotting.estimator_colours`): pass the same mapping to every
    figure of one comparison so that an estimator keeps its colour throughout."""
    return estimator_colours(r.estimator for r in runs)


def _colours(runs: Sequence[Run], colours: Colours | None) -> Colours:
    """``colours`` completed with a colour for every estimator of ``runs`` it lacks."""
    if colours is None:
        return run_colours(runs)
    missing = [r.estimator for r in runs if r.estimator not in colours]
    if not missing:
        return colours
    spare = [c for c in ESTIMATOR_PALETTE if c not in colours.values()]
    extra = estimator_colours(missing)
    out = dict(colours)
    for i, name in enumerate(dict.fromkeys(missing)):
        out[name] = spare[i] if i < len(spare) else extra[name]
    return out


def _title_source(run: Run) -> str:
    """``"loop600, seed 0"``, or the log's name alone for real data."""
    return log_name(run.metrics.scenario, run.metrics.seed)


def _fusion_title(run: Run, fusion: bool) -> str:
    if not fusion_for(run.log, True):
        return "no known map: nothing to fuse"
    return "with map fusion" if fusion else "without map fusion"


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


def fig6_errors_bounds(run: Run, *, colours: Colours | None = None) -> Figure:
    """x, y, θ errors of one run (the paper: EKF with fusion) with ±2σ bounds."""
    from matplotlib.figure import Figure

    dx, _ = run_errors(run)
    fig = Figure(figsize=(9, 7), layout="constrained")
    axes = list(fig.subplots(3, 1, sharex=True))
    t = run.timestamps
    colour = _colours([run], colours)[run.estimator]
    plot_errors_with_bounds(axes, t, dx, run.covs, label=run_label(run), color=colour)
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
        f"({_title_source(run)}, {m.steps} steps)"
    )
    return fig


# --------------------------------------------------------------------------- Fig. 7


def _matched_at(runs: Sequence[Run]) -> tuple[float, int] | None:
    """``(time, step)`` of the earliest map match among ``runs``, if any."""
    best: tuple[float, int] | None = None
    for run in runs:
        a = run.metrics.anchor
        if a is None:
            continue
        k = min(a.accepted_at_step, run.timestamps.shape[0] - 1)
        if best is None or k < best[1]:
            best = (float(run.timestamps[k]), k)
    return best


def fig7_error_fusion(
    runs: Sequence[Run], paper_reference: bool = True, *, colours: Colours | None = None
) -> Figure:
    """Position error against time: one panel per fusion setting (with fusion on
    top), one colour per estimator, the same y scale in both panels so that the gap
    fusion makes is read straight off them.

    Curves identical to the drawing's resolution (batch and iSAM2's smoothed
    estimates) are drawn once, dashed in both colours and named together.  The y axis
    is scaled to the errors alone; ``paper_reference`` adds the paper's levels (fused
    < 0.15 m, unfused ≈ 0.5 m) as lines when inside it, as a marked note on its edge
    otherwise.  A dotted vertical line marks the first map match.
    """
    from matplotlib.figure import Figure

    groups = _split_by_fusion(runs)
    if not groups:
        raise ValueError("fig7_error_fusion needs at least one run")
    colour = _colours(runs, colours)
    fig = Figure(figsize=(13, 1.2 + 2.9 * len(groups)), layout="constrained")
    axes = fig.subplots(len(groups), 1, sharex=True, sharey=True, squeeze=False)[:, 0]
    errors: list[FloatArray] = []
    for ax, (fusion, sel) in zip(axes, groups, strict=True):
        curves = []
        for run in sel:
            dx, _ = run_errors(run)
            e = np.hypot(dx[:, 0], dx[:, 1])
            errors.append(e)
            note = f": RMSE {math.sqrt(float(np.mean(e**2))):.3f} m, max {float(e.max()):.3f} m"
            curves.append(Curve(run.estimator, colour[run.estimator], run.timestamps, e, note))
        draw_curves(ax, curves, unit="m")
        matched = _matched_at(sel) if fusion else None
        if matched is not None:
            ax.axvline(
                matched[0], color="0.4", lw=0.8, ls=":", label=f"map matched (step {matched[1]})"
            )
        ax.set_title(_fusion_title(sel[0], fusion), fontsize=10)
    scale_to_data(axes[0], errors, zero=True)
    for ax, (fusion, sel) in zip(axes, groups, strict=True):
        if paper_reference and fusion_for(sel[0].log, True):
            if fusion:
                reference_line(ax, PAPER_FUSED_MAX_ERROR_M, "paper: fused max < 0.15 m")
            else:
                reference_line(ax, PAPER_UNFUSED_ERROR_M, "paper: unfused ≈ 0.50 m far from start")
        ax.set_ylabel("position error [m]")
        ax.grid(alpha=0.3)
        outside_legend(ax)
    for ax in axes:
        ax.set_xlabel("time [s]")
    fig.suptitle(
        f"Fig. 7: vehicle position error with and without map fusion ({_title_source(runs[0])})"
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


def _draw_gps(ax: Axes, xy: FloatArray) -> None:
    """GPS fixes as small black dots, with a legend entry large enough to read."""
    ax.plot(xy[:, 0], xy[:, 1], ".", ms=2, color="k", zorder=1.5)
    ax.plot([], [], ".", ms=7, color="k", label="GPS fixes")


def _draw_known(ax: Axes, known: KnownMapArrays) -> None:
    draw_features(
        ax,
        known.kinds,
        known.params,
        known.extents,
        role="known",
        colour=KNOWN_MAP_COLOUR,
        label=f"known map ({len(known)} features)",
    )


def fig10_maps(
    runs: Sequence[Run],
    world: World | None = None,
    line_extent_m: tuple[float, float] = (-4.0, 4.0),
    *,
    colours: Colours | None = None,
) -> Figure:
    """Estimated map and trajectory of each run over the known map, in ``Wknown``.

    One panel per run; features never observed (the known features an EKF with fusion
    holds) are not drawn as estimates.  The estimates are moved into the known-map frame through the
    run's own anchor ``x^Wknown_Wglobal``; a run without an anchor (no fusion) is
    drawn through the true start pose when the log has truth (said in the title),
    else in ``Wglobal``.  The true world (``world``, else the log's world arrays) and
    the true trajectory (or the GPS track of real data) are drawn underneath.
    Estimated lines are drawn over ``line_extent_m`` along them (m from their reference
    point; short indoor walls want a shorter piece than the default).  Known features
    are hollow red squares over dashed lines, estimated ones dots of the run's colour
    over solid lines (:func:`mapfuse.plotting.draw_features`), so that they are told
    apart whatever the map's extent.
    """
    from matplotlib.figure import Figure

    if not runs:
        raise ValueError("fig10_maps needs at least one run")
    colour = _colours(runs, colours)
    fig = Figure(figsize=(7.0 * len(runs), 8.0), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(runs)))
    for ax, run in zip(axes, runs, strict=True):
        log = run.log
        T, how = _display_frame(run)
        if world is not None:
            plot_world(ax, world, color="0.75", label="true world")
        elif log.world is not None:
            draw_features(
                ax,
                log.world.kinds,
                log.world.params,
                log.world.extents,
                role="world",
                colour="0.75",
                label="true world",
            )
        if log.true_poses is not None:
            plot_trajectory(ax, log.true_poses, label="true trajectory", color="k", lw=0.8)
        elif log.gps_xy is not None:
            _draw_gps(ax, log.gps_xy)
        _draw_known(ax, log.known_map)
        kinds, params, _, n_obs = map_of(run)
        # With fusion the EKF's map also holds every known feature; those never observed
        # are the known map itself, drawn already.
        seen = n_obs > 0
        c = colour[run.estimator]
        draw_features(
            ax,
            kinds[seen],
            _in_frame(T, kinds[seen], params[seen]),
            default_extent=line_extent_m,
            role="estimated",
            colour=c,
            label=f"estimated map ({int(seen.sum())} features observed)",
        )
        est = np.array([compose(T, p) for p in run.poses])
        plot_trajectory(ax, est, label="estimated trajectory", color=c, lw=1.0, ls="-.")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x in Wknown [m]")
        ax.set_ylabel("y in Wknown [m]")
        ax.set_title(f"{run_label(run)}: map {how}", fontsize=10)
        ax.grid(alpha=0.3)
        outside_legend(ax, "below", ncols=2)
    fig.suptitle(f"Fig. 10: estimated maps over the known map ({_title_source(runs[0])})")
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


def gps_error_figure(runs: Sequence[Run], *, colours: Colours | None = None) -> Figure:
    """Position error against GPS over time (real data): one panel per fusion
    setting on one y scale, one colour per estimator, identical curves named together."""
    from matplotlib.figure import Figure

    groups = _split_by_fusion(runs)
    if not groups:
        raise ValueError("gps_error_figure needs at least one run")
    colour = _colours(runs, colours)
    fig = Figure(figsize=(13, 1.2 + 2.7 * len(groups)), layout="constrained")
    axes = fig.subplots(len(groups), 1, sharex=True, sharey=True, squeeze=False)[:, 0]
    errors: list[FloatArray] = []
    for ax, (fusion, sel) in zip(axes, groups, strict=True):
        curves = []
        for run in sel:
            t, e = gps_errors(run)
            errors.append(e)
            how = str(_alignment(run)).replace("_", " ")
            note = f" ({how}): median {np.median(e):.3f} m, max {np.max(e):.3f} m"
            curves.append(
                Curve(run.estimator, colour[run.estimator], t - run.timestamps[0], e, note)
            )
        draw_curves(ax, curves, unit="m")
        ax.set_title(_fusion_title(sel[0], fusion), fontsize=10)
        ax.set_ylabel("error against GPS [m]")
        ax.grid(alpha=0.3)
        outside_legend(ax)
    scale_to_data(axes[0], errors, zero=True)
    for ax in axes:
        ax.set_xlabel("time since the first scan [s]")
    fig.suptitle(f"Position error against GPS ({_title_source(runs[0])}); GPS itself has errors")
    return fig


def gps_trajectory_figure(runs: Sequence[Run], *, colours: Colours | None = None) -> Figure:
    """Estimated trajectories over the GPS track and the known map, in the GPS frame
    (real data): one panel per fusion setting, one colour per estimator, identical
    trajectories named together."""
    from matplotlib.figure import Figure

    groups = [
        (f, [r for r in sel if _gps_alignment(r) is not None]) for f, sel in _split_by_fusion(runs)
    ]
    groups = [(f, sel) for f, sel in groups if sel]
    if not groups:
        raise ValueError("gps_trajectory_figure needs a run with GPS-based errors")
    colour = _colours(runs, colours)
    fig = Figure(figsize=(6.5 * len(groups), 7.5), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(groups)))
    gps = runs[0].log.gps
    known = runs[0].log.known_map
    for ax, (fusion, sel) in zip(axes, groups, strict=True):
        if gps is not None:
            _draw_gps(ax, gps[1])
        curves = []
        for run in sel:
            T = _gps_alignment(run)
            assert T is not None  # kept above
            est = np.array([compose(T, p) for p in run.poses])
            how = str(_alignment(run)).replace("_", " ")
            curves.append(
                Curve(run.estimator, colour[run.estimator], est[:, 0], est[:, 1], f" ({how})")
            )
        draw_curves(ax, curves, unit="m")
        if len(known) > 0:
            _draw_known(ax, known)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("East [m]")
        ax.set_ylabel("North [m]")
        ax.set_title(_fusion_title(sel[0], fusion), fontsize=10)
        ax.grid(alpha=0.3)
        outside_legend(ax, "below", ncols=2)
    fig.suptitle(f"Trajectories over GPS ({_title_source(runs[0])})")
    return fig


# --------------------------------------------------------------------------- NEES, timing


def _split_by_fusion(runs: Sequence[Run]) -> list[tuple[bool, list[Run]]]:
    out: list[tuple[bool, list[Run]]] = []
    for fusion in (True, False):
        sel = [r for r in runs if r.fusion is fusion]
        if sel:
            out.append((fusion, sel))
    return out


def _nees_curve(
    name: str, kind: str, colour: str, t: FloatArray, nees: FloatArray, window: int, style: str
) -> Curve:
    """The running mean of ``nees`` from step 1 on (step 0 is the frame ``Wglobal``
    itself: its error and covariance are zero by construction), with the estimate's
    ``kind`` and per-step statistics in the legend."""
    t, nees = t[1:], nees[1:]
    ok = np.isfinite(nees)
    within = 100.0 * float(np.mean(nees[ok] <= CHI2_3_95)) if ok.any() else math.nan
    mean = float(np.mean(nees[ok])) if ok.any() else math.nan
    note = f"{kind}: mean {mean:.2f}, {within:.0f} % of steps ≤ {CHI2_3_95:.3f}"
    return Curve(name, colour, running_mean(t, window), running_mean(nees, window), note, style)


def nees_figure(runs: Sequence[Run], *, colours: Colours | None = None) -> Figure:
    """Vehicle NEES against time, one panel per fusion setting on one log scale.

    Each curve is the running mean over ``steps // NEES_POINTS`` steps from step 1 on
    (said in the title); the legend gives each run's per-step mean and the fraction
    of its steps within χ²(3, 0.95).  Graph runs show the smoothed estimate; iSAM2
    also its filtered (per-step) estimate, dashed, the one comparable with the EKF's.
    Identical curves (batch and iSAM2 smoothed) are drawn once and named together.
    The reference levels (3, the expectation; χ²(3, 0.95)) are lines when inside the
    data's range, marked notes on the axis edge otherwise.
    """
    from matplotlib.figure import Figure

    groups = _split_by_fusion(runs)
    if not groups:
        raise ValueError("nees_figure needs at least one run")
    colour = _colours(runs, colours)
    steps = max(r.poses.shape[0] for r in runs)
    window = max(1, steps // NEES_POINTS)
    fig = Figure(figsize=(13, 1.2 + 2.9 * len(groups)), layout="constrained")
    axes = fig.subplots(len(groups), 1, sharex=True, sharey=True, squeeze=False)[:, 0]
    values: list[FloatArray] = []
    for ax, (fusion, sel) in zip(axes, groups, strict=True):
        curves = []
        for run in sel:
            _, nees = run_errors(run)
            c = colour[run.estimator]
            kind = " smoothed" if run.result.smoothed is not None else ""
            curves.append(_nees_curve(run.estimator, kind, c, run.timestamps, nees, window, "-"))
            f = run.result.filtered
            if run.result.smoothed is not None and f is not None:
                n = f.poses.shape[0]
                err = pose_errors(f.poses, _truth(run.log, n))
                curves.append(
                    _nees_curve(
                        run.estimator,
                        " filtered",
                        c,
                        run.timestamps[:n],
                        nees_series(err.dx, f.covs),
                        window,
                        "--",
                    )
                )
        values += [c.y for c in curves]
        draw_curves(ax, curves, log=True)
        ax.set_title(_fusion_title(sel[0], fusion), fontsize=10)
    axes[0].set_yscale("log")
    scale_to_data(axes[0], values, log=True)
    dt = float(np.median(np.diff(runs[0].timestamps))) if runs[0].timestamps.size > 1 else 0.0
    for ax in axes:
        reference_line(ax, 3.0, "3: expected NEES (3 dof)", colour="0.3", ls="-.")
        reference_line(ax, CHI2_3_95, f"χ²(3, 0.95) = {CHI2_3_95:.3f}", colour="k", ls="--")
        log_axis_ticks(ax)
        ax.set_ylabel("NEES (3 dof) [-]")
        ax.grid(alpha=0.3)
        outside_legend(ax)
    for ax in axes:
        ax.set_xlabel("time [s]")
    fig.suptitle(
        f"Vehicle NEES, running mean over {window} steps ({window * dt:.1f} s) from step 1 "
        f"({_title_source(runs[0])})"
    )
    return fig


def timing_figure(runs: Sequence[Run], *, colours: Colours | None = None) -> Figure:
    """Per-step wall time of each run (log scale); one panel per fusion setting.

    A smoother without per-step estimates (batch) has no per-step cost: its solve is
    shared equally among the steps (said in the legend).
    """
    from matplotlib.figure import Figure

    groups = _split_by_fusion(runs)
    if not groups:
        raise ValueError("timing_figure needs at least one run")
    colour = _colours(runs, colours)
    fig = Figure(figsize=(13, 1.2 + 2.9 * len(groups)), layout="constrained")
    axes = fig.subplots(len(groups), 1, sharex=True, sharey=True, squeeze=False)[:, 0]
    values: list[FloatArray] = []
    for ax, (fusion, sel) in zip(axes, groups, strict=True):
        for run in sel:
            st = 1e3 * step_times(run)
            values.append(st)
            # A smoother without per-step estimates (batch) shares its solve among the steps.
            shared = run.result.filtered is None and run.result.smoothed is not None
            label = (
                f"{run.estimator} (solve shared equally over steps)" if shared else run.estimator
            )
            label += f", total {float(np.sum(st)) / 1e3:.2f} s"
            ax.plot(
                run.timestamps[: st.shape[0]], st, color=colour[run.estimator], lw=0.7, label=label
            )
        ax.set_title(f"run time per step, {_fusion_title(sel[0], fusion)}", fontsize=10)
    axes[0].set_yscale("log")
    scale_to_data(axes[0], values, log=True)
    for ax in axes:
        log_axis_ticks(ax)
        ax.set_ylabel("wall time per step [ms]")
        ax.grid(alpha=0.3)
        outside_legend(ax)
    for ax in axes:
        ax.set_xlabel("time [s]")
    fig.suptitle(f"Per-step run time of each estimator ({_title_source(runs[0])})")
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
        draw_features(
            ax,
            map_b.kinds,
            map_b.params,
            map_b.extents,
            role="known",
            colour=KNOWN_MAP_COLOUR,
            label=f"map B: known map ({len(map_b)})",
        )
        draw_features(
            ax,
            map_a.kinds,
            a_in_b,
            map_a.extents,
            role="estimated",
            colour=ESTIMATOR_PALETTE[0],
            label=f"map A: SLAM map ({len(map_a)})",
        )
        for n, (i, j) in enumerate(result.pairings):
            pa, pb = a_in_b[i, :2], map_b.params[j, :2]
            ax.plot(
                [pa[0], pb[0]],
                [pa[1], pb[1]],
                color="0.2",
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
