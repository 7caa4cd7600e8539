"""The ``mapfuse`` command line: parses arguments, calls the library, prints results.

Every command keeps the same promises (``docs/cli.md``): options, inputs and the
output folder are checked before any work (:mod:`mapfuse.cli_common`); the result is
JSON alone on stdout and a one-line summary ends on stderr; progress bars show rate
and ETA; the exit status says what went wrong.  The options shared by several commands
are made by one helper each (:mod:`mapfuse.cli_args`).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
import traceback
from collections.abc import Sequence
from contextlib import ExitStack
from typing import Any

from mapfuse.cli_args import (
    Formatter,
    Parser,
    add_data,
    add_estimator,
    add_estimators,
    add_fusion,
    add_output,
    add_plugins,
    add_quiet,
    add_seed,
    add_source,
    add_steps,
    fusions,
)
from mapfuse.cli_common import (
    DEBUG_ENV,
    EXIT_BROKEN_PIPE,
    EXIT_CHECK_FAILED,
    EXIT_INPUT,
    EXIT_INTERNAL,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_USAGE,
    CommandError,
    UsageError,
    check_out_dir,
    check_out_file,
    check_source,
    checking,
    emit,
    labelled_bars,
    load_source,
    note,
    progress_bar,
    reading,
    run_line,
    run_with_bars,
    source_kind,
    summary,
    warn_runs,
)
from mapfuse.interrupt import catching_sigint

__all__ = ["EXIT_INTERRUPTED", "main"]


def _version() -> str:
    from importlib import metadata

    try:
        return metadata.version("mapfuse")
    except metadata.PackageNotFoundError:
        return "unknown (not installed)"


# --------------------------------------------------------------------------- graph options

#: Command-line flags that set an option field, and that field's path in the options.
_OPTION_FLAGS: dict[str, tuple[str, ...]] = {
    "association": ("association",),
    "robust": ("graph", "robust"),
}


def _has_option(estimator: str, path: tuple[str, ...]) -> bool:
    """Whether ``estimator``'s default options have the (nested) field ``path``."""
    from mapfuse.registry import resolve

    obj: Any = resolve(estimator).options_type()
    for name in path:
        if not dataclasses.is_dataclass(obj) or name not in {
            f.name for f in dataclasses.fields(obj)
        }:
            return False
        obj = getattr(obj, name)
    return True


def _nest(path: tuple[str, ...], value: Any) -> dict[str, Any]:
    out: dict[str, Any] = {path[-1]: value}
    for name in reversed(path[:-1]):
        out = {name: out}
    return out


def _check_graph_flags(
    args: argparse.Namespace, estimators: Sequence[str]
) -> dict[str, dict[str, Any]]:
    """``--association`` / ``--robust`` as option overrides, by estimator, for the
    estimators whose options have those fields (the graph backends); an error when none
    of ``estimators`` has them, or when a value is bad."""
    given = {f: getattr(args, f) for f in _OPTION_FLAGS if getattr(args, f) is not None}
    if not given:
        return {}
    if given.get("robust") == "none":
        given["robust"] = None  # stated: no kernel, whatever the dataset's profile says
    out: dict[str, dict[str, Any]] = {}
    for flag, value in given.items():
        takers = [b for b in estimators if _has_option(b, _OPTION_FLAGS[flag])]
        if not takers:
            raise UsageError(
                f"--{flag}: no option of {', '.join(estimators)} takes it (the graph backends do)"
            )
        for b in takers:
            out.setdefault(b, {}).update(_nest(_OPTION_FLAGS[flag], value))
    if "robust" in given:
        from mapfuse_graph.graph import GraphOptions

        try:
            GraphOptions(robust=given["robust"])
        except ValueError as exc:
            raise UsageError(f"--robust: {exc}") from None
    return out


def _resolve_all(names: Sequence[str]) -> None:
    """Every estimator name known (a plug-in registered by ``--plugin`` included)."""
    from mapfuse.registry import resolve

    with checking():
        for name in names:
            resolve(name)


# --------------------------------------------------------------------------- simulate


def _cmd_simulate(args: argparse.Namespace) -> int:
    from mapfuse.outdir import prepare_output_dir
    from mapfuse.plotting import world_figure
    from mapfuse_core.measlog import save_log
    from mapfuse_core.sim.scenario import load_scenario
    from mapfuse_core.sim.simulate import default_workers, simulate

    with checking():
        scenario = load_scenario(args.scenario)
    steps = scenario.steps if args.steps is None else args.steps
    if args.steps is not None and args.steps > scenario.steps:
        raise UsageError(
            f"--steps {args.steps} is more than scenario {scenario.name!r} drives "
            f"({scenario.steps} steps)"
        )
    if args.plot_step is not None and args.plot_step >= steps:
        raise UsageError(f"--plot-step {args.plot_step} is beyond the log's {steps} steps")
    check_out_dir(args)
    t0 = time.perf_counter()
    # A drive through waypoints stops at --steps; one by a table of controls is cut.
    run_sc = scenario if scenario.controls else dataclasses.replace(scenario, steps=steps)
    result = simulate(
        run_sc,
        seed=args.seed,
        progress=progress_bar(args, "simulate"),
        workers=default_workers(),
    )
    log = result.log if result.log.n_steps == steps else result.log.head(steps)
    elapsed = time.perf_counter() - t0
    with checking():
        out = prepare_output_dir(args.out, force=args.force)
    log_path = save_log(log, out / "log.npz")
    counts = [log.feature_slice(k).stop - log.feature_slice(k).start for k in range(log.n_steps)]
    step = (
        args.plot_step
        if args.plot_step is not None
        else int(max(range(len(counts)), key=counts.__getitem__))
    )
    fig = world_figure(scenario.world, log, result.scans[step], step)
    fig_path = out / "world.png"
    fig.savefig(fig_path, dpi=120)
    emit(
        {
            "scenario": log.scenario,
            "seed": log.seed,
            "steps": log.n_steps,
            "features": log.n_features,
            "rejected": log.rejected,
            "log": str(log_path),
            "figure": str(fig_path),
            "wall_time_s": round(elapsed, 3),
        }
    )
    summary(
        args,
        f"simulated {log.scenario} seed {log.seed}: {log.n_steps} steps, "
        f"{log.n_features} features in {elapsed:.1f} s → {log_path}",
    )
    return EXIT_OK


# --------------------------------------------------------------------------- run


def _cmd_run(args: argparse.Namespace) -> int:
    from mapfuse.outdir import prepare_output_dir
    from mapfuse.outputs import write_outputs
    from mapfuse.registry import resolve

    with checking():
        estimator = resolve(args.estimator)
    src = check_source(args)
    flags = _check_graph_flags(args, [estimator.name]).get(estimator.name, {})
    if args.export_graph and not estimator.capabilities.exports_graph:
        raise UsageError(f"--export-graph: the {estimator.name} estimator holds no factor graph")
    check_out_dir(args)
    log = load_source(args, src)
    run = run_with_bars(args, log, estimator.name, args.fusion == "on", flags)
    with checking():
        out = prepare_output_dir(args.out, force=args.force)
    paths = write_outputs(run, out)
    warn_runs([run.metrics])
    if args.export_graph:
        from mapfuse_graph.export import export_graph

        ex = export_graph(run.result, out)
        paths.update({"graph_g2o": str(ex.g2o), "graph_sidecar": str(ex.sidecar)})
        note(ex.summary())
    emit({"metrics": run.metrics.to_json(), "outputs": paths})
    summary(args, f"{run_line(run.metrics)} → {out}")
    return EXIT_OK


# --------------------------------------------------------------------------- compare


def _check_beside(args: argparse.Namespace) -> list[str]:
    """The ``--beside`` scenarios: simulated ones, at least ``--steps`` long."""
    from mapfuse_core.sim.scenario import load_scenario

    beside = list(args.beside or ())
    for b in beside:
        if source_kind(b) != "scenario":
            raise UsageError(f"--beside {b}: only simulated scenarios, not a log or dataset")
        with checking():
            sc = load_scenario(b)
        if args.steps is not None and args.steps > sc.steps:
            raise UsageError(
                f"--steps {args.steps} is more than --beside scenario {sc.name!r} drives "
                f"({sc.steps} steps)"
            )
    return beside


def _cmd_compare(args: argparse.Namespace) -> int:
    from mapfuse.comparison import compare, write_comparison
    from mapfuse.outdir import prepare_output_dir

    names = list(args.estimators)
    _resolve_all(names)
    src = check_source(args)
    overrides = _check_graph_flags(args, names)
    fus = fusions(args.fusion)
    beside = _check_beside(args)
    check_out_dir(args)
    log = load_source(args, src)
    bars = labelled_bars(args)
    comparison = compare(log, names, fusions=fus, overrides=overrides, progress=bars)
    others: tuple[Any, ...] = ()
    if beside:
        from mapfuse.compare_beside import compare_beside

        others = compare_beside(beside, args.seed, names, fus, overrides, bars, steps=args.steps)
    bars.close()
    # The report's wall time is the command's so far: simulation and every run included.
    wall = time.perf_counter() - args.started
    comparison = dataclasses.replace(comparison, wall_time_s=wall)
    with checking():
        out = prepare_output_dir(args.out, force=args.force)
    paths = write_comparison(comparison, out, scenario=src.scenario, beside=others)
    warn_runs(comparison.metrics, label=True)
    # The command's whole wall time: the files written too.
    total = time.perf_counter() - args.started
    emit({"outputs": paths, "runs": len(comparison.runs), "wall_time_s": round(total, 2)})
    seed = f" seed {log.seed}" if log.seed >= 0 else ""
    summary(
        args,
        f"compared {len(comparison.runs)} runs ({', '.join(names)}; fusion {args.fusion}) on "
        f"{log.scenario}{seed} in {total:.1f} s → {paths['report']}",
    )
    return EXIT_OK


# --------------------------------------------------------------------------- baseline


def _cmd_baseline_record(args: argparse.Namespace) -> int:
    from mapfuse.baseline import record_baselines, save_baseline

    _resolve_all([args.estimator])
    src = check_source(args)
    check_out_file(args)
    log = load_source(args, src)
    bars = labelled_bars(args)
    entries = record_baselines(
        log, estimators=(args.estimator,), fusions=fusions(args.fusion), note=args.note,
        progress=bars,
    )  # fmt: skip
    bars.close()
    out = save_baseline(entries, args.out)
    emit(
        {
            "baseline": str(out),
            "entries": len(entries),
            "runs": [run_line(e.metrics) for e in entries],
        }
    )
    runs = f"{len(entries)} run{'s' if len(entries) > 1 else ''}"
    summary(args, f"recorded a baseline of {runs} of {args.estimator} → {out}")
    return EXIT_OK


def _cmd_baseline_check(args: argparse.Namespace) -> int:
    from mapfuse.baseline import Tolerance, check_log_against_baseline, load_baseline

    with reading():
        entries = load_baseline(args.baseline)
    m0 = entries[0].metrics
    _resolve_all(sorted({e.metrics.estimator for e in entries}))
    source = args.scenario or m0.scenario
    src = check_source(args, source=source)
    # A CARMEN log's seed is that of its simulated odometry (-1: raw odometry, none).
    if src.kind == "scenario" or (src.kind == "carmen" and m0.seed >= 0):
        src = dataclasses.replace(src, seed=m0.seed)
    # The baseline's own length: a simulation stops there, a longer log is cut.
    if src.kind == "scenario" and src.scenario is not None:
        src = dataclasses.replace(src, steps=min(m0.steps, src.scenario.steps))
    log = load_source(args, src)
    if log.n_steps > m0.steps:
        log = log.head(m0.steps)
    tolerances = None if args.tolerance is None else Tolerance(rel=args.tolerance)
    bars = labelled_bars(args)
    reports = check_log_against_baseline(log, entries, tolerances=tolerances, progress=bars)
    bars.close()
    passed = all(r.passed for r in reports)
    for r in reports:
        if not r.passed or not args.quiet:
            note(r.summary())
    reports_json = [r.to_dict() for r in reports]
    emit({"baseline": str(args.baseline), "passed": passed, "reports": reports_json})
    bad = sum(not r.passed for r in reports)
    verdict = f"FAILED, {bad} of {len(reports)} runs" if bad else f"all {len(reports)} runs"
    summary(
        args,
        f"baseline check {args.baseline}: {verdict} within tolerance"
        if not bad
        else f"baseline check {args.baseline}: {verdict} out of tolerance",
    )
    return EXIT_OK if passed else EXIT_CHECK_FAILED


# --------------------------------------------------------------------------- parser


def _add_known_map(p: argparse.ArgumentParser) -> None:
    from mapfuse.carmen_input import KNOWN_MAPS

    p.add_argument(
        "--known-map",
        default=None,
        choices=list(KNOWN_MAPS),
        help="CARMEN logs only: the floor plan built from the log's reference trajectory "
        "as known map, or none (default: the floor plan when the log has a reference "
        "trajectory, else none)",
    )


def _add_odometry(p: argparse.ArgumentParser) -> None:
    from mapfuse.carmen_input import ODOMETRY_KINDS

    p.add_argument(
        "--odometry",
        default=None,
        choices=list(ODOMETRY_KINDS),
        help="CARMEN logs only: the log's poses are raw odometry, or corrected ones (a "
        "reference trajectory; the odometry is then simulated from it) (default: decided "
        "from the log's evidence, an error when it does not decide)",
    )


def _add_graph_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--association",
        default=None,
        choices=["ekf", "truth", "own"],
        help="graph backends only: the EKF's decisions, simulation truth, or the graph's "
        "own χ²-gated nearest neighbour (default: the EKF's decisions)",
    )
    p.add_argument(
        "--robust",
        default=None,
        metavar="KERNEL",
        help="graph backends only: robust kernel on observations, huber[:k], cauchy[:k] "
        "or none (default: the dataset profile's: cauchy on CARMEN logs, else none)",
    )


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def _non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def _add_simulate(sub: Any) -> None:
    from mapfuse_core.sim.scenario import list_builtin_scenarios

    sim = sub.add_parser(
        "simulate",
        help="simulate a scenario into a measurement log",
        description="Simulate SCENARIO and write OUT/log.npz and OUT/world.png.",
        formatter_class=Formatter,
    )
    sim.add_argument(
        "scenario",
        metavar="SCENARIO",
        help=f"built-in scenario ({', '.join(list_builtin_scenarios())}) or a .toml path",
    )
    add_seed(sim, "seed of the simulation (default: the scenario's own)")
    add_steps(sim)
    sim.add_argument(
        "--plot-step",
        type=_non_negative_int,
        default=None,
        metavar="K",
        help="step whose scan world.png shows (default: the one with most features)",
    )
    add_output(sim)
    add_quiet(sim)
    sim.set_defaults(func=_cmd_simulate)


def _add_run(sub: Any) -> None:
    run = sub.add_parser(
        "run",
        help="run an estimator on a scenario, a log or a dataset",
        description="Run ESTIMATOR on SCENARIO and write OUT/metrics.json, the TUM "
        "trajectories (trajectory.tum, trajectory_known.tum, truth.tum, ...) and the "
        "error figures.",
        formatter_class=Formatter,
    )
    add_source(run)
    add_estimator(run)
    add_fusion(run, several=False)
    _add_graph_flags(run)
    _add_known_map(run)
    _add_odometry(run)
    add_seed(run)
    add_steps(run)
    add_data(run)
    run.add_argument(
        "--export-graph",
        action="store_true",
        help="graph backends: also write the solved graph, OUT/graph.g2o (poses and "
        "odometry) and OUT/graph.json (what g2o cannot hold, by name)",
    )
    add_plugins(run)
    add_output(run)
    add_quiet(run)
    run.set_defaults(func=_cmd_run)


def _add_compare(sub: Any) -> None:
    from mapfuse.comparison import DEFAULT_ESTIMATORS

    cmp_ = sub.add_parser(
        "compare",
        help="several estimators, with and without fusion, on one log",
        description="Run ESTIMATORS x FUSION on one measurement log (without fusion only, "
        "on a log without a known map) and write OUT/comparison.json, OUT/report.md, the "
        "paper's figures and each run's files in OUT/runs/.",
        formatter_class=Formatter,
    )
    add_source(cmp_)
    add_estimators(cmp_, ",".join(DEFAULT_ESTIMATORS))
    add_fusion(cmp_, several=True)
    _add_graph_flags(cmp_)
    _add_known_map(cmp_)
    _add_odometry(cmp_)
    add_seed(cmp_)
    add_steps(cmp_)
    add_data(cmp_)
    cmp_.add_argument(
        "--beside",
        action="append",
        default=None,
        metavar="SCENARIO",
        help="also compare the same estimators on this simulated scenario, same seed and "
        "steps, and put its table in the report (repeatable; e.g. loop600-sparse, the "
        "paper's regime) (default: none)",
    )
    add_plugins(cmp_)
    add_output(cmp_)
    add_quiet(cmp_)
    cmp_.set_defaults(func=_cmd_compare)


def _add_baseline(sub: Any) -> None:
    base = sub.add_parser(
        "baseline",
        help="record or check regression baselines",
        description="Record an estimator's metrics as a baseline JSON file, or re-run and "
        "check against one.",
        formatter_class=Formatter,
    )
    bsub = base.add_subparsers(dest="baseline_command", required=True, metavar="SUBCOMMAND")
    rec = bsub.add_parser(
        "record",
        help="record an estimator's metrics as a baseline",
        description="Run ESTIMATOR on SCENARIO (with and without fusion unless one is "
        "chosen) and write its metrics to the baseline file OUT.",
        formatter_class=Formatter,
    )
    add_source(rec)
    add_estimator(rec)
    add_fusion(rec, several=True)
    add_seed(rec)
    add_steps(rec)
    add_data(rec)
    rec.add_argument(
        "--note",
        default="",
        metavar="TEXT",
        help="free text stored with the baseline (default: none)",
    )
    add_plugins(rec)
    add_output(rec, kind="file", what="baseline JSON file to write")
    add_quiet(rec)
    rec.set_defaults(func=_cmd_baseline_record)
    chk = bsub.add_parser(
        "check",
        help="re-run and compare against a stored baseline",
        description="Re-run the baseline's runs (same seed and steps) and compare their "
        "metrics; exit 1 when one is out of tolerance. The reports are JSON on stdout.",
        formatter_class=Formatter,
    )
    add_source(chk, nargs="?", default=None)
    chk.add_argument("--baseline", required=True, metavar="FILE", help="baseline JSON file")
    chk.add_argument(
        "--tolerance",
        type=_positive_float,
        default=None,
        metavar="REL",
        help="relative tolerance for every checked metric (default: per-metric defaults, "
        "docs in mapfuse/baseline.py)",
    )
    add_data(chk)
    add_plugins(chk)
    add_quiet(chk)
    chk.set_defaults(func=_cmd_baseline_check)


def _parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="mapfuse",
        description="Map fusion SLAM toolkit: simulate, run the EKF reference or the GTSAM "
        "mirror, compare them, keep baselines. Results are JSON on stdout; progress, "
        "messages and a one-line summary go to stderr. Exit status: 0 done, 1 a check "
        "failed, 2 usage error, 3 input error, 70 internal error, 130 interrupted.",
        formatter_class=Formatter,
    )
    p.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _add_simulate(sub)
    _add_run(sub)
    _add_compare(sub)

    from mapfuse.campaign_cli import add_montecarlo, add_world

    add_montecarlo(sub)
    add_world(sub)
    _add_baseline(sub)

    from mapfuse.spectrum_cli import add_spectrum_parser

    add_spectrum_parser(sub)

    from mapfuse.changes_cli import add_parser as add_changes

    add_changes(sub)
    return p


# --------------------------------------------------------------------------- main


def _internal_error(exc: BaseException) -> int:
    if os.environ.get(DEBUG_ENV):
        traceback.print_exception(type(exc), exc, exc.__traceback__, file=sys.stderr)
    first = (str(exc).splitlines() or [""])[0]
    note(
        f"mapfuse: internal error: {type(exc).__name__}: {first} (a bug; run again with "
        f"{DEBUG_ENV}=1 for the traceback, and report it)"
    )
    return EXIT_INTERNAL


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``mapfuse`` command.

    Exit status (:mod:`mapfuse.cli_common`): 0 done, 1 a check failed (``baseline
    check``), 2 a usage error, 3 an input error (one line on stderr each), 70 an
    internal error (one line; ``MAPFUSE_DEBUG=1`` adds the traceback), 130 interrupted
    by Ctrl-C.
    """
    started = time.perf_counter()
    try:
        args = _parser().parse_args(argv)
    except SystemExit as exc:  # --help, --version, or a usage error argparse printed
        return exc.code if isinstance(exc.code, int) else EXIT_USAGE
    args.started = started
    from mapfuse.progress import close_all

    with catching_sigint():
        try:
            with ExitStack() as stack:
                plugins = getattr(args, "plugin", None) or ()
                if plugins:
                    from mapfuse.registry import registered_plugins

                    # A plug-in module in the current folder imports as from ``python``
                    # (the ``mapfuse`` script's own folder is first on the path).
                    if "" not in sys.path and os.getcwd() not in sys.path:
                        sys.path.append(os.getcwd())
                    try:
                        stack.enter_context(registered_plugins(plugins))
                    except (ValueError, TypeError) as exc:
                        raise UsageError(f"--plugin: {exc}") from None
                code: int = args.func(args)
        except KeyboardInterrupt:
            close_all()
            note("mapfuse: interrupted")
            return EXIT_INTERRUPTED
        except CommandError as exc:
            close_all()
            note(f"mapfuse: error: {exc}")
            return exc.code
        except BrokenPipeError:
            # The reader of stdout went away (``| head``): nothing more reaches it.
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return EXIT_BROKEN_PIPE
        except OSError as exc:
            close_all()
            where = f"{exc.filename}: " if exc.filename else ""
            note(f"mapfuse: error: {where}{exc.strerror or exc}")
            return EXIT_INPUT
        except Exception as exc:
            close_all()
            return _internal_error(exc)
    return code


if __name__ == "__main__":
    raise SystemExit(main())
