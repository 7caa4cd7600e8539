"""Dependencies point one way: core ← ekf_reference ← mapfuse_graph."""

from __future__ import annotations

import subprocess
import sys

import pytest


@pytest.mark.parametrize(
    ("package", "forbidden"),
    [
        ("mapfuse_core", ("gtsam", "ekf_reference", "mapfuse_graph", "matplotlib")),
        ("ekf_reference", ("gtsam", "mapfuse_graph")),
    ],
)
def test_package_does_not_load(package: str, forbidden: tuple[str, ...]) -> None:
    # A fresh interpreter: this test process may already have loaded gtsam.
    code = (
        f"import sys, importlib, pkgutil, {package}\n"
        f"for m in pkgutil.walk_packages({package}.__path__, '{package}.'):\n"
        "    if not m.name.endswith('plotting'):\n"
        "        importlib.import_module(m.name)\n"
        f"print(','.join(sorted(set(sys.modules) & set({forbidden!r}))))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.strip()
    assert out == "", f"importing {package} loaded {out}"
