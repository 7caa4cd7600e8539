"""Shared pytest configuration: hypothesis profile, test order, the workers' shared directory
and the real-data directory."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import settings

# Deterministic hypothesis runs: a failing example must reproduce on every machine.
settings.register_profile("mapfuse", derandomize=True, max_examples=200, deadline=None)
settings.load_profile("mapfuse")

#: tests/loop600.py's name for the directory (kept here to avoid importing it early).
SHARED_DIR_ENV = "MAPFUSE_TEST_SHARED_DIR"


def pytest_configure(config: pytest.Config) -> None:
    """Under ``pytest -n``, name the directory the workers of this run share.

    It is the parent of the worker's ``basetemp``, the run's own temporary directory
    (pytest keeps the last three runs'); ``tests/loop600.py`` caches its runs there.
    """
    if hasattr(config, "workerinput") and config.option.basetemp:
        os.environ[SHARED_DIR_ENV] = str(Path(config.option.basetemp).parent / "shared")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Tests marked ``slow`` first, each part in collection order.

    Under ``pytest -n`` the workers take the tests in this order: the long runs start
    at once and the short tests fill the end, so no worker waits alone on a long test
    at the end of the suite.  The sort is stable, so every worker collects the same
    order (xdist requires it).
    """
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


@pytest.fixture
def jacobian_checks() -> Iterator[None]:
    """The graph factors' Jacobian shape guard on for one test, restored after it
    (``pytestmark = pytest.mark.usefixtures("jacobian_checks")`` in a module)."""
    from mapfuse_graph import factors as fx

    before = fx.jacobian_checks_enabled()
    fx.set_jacobian_checks(True)
    yield
    fx.set_jacobian_checks(before)


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """Directory of the shared real datasets (``MAPFUSE_DATA``), or skip."""
    raw = os.environ.get("MAPFUSE_DATA", "")
    path = Path(raw) if raw else Path(__file__).resolve().parents[1].parent / "shared" / "data"
    if not path.is_dir():
        pytest.skip(f"real-data directory not found ({path}); set MAPFUSE_DATA to run this test")
    return path
