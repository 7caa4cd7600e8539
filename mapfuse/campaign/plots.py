"""Campaign figures.  Each ``plot_*`` draws on a given matplotlib ``Axes``; the
``*_figure`` functions lay them out for ``report.md``.

Every figure gives each estimator one colour (:func:`group_colours`, in the
campaign's order), puts the fusion settings in separate panels on one scale, and
scales its axes to the data from step 1 on: step 0 is the frame ``Wglobal`` itself,
whose error and covariance are zero by construction.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from mapfuse.campaign.summary import MAX_ERROR_LIMIT_M, GroupSummary
from mapfuse.plotting import (
    Curve,
    draw_curves,
    estimator_colours,
    log_axis_ticks,
    outside_legend,
    reference_line,
    scale_to_data,
)
from mapfuse_core.geometry.se2 import FloatArray

if TYPE_CHECKING:
    from matplotlib.artist import Artist
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = [
    "anees_figure",
    "group_colours",
    "max_error_figure",
    "plot_anees",
    "plot_max_errors",
    "plot_rmse",
    "rmse_figure",
]


def _label(g: GroupSummary) -> str:
    return f"{g.estimator} {'with' if g.fusion else 'without'} fusion"


def group_colours(groups: Sequence[GroupSummary]) -> dict[str, str]:
    """One colour per estimator of ``groups``, in their order."""
    return estimator_colours(g.estimator for g in groups)


def _times(group: GroupSummary, n: int) -> FloatArray:
    """Step times of ``group`` for a series of ``n`` steps (step indices without them)."""
    return group.timestamps if group.timestamps.size == n else np.arange(n, dtype=float)


def _anees_parts(group: GroupSummary) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """``(t, ANEES, lower, upper)`` from step 1 on."""
    a = group.anees
    t = _times(group, a.anees.size)
    return t[1:], a.anees[1:], a.lower[1:], a.upper[1:]


def plot_anees(ax: Axes, group: GroupSummary, colour: str | None = None) -> None:
    """ANEES of ``group`` against time from step 1 on, with its two-sided bounds
    shaded in the same colour."""
    t, anees, lower, upper = _anees_parts(group)
    c = colour or estimator_colours([group.estimator])[group.estimator]
    ax.fill_between(
        t,
        lower,
        upper,
        color=c,
        alpha=0.2,
        lw=0,
        label=f"two-sided {100 * group.anees.p:.0f} % bounds of a consistent ANEES",
    )
    ax.plot(t, anees, color=c, lw=0.9, label="ANEES over the runs")


def _anees_title(group: GroupSummary | None, name: str, fusion: bool) -> str:
    head = f"{name} {'with' if fusion else 'without'} fusion"
    if group is None or not group.seeds:
        return f"{head}: no run finished"
    a = group.anees
    return (
        f"{head}: {len(group.seeds)} runs, {100 * a.fraction_inside:.0f} % of steps "
        f"inside, mean {a.overall:.2f}"
    )


def plot_rmse(ax: Axes, group: GroupSummary, colour: str | None = None) -> None:
    """Position RMSE per step over the runs of ``group``."""
    c = colour or estimator_colours([group.estimator])[group.estimator]
    ax.plot(
        _times(group, group.rmse.size),
        group.rmse,
        color=c,
        lw=1.0,
        label=f"{_label(group)} ({len(group.seeds)} runs)",
    )


def plot_max_errors(
    ax: Axes, groups: Sequence[GroupSummary], colours: Mapping[str, str] | None = None
) -> None:
    """Box plot of the per-run maximum position error of each group, each box in its
    estimator's colour."""
    colour = group_colours(groups) if colours is None else colours
    data = [g.values("max_m") for g in groups]
    keep = [i for i, d in enumerate(data) if d]
    if keep:
        boxes = ax.boxplot([data[i] for i in keep], orientation="horizontal", patch_artist=True)
        for box, i in zip(boxes["boxes"], keep, strict=True):
            box.set_facecolor(colour[groups[i].estimator])
            box.set_alpha(0.5)
        ax.set_yticks(range(1, len(keep) + 1), [_label(groups[i]) for i in keep])
    ax.axvline(MAX_ERROR_LIMIT_M, color="k", ls=":", lw=1, label=f"{MAX_ERROR_LIMIT_M} m")
    ax.set_xlabel("maximum position error of a run (m)")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)


def _figure(width: float, height: float) -> Figure:
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), layout="constrained")


def _fusions(groups: Sequence[GroupSummary]) -> list[bool]:
    return list(dict.fromkeys(g.fusion for g in groups))


def anees_figure(
    groups: Sequence[GroupSummary], colours: Mapping[str, str] | None = None
) -> Figure:
    """One panel per estimator (rows) and fusion setting (columns), all on one log
    scale fitted to the ANEES and its bounds from step 1 on: each ANEES in its
    estimator's colour over its shaded two-sided 95 % bounds, 3 (the expectation)
    marked; each title gives the runs, the fraction of steps inside and the mean."""
    colour = group_colours(groups) if colours is None else colours
    names = list(dict.fromkeys(g.estimator for g in groups))
    fusions = _fusions(groups)
    fig = _figure(6.5 * len(fusions) + 1.0, 0.8 + 3.0 * len(names))
    axes = fig.subplots(len(names), len(fusions), sharex=True, sharey=True, squeeze=False)
    values: list[FloatArray] = []
    for r, name in enumerate(names):
        for k, fusion in enumerate(fusions):
            ax = axes[r, k]
            g = next((g for g in groups if g.estimator == name and g.fusion is fusion), None)
            if g is not None and g.seeds:
                plot_anees(ax, g, colour[name])
                values += list(_anees_parts(g)[1:])
            ax.set_title(_anees_title(g, name, fusion), fontsize=9, color=colour[name])
    axes[0, 0].set_yscale("log")
    scale_to_data(axes[0, 0], values, log=True)
    for ax in axes.ravel():
        reference_line(ax, 3.0, "3: expected ANEES (3 dof)", colour="0.3", ls="-.")
        log_axis_ticks(ax)
        ax.grid(alpha=0.3)
    # One legend for all panels (the same entries in each, in its estimator's colour),
    # below them: nothing drawn is hidden.
    entries: dict[str, Artist] = {}
    for ax in axes.ravel():
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            entries.setdefault(lab, h)
    fig.legend(
        list(entries.values()),
        list(entries),
        loc="outside lower center",
        ncols=min(3, max(1, len(entries))),
        fontsize=8,
    )
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    for ax in axes[:, 0]:
        ax.set_ylabel("ANEES (3 dof)")
    fig.suptitle("ANEES over the runs with its two-sided 95 % bounds, from step 1")
    return fig


def rmse_figure(groups: Sequence[GroupSummary], colours: Mapping[str, str] | None = None) -> Figure:
    """Position RMSE per step over runs: one panel per fusion setting on one scale,
    one colour per estimator, identical curves named together (the statistical form
    of the paper's Fig. 7)."""
    colour = group_colours(groups) if colours is None else colours
    fusions = _fusions(groups)
    fig = _figure(12, 1.0 + 2.8 * len(fusions))
    axes = fig.subplots(len(fusions), 1, sharex=True, sharey=True, squeeze=False)[:, 0]
    values: list[FloatArray] = []
    for ax, fusion in zip(axes, fusions, strict=True):
        curves = []
        for g in groups:
            if g.fusion is not fusion or not g.seeds:
                continue
            t, y = _times(g, g.rmse.size)[1:], g.rmse[1:]
            values.append(y)
            note = f" ({len(g.seeds)} runs): mean {float(np.nanmean(y)):.3f} m"
            curves.append(Curve(g.estimator, colour[g.estimator], t, y, note))
        draw_curves(ax, curves, unit="m")
        ax.set_title(f"{'with' if fusion else 'without'} fusion", fontsize=10)
        ax.set_ylabel("position RMSE (m)")
        ax.grid(alpha=0.3)
    scale_to_data(axes[0], values, zero=True)
    for ax in axes:
        outside_legend(ax)
    axes[-1].set_xlabel("time (s)")
    fig.suptitle("Position RMSE per step over the runs, with and without fusion")
    return fig


def max_error_figure(
    groups: Sequence[GroupSummary], colours: Mapping[str, str] | None = None
) -> Figure:
    """Distribution of the per-run maximum position error."""
    fig = _figure(9, 1.2 + 0.5 * len(groups))
    plot_max_errors(fig.subplots(), groups, colours)
    return fig
