"""Dependencies point one way: core ← ekf_reference, core ← mapfuse_graph ← mapfuse.

The harness package ``mapfuse`` is the only code that knows every estimator; the
numeric packages never load a plotting library, and the EKF path never loads gtsam.
Inside the core, subpackages sit in layers (:data:`CORE_LAYERS`): each imports only
from layers below it, so no two subpackages import each other.
"""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("mapfuse_core", "ekf_reference", "mapfuse_graph", "mapfuse")

#: The core's subpackages, lowest layer first.  A subpackage imports only from
#: subpackages of lower layers: bottom-layer types (features, the laser and its
#: scans, the measurement log and known map, the estimate every estimator returns)
#: sit below everything that reads them.  Change detection predicts the view with the
#: simulator's ray caster and needs nothing of the evaluation, which scores its
#: reports against the true changes: it sits between the two.
CORE_LAYERS: tuple[tuple[str, ...], ...] = (
    ("geometry",),
    ("models", "sensor", "measlog", "estimate"),
    ("perception", "matching"),
    ("sim",),
    ("changes",),
    ("evaluation",),
    ("data",),
)


@pytest.mark.parametrize(
    ("package", "forbidden"),
    [
        ("mapfuse_core", ("gtsam", "matplotlib", "ekf_reference", "mapfuse_graph", "mapfuse")),
        ("ekf_reference", ("gtsam", "matplotlib", "mapfuse_graph", "mapfuse")),
        ("mapfuse_graph", ("matplotlib", "ekf_reference", "mapfuse")),
    ],
)
def test_package_does_not_load(package: str, forbidden: tuple[str, ...]) -> None:
    # A fresh interpreter: this test process may already have loaded gtsam.
    code = (
        f"import sys, importlib, pkgutil, {package}\n"
        f"for m in pkgutil.walk_packages({package}.__path__, '{package}.'):\n"
        "    importlib.import_module(m.name)\n"
        "loaded = {name.split('.')[0] for name in sys.modules}\n"
        f"print(','.join(sorted(loaded & set({forbidden!r}))))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
    ).stdout.strip()
    assert out == "", f"importing {package} loaded {out}"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING"
    )


def _imports(tree: ast.AST, module: str, is_package: bool, known: set[str]) -> set[str]:
    """Project modules imported anywhere in ``tree`` (functions included), except in
    ``if TYPE_CHECKING:`` blocks, which never run."""
    out: set[str] = set()

    def resolve(name: str) -> str | None:
        # The longest known module that ``name`` is or lies in.
        while name and name not in known:
            name = name.rpartition(".")[0]
        return name or None

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _is_type_checking(node):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            for alias in node.names:
                if (m := resolve(alias.name)) is not None:
                    out.add(m)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                pkg = module if is_package else module.rpartition(".")[0]
                for _ in range(node.level - 1):
                    pkg = pkg.rpartition(".")[0]
                base = f"{pkg}.{base}" if base else pkg
            for alias in node.names:
                m = resolve(f"{base}.{alias.name}") or resolve(base)
                if m is not None:
                    out.add(m)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    out.discard(module)
    return out


def _import_graph() -> dict[str, set[str]]:
    files = {_module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}
    known = set(files)
    graph: dict[str, set[str]] = {}
    for name, path in files.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        deps = _imports(tree, name, path.name == "__init__.py", known)
        # Importing a submodule runs its package's __init__, which is no dependency cycle.
        graph[name] = {d for d in deps if not name.startswith(d + ".")}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every strongly connected component of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def strong(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for v in sorted(graph):
        if v not in index:
            strong(v)
    return out


def test_no_import_cycles_between_modules() -> None:
    graph = _import_graph()
    assert len(graph) > 40, "the scan found too few modules"
    assert "mapfuse.figures" in graph["mapfuse.comparison"]  # function-level imports count too
    assert _cycles(graph) == []


def test_cycle_finder_sees_a_function_level_cycle() -> None:
    a = ast.parse("def f():\n    from pkg import b\n")
    b = ast.parse("import pkg.a\n")
    known = {"pkg", "pkg.a", "pkg.b"}
    graph = {
        "pkg.a": _imports(a, "pkg.a", False, known),
        "pkg.b": _imports(b, "pkg.b", False, known),
    }
    assert _cycles(graph) == [["pkg.a", "pkg.b"]]
    typing_only = ast.parse(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import pkg.b\n"
    )
    assert _imports(typing_only, "pkg.a", False, known) == set()


def _subpackage(module: str) -> str | None:
    """``mapfuse_core.sim`` for any module in it; ``None`` for a top-level module."""
    parts = module.split(".")
    return ".".join(parts[:2]) if len(parts) > 1 else None


def _subpackage_graph(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """Which subpackage imports which (a package's own modules are one node each)."""
    out: dict[str, set[str]] = {}
    for name, deps in graph.items():
        a = _subpackage(name)
        if a is None:
            continue
        out.setdefault(a, set())
        for d in deps:
            b = _subpackage(d)
            if b is not None and b != a:
                out[a].add(b)
    return out


def _layer_violations(graph: dict[str, set[str]]) -> list[str]:
    """``"a -> b"`` for every import of a core subpackage from its own or a higher layer."""
    layer = {f"mapfuse_core.{s}": i for i, names in enumerate(CORE_LAYERS) for s in names}
    bad = []
    for name, deps in graph.items():
        a = _subpackage(name)
        if a is None or not a.startswith("mapfuse_core."):
            continue
        for d in deps:
            b = _subpackage(d)
            if b is None or b == a or not b.startswith("mapfuse_core."):
                continue
            if layer[b] >= layer[a]:
                bad.append(f"{name} -> {d}")
    return sorted(bad)


def test_every_core_subpackage_has_a_layer() -> None:
    found = {p.name for p in (ROOT / "mapfuse_core").iterdir() if (p / "__init__.py").is_file()}
    declared = {s for names in CORE_LAYERS for s in names}
    assert found <= declared, f"core subpackages without a layer: {sorted(found - declared)}"


def test_core_subpackages_import_only_lower_layers() -> None:
    assert _layer_violations(_import_graph()) == []


def test_no_import_cycles_between_subpackages() -> None:
    assert _cycles(_subpackage_graph(_import_graph())) == []


def test_layer_check_sees_an_upward_and_a_sideways_import() -> None:
    graph = {
        "mapfuse_core.sim.simulate": {"mapfuse_core.geometry.se2"},
        "mapfuse_core.geometry.se2": {"mapfuse_core.sim.simulate"},
        "mapfuse_core.models.line": {"mapfuse_core.measlog.log"},
    }
    assert _layer_violations(graph) == [
        "mapfuse_core.geometry.se2 -> mapfuse_core.sim.simulate",
        "mapfuse_core.models.line -> mapfuse_core.measlog.log",
    ]
    assert _cycles(_subpackage_graph(graph)) == [["mapfuse_core.geometry", "mapfuse_core.sim"]]


def test_numeric_packages_never_import_the_harness() -> None:
    graph = _import_graph()
    for name, deps in graph.items():
        top = name.split(".")[0]
        if top == "mapfuse":
            continue
        assert not {d for d in deps if d.split(".")[0] == "mapfuse"}, name
        if top in ("mapfuse_core", "mapfuse_graph"):
            assert not {d for d in deps if d.startswith("ekf_reference")}, name
        if top in ("mapfuse_core", "ekf_reference"):
            assert not {d for d in deps if d.startswith("mapfuse_graph")}, name


@pytest.mark.slow
def test_mapfuse_run_ekf_works_without_gtsam(tmp_path: Path) -> None:
    # gtsam made unimportable for the whole subprocess: `import gtsam` raises.
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text("import sys\nsys.modules['gtsam'] = None\n")
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(site), str(ROOT)]),
        "OPENBLAS_NUM_THREADS": "1",
    }
    out = tmp_path / "out"
    code = "import sys; from mapfuse.cli import main; sys.exit(main(sys.argv[1:]))"
    args = ["run", "loop600", "--estimator", "ekf", "--steps", "120", "--out", str(out), "--quiet"]
    proc = subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, env=env, cwd=tmp_path
    )
    assert proc.returncode == 0, proc.stderr
    assert (out / "metrics.json").is_file()
    said = json.loads((out / "metrics.json").read_text())
    assert said["steps"] == 120
    # The command line's metrics are the library's for the same input.
    import mapfuse as mf

    lib = mf.run(mf.simulate("loop600", seed=0, steps=120), "ekf").metrics.to_json()
    for key in ("position_error_m", "heading_error_rad", "nees", "anchor", "map"):
        assert said[key] == lib[key], key
    # The same interpreter set-up does refuse gtsam (the test is not vacuous).
    probe = subprocess.run(
        [sys.executable, "-c", "import gtsam"], capture_output=True, text=True, env=env
    )
    assert probe.returncode != 0
    assert "ModuleNotFoundError" in probe.stderr or "ImportError" in probe.stderr
