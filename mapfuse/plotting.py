"""Plot helpers.  Each draws on a given matplotlib ``Axes`` and never calls ``show()``.

Part of the harness: the numeric packages (``mapfuse_core``, ``ekf_reference``,
``mapfuse_graph``) never import matplotlib.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray, compose, transform_point
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog
from mapfuse_core.sim.world import World

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    from mapfuse.runner import Run
    from mapfuse_core.sensor import Scan

__all__ = [
    "ESTIMATOR_PALETTE",
    "IDENTICAL_FRACTION",
    "KNOWN_MAP_COLOUR",
    "Curve",
    "CurveGroup",
    "draw_circle",
    "draw_curves",
    "draw_features",
    "draw_line_feature",
    "errors_figure",
    "estimator_colours",
    "log_axis_ticks",
    "log_name",
    "merge_identical",
    "outside_legend",
    "plot_errors_with_bounds",
    "plot_known_map",
    "plot_scan",
    "plot_trajectory",
    "plot_world",
    "reference_line",
    "run_error_axes",
    "running_mean",
    "scale_to_data",
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
    ax.set_title(f"{log_name(run.log.scenario, run.log.seed)}: RMSE {err.rmse:.3f} m")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    return ax


# --------------------------------------------------------------------------- conventions
# What every figure of a comparison or campaign shares: one colour per estimator,
# identical curves drawn once and named together, axes scaled to the data with the
# reference levels annotated, known and estimated features told apart by marker.

#: Colours given to estimators in the order a figure meets them.  Red (the known map),
#: black and greys (truth, GPS, reference levels) are kept out, so an estimator's
#: colour never stands for anything else.
ESTIMATOR_PALETTE: tuple[str, ...] = (
    "tab:blue",
    "tab:orange",
    "tab:green",
    "tab:purple",
    "tab:brown",
    "tab:pink",
    "tab:olive",
    "tab:cyan",
)
#: Colour of the known (a-priori) map in every map figure.
KNOWN_MAP_COLOUR = "tab:red"
#: Curves closer than this fraction of their axis's span are drawn as one and named
#: together: on an axis under 1,000 pixels they differ by less than a pixel.
IDENTICAL_FRACTION = 1e-3

FeatureRole = Literal["known", "estimated", "world"]


def estimator_colours(names: Iterable[str]) -> dict[str, str]:
    """One distinct colour per estimator name, in order of first appearance: from
    :data:`ESTIMATOR_PALETTE`, or evenly spaced hues when there are more names."""
    unique = list(dict.fromkeys(names))
    if len(unique) <= len(ESTIMATOR_PALETTE):
        return dict(zip(unique, ESTIMATOR_PALETTE, strict=False))
    from matplotlib import colormaps
    from matplotlib.colors import to_hex

    hues = colormaps["hsv"]
    return {n: to_hex(hues(i / len(unique))) for i, n in enumerate(unique)}


def log_name(scenario: str, seed: int) -> str:
    """``"loop600, seed 0"`` for a simulated log; just the name for real data (seed −1)."""
    return scenario if seed < 0 else f"{scenario}, seed {seed}"


@dataclass(frozen=True)
class Curve:
    """One series of a panel."""

    name: str
    """What the curve is of (an estimator, ``"isam2 (filtered)"``); the names of
    identical curves are joined by ``=`` in the legend."""
    colour: str
    """Line colour (its estimator's)."""
    x: FloatArray
    """(N,) abscissae."""
    y: FloatArray
    """(N,) ordinates (NaN: a gap)."""
    note: str = ""
    """Legend text after the name (e.g. ``": RMSE 0.032 m"``)."""
    style: str = "-"
    """Line style."""


@dataclass(frozen=True)
class CurveGroup:
    """Curves that coincide on the axis, drawn as one."""

    curves: tuple[Curve, ...]
    """The curves, the first one's note standing for all."""
    difference: float
    """Largest distance between the first curve and the others, in the data's units
    (a ratio − 1 on a log axis); 0 for a single curve."""

    def label(self, unit: str = "", log: bool = False) -> str:
        """``"batch = isam2: RMSE 0.021 m (identical within 2e-06 m)"``-style label."""
        first = self.curves[0]
        text = " = ".join(c.name for c in self.curves) + first.note
        if len(self.curves) == 1:
            return text
        if self.difference == 0.0:
            return f"{text} (identical)"
        if log:
            return f"{text} (identical within {100 * self.difference:.1g} %)"
        return f"{text} (identical within {self.difference:.1g}{' ' + unit if unit else ''})"


def _finite(values: Iterable[FloatArray], log: bool) -> FloatArray:
    parts = [np.asarray(v, dtype=float).ravel() for v in values]
    allv = np.concatenate(parts) if parts else np.zeros(0)
    keep = np.isfinite(allv) & ((allv > 0) if log else True)
    out = allv[keep]
    return np.log10(out) if log else out


def _span(values: Iterable[FloatArray], log: bool) -> float:
    v = _finite(values, log)
    return float(v.max() - v.min()) if v.size else 0.0


def _distance(a: FloatArray, b: FloatArray, log: bool) -> float:
    """Largest difference of two series (NaN where either is NaN counts only when not
    both are); ``inf`` when their gaps differ."""
    if a.shape != b.shape:
        return math.inf
    na, nb = ~np.isfinite(a), ~np.isfinite(b)
    if np.any(na != nb):
        return math.inf
    ok = ~na
    if log:
        if np.any((a[ok] <= 0) != (b[ok] <= 0)):
            return math.inf
        pos = ok & (a > 0)
        d = np.abs(np.log10(a[pos]) - np.log10(b[pos]))
    else:
        d = np.abs(a[ok] - b[ok])
    return float(d.max()) if d.size else 0.0


def merge_identical(curves: Sequence[Curve], *, log: bool = False) -> list[CurveGroup]:
    """``curves`` grouped with those they coincide with (in order of first appearance):
    the same abscissae, and ordinates within :data:`IDENTICAL_FRACTION` of the span of
    all the curves' ordinates (in decades on a log axis), so that drawn apart they
    would hide one another."""
    tol = IDENTICAL_FRACTION * _span((c.y for c in curves), log)
    xtol = IDENTICAL_FRACTION * _span((c.x for c in curves), False)
    groups: list[list[Curve]] = []
    for c in curves:
        for g in groups:
            first = g[0]
            if (
                first.style == c.style
                and _distance(first.x, c.x, False) <= xtol
                and _distance(first.y, c.y, log) <= tol
            ):
                g.append(c)
                break
        else:
            groups.append([c])
    out = []
    for g in groups:
        d = max((_distance(g[0].y, c.y, log) for c in g[1:]), default=0.0)
        out.append(CurveGroup(tuple(g), 10.0**d - 1.0 if log else d))
    return out


def draw_curves(
    ax: Axes, curves: Sequence[Curve], *, log: bool = False, unit: str = "", lw: float = 1.0
) -> list[CurveGroup]:
    """Draw ``curves`` on ``ax``, identical ones (:func:`merge_identical`) as one line
    dashed in the first two's colours and named together in the legend."""
    groups = merge_identical(curves, log=log)
    for g in groups:
        first = g.curves[0]
        style: dict[str, object] = {"color": first.colour, "ls": first.style}
        if len(g.curves) > 1:
            # Dashes of the first colour, gaps of the second: both estimators show.
            style = {"color": first.colour, "ls": (0, (4, 4)), "gapcolor": g.curves[1].colour}
        ax.plot(first.x, first.y, lw=lw, label=g.label(unit, log), **style)  # type: ignore[arg-type]
    return groups


def scale_to_data(
    ax: Axes,
    values: Iterable[FloatArray],
    *,
    log: bool = False,
    zero: bool = False,
    margin: float = 0.05,
) -> None:
    """Set ``ax``'s y limits to the finite ``values`` (positive ones on a log axis)
    with ``margin`` of their span either side; from 0 when ``zero``.  Nothing else (a
    reference level, step 0) stretches the axis."""
    v = _finite(values, log)
    if not v.size:
        return
    lo, hi = float(v.min()), float(v.max())
    if log:
        pad = max(margin * (hi - lo), 0.05)
        ax.set_ylim(10.0 ** (lo - pad), 10.0 ** (hi + pad))
        return
    if zero:
        lo = min(lo, 0.0)
    pad = margin * (hi - lo) if hi > lo else max(abs(hi), 1.0) * 0.1
    ax.set_ylim(lo if zero and lo == 0.0 else lo - pad, hi + pad)


def reference_line(
    ax: Axes, y: float, text: str, *, colour: str = "k", ls: str = ":"
) -> Literal["line", "above", "below"]:
    """A reference level ``y`` on ``ax`` (after its limits are set): a labelled
    horizontal line when inside the limits; otherwise a triangle on the top or bottom
    edge pointing out, labelled in the legend with where the level is, so that the
    limits stay the data's.  Returns which of the three was drawn."""
    lo, hi = ax.get_ylim()
    if lo <= y <= hi:
        ax.axhline(y, color=colour, lw=0.9, ls=ls, label=text)
        return "line"
    where: Literal["above", "below"] = "above" if y > hi else "below"
    ax.plot(
        [0.985],
        [1.0 if where == "above" else 0.0],
        ls="none",
        marker="^" if where == "above" else "v",
        ms=9,
        color=colour,
        transform=ax.transAxes,
        clip_on=False,
        gid=f"reference-{where}",
        label=f"{text}: {where} this axis ({'↑' if where == 'above' else '↓'})",
    )
    return where


def log_axis_ticks(ax: Axes) -> None:
    """Plain-number ticks on ``ax``'s log y axis, spaced so that their labels never
    overlap: 1-2-3-5 within a decade, 1-2-5 up to a few decades, powers of ten
    beyond (every k-th over many); unlabelled minor ticks.  On a span too short to
    hold two of those, evenly spaced round values."""
    from matplotlib.ticker import (
        FixedLocator,
        FuncFormatter,
        LogLocator,
        MaxNLocator,
        NullFormatter,
    )

    lo, hi = ax.get_ylim()
    if not (lo > 0 and hi > lo):
        return
    decades = math.log10(hi / lo)
    mantissas = (1, 2, 3, 5) if decades <= 1.0 else (1, 2, 5) if decades <= 2.5 else (1,)
    k0, k1 = math.floor(math.log10(lo)), math.ceil(math.log10(hi))
    ticks = [m * 10.0**k for k in range(k0, k1 + 1) for m in mantissas]
    ticks = [t for t in ticks if lo <= t <= hi]
    if len(ticks) > 8:
        step = math.ceil(len(ticks) / 8)
        ticks = ticks[::step]
    if len(ticks) < 2:
        ticks = [t for t in MaxNLocator(nbins=4).tick_values(lo, hi) if lo <= t <= hi]
    ax.yaxis.set_major_locator(FixedLocator(ticks))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.3g}"))
    ax.yaxis.set_minor_locator(LogLocator(subs="auto"))
    ax.yaxis.set_minor_formatter(NullFormatter())


def running_mean(y: FloatArray, window: int) -> FloatArray:
    """(N − window + 1,) mean of every ``window`` consecutive values, ignoring NaN
    (NaN where a window holds none)."""
    y = np.asarray(y, dtype=float)
    if window < 1:
        raise ValueError(f"window must be at least 1, got {window}")
    if y.size < window:
        return np.zeros(0)
    ok = np.isfinite(y)
    s = np.concatenate([[0.0], np.cumsum(np.where(ok, y, 0.0))])
    n = np.concatenate([[0], np.cumsum(ok)])
    total, count = s[window:] - s[:-window], n[window:] - n[:-window]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


#: How each role's features are drawn: line style and width, circle-centre marker,
#: its size in points (the same on screen whatever the map's extent), filled or not.
_FEATURE_STYLE: Mapping[str, tuple[str, float, str, float, bool, int]] = {
    "known": ("--", 1.2, "s", 9.0, False, 3),
    "estimated": ("-", 1.8, "o", 4.5, True, 2),
    "world": ("-", 1.0, ".", 4.0, True, 1),
}


def draw_features(
    ax: Axes,
    kinds: np.ndarray,
    params: FloatArray,
    extents: FloatArray | None = None,
    *,
    role: FeatureRole,
    colour: str,
    label: str | None = None,
    default_extent: tuple[float, float] = (-4.0, 4.0),
) -> Line2D | None:
    """Map features drawn by ``role``: lines over their extent (else
    ``default_extent``), circles at their true size and, at their centres, a marker
    of fixed size on screen (known: hollow squares over dashed lines; estimated:
    filled dots over solid lines; world: small dots), so that known and estimated
    features are told apart at any map extent.  The legend entry is a proxy drawn
    in the same style (marker and line as present).  Returns it, ``None`` when there
    are no features."""
    if len(kinds) == 0:
        return None
    ls, lw, marker, ms, filled, z = _FEATURE_STYLE[role]
    is_line = np.asarray(kinds, dtype=int) == int(FeatureKind.LINE)
    for i in np.flatnonzero(is_line):
        ext = default_extent
        if extents is not None and np.all(np.isfinite(extents[i])):
            ext = (float(extents[i, 0]), float(extents[i, 1]))
        draw_line_feature(ax, params[i], ext, color=colour, lw=lw, ls=ls, zorder=z)
    circles = params[~is_line]
    for c in circles:
        draw_circle(ax, c, color=colour, lw=0.8, zorder=z)
    mstyle = {
        "marker": marker,
        "ms": ms,
        "mec": colour,
        "mfc": colour if filled else "none",
        "mew": 1.4,
    }
    if circles.shape[0]:
        ax.plot(circles[:, 0], circles[:, 1], ls="none", zorder=z + 0.5, **mstyle)  # type: ignore[arg-type]
    proxy_marker = mstyle if circles.shape[0] else {}
    (proxy,) = ax.plot(
        [],
        [],
        color=colour,
        ls=ls if is_line.any() else "none",
        lw=lw,
        label=label,
        **proxy_marker,  # type: ignore[arg-type]
    )
    return proxy


def outside_legend(ax: Axes, where: Literal["right", "below"] = "right", ncols: int = 1) -> None:
    """``ax``'s legend outside its data area (right of it or below), so that it hides
    nothing drawn."""
    if where == "right":
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, fontsize=8)
    else:
        ax.legend(
            loc="upper center",
            bbox_to_anchor=(0.5, -0.1),
            borderaxespad=0.0,
            fontsize=8,
            ncols=ncols,
        )
