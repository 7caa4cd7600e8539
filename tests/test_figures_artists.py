"""Figures make their claim visible: read from the drawn artists, not from the PNG's
existence.

Each test builds a figure from small runs (a 150-step synthetic ring, with truth or
with GPS only) or from stub campaign summaries, then checks what a reader sees:
one distinct colour per estimator, identical curves named together, every plotted
value inside the axis limits, reference levels that do not stretch an axis, step 0
left out of NEES axes, bounds in view, tick labels that read their values without
overlapping, known and estimated map features drawn differently.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import pytest
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Rectangle

from mapfuse.campaign.plots import anees_figure, max_error_figure, rmse_figure
from mapfuse.campaign.stats import anees_series
from mapfuse.campaign.summary import GroupSummary
from mapfuse.comparison import BESIDE_DIR, Comparison, compare, write_comparison
from mapfuse.figures import (
    NEES_POINTS,
    PAPER_FUSED_MAX_ERROR_M,
    PAPER_UNFUSED_ERROR_M,
    fig7_error_fusion,
    fig10_maps,
    gps_error_figure,
    gps_trajectory_figure,
    nees_figure,
    run_colours,
)
from mapfuse.plotting import (
    ESTIMATOR_PALETTE,
    IDENTICAL_FRACTION,
    KNOWN_MAP_COLOUR,
    Curve,
    estimator_colours,
    log_axis_ticks,
    merge_identical,
    reference_line,
    running_mean,
)
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.measlog import MeasurementLog
from tests.synthetic import synthetic_log

# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def ring() -> Comparison:
    """Every built-in estimator with and without fusion on a synthetic ring with truth;
    its errors stay far below the paper's 0.5 m."""
    return compare(synthetic_log(150, 0))


@pytest.fixture(scope="module")
def short_ring() -> Comparison:
    """Fewer steps than NEES_POINTS: the NEES curves are the per-step values."""
    log = synthetic_log(60, 2)
    assert log.n_steps < NEES_POINTS
    return compare(log, ("ekf", "batch"))


def _gps_log(steps: int, seed: int) -> MeasurementLog:
    """A real-data-like log: no truth, no world, seed −1, GPS fixes (every 4th true
    position with 2 cm of seeded noise) in the known map's frame."""
    log = synthetic_log(steps, seed)
    assert log.true_poses is not None
    rng = np.random.default_rng(seed + 100)
    k = np.arange(0, log.n_steps, 4)
    return dataclasses.replace(
        log,
        scenario="synthetic-gps",
        seed=-1,
        true_poses=None,
        world=None,
        gps_times=log.timestamps[k],
        gps_xy=log.true_poses[k, :2] + rng.normal(0.0, 0.02, (k.size, 2)),
    )


@pytest.fixture(scope="module")
def gps() -> Comparison:
    c = compare(_gps_log(120, 3))
    assert c.has_gps
    assert not c.has_truth
    return c


# --------------------------------------------------------------------------- helpers


def _drawn(fig: Figure) -> Figure:
    """``fig`` laid out and drawn (limits of equal-aspect axes, tick labels settle)."""
    FigureCanvasAgg(fig).draw()
    return fig


def _data_lines(ax: Axes) -> list[Line2D]:
    """Lines plotted in data coordinates with data (not axhline/axvline, not edge
    notes in axes coordinates, not legend proxies)."""
    return [
        ln
        for ln in ax.get_lines()
        if ln.get_transform() == ax.transData and np.asarray(ln.get_xdata()).size > 0
    ]


def _assert_inside(ax: Axes) -> None:
    """Every finite plotted value of ``ax`` lies inside its limits."""
    x0, x1 = sorted(ax.get_xlim())
    y0, y1 = sorted(ax.get_ylim())
    for ln in _data_lines(ax):
        x = np.asarray(ln.get_xdata(), dtype=float)
        y = np.asarray(ln.get_ydata(), dtype=float)
        ok = np.isfinite(x) & np.isfinite(y)
        assert ok.any(), ln.get_label()
        assert x[ok].min() >= x0, (ln.get_label(), (x0, x1))
        assert x[ok].max() <= x1, (ln.get_label(), (x0, x1))
        assert y[ok].min() >= y0, (ln.get_label(), (y0, y1))
        assert y[ok].max() <= y1, (ln.get_label(), (y0, y1))


def _rgba(c: object) -> tuple[float, ...]:
    return tuple(round(v, 4) for v in to_rgba(c))  # type: ignore[arg-type]


def _colours_of(ln: Line2D) -> set[tuple[float, ...]]:
    """The line's colour and, when its gaps are coloured, that colour too."""
    out = {_rgba(ln.get_color())}
    gap = ln.get_gapcolor()
    if gap is not None:
        out.add(_rgba(gap))
    return out


def _legend_labels(ax: Axes) -> list[str]:
    legend = ax.get_legend()
    assert legend is not None, ax.get_title()
    return [t.get_text() for t in legend.get_texts()]


def _tick_labels(fig: Figure, ax: Axes) -> list[tuple[float, str, object]]:
    """``(location, text, extent)`` of the y tick labels drawn on ``ax``, major and minor."""
    renderer = fig.canvas.get_renderer()  # type: ignore[attr-defined]
    y0, y1 = sorted(ax.get_ylim())
    out = []
    for ticks in (ax.yaxis.get_major_ticks(), ax.yaxis.get_minor_ticks()):
        for t in ticks:
            loc = float(t.get_loc())
            text = t.label1.get_text()
            if text and t.label1.get_visible() and y0 <= loc <= y1:
                out.append((loc, text, t.label1.get_window_extent(renderer)))
    return out


def _assert_ticks_readable(fig: Figure, ax: Axes) -> None:
    """Tick labels say their own values (no "0" for 0.1) and do not overlap."""
    labels = _tick_labels(fig, ax)
    assert len(labels) >= 2, [t for _, t, _ in labels]
    for loc, text, _ in labels:
        assert math.isclose(float(text), loc, rel_tol=0.01), (text, loc)
    for (_, ta, a), (_, tb, b) in itertools.combinations(labels, 2):
        assert not a.overlaps(b), (ta, tb)


def _by_label(ax: Axes, start: str) -> Line2D:
    lines = [ln for ln in ax.get_lines() if str(ln.get_label()).startswith(start)]
    assert len(lines) == 1, [ln.get_label() for ln in ax.get_lines()]
    return lines[0]


# --------------------------------------------------------------------------- conventions


def test_estimator_colours_are_distinct_stable_and_not_by_builtin_name() -> None:
    names = [f"plugin{i}" for i in range(12)]
    colours = estimator_colours(names)
    assert len({_rgba(c) for c in colours.values()}) == 12
    # The order of first appearance decides, not the name: a plug-in listed first gets
    # the first colour, and repeated names keep theirs.
    assert estimator_colours(["toy", "ekf", "toy"]) == {
        "toy": ESTIMATOR_PALETTE[0],
        "ekf": ESTIMATOR_PALETTE[1],
    }
    # The known map's red and the greys of truth and references are never an estimator's.
    assert KNOWN_MAP_COLOUR not in ESTIMATOR_PALETTE
    assert all(_rgba(c)[0] != _rgba(c)[1] or _rgba(c)[1] != _rgba(c)[2] for c in ESTIMATOR_PALETTE)


def test_identical_curves_merge_and_different_ones_do_not() -> None:
    t = np.linspace(0.0, 10.0, 50)
    y = np.sin(t) + 2.0
    span = float(y.max() - y.min())
    near = y + 0.5 * IDENTICAL_FRACTION * span  # within half a pixel of the axis
    far = y + 3.0 * IDENTICAL_FRACTION * span  # a few pixels off: visible, kept apart
    groups = merge_identical(
        [
            Curve("a", "tab:blue", t, y),
            Curve("b", "tab:orange", t, near),
            Curve("c", "tab:green", t, far),
        ]
    )
    assert [[c.name for c in g.curves] for g in groups] == [["a", "b"], ["c"]]
    assert groups[0].label("m").startswith("a = b (identical within")
    assert groups[1].label("m") == "c"
    # A different line style (a filtered beside a smoothed estimate) is never merged.
    dashed = merge_identical([Curve("a", "k", t, y), Curve("a", "k", t, y, style="--")])
    assert len(dashed) == 2


def test_running_mean_skips_nan() -> None:
    y = np.array([1.0, np.nan, 3.0, 5.0, np.nan, np.nan])
    np.testing.assert_allclose(running_mean(y, 2), [1.0, 3.0, 4.0, 5.0, np.nan])
    with pytest.raises(ValueError, match="window must be at least 1"):
        running_mean(y, 0)


@pytest.mark.parametrize(
    ("lo", "hi"), [(1.1, 1.25), (1.1, 5.8), (0.3, 12.0), (0.02, 40.0), (1e-5, 3.0), (1e-6, 1e7)]
)
def test_log_ticks_read_their_values_without_overlap(lo: float, hi: float) -> None:
    fig = Figure(figsize=(6, 2.6), layout="constrained")
    ax = fig.subplots()
    ax.set_yscale("log")
    ax.plot([0, 1], [lo, hi])
    ax.set_ylim(lo, hi)
    log_axis_ticks(ax)
    _assert_ticks_readable(_drawn(fig), ax)


def test_a_reference_level_out_of_the_data_is_noted_not_drawn() -> None:
    fig = Figure()
    ax = fig.subplots()
    ax.plot([0, 1], [0.0, 0.1])
    ax.set_ylim(0.0, 0.11)
    assert reference_line(ax, 0.5, "paper: 0.5 m") == "above"
    assert reference_line(ax, 0.05, "half") == "line"
    assert ax.get_ylim() == (0.0, 0.11)
    labels = ax.get_legend_handles_labels()[1]
    assert "paper: 0.5 m: above this axis (↑)" in labels
    assert "half" in labels


# --------------------------------------------------------------------------- Fig. 7


def test_fig7_one_colour_per_estimator_fusion_in_panels_identical_named(
    ring: Comparison,
) -> None:
    fig = _drawn(fig7_error_fusion(ring.runs))
    top, bottom = fig.axes
    assert (top.get_title(), bottom.get_title()) == ("with map fusion", "without map fusion")
    # One scale for both panels: the gap fusion makes is read across them.
    assert top.get_ylim() == bottom.get_ylim()
    colours = run_colours(ring.runs)
    assert len({_rgba(c) for c in colours.values()}) == len(colours) == 3
    for ax in (top, bottom):
        _assert_inside(ax)
        ekf = _by_label(ax, "ekf: RMSE")
        # batch and iSAM2's smoothed errors coincide: one line, named together, drawn in
        # both colours (dashes of one, gaps of the other), not one hidden under the other.
        both = _by_label(ax, "batch = isam2: RMSE")
        assert "identical" in str(both.get_label())
        assert _colours_of(ekf) == {_rgba(colours["ekf"])}
        assert _colours_of(both) == {_rgba(colours["batch"]), _rgba(colours["isam2"])}
        labels = _legend_labels(ax)
        assert any(lab.startswith("ekf: RMSE") for lab in labels)
        assert any(lab.startswith("batch = isam2") for lab in labels)


def test_fig7_axis_fits_the_errors_and_places_the_papers_levels(ring: Comparison) -> None:
    fig = _drawn(fig7_error_fusion(ring.runs))
    top_panel, bottom_panel = fig.axes
    errors = np.concatenate(
        [np.asarray(ln.get_ydata(), dtype=float) for ax in fig.axes for ln in _data_lines(ax)]
    )
    top = float(np.nanmax(errors))
    y0, y1 = top_panel.get_ylim()
    # Scaled to the errors (5 % margin above), from 0; not stretched to 0.5 m.
    assert y0 == 0.0
    assert top <= y1 <= 1.1 * top, (top, y1)
    # This log's largest error (0.18 m) puts the fused level (0.15 m) inside the axis: a
    # labelled line at 0.15 m; the unfused level (0.5 m) is outside: a note on the edge.
    assert PAPER_FUSED_MAX_ERROR_M < y1 < PAPER_UNFUSED_ERROR_M
    fused = _by_label(top_panel, "paper: fused")
    assert np.all(np.asarray(fused.get_ydata()) == PAPER_FUSED_MAX_ERROR_M)
    notes = [ln for ln in bottom_panel.get_lines() if str(ln.get_gid()) == "reference-above"]
    assert len(notes) == 1
    assert str(notes[0].get_label()).startswith("paper: unfused")
    assert any(
        lab.startswith("paper: unfused") and "above this axis" in lab
        for lab in _legend_labels(bottom_panel)
    )


def test_fig7_without_the_papers_reference_has_no_level(ring: Comparison) -> None:
    fig = _drawn(fig7_error_fusion(ring.runs, paper_reference=False))
    for ax in fig.axes:
        assert not any("paper" in lab for lab in _legend_labels(ax))


# --------------------------------------------------------------------------- NEES


def test_nees_from_step_1_on_a_log_axis_fitted_to_the_curves(ring: Comparison) -> None:
    fig = _drawn(nees_figure(ring.runs))
    assert len(fig.axes) == 2
    assert fig.axes[0].get_ylim() == fig.axes[1].get_ylim()
    t0 = float(ring.log.timestamps[0])
    values = np.concatenate(
        [np.asarray(ln.get_ydata(), float) for ax in fig.axes for ln in _data_lines(ax)]
    )
    lo = float(np.nanmin(values[values > 0]))
    for ax in fig.axes:
        assert ax.get_yscale() == "log"
        _assert_inside(ax)
        # The axis starts near the lowest curve, not decades below it (step 0's ~0).
        assert ax.get_ylim()[0] >= lo / 10**0.5
        for ln in _data_lines(ax):
            assert float(np.min(ln.get_xdata())) > t0
        labels = _legend_labels(ax)
        assert any(lab.startswith("ekf: mean") for lab in labels)
        assert any(lab.startswith("batch = isam2 smoothed") for lab in labels)
        assert any(lab.startswith("isam2 filtered") for lab in labels)
        assert any("χ²(3, 0.95)" in lab for lab in labels)
        _assert_ticks_readable(fig, ax)
    assert "running mean over" in fig.get_suptitle()


def test_nees_of_a_short_log_leaves_step_0_out(short_ring: Comparison) -> None:
    # Window 1: the curves are the per-step NEES; step 0 (error and covariance zero by
    # construction) must not be among them.
    fig = _drawn(nees_figure(short_ring.runs))
    t = short_ring.log.timestamps
    for ax in fig.axes:
        for ln in _data_lines(ax):
            x = np.asarray(ln.get_xdata(), dtype=float)
            assert x.size == t.size - 1
            np.testing.assert_array_equal(x, t[1:])
        _assert_inside(ax)
        assert ax.get_ylim()[0] > 1e-2


# --------------------------------------------------------------------------- maps


def _markers(ax: Axes, colour: str) -> list[Line2D]:
    """Marker-only lines (feature centres) of ``colour`` with data."""
    return [
        ln
        for ln in _data_lines(ax)
        if ln.get_linestyle() in ("None", "none", "")
        and _rgba(ln.get_markeredgecolor()) == _rgba(colour)
    ]


def _assert_known_and_estimated_apart(ax: Axes, estimated_colour: str) -> None:
    known = _markers(ax, KNOWN_MAP_COLOUR)
    est = _markers(ax, estimated_colour)
    assert known
    assert est
    k, e = known[0], est[0]
    # A different colour, marker and fill, and a size in points (the same on screen at
    # any map extent) large enough to see.
    assert _rgba(k.get_markeredgecolor()) != _rgba(e.get_markeredgecolor())
    assert k.get_marker() != e.get_marker()
    assert (k.get_markerfacecolor() == "none") != (e.get_markerfacecolor() == "none")
    assert min(k.get_markersize(), e.get_markersize()) >= 4.0
    # Their legend entries show the marker drawn, not a patch's rectangle.
    legend = ax.get_legend()
    assert legend is not None
    handles = dict(
        zip([t.get_text() for t in legend.get_texts()], legend.legend_handles, strict=True)
    )
    for start, marker in (("known map", k.get_marker()), ("estimated map", e.get_marker())):
        (h,) = [h for lab, h in handles.items() if lab.startswith(start)]
        assert isinstance(h, Line2D)
        assert not isinstance(h, Rectangle)
        assert h.get_marker() == marker


def test_fig10_known_and_estimated_features_apart(ring: Comparison) -> None:
    fused = [r for r in ring.runs if r.fusion][:2]
    colours = run_colours(ring.runs)
    fig = _drawn(fig10_maps(fused, colours=colours))
    for ax, run in zip(fig.axes, fused, strict=True):
        _assert_known_and_estimated_apart(ax, colours[run.estimator])
        _assert_inside(ax)


def test_gps_figures_real_data(gps: Comparison) -> None:
    colours = run_colours(gps.runs)
    fig = _drawn(gps_trajectory_figure(gps.runs, colours=colours))
    assert [ax.get_title() for ax in fig.axes] == ["with map fusion", "without map fusion"]
    for ax in fig.axes:
        _assert_known_and_estimated_apart_known_only(ax)
        labels = _legend_labels(ax)
        assert any(lab.startswith("batch = isam2") for lab in labels)
        assert any(lab.startswith("ekf") for lab in labels)
        assert "GPS fixes" in labels
        _assert_inside(ax)
    # Real data has no seed: titles do not say "seed -1".
    assert "seed" not in fig.get_suptitle()
    fig = _drawn(gps_error_figure(gps.runs, colours=colours))
    assert fig.axes[0].get_ylim() == fig.axes[1].get_ylim()
    for ax in fig.axes:
        _assert_inside(ax)
        ekf = _by_label(ax, "ekf")
        assert _colours_of(ekf) == {_rgba(colours["ekf"])}
    assert "seed" not in fig.get_suptitle()
    maps = _drawn(fig10_maps([r for r in gps.runs if r.fusion][:2], colours=colours))
    assert "seed" not in maps.get_suptitle()
    for ax, run in zip(maps.axes, [r for r in gps.runs if r.fusion][:2], strict=True):
        _assert_known_and_estimated_apart(ax, colours[run.estimator])


def _assert_known_and_estimated_apart_known_only(ax: Axes) -> None:
    """The known map's features drawn as hollow markers with a marker legend entry."""
    (known,) = _markers(ax, KNOWN_MAP_COLOUR)
    assert known.get_markerfacecolor() == "none"
    assert known.get_markersize() >= 4.0


# --------------------------------------------------------------------------- campaign


def _group(estimator: str, fusion: bool, seed: int, runs: int, scale: float = 1.0) -> GroupSummary:
    """A campaign group of ``runs`` runs from seeded χ²(3) NEES times ``scale`` (1: a
    consistent estimator, below 1: a pessimistic one) whose step 0 is ~0 (the start
    pose fixed by a prior), and RMSE growing with time at a rate of its own (``seed``)."""
    rng = np.random.default_rng(seed)
    steps = 300
    nees = scale * rng.chisquare(3, size=(runs, steps))
    nees[:, 0] = 1e-6
    t = 0.125 * np.arange(steps)
    rmse = 0.01 + 0.0001 * (1 + seed) * np.arange(steps)
    rmse[0] = 0.0
    rows = tuple({"seed": s, "max_m": float(0.1 + 0.01 * s)} for s in range(runs))
    return GroupSummary(
        estimator=estimator,
        fusion=fusion,
        seeds=tuple(range(runs)),
        failed=(),
        errors=(),
        anees=anees_series(nees),
        timestamps=t,
        rmse=rmse,
        rows=rows,
    )


@pytest.fixture(scope="module")
def groups() -> list[GroupSummary]:
    """EKF with fusion: two pessimistic runs, whose wide bounds (0.6-7.2) reach beyond
    every ANEES drawn; the others: twenty consistent runs each (ANEES within about
    1.5-4.5)."""
    return [
        _group("ekf", True, 0, runs=2, scale=0.3),
        _group("batch", True, 11, runs=20),
        _group("ekf", False, 1, runs=20),
        _group("batch", False, 10, runs=20),
    ]


def _bounds(ax: Axes) -> Iterator[np.ndarray]:
    for coll in ax.collections:
        if isinstance(coll, PolyCollection):
            for path in coll.get_paths():
                yield path.vertices


def test_anees_bounds_in_view_step_0_out_ticks_readable(groups: Sequence[GroupSummary]) -> None:
    fig = _drawn(anees_figure(groups))
    axes = fig.axes
    assert len(axes) == 4  # estimators × fusion settings
    assert len({ax.get_ylim() for ax in axes}) == 1
    colours = estimator_colours(g.estimator for g in groups)
    lowest = min(
        float(np.nanmin(np.concatenate([g.anees.anees[1:], g.anees.lower[1:]]))) for g in groups
    )
    for ax, g in zip(axes, [groups[0], groups[2], groups[1], groups[3]], strict=True):
        assert ax.get_title().startswith(f"{g.estimator} {'with' if g.fusion else 'without'}")
        assert ax.get_yscale() == "log"
        _assert_inside(ax)
        y0, y1 = ax.get_ylim()
        # Near the lowest ANEES or bound from step 1 on; step 0's 1e-6 would put the axis
        # five decades below.
        assert y0 >= lowest / 10**0.5
        (line,) = _data_lines(ax)
        assert _colours_of(line) == {_rgba(colours[g.estimator])}
        assert float(np.min(line.get_xdata())) > float(g.timestamps[0])
        # The shaded bounds are drawn and lie wholly inside the view.
        verts = list(_bounds(ax))
        assert verts
        for v in verts:
            ok = np.isfinite(v[:, 1])
            assert y0 <= v[ok, 1].min()
            assert v[ok, 1].max() <= y1
        if ax.get_subplotspec().is_first_col():  # the others share its labels
            _assert_ticks_readable(fig, ax)
    labels = [t.get_text() for legend in fig.legends for t in legend.get_texts()]
    assert "ANEES over the runs" in labels
    assert any("bounds" in lab for lab in labels)
    assert any(lab.startswith("3: expected ANEES") for lab in labels)


def test_campaign_rmse_and_max_error_colours(groups: Sequence[GroupSummary]) -> None:
    fig = _drawn(rmse_figure(groups))
    colours = estimator_colours(g.estimator for g in groups)
    assert [ax.get_title() for ax in fig.axes] == ["with fusion", "without fusion"]
    assert fig.axes[0].get_ylim() == fig.axes[1].get_ylim()
    for ax in fig.axes:
        _assert_inside(ax)
        drawn = {frozenset(_colours_of(ln)) for ln in _data_lines(ax)}
        assert drawn == {frozenset({_rgba(colours["ekf"])}), frozenset({_rgba(colours["batch"])})}
        labels = _legend_labels(ax)
        assert any(lab.startswith("ekf (") for lab in labels)
        assert any(lab.startswith("batch (20 runs)") for lab in labels)
    fig = _drawn(max_error_figure(groups))
    faces = {_rgba(p.get_facecolor())[:3] for p in fig.axes[0].patches}
    assert {_rgba(colours[e])[:3] for e in ("ekf", "batch")} <= faces


# --------------------------------------------------------------------------- report


def test_beside_comparisons_get_their_figures(ring: Comparison, tmp_path: Path) -> None:
    sparse = dataclasses.replace(ring, log=dataclasses.replace(ring.log, scenario="loop600-sparse"))
    main = dataclasses.replace(ring, log=dataclasses.replace(ring.log, scenario="loop600"))
    paths = write_comparison(main, tmp_path, beside=(sparse,))
    fig7 = tmp_path / BESIDE_DIR / "loop600-sparse" / "fig7_error_fusion.png"
    assert fig7.is_file()
    assert paths[f"{BESIDE_DIR}/loop600-sparse/fig7_error_fusion"] == str(fig7)
    report = (tmp_path / "report.md").read_text()
    _, other = report.split("## loop600-sparse, seed 0 (the paper's regime)")
    assert f"]({BESIDE_DIR}/loop600-sparse/fig7_error_fusion.png)" in other
    assert "![" in other  # Fig. 7 shown in place
    assert (tmp_path / BESIDE_DIR / "loop600-sparse" / "report.md").is_file()


def test_real_data_report_title_has_no_seed(gps: Comparison) -> None:
    from mapfuse.comparison import report_markdown

    report = report_markdown(gps)
    assert report.splitlines()[0] == "# Backend comparison: synthetic-gps"
    assert "seed -1" not in report
    assert "*paper:" not in report


def test_changes_figure_marks_circles_at_any_map_extent(ring: Comparison) -> None:
    from mapfuse.changes import detect_changes
    from mapfuse.changes_figure import changes_figure

    run = ring.get("ekf", True)
    report = detect_changes(run.result, ring.log)
    fig = _drawn(changes_figure(report, ring.log, run.result.poses))
    (ax,) = fig.axes
    # Every known circle has a centre marker of fixed size on screen.
    circles = int(np.sum(ring.log.known_map.kinds == FeatureKind.CIRCLE))
    centres = [
        ln
        for ln in _data_lines(ax)
        if ln.get_marker() == "o" and ln.get_linestyle() in ("None", "none", "")
    ]
    assert circles > 0
    assert len(centres) >= circles
    assert min(ln.get_markersize() for ln in centres) >= 4.0
    legend = ax.get_legend()
    assert legend is not None
    for text, handle in zip(legend.get_texts(), legend.legend_handles, strict=True):
        assert not isinstance(handle, Rectangle), text.get_text()
