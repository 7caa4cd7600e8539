"""``DIR/report.md`` and its figures for a campaign directory: :func:`write_report`."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

from mapfuse.campaign.plots import anees_figure, max_error_figure, rmse_figure
from mapfuse.campaign.stats import mean_interval
from mapfuse.campaign.store import CampaignStore
from mapfuse.campaign.summary import (
    MAX_ERROR_LIMIT_M,
    NEES_WITHIN_LIMIT,
    GroupSummary,
    summarise,
)

__all__ = ["FIGURE_FILES", "report_markdown", "write_report"]

#: Figures written beside ``report.md``, and what each shows.
FIGURE_FILES = {
    "anees.png": "ANEES against time with its two-sided 95 % bounds, one panel per estimator",
    "rmse.png": "position RMSE per step over the runs, with and without fusion",
    "max_error.png": "distribution of the per-run maximum position error",
}


def _f(x: float, digits: int = 3) -> str:
    return "n/a" if not math.isfinite(x) else f"{x:.{digits}f}"


def _label(g: GroupSummary) -> str:
    return f"{g.estimator} {'with' if g.fusion else 'without'} fusion"


def _consistency_table(groups: Sequence[GroupSummary]) -> list[str]:
    out = [
        "| run | runs (failed) | ANEES | steps inside bounds | above | "
        "anchor ANEES [bounds] (runs) | wrong pairings (runs with any) |",
        "|---|---|---|---|---|---|---|",
    ]
    for g in groups:
        a = g.anees
        m, lo, hi, n = g.anchor_anees
        anchor = "n/a" if n == 0 else f"{_f(m)} [{_f(lo)}, {_f(hi)}] ({n})"
        wrong, runs_wrong = g.wrong_pairings
        wp = "n/a" if n == 0 and not g.values("wrong_pairings") else f"{wrong} ({runs_wrong})"
        out.append(
            f"| {_label(g)} | {len(g.seeds)} ({len(g.failed)}) | {_f(a.overall)} | "
            f"{100 * a.fraction_inside:.1f} % | {100 * a.fraction_above:.1f} % | {anchor} | {wp} |"
            if g.seeds
            else f"| {_label(g)} | 0 ({len(g.failed)}) | n/a | n/a | n/a | n/a | n/a |"
        )
    return out


def _error_table(groups: Sequence[GroupSummary]) -> list[str]:
    out = [
        "| run | RMSE (m) | max error (m) | max median / p90 / max (m) | "
        f"runs max ≤ {MAX_ERROR_LIMIT_M} m | runs NEES within ≥ {NEES_WITHIN_LIMIT:.0%} | "
        "NEES mean | run time (s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for g in groups:
        med, p90, mx = g.max_error_quantiles
        out.append(
            f"| {_label(g)} | {g.interval('rmse_m').text(3)} | {g.interval('max_m').text(3)} | "
            f"{_f(med)} / {_f(p90)} / {_f(mx)} | {g.max_error_ok.text(2)} | "
            f"{g.nees_within_ok.text(2)} | {g.interval('nees_mean').text(2)} | "
            f"{g.interval('runtime_s').text(2)} |"
        )
    return out


def report_markdown(store: CampaignStore, groups: Sequence[GroupSummary]) -> str:
    """The text of ``report.md``."""
    spec = store.spec()
    rows = store.rows()
    finished = sorted({r["seed"] for r in rows})
    wall = mean_interval([r["wall_s"] for r in rows if "wall_s" in r])
    failed = [g for g in groups if g.failed]
    world = "" if spec.world is None else f", a generated world per run ({dict(spec.world)})"
    lines = [
        f"# Monte Carlo campaign: {spec.scenario}",
        "",
        f"{len(finished)} of {len(spec.seeds)} runs finished (seeds "
        f"{_seed_text(finished)}){world}; estimators {', '.join(spec.estimators)}; fusion "
        f"{', '.join('on' if f else 'off' for f in spec.fusions)}"
        + ("" if spec.steps is None else f"; first {spec.steps} steps of each log")
        + f". Wall time of a run (simulation and every estimator): {wall.text(1)} s.",
        "",
        "## Consistency",
        "",
        "ANEES: the mean NEES over the runs at each step, against the two-sided 95 % "
        "bounds χ²₃ₙ(0.025)/N and χ²₃ₙ(0.975)/N for N runs; a consistent estimator has "
        "about 95 % of the steps inside them and an overall ANEES near 3. The anchor "
        "ANEES is the mean over the runs with an anchor of its 3-dof NEES, with the same "
        "bounds for that number of runs.",
        "",
        *_consistency_table(groups),
        "",
        "## Errors (mean over runs with 95 % intervals; fractions with Clopper–Pearson intervals)",
        "",
        *_error_table(groups),
    ]
    if failed:
        lines += ["", "## Failed runs", ""]
        for g in failed:
            for seed, err in zip(g.failed, g.errors, strict=True):
                lines.append(f"- {_label(g)}, seed {seed}: {err}")
    lines += ["", "Figures:", ""]
    lines += [f"- [`{n}`]({n}): {d}" for n, d in FIGURE_FILES.items()]
    lines += [
        "",
        "Per-run table: `runs.jsonl` (`pandas.read_json(path, lines=True)`); per-step "
        "arrays: `arrays/seed_NNNNNN.npz`.",
        "",
    ]
    return "\n".join(lines)


def _seed_text(seeds: Sequence[int]) -> str:
    if not seeds:
        return "none"
    parts: list[str] = []
    start = prev = seeds[0]
    for s in [*seeds[1:], None]:
        if s is not None and s == prev + 1:
            prev = s
            continue
        parts.append(str(start) if start == prev else f"{start}-{prev}")
        if s is not None:
            start = prev = s
    return ",".join(parts)


def write_report(out: str | Path) -> dict[str, str]:
    """Write ``report.md`` and :data:`FIGURE_FILES` into campaign directory ``out``;
    returns the paths by name."""
    store = CampaignStore(Path(out))
    groups = summarise(store)
    paths: dict[str, str] = {}
    figures = {
        "anees.png": anees_figure(groups),
        "rmse.png": rmse_figure(groups),
        "max_error.png": max_error_figure(groups),
    }
    for name, fig in figures.items():
        path = store.root / name
        fig.savefig(path, dpi=110)
        paths[name] = str(path)
    report = store.root / "report.md"
    report.write_text(report_markdown(store, groups))
    paths["report"] = str(report)
    return paths
