"""The strict docs build can fail: a dead link in a page fails it, as ``make docs``
(part of ``make test``) runs it."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _build(tmp_path: Path, docs: Path) -> subprocess.CompletedProcess[str]:
    """``mkdocs build --strict`` of ``docs`` with the project's configuration."""
    config = (ROOT / "mkdocs.yml").read_text()
    config = config.replace("docs_dir: docs", f"docs_dir: {docs}")
    config = config.replace("site_dir: build/site", f"site_dir: {tmp_path / 'site'}")
    config = config.replace("paths: [.]", f"paths: [{ROOT}]")
    cfg = tmp_path / "mkdocs.yml"
    cfg.write_text(config)
    return subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(cfg)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )


@pytest.mark.slow
def test_a_dead_link_fails_the_strict_build(tmp_path: Path) -> None:
    docs = tmp_path / "docs"
    shutil.copytree(ROOT / "docs", docs)
    good = _build(tmp_path, docs)
    assert good.returncode == 0, good.stderr
    page = docs / "index.md"
    page.write_text(page.read_text() + "\nSee [a page that is not there](no-such-page.md).\n")
    bad = _build(tmp_path, docs)
    assert bad.returncode != 0
    assert "no-such-page.md" in bad.stderr
