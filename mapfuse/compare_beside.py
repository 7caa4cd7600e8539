"""Other scenarios beside a comparison: ``mapfuse compare SCENARIO --beside OTHER``.

The dense ``loop600`` keeps every estimator within a few centimetres of the others;
the paper's regime, where SLAM without fusion drifts about 0.5 m far from the start,
is the sparser ``loop600-sparse`` (see its TOML).  :func:`compare_beside`
runs the same backends and fusion settings on each other scenario with the same seed;
:func:`mapfuse.comparison.write_comparison` puts their tables after the main one in
``report.md`` (:func:`mapfuse.comparison.beside_lines`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from mapfuse.comparison import Comparison, Progress, compare
from mapfuse.runner import load

__all__ = ["compare_beside"]


def compare_beside(
    scenarios: Sequence[str],
    seed: int | None,
    estimators: Sequence[str] | None = None,
    fusions: Sequence[bool] = (True, False),
    overrides: Mapping[str, Mapping[str, Any]] | None = None,
    progress: Progress | None = None,
    steps: int | None = None,
) -> tuple[Comparison, ...]:
    """:func:`mapfuse.comparison.compare` on each of ``scenarios`` (built-in names or TOML
    paths), simulated with ``seed`` (``None``: each scenario's own) for its first
    ``steps`` steps (``None``: all)."""
    out = []
    for name in scenarios:
        log = load(name, seed=seed, steps=steps)
        p = None if progress is None else _prefixed(progress, name)
        out.append(
            compare(log, progress=p, estimators=estimators, fusions=fusions, overrides=overrides)
        )
    return tuple(out)


def _prefixed(progress: Progress, name: str) -> Progress:
    """``progress`` with every run's label prefixed by the scenario name."""

    def call(label: str, k: int, n: int) -> None:
        progress(f"{name}: {label}", k, n)

    return call
