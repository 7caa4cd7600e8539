"""What every ``mapfuse`` command does the same way: exit statuses and errors, stdout
and stderr, progress, the input and the output checks made before any work.

Exit statuses (:func:`mapfuse.cli.main`; ``docs/cli.md``, *Exit status*):

* 0 done;
* 1 a check failed (``baseline check``);
* 2 usage error: a bad option or value, an option that does not apply, ``--steps``
  beyond the log, an output folder or file refused (``--force``); found before any
  work;
* 3 input error: a named input (scenario, TOML, log, CARMEN file, dataset, baseline) is
  missing, unreadable or malformed, a run cannot give the command's result, or a file
  cannot be written;
* 70 internal error (a bug): one line naming the exception; ``MAPFUSE_DEBUG=1`` prints
  the traceback too;
* 130 interrupted by Ctrl-C;
* 141 stdout closed by its reader (``mapfuse ... | head``), as a shell reports SIGPIPE.

Streams: a command's result is JSON alone on stdout (:func:`emit`); progress bars
(rate and ETA), warnings, errors and a one-line summary at the end (:func:`summary`)
go to stderr.  ``--quiet`` hides the bars and the summary.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from mapfuse.datadir import data_dir

if TYPE_CHECKING:
    from mapfuse.progress import LabelledProgress, ProgressBar
    from mapfuse.runner import Run
    from mapfuse_core.estimate import RunMetrics
    from mapfuse_core.measlog import MeasurementLog
    from mapfuse_core.sim.scenario import Scenario

__all__ = [
    "DEBUG_ENV",
    "EXIT_BROKEN_PIPE",
    "EXIT_CHECK_FAILED",
    "EXIT_INPUT",
    "EXIT_INTERNAL",
    "EXIT_INTERRUPTED",
    "EXIT_OK",
    "EXIT_USAGE",
    "CommandError",
    "InputError",
    "Source",
    "UsageError",
    "check_out_dir",
    "check_out_file",
    "check_source",
    "checking",
    "emit",
    "labelled_bars",
    "load_source",
    "note",
    "progress_bar",
    "reading",
    "run_line",
    "run_with_bars",
    "source_kind",
    "summary",
    "warn_runs",
]

EXIT_OK = 0
EXIT_CHECK_FAILED = 1
EXIT_USAGE = 2
EXIT_INPUT = 3
#: ``EX_SOFTWARE`` of BSD's ``sysexits.h``: an internal software error.
EXIT_INTERNAL = 70
#: 128 + SIGINT, as shells report a command stopped by Ctrl-C.
EXIT_INTERRUPTED = 130
#: 128 + SIGPIPE: the reader of stdout went away.
EXIT_BROKEN_PIPE = 141

#: Environment variable that makes an internal error print its traceback.
DEBUG_ENV = "MAPFUSE_DEBUG"


class CommandError(Exception):
    """An error the command line reports in one line, with its exit status."""

    code: int = EXIT_USAGE


class UsageError(CommandError):
    """A bad option or value, or one that does not apply, found before any work."""

    code = EXIT_USAGE


class InputError(CommandError):
    """A named input that is missing, unreadable or malformed."""

    code = EXIT_INPUT


@contextmanager
def checking() -> Iterator[None]:
    """Checks of the options: a :class:`ValueError` in the block is a usage error, a
    bad scenario file or a missing file an input error."""
    from mapfuse_core.sim.scenario import ScenarioError

    try:
        yield
    except (ScenarioError, OSError) as exc:
        raise InputError(str(exc)) from None
    except ValueError as exc:
        raise UsageError(str(exc)) from None


@contextmanager
def reading() -> Iterator[None]:
    """Reading a named input: a :class:`ValueError` or :class:`OSError` in the block is
    an input error (the readers name the file and the problem), but an option the input
    needs or refuses (:class:`~mapfuse.carmen_input.CarmenOptionError`) a usage error."""
    from mapfuse.carmen_input import CarmenOptionError

    try:
        yield
    except CarmenOptionError as exc:
        raise UsageError(str(exc)) from None
    except (ValueError, OSError) as exc:
        raise InputError(str(exc)) from None


def emit(obj: Any) -> None:
    """The command's result: JSON alone on stdout."""
    print(json.dumps(obj, indent=2), flush=True)


def note(text: str) -> None:
    """A message for the user on stderr (warnings, notes; shown with ``--quiet``)."""
    print(text, file=sys.stderr, flush=True)


def summary(args: argparse.Namespace, text: str) -> None:
    """The command's one-line human summary on stderr (not with ``--quiet``)."""
    if not getattr(args, "quiet", False):
        note(text)


def progress_bar(args: argparse.Namespace, label: str, delay_s: float = 0.0) -> ProgressBar:
    """A ``progress(k, n)`` bar labelled ``label`` (drawing nothing with ``--quiet``),
    shown after ``delay_s`` seconds."""
    from mapfuse.progress import ProgressBar

    return ProgressBar(label, enabled=not args.quiet, delay_s=delay_s)


def labelled_bars(args: argparse.Namespace) -> LabelledProgress:
    """A ``progress(label, k, n)`` callback: one bar per run."""
    from mapfuse.progress import LabelledProgress

    return LabelledProgress(not args.quiet)


def run_with_bars(
    args: argparse.Namespace,
    log: MeasurementLog,
    estimator: str,
    fusion: bool,
    overrides: dict[str, Any] | None = None,
) -> Run:
    """One estimator's run (:mod:`mapfuse.plan`), with a bar for it and one for the run
    it consumes, if any (the EKF whose decisions a graph backend takes)."""
    from mapfuse.metrics import run_metrics
    from mapfuse.plan import RunRequest, execute, plan_runs
    from mapfuse.runner import Run

    plan = plan_runs([RunRequest(estimator, fusion, overrides or {})], len(log.known_map) > 0)
    bars = labelled_bars(args)
    done = execute(plan, log, progress=bars)
    bars.close()
    result = done[-1].result
    assert result is not None  # errors raise
    return Run(result=result, log=log, metrics=run_metrics(result, log))


def warn_runs(metrics: Sequence[RunMetrics], label: bool = False) -> None:
    """Each run's ``metrics.json`` warnings, once each, on stderr."""
    for m in metrics:
        who = f"{m.estimator} {'with' if m.fusion else 'without'} fusion: " if label else ""
        for w in m.warnings:
            note(f"mapfuse: warning: {who}{w}")


def run_line(m: RunMetrics) -> str:
    """``"ekf with fusion on loop600 seed 0: RMSE 0.032 m, NEES 2.64, anchor 0.030 m"``."""
    seed = f" seed {m.seed}" if m.seed >= 0 else ""
    head = f"{m.estimator} {'with' if m.fusion else 'without'} fusion on {m.scenario}{seed}"
    parts = []
    pe = m.position_error
    if pe is None:
        parts.append("no truth")
    else:
        against = " against GPS" if pe.reference == "gps" else ""
        parts.append(f"RMSE {pe.rmse:.3f} m{against}")
    if m.nees is not None:
        parts.append(f"NEES {m.nees.mean:.2f}")
    if m.anchor is not None:
        a = m.anchor.position_error_m
        parts.append(
            f"anchor {a:.3f} m" if a is not None else f"anchor at step {m.anchor.accepted_at_step}"
        )
    elif m.fusion:
        parts.append("no anchor")
    return f"{head}: {', '.join(parts)}"


# --------------------------------------------------------------------------- outputs


def check_out_dir(args: argparse.Namespace) -> Path:
    """``--out`` checked as a folder for this run's files (``--force``), changing
    nothing (:func:`mapfuse.outdir.check_output_dir`)."""
    from mapfuse.outdir import check_output_dir

    with checking():
        return check_output_dir(args.out, force=args.force)


def check_out_file(args: argparse.Namespace) -> Path:
    """``--out`` checked as a file to write (``--force``), changing nothing."""
    from mapfuse.outdir import check_output_file

    with checking():
        return check_output_file(args.out, force=args.force)


# --------------------------------------------------------------------------- inputs

SourceKind = Literal["scenario", "npz", "dataset", "carmen"]


@dataclass(frozen=True)
class Source:
    """A command's input, checked: what to load and how."""

    text: str
    """The source as :func:`mapfuse.runner.load` takes it (``--odometry`` folded into a
    CARMEN source)."""
    kind: SourceKind
    """A scenario to simulate, a saved log, a real dataset or a CARMEN log."""
    seed: int | None
    """Seed of a simulation or of a CARMEN log's simulated odometry."""
    steps: int | None
    """The first steps to keep (``None``: all)."""
    data: str | None
    """Data directory of a dataset (``--data`` or ``$MAPFUSE_DATA``)."""
    known_map: str | None
    """A CARMEN log's known-map choice."""
    scenario: Scenario | None
    """The scenario of a simulation, loaded."""


def source_kind(source: str) -> SourceKind:
    """What ``source`` names: a CARMEN log, a saved log, a real dataset or a scenario."""
    from mapfuse.carmen_input import is_carmen
    from mapfuse.runner import DATASETS

    if is_carmen(source):
        return "carmen"
    if source.endswith(".npz"):
        return "npz"
    if source in DATASETS:
        return "dataset"
    return "scenario"


def _data_dir(args: argparse.Namespace, source: str, kind: SourceKind) -> str | None:
    given = getattr(args, "data", None)
    if kind != "dataset":
        if given is not None:
            raise UsageError(f"--data applies to carpark and victoria-park only, not {source!r}")
        return None
    try:
        return data_dir(given, source, "--data")
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def _check_steps(steps: int, n_steps: int, source: str) -> None:
    if steps > n_steps:
        raise UsageError(f"--steps {steps} is more than {source} holds ({n_steps} steps)")


def _carmen_steps(source: str) -> int:
    """Steps of a CARMEN log (one per laser scan), read without extracting features."""
    from mapfuse.carmen_input import carmen_path
    from mapfuse_core.data.datasets import read_carmen

    with reading():
        return len(read_carmen(carmen_path(source)).lasers)


def check_source(
    args: argparse.Namespace,
    source: str | None = None,
    seed: int | None = None,
    steps: int | None = None,
    kinds: Sequence[SourceKind] = ("scenario", "npz", "dataset", "carmen"),
) -> Source:
    """The command's input (``source``, default ``args.scenario``) and the options that
    depend on it, checked before any work; ``seed`` and ``steps`` default to
    ``args.seed`` and ``args.steps``.  ``kinds``: the inputs the command takes."""
    from mapfuse.carmen_input import parse_carmen_source, with_odometry
    from mapfuse_core.sim.scenario import load_scenario

    text = args.scenario if source is None else source
    seed = getattr(args, "seed", None) if seed is None else seed
    steps = getattr(args, "steps", None) if steps is None else steps
    kind = source_kind(text)
    if kind not in kinds:
        names = {"npz": "a saved log", "dataset": "a real dataset", "carmen": "a CARMEN log"}
        raise UsageError(
            f"{names.get(kind, 'a scenario')} ({text}) is not an input of this command"
        )
    odometry = getattr(args, "odometry", None)
    known_map = getattr(args, "known_map", None)
    if kind != "carmen":
        if odometry is not None:
            raise UsageError(f"--odometry applies to CARMEN logs (carmen:PATH) only, not {text!r}")
        if known_map is not None:
            raise UsageError(f"--known-map applies to CARMEN logs (carmen:PATH) only, not {text!r}")
    if seed is not None and kind in ("npz", "dataset"):
        what = (
            f"a saved log ({text}): it is simulated"
            if kind == "npz"
            else f"the real dataset {text!r}"
        )
        raise UsageError(f"--seed does not apply to {what}")
    data = _data_dir(args, text, kind)
    scenario = None
    if kind == "carmen":
        raw = text.partition(":")[2]
        if raw and not Path(raw).is_file():
            problem = "is not a file" if Path(raw).exists() else "does not exist"
            raise InputError(f"CARMEN log {raw} {problem}")
        with checking():
            parse_carmen_source(text)
            text = with_odometry(text, odometry)
        if steps is not None:
            _check_steps(steps, _carmen_steps(text), text)
    elif kind == "npz":
        if not Path(text).is_file():
            raise InputError(f"log file {text} does not exist")
        if steps is not None:
            from mapfuse_core.measlog import load_log

            with reading():
                _check_steps(steps, load_log(text).n_steps, text)
    elif kind == "scenario":
        with checking():
            scenario = load_scenario(text)
        if steps is not None and steps > scenario.steps:
            raise UsageError(
                f"--steps {steps} is more than scenario {scenario.name!r} drives "
                f"({scenario.steps} steps)"
            )
    return Source(text, kind, seed, steps, data, known_map, scenario)


def load_source(args: argparse.Namespace, src: Source) -> MeasurementLog:
    """The log of ``src``: a simulation stopped at ``--steps`` (progress bar ``simulate``),
    or a saved log, dataset or CARMEN log read (an input error when it cannot be) and
    cut to ``--steps`` (a usage error beyond its length)."""
    from mapfuse.runner import load
    from mapfuse_core.sim.simulate import default_workers

    if src.kind == "scenario":
        return load(
            src.text,
            seed=src.seed,
            steps=src.steps,
            progress=progress_bar(args, "simulate"),
            workers=default_workers(),
        )
    # A reader that reports progress (a CARMEN log's scans) draws its bar after a
    # second: a snippet or a short log draws none.
    bar = progress_bar(args, "read scans", delay_s=1.0)
    with reading():
        log = load(src.text, seed=src.seed, data=src.data, known_map=src.known_map, progress=bar)
    if src.steps is not None:
        _check_steps(src.steps, log.n_steps, src.text)
        log = log.head(src.steps)
    return log
