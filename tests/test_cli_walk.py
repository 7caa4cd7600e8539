"""Every subcommand keeps the command line's promises (``docs/cli.md``, *Promises*).

One table of subcommands (:data:`COMMANDS`, tiny inputs: 60 steps of ``loop600``, the
EKF) is walked for each promise: help text with real defaults and every option in
``docs/cli.md``; ``--force`` or a refusal before any work; JSON alone on stdout and a
one-line summary last on stderr; ``--steps`` beyond the log refused (exit 2) before any
work; ``$MAPFUSE_DATA`` standing in for ``--data``; an internal error reported in one
line with status 70, no traceback; ``--plugin`` on every command that runs estimators.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import re
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from mapfuse.cli import _parser, main
from mapfuse.cli_common import EXIT_INTERNAL, EXIT_USAGE

ROOT = Path(__file__).resolve().parents[1]
STEPS = "60"
TOY = "tests.toy_estimator:DeadReckoning"


@dataclass(frozen=True)
class Command:
    """One subcommand of the walk."""

    path: tuple[str, ...]
    """Its words, e.g. ``("baseline", "record")``."""
    argv: tuple[str, ...]
    """Its arguments on a tiny input, but ``--out``."""
    out: str | None = "dir"
    """What ``--out`` names: a folder, a file, or nothing."""
    summary: str = ""
    """How its summary line starts (a regular expression)."""
    steps: bool = True
    """Whether it takes ``--steps``."""
    plugin: tuple[str, ...] | None = None
    """Its arguments running the toy plug-in (``None``: it runs no estimator)."""
    data: tuple[str, ...] | None = None
    """Its arguments on the car park by name (``None``: no real dataset)."""
    boom: str = "ekf"
    """What raises in the internal-error walk: the EKF, or ``module:function``."""

    @property
    def name(self) -> str:
        return " ".join(self.path)


#: The toy plug-in in a campaign and as the spectrum's filter.
MC_TOY = (
    "loop600", "--runs", "1", "--steps", STEPS, "--fusion", "off", "--serial",
    "--no-report", "--estimators", "toy", "--plugin", TOY,
)  # fmt: skip
SPECTRUM_TOY = (
    "loop600", "--lags", "0", "--steps", STEPS, "--association", "truth", "--serial",
    "--estimators", "toy,fixedlag,batch", "--plugin", TOY,
)  # fmt: skip

COMMANDS: tuple[Command, ...] = (
    Command(
        ("simulate",),
        ("loop600", "--steps", STEPS),
        summary=r"simulated loop600 seed 0: 60 steps",
        boom="mapfuse_core.sim.simulate:simulate",
    ),
    Command(
        ("run",),
        ("loop600", "--steps", STEPS),
        summary=r"ekf with fusion on loop600 seed 0: RMSE \d\.\d{3} m, NEES",
        plugin=("loop600", "--steps", STEPS, "--estimator", "toy", "--plugin", TOY),
        data=("carpark", "--steps", STEPS),
    ),
    Command(
        ("compare",),
        ("loop600", "--steps", STEPS, "--estimators", "ekf"),
        summary=r"compared 2 runs \(ekf; fusion both\) on loop600 seed 0 in [\d.]+ s",
        plugin=("loop600", "--steps", STEPS, "--estimators", "ekf,toy", "--plugin", TOY),
        data=("carpark", "--steps", STEPS, "--estimators", "ekf", "--fusion", "on"),
    ),
    Command(
        ("baseline", "record"),
        ("loop600", "--steps", STEPS, "--fusion", "on"),
        out="file",
        summary=r"recorded a baseline of 1 run of ekf",
        plugin=("loop600", "--steps", STEPS, "--estimator", "toy", "--plugin", TOY),
        data=("carpark", "--steps", STEPS, "--fusion", "on"),
    ),
    Command(
        ("baseline", "check"),
        ("--baseline", "{baseline}"),
        out=None,
        summary=r"baseline check .*: all 1 runs within tolerance",
        steps=False,
    ),
    Command(
        ("montecarlo",),
        ("loop600", "--runs", "1", "--steps", STEPS, "--fusion", "on", "--serial", "--no-report"),
        summary=r"montecarlo loop600: ran 1 seeds",
        plugin=MC_TOY,
        boom="mapfuse.campaign.engine:run_campaign",
    ),
    Command(
        ("spectrum",),
        ("loop600", "--lags", "0", "--steps", STEPS, "--association", "truth", "--serial"),
        summary=r"spectrum of loop600 over 1 seeds, 3 rows",
        plugin=SPECTRUM_TOY,
    ),
    Command(
        ("changes",),
        ("loop600", "--steps", STEPS),
        summary=r"changes of loop600's known map \(ekf\): \d+ confirmed",
        data=("carpark", "--steps", "150"),
    ),
    Command(
        ("world", "generate"),
        ("--seed", "1", "--walls", "4", "--trees", "10", "--loop-length", "150"),
        out="file",
        summary=r"generated world-loop-1: \d+ steps",
        steps=False,
        boom="mapfuse_core.sim.worldgen:world_toml",
    ),
)

BY_NAME = {c.name: c for c in COMMANDS}


def _walk(which: str | None = None) -> list[object]:
    """The commands (those with ``which`` set), as test parameters named after them."""
    return [pytest.param(c, id=c.name) for c in COMMANDS if which is None or getattr(c, which)]


@pytest.fixture(scope="module")
def baseline_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A baseline of the EKF with fusion on 60 steps of loop600 seed 0."""
    path = tmp_path_factory.mktemp("baseline") / "b.json"
    argv = ["baseline", "record", "loop600", "--steps", STEPS, "--fusion", "on", "--quiet"]
    assert main([*argv, "--out", str(path)]) == 0
    return path


def _argv(
    cmd: Command, args: tuple[str, ...], out: Path, baseline: Path | None = None
) -> list[str]:
    words = [*cmd.path, *(a.format(baseline=baseline) for a in args)]
    if cmd.out == "dir":
        words += ["--out", str(out)]
    elif cmd.out == "file":
        words += ["--out", str(out / "out.file")]
    return words


def _lines(text: str) -> list[str]:
    """The lines of a stream, progress bars' carriage returns as line ends."""
    return [ln for ln in re.split(r"[\r\n]", text) if ln.strip()]


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """Loading, simulating or running anything fails the test."""

    def fail(*args: object, **kwargs: object) -> None:
        raise AssertionError("work started before the checks")

    for target in (
        "mapfuse.runner:load",
        "mapfuse.runner:simulate",
        "mapfuse_core.sim.simulate:simulate",
        "mapfuse.plan:estimate",
        "mapfuse.campaign.engine:run_campaign",
        "mapfuse.spectrum:spectrum",
        "mapfuse_core.sim.worldgen:world_toml",
    ):
        module, _, name = target.partition(":")
        monkeypatch.setattr(importlib.import_module(module), name, fail)


# --------------------------------------------------------------------------- help


def _subparsers(p: argparse.ArgumentParser) -> Iterator[tuple[str, argparse.ArgumentParser]]:
    for a in p._actions:
        if isinstance(a, argparse._SubParsersAction):
            for name, sp in a.choices.items():
                yield name, sp
                for sub, ssp in _subparsers(sp):
                    yield f"{name} {sub}", ssp


def test_the_walk_covers_every_subcommand() -> None:
    leaves = {name for name, sp in _subparsers(_parser()) if not list(_subparsers(sp))}
    assert leaves == set(BY_NAME)


@pytest.mark.parametrize("cmd", _walk())
def test_help_shows_real_defaults_and_docs_list_every_option(
    cmd: Command, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main([*cmd.path, "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "None" not in text
    assert "(default: True)" not in text
    assert "(default: False)" not in text
    parser = dict(_subparsers(_parser()))[cmd.name]
    formatter = parser._get_formatter()
    docs = (ROOT / "docs" / "cli.md").read_text()
    section = docs.split(f"\n## `{cmd.name}`", 1)[1].split("\n## ", 1)[0]
    for a in parser._actions:
        if isinstance(a, argparse._HelpAction):
            continue
        value = a.default not in (None, "", argparse.SUPPRESS) and not isinstance(a.default, bool)
        if value and a.nargs != 0:
            shown = formatter._get_help_string(a) or ""
            assert "%(default)s" in shown, f"{cmd.name} {a.option_strings}: no default shown"
        for opt in a.option_strings or [a.metavar or a.dest]:
            assert f"`{opt}" in section, f"docs/cli.md, {cmd.name}: {opt} not documented"


# --------------------------------------------------------------------------- --force


@pytest.mark.parametrize("cmd", _walk("out"))
def test_another_runs_files_are_refused_before_any_work(
    cmd: Command,
    tmp_path: Path,
    no_work: None,
    baseline_file: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    marker = out / ("out.file" if cmd.out == "file" else "metrics.json")
    marker.write_text("another run's\n")
    assert main(_argv(cmd, cmd.argv, out, baseline_file)) == EXIT_USAGE
    cap = capsys.readouterr()
    assert cap.out == ""
    (line,) = cap.err.strip().splitlines()
    assert line.startswith("mapfuse: error: --out ")
    assert "--force" in line
    assert marker.read_text() == "another run's\n"


# --------------------------------------------------------------------------- streams


@pytest.mark.parametrize("cmd", _walk())
def test_stdout_is_json_alone_and_stderr_ends_with_a_summary(
    cmd: Command, tmp_path: Path, baseline_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(_argv(cmd, cmd.argv, tmp_path / "out", baseline_file)) == 0
    cap = capsys.readouterr()
    assert isinstance(json.loads(cap.out), dict)
    lines = _lines(cap.err)
    assert lines, "no summary"
    assert re.match(cmd.summary, lines[-1]), lines[-1]
    assert not lines[-1].startswith("mapfuse:")
    assert "Traceback" not in cap.err


@pytest.mark.parametrize("name", ["simulate", "world generate", "baseline check"])
def test_quiet_leaves_stderr_empty(
    name: str, tmp_path: Path, baseline_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cmd = BY_NAME[name]
    assert main([*_argv(cmd, cmd.argv, tmp_path / "out", baseline_file), "--quiet"]) == 0
    cap = capsys.readouterr()
    json.loads(cap.out)
    assert cap.err == ""


# --------------------------------------------------------------------------- --steps


@pytest.mark.parametrize("cmd", _walk("steps"))
def test_steps_beyond_the_log_are_refused_before_any_work(
    cmd: Command, tmp_path: Path, no_work: None, capsys: pytest.CaptureFixture[str]
) -> None:
    args = list(cmd.argv)
    args[args.index("--steps") + 1] = "99999"
    assert main(_argv(cmd, tuple(args), tmp_path / "out")) == EXIT_USAGE
    cap = capsys.readouterr()
    assert cap.out == ""
    (line,) = cap.err.strip().splitlines()
    assert "--steps 99999 is more than scenario 'loop600' drives (2400 steps)" in line
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- $MAPFUSE_DATA


@pytest.mark.parametrize("cmd", _walk("data"))
def test_mapfuse_data_stands_in_for_data(
    cmd: Command,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    raw = os.environ.get("MAPFUSE_DATA", "")
    data = Path(raw) if raw else ROOT.parent / "shared" / "data"
    if not (data / "acfr_carpark").is_dir():
        pytest.skip(f"car park data not found under {data}; set MAPFUSE_DATA to run this test")
    assert cmd.data is not None
    monkeypatch.setenv("MAPFUSE_DATA", str(data))
    assert main([*_argv(cmd, cmd.data, tmp_path / "out"), "--quiet"]) == 0, capsys.readouterr().err
    json.loads(capsys.readouterr().out)
    # Without it, and without --data, the same command names both.
    monkeypatch.delenv("MAPFUSE_DATA")
    assert main([*_argv(cmd, cmd.data, tmp_path / "again"), "--quiet"]) == EXIT_USAGE
    assert "(--data DIR or $MAPFUSE_DATA)" in capsys.readouterr().err


# --------------------------------------------------------------------------- internal errors


def _boom(*args: object, **kwargs: object) -> None:
    raise ZeroDivisionError("division by zero")


@pytest.mark.parametrize("cmd", _walk())
def test_an_internal_error_is_one_line_and_its_own_status(
    cmd: Command,
    tmp_path: Path,
    baseline_file: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    if ":" in cmd.boom:
        module, _, name = cmd.boom.partition(":")
        monkeypatch.setattr(importlib.import_module(module), name, _boom)
    else:
        from mapfuse.estimators.ekf import EKFEstimator

        monkeypatch.setattr(EKFEstimator, "run", _boom)
    monkeypatch.delenv("MAPFUSE_DEBUG", raising=False)
    argv = [*_argv(cmd, cmd.argv, tmp_path / "out", baseline_file), "--quiet"]
    assert main(argv) == EXIT_INTERNAL
    cap = capsys.readouterr()
    assert cap.out == ""
    (line,) = cap.err.strip().splitlines()
    assert line.startswith("mapfuse: internal error: ZeroDivisionError: division by zero")
    assert "MAPFUSE_DEBUG=1" in line


def test_mapfuse_debug_adds_the_traceback(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from mapfuse.estimators.ekf import EKFEstimator

    monkeypatch.setattr(EKFEstimator, "run", _boom)
    monkeypatch.setenv("MAPFUSE_DEBUG", "1")
    cmd = BY_NAME["run"]
    assert main([*_argv(cmd, cmd.argv, tmp_path / "out"), "--quiet"]) == EXIT_INTERNAL
    err = capsys.readouterr().err
    assert err.startswith("Traceback (most recent call last):")
    assert err.strip().splitlines()[-1].startswith("mapfuse: internal error: ZeroDivisionError")


def test_an_internal_error_in_a_real_process_has_no_traceback(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    env.pop("MAPFUSE_DEBUG", None)
    argv = ["run", "loop600", "--steps", "30", "--estimator", "divides_by_zero"]
    argv += ["--plugin", "tests.campaign_plugins:DividesByZero", "--out", str(tmp_path / "o")]
    proc = subprocess.run(
        [sys.executable, "-m", "mapfuse.cli", *argv, "--quiet"],
        capture_output=True, text=True, env=env, cwd=ROOT, timeout=300, check=False,
    )  # fmt: skip
    assert proc.returncode == EXIT_INTERNAL, proc.stderr
    assert proc.stdout == ""
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines() == [
        "mapfuse: internal error: ZeroDivisionError: deliberate division by zero (a bug; run "
        "again with MAPFUSE_DEBUG=1 for the traceback, and report it)"
    ]


# --------------------------------------------------------------------------- --plugin


@pytest.mark.parametrize("cmd", _walk("plugin"))
def test_plugin_registers_an_estimator_for_the_command(
    cmd: Command, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from mapfuse.registry import available

    assert cmd.plugin is not None
    assert "toy" not in available()
    assert main([*_argv(cmd, cmd.plugin, tmp_path / "out"), "--quiet"]) == 0, (
        capsys.readouterr().err
    )
    printed = capsys.readouterr().out
    assert "toy" in printed or '"ran": 1' in printed
    assert "toy" not in available()  # the command leaves the registry as it found it
    if cmd.name == "montecarlo":
        rows = [json.loads(x) for x in (tmp_path / "out" / "runs.jsonl").read_text().splitlines()]
        assert [(r["estimator"], r["status"]) for r in rows] == [("toy", "ok")]
