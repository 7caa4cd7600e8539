"""One log through every backend, with and without map fusion, and the report of it.

The library side of ``mapfuse compare``: :func:`compare` runs registered estimators
(by default the EKF reference, batch Levenberg–Marquardt and iSAM2) on one log for
each fusion setting (an estimator that consumes another's result, as the graph runs
consume the EKF's association decisions, gets that run of the same setting, made
once per setting), and :func:`write_comparison` writes ``comparison.json`` (the list
of ``metrics.json`` objects), ``report.md`` (one table, the paper's numbers beside
ours) and the figures of :mod:`mapfuse.figures`.
"""

from __future__ import annotations

import json
import math
import re
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mapfuse import registry
from mapfuse.execution import fusion_for
from mapfuse.figures import (
    PAPER_ANCHOR_ESTIMATE,
    PAPER_ANCHOR_TRUTH,
    PAPER_FUSED_MAX_ERROR_M,
    PAPER_SCENARIOS,
    PAPER_UNFUSED_ERROR_M,
    fig6_errors_bounds,
    fig7_error_fusion,
    fig10_maps,
    gps_error_figure,
    gps_trajectory_figure,
    nees_figure,
    run_colours,
    timing_figure,
)
from mapfuse.metrics import run_metrics
from mapfuse.outputs import write_outputs
from mapfuse.plan import RunRequest, execute, plan_runs
from mapfuse.plotting import log_name
from mapfuse.registry import resolve
from mapfuse.runner import Run
from mapfuse_core.estimate import RunMetrics
from mapfuse_core.evaluation import CHI2_3_95, path_length
from mapfuse_core.geometry.se2 import wrap_scalar
from mapfuse_core.measlog import MeasurementLog

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from mapfuse_core.sim.scenario import Scenario

__all__ = [
    "BESIDE_DIR",
    "DEFAULT_ESTIMATORS",
    "FIGURE_FILES",
    "PAPER_REGIME",
    "RUNS_DIR",
    "Comparison",
    "beside_lines",
    "compare",
    "comparison_figures",
    "is_paper_scenario",
    "report_markdown",
    "results_table",
    "run_folder_name",
    "write_comparison",
]

#: Figure file names written by :func:`write_comparison`, and what each shows.
FIGURE_FILES: Mapping[str, str] = {
    "fig6_errors_bounds.png": "EKF with fusion: x, y, θ errors with 2σ bounds (paper Fig. 6)",
    "fig7_error_fusion.png": "position error with fusion (top) and without (bottom), one "
    "colour per estimator, on one scale (Fig. 7)",
    "fig10_maps.png": "estimated maps and trajectories over the known map, in Wknown (Fig. 10)",
    "nees.png": "vehicle NEES (running mean, from step 1) against 3 and χ²(3, 0.95)",
    "timing.png": "per-step run time of each estimator (log scale)",
    "gps_errors.png": "position error against GPS over time, with and without fusion (real data)",
    "gps_trajectories.png": "estimated trajectories over the GPS track and the known map "
    "(real data)",
}

#: Sub-folder of a comparison holding one folder of files per run.
RUNS_DIR = "runs"
#: Sub-folder of a comparison holding the full output (report, figures, runs) of each
#: comparison beside it (``--beside``), one folder per scenario.
BESIDE_DIR = "beside"

# Figures that compare with truth: not written for a log without true poses.
_NEEDS_TRUTH = ("fig6_errors_bounds.png", "fig7_error_fusion.png", "nees.png")

Progress = Callable[[str, int, int], None]

#: What :func:`compare` runs when no estimators are named.
DEFAULT_ESTIMATORS: tuple[str, ...] = tuple(registry.BUILTIN)


@dataclass(frozen=True)
class Comparison:
    """Every estimator on one log, for each fusion setting."""

    log: MeasurementLog
    """The log all runs consumed."""
    runs: tuple[Run, ...]
    """Runs ordered by fusion setting (as requested; only without fusion on a log without a
    known map), then estimator (as requested, those whose results others consume first)."""
    wall_time_s: float
    """Wall time (s) of the whole :func:`compare` call; ``mapfuse compare`` sets the
    command's own (its simulation included) before writing the report."""

    @property
    def metrics(self) -> list[RunMetrics]:
        """The metrics of every run, in :attr:`runs` order."""
        return [r.metrics for r in self.runs]

    @property
    def has_truth(self) -> bool:
        """Whether the log holds true poses (simulation), i.e. errors can be computed."""
        return self.log.true_poses is not None

    @property
    def has_gps(self) -> bool:
        """Whether every run has position errors against GPS (real data with GPS)."""
        return all(
            m.position_error is not None and m.position_error.reference == "gps"
            for m in self.metrics
        )

    def get(self, estimator: str, fusion: bool) -> Run:
        """The run of ``estimator`` with or without fusion; :class:`KeyError` if not run."""
        for r in self.runs:
            if r.estimator == estimator and r.fusion is bool(fusion):
                return r
        have = ", ".join(
            f"{r.estimator}/{'fusion' if r.fusion else 'no fusion'}" for r in self.runs
        )
        raise KeyError(f"no {estimator} run {'with' if fusion else 'without'} fusion (have {have})")

    def find(self, estimator: str, fusion: bool) -> Run | None:
        """:meth:`get`, or ``None`` when that run was not made."""
        try:
            return self.get(estimator, fusion)
        except KeyError:
            return None


def compare(
    log: MeasurementLog,
    estimators: Sequence[str] | None = None,
    *,
    fusions: Sequence[bool] = (True, False),
    overrides: Mapping[str, Mapping[str, Any]] | None = None,
    progress: Progress | None = None,
) -> Comparison:
    """Run ``estimators`` × ``fusions`` on ``log``.

    ``estimators``: registered estimator names (default :data:`DEFAULT_ESTIMATORS`).  An
    estimator that consumes another's result (the graph backends: the EKF's association
    decisions) gets that estimator's run of the same fusion setting, made once per
    setting (also when it is not among ``estimators``: it is then used but not
    reported; :mod:`mapfuse.plan`).  ``progress(label, k, n)`` is called as each run
    advances, ``label`` naming the run (e.g. ``"isam2 without fusion"``).  A log
    without a known map (Victoria Park) has nothing to fuse, so there each estimator
    runs once, without fusion, whatever ``fusions`` asks.  ``overrides``: option fields
    per estimator name (e.g. ``{"batch": {"graph": {"robust": "huber"}}}``,
    :func:`mapfuse.options.make_options`); a name not among ``estimators`` is an error.
    """
    names = DEFAULT_ESTIMATORS if estimators is None else tuple(estimators)
    if not names or len(set(names)) != len(names):
        raise ValueError(f"estimators must be distinct registered names, got {list(names)}")
    ests = [resolve(b) for b in names]
    overrides = dict(overrides or {})
    stray = sorted(set(overrides) - set(names))
    if stray:
        raise ValueError(f"overrides for {', '.join(stray)}, which are not among the estimators")
    if not fusions or len(set(fusions)) != len(fusions):
        raise ValueError(f"fusions must be distinct booleans, got {list(fusions)}")
    consumed = {e.capabilities.consumes for e in ests}
    # Estimators whose results others consume come first (stable otherwise).
    ests.sort(key=lambda e: e.name not in consumed)
    requests = [RunRequest(e.name, f, overrides.get(e.name, {})) for f in fusions for e in ests]
    t0 = time.perf_counter()
    plan = plan_runs(requests, len(log.known_map) > 0)
    done = execute(plan, log, progress=progress)
    runs = [
        Run(result=d.result, log=log, metrics=run_metrics(d.result, log))
        for d in done
        if d.planned.reported and d.result is not None
    ]
    # By the fusion each run reports (an estimator that cannot fuse reports none).
    order = [e.name for e in ests]
    fused = [fusion_for(log, f) for f in fusions]
    runs.sort(
        key=lambda r: (
            fused.index(r.fusion) if r.fusion in fused else len(fused),
            order.index(r.estimator) if r.estimator in order else len(order),
        )
    )
    return Comparison(log=log, runs=tuple(runs), wall_time_s=time.perf_counter() - t0)


# --------------------------------------------------------------------------- figures


def is_paper_scenario(log: MeasurementLog) -> bool:
    """Whether the paper's numbers (Sect. 4.2) are a reference for ``log``: a simulated
    log (true poses) of one of :data:`mapfuse.figures.PAPER_SCENARIOS`."""
    return log.true_poses is not None and log.scenario in PAPER_SCENARIOS


def comparison_figures(
    comparison: Comparison, scenario: Scenario | None = None
) -> dict[str, Figure]:
    """The figures of :data:`FIGURE_FILES` that this comparison can draw, by file name.

    Without truth only ``fig10_maps.png`` and ``timing.png``; ``fig6`` needs the EKF
    with fusion.  ``scenario`` (optional) supplies the true world's wall segments.
    """
    runs = comparison.runs
    # One colour per estimator, in the comparison's order, in every figure.
    colours = run_colours(runs)
    out: dict[str, Figure] = {}
    if comparison.has_truth:
        first_fused = next((r for r in runs if r.fusion), None)
        if first_fused is not None:
            out["fig6_errors_bounds.png"] = fig6_errors_bounds(first_fused, colours=colours)
        out["fig7_error_fusion.png"] = fig7_error_fusion(
            runs, paper_reference=is_paper_scenario(comparison.log), colours=colours
        )
    # The first two fused runs (the unfused ones when nothing was fused): the consumed
    # estimator first, then the first that consumes it.
    fused = [r for r in runs if r.fusion]
    panels = (fused if fused else list(runs))[:2]
    world = None if scenario is None else scenario.world
    out["fig10_maps.png"] = fig10_maps(panels, world, colours=colours)
    if comparison.has_truth:
        out["nees.png"] = nees_figure(runs, colours=colours)
    elif comparison.has_gps:
        out["gps_errors.png"] = gps_error_figure(runs, colours=colours)
        out["gps_trajectories.png"] = gps_trajectory_figure(runs, colours=colours)
    out["timing.png"] = timing_figure(runs, colours=colours)
    return out


# --------------------------------------------------------------------------- report


def _num(v: Any, digits: int = 3, scale: float = 1.0) -> str:
    if v is None:
        return "n/a"
    x = float(v)
    if not math.isfinite(x):
        return "n/a"
    return f"{scale * x:.{digits}f}"


def _label(m: RunMetrics) -> str:
    return f"{m.estimator} {'with' if m.fusion else 'without'} fusion"


def _run_name(m: RunMetrics) -> str:
    """Label of a row, marking smoothed estimates."""
    return f"{_label(m)}{' (smoothed)' if m.estimate == 'smoothed' else ''}"


def _map_and_runtime(m: RunMetrics) -> list[str]:
    """The map-size and run-time cells every table ends with."""
    mp, rt = m.map, m.runtime
    return [
        f"{mp.features} ({mp.matched_known})",
        f"{_num(rt.total, 2)} ({_num(rt.per_step_p50, 2, 1e3)})",
    ]


def _figure_list(figures: Sequence[str]) -> list[str]:
    if not figures:
        return []
    lines = ["", "Figures:", ""] + [
        f"- [`{n}`]({n}): {FIGURE_FILES.get(Path(n).name, '')}" for n in figures
    ]
    # Fig. 7 shown in place: what fusion does, at a glance.
    fig7 = [n for n in figures if Path(n).name == "fig7_error_fusion.png"]
    return lines + [f"\n![{FIGURE_FILES['fig7_error_fusion.png']}]({n})" for n in fig7]


def _row(cells: Sequence[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def _metric_row(m: RunMetrics, has_truth: bool) -> list[str]:
    pos, head, nees, anchor = m.position_error, m.heading_error, m.nees, m.anchor
    no = "no truth"
    cells = [_run_name(m)]
    if has_truth and pos is not None and head is not None and nees is not None:
        cells += [
            _num(pos.rmse),
            _num(pos.max),
            _num(head.rmse, 2, 1e3),
            _num(nees.mean, 2),
            _num(nees.fraction_within_chi2_95, 3),
        ]
    else:
        cells += [no] * 5
    if anchor is None:
        cells.append("none")
    elif anchor.position_error_m is None:
        cells.append(f"{no} ({anchor.pairings} pairings)")
    else:
        cells.append(
            f"{_num(anchor.position_error_m)}, {_num(anchor.heading_error_rad, 2, 1e3)}"
            f" ({anchor.correct_pairings}/{anchor.pairings} pairings correct)"
        )
    return cells + _map_and_runtime(m)


def _filtered_row(m: RunMetrics) -> list[str] | None:
    pos, nees = m.position_error_filtered, m.nees_filtered
    if pos is None or nees is None:
        return None
    return [
        f"{_label(m)} (filtered)",
        _num(pos.rmse),
        _num(pos.max),
        "",
        _num(nees.mean, 2),
        _num(nees.fraction_within_chi2_95, 3),
        "",
        "",
        "",
    ]


def _gps_row(m: RunMetrics) -> list[str]:
    pos, anchor = m.position_error, m.anchor
    assert pos is not None  # a GPS table holds runs with GPS errors only
    cells = [_run_name(m), str(pos.alignment).replace("_", " ")]
    cells += [_num(v) for v in (pos.median, pos.rmse, pos.max, pos.final)]
    filtered = m.position_error_filtered
    cells.append(_num(filtered.median) if filtered is not None else "")
    if anchor is None:
        cells.append("none")
    else:
        cells.append(
            f"step {anchor.accepted_at_step}: {anchor.correct_pairings}/{anchor.pairings} correct"
        )
    return cells + _map_and_runtime(m)


def _gps_table(comparison: Comparison) -> list[str]:
    header = [
        "run",
        "alignment to GPS",
        "median [m]",
        "RMSE [m]",
        "max [m]",
        "final [m]",
        "filtered median [m]",
        "anchor (pairings)",
        "map features (matched known)",
        "run time [s] (median per step [ms])",
    ]
    lines = [_row(header), _row(["---"] * len(header))]
    lines += [_row(_gps_row(m)) for m in comparison.metrics]
    lines += [
        "",
        "Notes:",
        "",
        "- Position error of the laser against the GPS fix, the estimate interpolated at "
        "the GPS times. *anchor*: the estimate is put in the known-map (= GPS) frame "
        "through the run's own anchor `x^Wknown_Wglobal`, an honest test. *best fit*: "
        "no anchor, so the rigid transform that best fits the whole trajectory to GPS is "
        "used, which hides any rigid error and favours the run.",
        "- GPS is a reference, not truth: it has its own errors, and its antenna is not "
        "exactly at the laser, which shows in tight turns.",
        "- Pairings are judged correct against reference beacon labels obtained by "
        "projecting each detection through GPS-aligned dead reckoning (car park only).",
        "- Graph runs use the EKF's association decisions of the same fusion setting; "
        "their rows are smoothed, the *filtered median* is iSAM2's per-step estimate.",
    ]
    return lines


def _warning_lines(metrics: Sequence[RunMetrics]) -> list[str]:
    """A *Warnings* section: every run's warnings (docs/warnings.md)."""
    items = [f"- {_label(m)}: {w}" for m in metrics for w in m.warnings]
    return ["", "Warnings:", "", *items] if items else []


def _paper_anchor_error() -> tuple[float, float]:
    e, t = PAPER_ANCHOR_ESTIMATE, PAPER_ANCHOR_TRUTH
    return math.hypot(e[0] - t[0], e[1] - t[1]), abs(wrap_scalar(e[2] - t[2]))


def _paper_row(fusion: bool) -> list[str]:
    if fusion:
        d, h = _paper_anchor_error()
        return [
            "*paper: EKF with fusion*",
            "",
            f"*< {PAPER_FUSED_MAX_ERROR_M:.2f}*",
            "",
            "",
            "",
            f"*{d:.3f}, {1e3 * h:.2f}*",
            "",
            "",
        ]
    return [
        "*paper: EKF without fusion*",
        "",
        f"*≈ {PAPER_UNFUSED_ERROR_M:.2f} far from the start*",
        "",
        "",
        "",
        "*none*",
        "",
        "",
    ]


def results_table(comparison: Comparison) -> list[str]:
    """The markdown table of a comparison with truth: one row per run (and per
    filtered estimate), the fused runs first, each group followed by the paper's row
    for a log of the paper's drive (:func:`is_paper_scenario`)."""
    truth = comparison.has_truth
    paper = is_paper_scenario(comparison.log)
    metrics = comparison.metrics
    header = [
        "run",
        "position RMSE [m]",
        "position max [m]",
        "heading RMSE [mrad]",
        "NEES mean",
        f"NEES ≤ {CHI2_3_95:.3f} (fraction)",
        "anchor error [m, mrad]",
        "map features (matched known)",
        "run time [s] (median per step [ms])",
    ]
    lines = [_row(header), _row(["---"] * len(header))]
    for fusion in (True, False):
        sel = [m for m in metrics if m.fusion is fusion]
        if not sel:
            continue
        for m in sel:
            lines.append(_row(_metric_row(m, truth)))
            filtered = _filtered_row(m)
            if filtered is not None and truth:
                lines.append(_row(filtered))
        if paper:
            lines.append(_row(_paper_row(fusion)))
    return lines


#: The built-in scenario in the paper's regime that a scenario's report names (`--beside`).
PAPER_REGIME: Mapping[str, str] = {"loop600": "loop600-sparse"}


def _log_summary(log: MeasurementLog, span: str) -> str:
    """``span``, the true path length when known, the features and the known map."""
    out = span
    if log.true_poses is not None:
        out += f", true path {path_length(log.true_poses):.1f} m"
    return f"{out}; {log.n_features} extracted features; known map of {len(log.known_map)} features"


def beside_lines(
    main_scenario: str,
    beside: Sequence[Comparison],
    figures: Sequence[Sequence[str]] = (),
) -> list[str]:
    """The report section of the comparisons ``beside`` the one of ``main_scenario``:
    a heading, the log's description, the results table and (``figures``, as
    ``beside``: paths relative to the report) the figures of each; with none, for a
    scenario of :data:`PAPER_REGIME`, a note naming the option that adds it."""
    if not beside:
        other = PAPER_REGIME.get(main_scenario)
        if other is None:
            return []
        return [
            "",
            f"The paper's regime, where SLAM without fusion drifts about 0.5 m far from "
            f"the start, is the sparser `{other}`: `--beside {other}` puts its table here.",
        ]
    lines: list[str] = []
    for i, b in enumerate(beside):
        log = b.log
        desc = f"{_log_summary(log, f'{log.n_steps} steps')}; {b.wall_time_s:.1f} s wall time."
        title = "the paper's regime" if log.scenario in PAPER_REGIME.values() else "beside"
        lines += ["", f"## {log_name(log.scenario, log.seed)} ({title})", "", desc, ""]
        lines += results_table(b)
        lines += _figure_list(figures[i] if i < len(figures) else ())
    return lines


def _notes(log: MeasurementLog) -> list[str]:
    """The notes under the results table; the paper's numbers only for its drive."""
    paper = is_paper_scenario(log)
    anchor = (
        "- Anchor error: distance and heading difference between the estimated pose of "
        "`Wglobal` in the known map (`x^Wknown_Wglobal`) and the true start pose."
    )
    if paper:
        anchor += (
            " The paper estimates "
            f"[{', '.join(f'{v:.3f}' for v in PAPER_ANCHOR_ESTIMATE[:2])}, "
            f"{PAPER_ANCHOR_ESTIMATE[2]:.4f}] against the truth [−29, −11, π/3], i.e. "
            f"{100 * _paper_anchor_error()[0]:.1f} cm."
        )
    notes = [
        "- Errors are of the vehicle pose in `Wglobal` (the vehicle at step 0) against "
        "truth; NEES is that of the 3-dof pose error, consistent when below "
        f"χ²(3, 0.95) = {CHI2_3_95:.3f}.",
        anchor,
        "- Graph runs (batch, isam2) use the EKF's association decisions of the same fusion "
        "setting. Their rows are smoothed estimates (every step uses the whole log), the "
        "EKF's and iSAM2's *filtered* rows use only the steps so far, which is what the "
        "paper's figures show.",
        "- Run time: batch has no per-step cost; its build, solve and marginals are shared "
        "equally over the steps.",
    ]
    if paper:
        notes.append(
            "- Rows in *italics* are the paper's simulation (Sect. 4.2) where it gives numbers."
        )
    if paper and log.scenario != PAPER_SCENARIOS[0]:
        notes.append(
            f"- The paper's numbers are for its 600 m loop (our `{PAPER_SCENARIOS[0]}`); this "
            f"log is `{log.scenario}`, so they are only a scale reference here."
        )
    return notes


def report_markdown(
    comparison: Comparison,
    figures: Sequence[str] = (),
    scenario: Scenario | None = None,
    beside: Sequence[Comparison] = (),
    beside_figures: Sequence[Sequence[str]] = (),
) -> str:
    """The ``report.md`` text: run description, one table, notes, known-map changes,
    warnings, figure list, then the comparisons ``beside`` it with their figures
    (:func:`beside_lines`)."""
    log = comparison.log
    truth = comparison.has_truth
    lines = [f"# Backend comparison: {log_name(log.scenario, log.seed)}", ""]
    span = f"{log.n_steps} steps over {log.timestamps[-1] - log.timestamps[0]:.1f} s"
    desc = f"{_log_summary(log, span)}. Whole comparison: {comparison.wall_time_s:.1f} s wall time."
    if scenario is not None and scenario.description:
        lines += [f"Scenario: {scenario.description}.", ""]
    lines += [desc, ""]
    if log.metadata:
        facts = "; ".join(f"{k.replace('_', ' ')}: {v}" for k, v in sorted(log.metadata.items()))
        lines += [f"Log: {facts}.", ""]
    if not truth and comparison.has_gps:
        lines += [
            "**Real data**: no true poses, so errors are against GPS; heading errors and "
            "NEES cannot be computed.",
            "",
        ]
        from mapfuse.changes import change_report_lines

        lines += _gps_table(comparison)
        lines += change_report_lines([r.result for r in comparison.runs], log, None)
        lines += _warning_lines(comparison.metrics)
        lines += _figure_list(figures)
        return "\n".join(lines) + "\n"
    if not truth:
        lines += [
            "**This log has no ground truth** (no true poses, e.g. real data): position, "
            "heading, NEES and anchor errors cannot be computed and read *no truth*; the "
            "figures that need truth (Figs. 6 and 7, NEES) are not written.",
            "",
        ]
    lines += results_table(comparison)
    lines += ["", "Notes:", "", *_notes(log)]
    from mapfuse.changes import change_report_lines

    lines += change_report_lines([r.result for r in comparison.runs], log, scenario)
    lines += _warning_lines(comparison.metrics)
    lines += _figure_list(figures)
    lines += beside_lines(log.scenario, beside, beside_figures)
    return "\n".join(lines) + "\n"


def write_comparison(
    comparison: Comparison,
    out_dir: str | Path,
    scenario: Scenario | None = None,
    beside: Sequence[Comparison] = (),
) -> dict[str, str]:
    """Write ``comparison.json``, ``report.md`` and the figures into ``out_dir``, and
    each run's own files (:func:`mapfuse.outputs.write_outputs` without figures: its
    ``metrics.json`` and TUM trajectories) into ``out_dir/runs/<backend>_<fusion>/``
    (:func:`run_folder_name`).

    ``scenario`` (optional) adds its description to the report and draws the true
    world's walls in Fig. 10.  ``beside``: comparisons of other scenarios the report
    shows after its own table, their metrics in ``beside.json``
    (``{scenario: [metrics, ...]}``).  Returns ``{name: path}`` of everything written (figure
    entries keyed by file name without ``.png``, a run's files by
    ``runs/<folder>/<name>``).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {"comparison": out / "comparison.json"}
    paths["comparison"].write_text(
        json.dumps([m.to_json() for m in comparison.metrics], indent=2) + "\n"
    )
    figures = comparison_figures(comparison, scenario)
    for name, fig in figures.items():
        p = out / name
        fig.savefig(p, dpi=110)
        paths[name.removesuffix(".png")] = p
    beside_figures: list[list[str]] = []
    nested: dict[str, str] = {}
    if beside:
        paths["beside"] = out / "beside.json"
        paths["beside"].write_text(
            json.dumps({b.log.scenario: [m.to_json() for m in b.metrics] for b in beside}, indent=2)
            + "\n"
        )
        taken: set[str] = set()
        for b in beside:
            folder = _beside_folder(b.log.scenario, taken)
            written = write_comparison(b, out / BESIDE_DIR / folder)
            nested.update({f"{BESIDE_DIR}/{folder}/{k}": v for k, v in written.items()})
            beside_figures.append(
                [
                    f"{BESIDE_DIR}/{folder}/{name}"
                    for name in FIGURE_FILES
                    if name.removesuffix(".png") in written
                ]
            )
    paths["report"] = out / "report.md"
    paths["report"].write_text(
        report_markdown(comparison, tuple(figures), scenario, beside, beside_figures)
    )
    result = {k: str(v) for k, v in paths.items()}
    result.update(nested)
    for r in comparison.runs:
        name = run_folder_name(r)
        files = write_outputs(r, out / RUNS_DIR / name, figures=False)
        result.update({f"{RUNS_DIR}/{name}/{k}": v for k, v in files.items()})
    return result


def _beside_folder(scenario: str, taken: set[str]) -> str:
    """A folder name for a comparison beside the main one: the scenario's name (a TOML
    file's stem), made safe for a path and distinct from those ``taken``."""
    name = Path(scenario).stem if scenario.endswith(".toml") else scenario
    base = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "scenario"
    folder, k = base, 2
    while folder in taken:
        folder, k = f"{base}-{k}", k + 1
    taken.add(folder)
    return folder


def run_folder_name(r: Run) -> str:
    """Sub-folder of :data:`RUNS_DIR` holding a run's own files, e.g. ``isam2_fusion``."""
    return f"{r.estimator}_{'fusion' if r.fusion else 'no_fusion'}"
