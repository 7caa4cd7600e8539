"""The documentation is a guide in the mkdocs nav plus results pages outside it
(``docs/results/``); the configuration page lists every option with its default, as the
dataclasses hold them; every ``docs/...md`` path named in the repository exists."""

from __future__ import annotations

import dataclasses
import importlib.util
import re
import subprocess
import sys
import typing
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

#: Phrases that tell a page's history rather than what is: the guide states what the
#: code does now in the present tense (history belongs to git and the results pages).
HISTORY = re.compile(
    r"before this section|a review then|last stop|as it stood|no longer|previously"
    r"|this commit|before the change|after the change|formerly|was tried|were tried|\bnow\b",
    re.IGNORECASE,
)


def _nav_entries(node: Any) -> Iterator[str]:
    if isinstance(node, str):
        yield node
    elif isinstance(node, list):
        for item in node:
            yield from _nav_entries(item)
    elif isinstance(node, dict):
        for value in node.values():
            yield from _nav_entries(value)


def nav_pages(config: Path = ROOT / "mkdocs.yml") -> set[str]:
    """Every page of the mkdocs nav, relative to ``docs/``."""
    return set(_nav_entries(yaml.safe_load(config.read_text())["nav"]))


def doc_pages(docs: Path = DOCS) -> set[str]:
    """Every Markdown page under ``docs/``, relative to it (the page tools excluded)."""
    return {
        p.relative_to(docs).as_posix()
        for p in docs.rglob("*.md")
        if p.relative_to(docs).parts[0] != "tools"
    }


def misplaced(pages: set[str], nav: set[str]) -> tuple[list[str], list[str], list[str]]:
    """Guide pages missing from the nav, pages neither in the nav nor in the results,
    and results pages in the nav."""
    guide = {p for p in pages if "/" not in p}
    unplaced = {p for p in pages if p not in nav and not p.startswith("results/")}
    return (
        sorted(guide - nav),
        sorted(unplaced),
        sorted(p for p in nav if p.startswith("results/")),
    )


def test_every_page_is_in_the_nav_or_in_the_results() -> None:
    nav = nav_pages()
    assert sorted(nav - doc_pages()) == [], "nav entries without a page"
    assert misplaced(doc_pages(), nav) == ([], [], [])


def test_a_misplaced_page_is_found() -> None:
    nav = nav_pages()
    pages = doc_pages() | {"orphan.md", "api/orphan.md"}
    missing, unplaced, _ = misplaced(pages, nav)
    assert missing == ["orphan.md"]
    assert unplaced == ["api/orphan.md", "orphan.md"]
    assert misplaced(doc_pages(), nav | {"results/ccda.md"})[2] == ["results/ccda.md"]


def test_the_guide_tells_no_history() -> None:
    guide = sorted(p for p in nav_pages() if not p.startswith("api/"))
    found = [
        f"{page}:{n}: {line.strip()}"
        for page in guide
        for n, line in enumerate((DOCS / page).read_text().splitlines(), 1)
        if HISTORY.search(line)
    ]
    assert found == []


def test_history_is_caught() -> None:
    assert HISTORY.search("The table above scores the classifier as it stood before this section.")
    assert HISTORY.search("The gate now un-fuses it.")
    assert not HISTORY.search("The known map's features are known; a nowhere land.")


def _config_tool() -> ModuleType:
    path = DOCS / "tools" / "config_reference.py"
    spec = importlib.util.spec_from_file_location("config_reference", path)
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_the_configuration_page_is_current() -> None:
    tool = _config_tool()
    assert (DOCS / "configuration.md").read_text() == tool.page(), (
        "docs/configuration.md is out of date: run PYTHONPATH=. python "
        "docs/tools/config_reference.py"
    )


def _sections(text: str) -> dict[str, str]:
    """The page's text under each ``### `ClassName``` heading."""
    parts = re.split(r"^### `(\w+)`$", text, flags=re.MULTILINE)
    return dict(zip(parts[1::2], parts[2::2], strict=True))


def unlisted_fields(text: str, classes: list[type]) -> list[str]:
    """``Class.field`` of every field without its row in the class's section."""
    sections = _sections(text)
    return [
        f"{cls.__name__}.{f.name}"
        for cls in classes
        for f in dataclasses.fields(cls)
        if f"| `{f.name}` |" not in sections.get(cls.__name__, "")
    ]


def test_the_configuration_page_lists_every_field() -> None:
    tool = _config_tool()
    text = (DOCS / "configuration.md").read_text()
    assert unlisted_fields(text, tool.covered()) == []
    # A field the page leaves out is found.
    cut = text.replace("| `carry_seen_steps` |", "| `carried` |")
    assert unlisted_fields(cut, tool.covered()) == ["EKFConfig.carry_seen_steps"]


#: Dataclasses reachable from the options that the page leaves out, with the reason.
NOT_CONFIGURATION = {
    "LaserParams": "a scenario's sensor (its `[laser]` table), which ChangeParams borrows",
}


def _dataclasses_in(annotation: Any) -> Iterator[type]:
    if dataclasses.is_dataclass(annotation) and isinstance(annotation, type):
        yield annotation
    for arg in typing.get_args(annotation):
        yield from _dataclasses_in(arg)


def test_the_configuration_page_covers_every_options_dataclass() -> None:
    import mapfuse as mf
    from mapfuse.registry import resolve

    tool = _config_tool()
    covered = {c.__name__ for c in tool.covered()}
    roots = [resolve(name).options_type for name in mf.available()]
    assert {c.__name__ for c in roots} <= covered
    nested = {
        t.__name__
        for cls in tool.covered()
        for hint in typing.get_type_hints(cls).values()
        for t in _dataclasses_in(hint)
    }
    assert sorted(nested - covered - set(NOT_CONFIGURATION)) == []


_DOCS_PATH = re.compile(r"docs/[a-z0-9_/-]+\.md")


def test_every_named_docs_page_exists() -> None:
    files = subprocess.run(
        ["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.split()
    missing = sorted(
        f"{name}: {m}"
        for name in files
        if name.endswith((".py", ".md", ".toml", ".ipynb", ".yml", "Makefile"))
        and (ROOT / name).is_file()
        for m in _DOCS_PATH.findall((ROOT / name).read_text(errors="replace"))
        if not (ROOT / m).is_file()
    )
    assert missing == []


# Spelt in two parts, so that this file does not name a page that is not there.
@pytest.mark.parametrize("page", ["docs" + "/ccda.md", "docs" + "/results/no-such-page.md"])
def test_a_named_page_that_is_gone_is_caught(page: str) -> None:
    assert _DOCS_PATH.findall(f"see ``{page}``") == [page]
    assert not (ROOT / page).is_file()
