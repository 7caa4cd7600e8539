"""Every benchmark script imports: a renamed or moved library module breaks a
benchmark only when it is run, which may be long after the change."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest

BENCHMARKS = sorted(
    p.stem for p in (Path(__file__).resolve().parents[1] / "benchmarks").glob("*.py")
)


def test_the_benchmarks_are_found() -> None:
    assert len(BENCHMARKS) >= 20
    assert "extraction_whitened" in BENCHMARKS


@pytest.mark.parametrize("name", BENCHMARKS)
def test_a_benchmark_imports(name: str) -> None:
    importlib.import_module(f"benchmarks.{name}")
