"""Other scenarios beside a comparison: ``mapfuse compare SCENARIO --beside OTHER``.

The dense ``loop600`` keeps every estimator within a few centimetres of the others;
the paper's Fig. 7 gap (about 0.5 m without fusion far from the start, under 0.15 m
with it) shows in the sparser ``loop600-sparse`` (see its TOML).  :func:`compare_beside`
runs the same backends and fusion settings on each other scenario with the same seed,
and :func:`beside_lines` puts their tables after the main one in ``report.md``.  A
``loop600`` report without them says how to add the paper's regime.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from mapfuse.compare import Comparison, Progress, compare, results_table
from mapfuse.run import prepare_log
from mapfuse_core.evaluation import path_length

__all__ = ["PAPER_REGIME", "beside_lines", "compare_beside"]

#: The built-in scenario in the paper's regime, and the one it is beside by default.
PAPER_REGIME: Mapping[str, str] = {"loop600": "loop600-sparse"}


def compare_beside(
    scenarios: Sequence[str],
    seed: int | None,
    backends: Sequence[str] | None = None,
    fusions: Sequence[bool] = (True, False),
    overrides: Mapping[str, Mapping[str, Any]] | None = None,
    progress: Progress | None = None,
) -> tuple[Comparison, ...]:
    """:func:`mapfuse.compare.compare` on each of ``scenarios`` (built-in names or TOML
    paths), simulated with ``seed`` (``None``: each scenario's own)."""
    out = []
    for name in scenarios:
        log = prepare_log(name, seed=seed)
        p = None if progress is None else _prefixed(progress, name)
        out.append(
            compare(log, progress=p, backends=backends, fusions=fusions, overrides=overrides)
        )
    return tuple(out)


def _prefixed(progress: Progress, name: str) -> Progress:
    """``progress`` with every run's label prefixed by the scenario name."""

    def call(label: str, k: int, n: int) -> None:
        progress(f"{name}: {label}", k, n)

    return call


def beside_lines(main_scenario: str, beside: Sequence[Comparison]) -> list[str]:
    """The report section of the comparisons ``beside`` the one of ``main_scenario``:
    a heading, the log's description and the results table of each; with none, for a
    scenario of :data:`PAPER_REGIME`, a note naming the option that adds it."""
    if not beside:
        other = PAPER_REGIME.get(main_scenario)
        if other is None:
            return []
        return [
            "",
            f"The paper's regime (about 0.5 m without fusion far from the start, under "
            f"0.15 m with it) is the sparser `{other}`: `--beside {other}` puts its "
            "table here.",
        ]
    lines: list[str] = []
    for b in beside:
        log = b.log
        desc = f"{log.n_steps} steps"
        if log.true_poses is not None:
            desc += f", true path {path_length(log.true_poses):.1f} m"
        desc += (
            f"; {log.n_features} extracted features; known map of {len(log.known_map)} "
            f"features; {b.wall_time_s:.1f} s wall time."
        )
        title = "the paper's regime" if log.scenario in PAPER_REGIME.values() else "beside"
        lines += ["", f"## {log.scenario}, seed {log.seed} ({title})", "", desc, ""]
        lines += results_table(b)
    return lines
