"""Campaign figures.  Each ``plot_*`` draws on a given matplotlib ``Axes``; the
``*_figure`` functions lay them out for ``report.md``."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from mapfuse.campaign.summary import MAX_ERROR_LIMIT_M, GroupSummary

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = [
    "anees_figure",
    "max_error_figure",
    "plot_anees",
    "plot_max_errors",
    "plot_rmse",
    "rmse_figure",
]

_COLOURS = {"ekf": "tab:blue", "batch": "tab:orange", "isam2": "tab:green"}


def _label(g: GroupSummary) -> str:
    return f"{g.estimator} {'with' if g.fusion else 'without'} fusion"


def _colour(g: GroupSummary) -> str:
    return _COLOURS.get(g.estimator, "tab:gray")


def plot_anees(ax: Axes, group: GroupSummary, colour: str | None = None) -> None:
    """ANEES of ``group`` against time with its two-sided bounds (shaded)."""
    a = group.anees
    t = group.timestamps if group.timestamps.size == a.anees.size else np.arange(a.anees.size)
    c = colour or ("tab:blue" if group.fusion else "tab:red")
    n = len(group.seeds)
    ax.plot(
        t,
        a.anees,
        color=c,
        lw=0.9,
        label=f"{'with' if group.fusion else 'without'} fusion: "
        f"{100 * a.fraction_inside:.0f} % inside, mean {a.overall:.2f} ({n} runs)",
    )
    ax.fill_between(t, a.lower, a.upper, color=c, alpha=0.15, lw=0)


def plot_rmse(ax: Axes, group: GroupSummary) -> None:
    """Position RMSE per step over the runs of ``group``."""
    t = group.timestamps if group.timestamps.size == group.rmse.size else np.arange(group.rmse.size)
    ax.plot(
        t,
        group.rmse,
        color=_colour(group),
        ls="-" if group.fusion else "--",
        lw=1.0,
        label=f"{_label(group)} ({len(group.seeds)} runs)",
    )


def plot_max_errors(ax: Axes, groups: Sequence[GroupSummary]) -> None:
    """Box plot of the per-run maximum position error of each group."""
    data = [g.values("max_m") for g in groups]
    keep = [i for i, d in enumerate(data) if d]
    if keep:
        ax.boxplot([data[i] for i in keep], orientation="horizontal")
        ax.set_yticks(range(1, len(keep) + 1), [_label(groups[i]) for i in keep])
    ax.axvline(MAX_ERROR_LIMIT_M, color="k", ls=":", lw=1, label=f"{MAX_ERROR_LIMIT_M} m")
    ax.set_xlabel("maximum position error of a run (m)")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)


def _figure(width: float, height: float) -> Figure:
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), layout="constrained")


def anees_figure(groups: Sequence[GroupSummary]) -> Figure:
    """One panel per estimator: its ANEES with bounds, each fusion setting."""
    from matplotlib.ticker import ScalarFormatter

    names = list(dict.fromkeys(g.estimator for g in groups))
    fig = _figure(10, 3.2 * len(names))
    axes = fig.subplots(len(names), 1, squeeze=False)[:, 0]
    for ax, name in zip(axes, names, strict=True):
        for g in groups:
            if g.estimator == name and g.seeds:
                plot_anees(ax, g)
        ax.axhline(3.0, color="k", lw=0.6, ls=":")
        ax.set_yscale("log")
        # Plain numbers on the log axis (2, 3, 4, not 2×10⁰).
        ax.yaxis.set_major_formatter(ScalarFormatter())
        ax.yaxis.set_minor_formatter(ScalarFormatter())
        ax.set_xlabel("time (s)")
        ax.set_ylabel("ANEES")
        ax.set_title(f"{name}: ANEES over runs with its two-sided 95 % bounds (shaded)")
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    return fig


def rmse_figure(groups: Sequence[GroupSummary]) -> Figure:
    """Position RMSE per step over runs, with and without fusion (the statistical
    form of the paper's Fig. 7)."""
    fig = _figure(10, 4.5)
    ax = fig.subplots()
    for g in groups:
        if g.seeds:
            plot_rmse(ax, g)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("position RMSE over runs (m)")
    ax.set_title("Position RMSE per step over the runs, with (solid) and without (dashed) fusion")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    return fig


def max_error_figure(groups: Sequence[GroupSummary]) -> Figure:
    """Distribution of the per-run maximum position error."""
    fig = _figure(9, 1.2 + 0.5 * len(groups))
    plot_max_errors(fig.subplots(), groups)
    return fig
