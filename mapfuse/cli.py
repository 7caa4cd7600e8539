"""The ``mapfuse`` command line: parses arguments, calls the library, prints results."""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mapfuse.interrupt import catching_sigint
from mapfuse_core.measlog import MeasurementLog, save_log
from mapfuse_core.sim.limits import check_seed
from mapfuse_core.sim.scenario import ScenarioError, list_builtin_scenarios, load_scenario
from mapfuse_core.sim.simulate import default_workers, simulate

__all__ = ["main"]

#: Exit status of a command stopped by Ctrl-C (128 + SIGINT), as shells report it.
EXIT_INTERRUPTED = 130


class UsageError(ValueError):
    """An option that does not apply, or a bad option value, found before any work."""


def _version() -> str:
    from importlib import metadata

    try:
        return metadata.version("mapfuse")
    except metadata.PackageNotFoundError:
        return "unknown (not installed)"


def _emit(obj: Any) -> None:
    """The command's result: JSON alone on stdout."""
    print(json.dumps(obj, indent=2))


def _note(text: str) -> None:
    """A message for the user, on stderr."""
    print(text, file=sys.stderr)


def _warn_runs(runs: Sequence[Any], label: bool = False) -> None:
    """Each run's ``metrics.json`` warnings, once each, on stderr (stdout is JSON)."""
    for r in runs:
        m = r.metrics
        who = f"{m.estimator} {'with' if m.fusion else 'without'} fusion: " if label else ""
        for w in m.warnings:
            _note(f"mapfuse: warning: {who}{w}")


# --------------------------------------------------------------------------- validation


def _is_dataset(source: str) -> bool:
    from mapfuse.runner import DATASETS

    return source in DATASETS


def _is_carmen(source: str) -> bool:
    from mapfuse.carmen_input import is_carmen

    return is_carmen(source)


def _simulated(source: str) -> bool:
    """Whether ``source`` is a scenario to simulate (not a saved log or real data)."""
    return not (source.endswith(".npz") or _is_dataset(source) or _is_carmen(source))


def _source(args: argparse.Namespace) -> str:
    """The command's input, with ``--odometry`` folded into a CARMEN source."""
    from mapfuse.carmen_input import with_odometry

    odometry = getattr(args, "odometry", None)
    if odometry is not None and not _is_carmen(args.scenario):
        raise UsageError(
            f"--odometry applies to CARMEN logs (carmen:PATH) only, not {args.scenario!r}"
        )
    return with_odometry(args.scenario, odometry)


def _check_source(args: argparse.Namespace, source: str, seed: int | None) -> None:
    """The input and the options that depend on it, checked before any work."""
    data = getattr(args, "data", None)
    known_map = getattr(args, "known_map", None)
    if known_map is not None and not _is_carmen(source):
        raise UsageError(f"--known-map applies to CARMEN logs (carmen:PATH) only, not {source!r}")
    if _is_carmen(source):
        from mapfuse.carmen_input import parse_carmen_source

        parse_carmen_source(source)  # names a bad option or a missing file
    elif source.endswith(".npz"):
        if not Path(source).is_file():
            raise UsageError(f"log file {source} does not exist")
        if seed is not None:
            raise UsageError(f"--seed does not apply to a saved log ({source}): it is simulated")
    elif _is_dataset(source):
        if seed is not None:
            raise UsageError(f"--seed does not apply to the real dataset {source!r}")
        if data is None:
            raise UsageError(f"dataset {source!r} needs a data directory (--data DIR)")
        if not Path(data).is_dir():
            raise UsageError(f"--data {data} is not a directory")
    else:
        load_scenario(source)  # ScenarioError names what is wrong
    if data is not None and not _is_dataset(source):
        raise UsageError(f"--data applies to carpark and victoria-park only, not {source!r}")


#: Command-line flags that set an option field, and that field's path in the options.
_OPTION_FLAGS: dict[str, tuple[str, ...]] = {
    "association": ("association",),
    "robust": ("graph", "robust"),
}


def _has_option(estimator: str, path: tuple[str, ...]) -> bool:
    """Whether ``estimator``'s default options have the (nested) field ``path``."""
    import dataclasses

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
    args: argparse.Namespace, backends: Sequence[str]
) -> dict[str, dict[str, Any]]:
    """``--association`` / ``--robust`` as option overrides, by estimator, for the
    estimators whose options have those fields (the graph backends); an error when none
    of ``backends`` has them, or when a value is bad."""
    given = {f: getattr(args, f) for f in _OPTION_FLAGS if getattr(args, f) is not None}
    if not given:
        return {}
    out: dict[str, dict[str, Any]] = {}
    for flag, value in given.items():
        takers = [b for b in backends if _has_option(b, _OPTION_FLAGS[flag])]
        if not takers:
            raise UsageError(
                f"--{flag}: no option of {', '.join(backends)} takes it (the graph backends do)"
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


def _check_out(args: argparse.Namespace) -> Path:
    from mapfuse.outdir import prepare_output_dir

    return prepare_output_dir(args.out, force=args.force)


def _check_file_out(path: str) -> Path:
    """A file to write: its folder must exist or be creatable, and be writable."""
    import tempfile

    p = Path(path)
    if p.is_dir():
        raise UsageError(f"--out {p} is a folder; give a file name")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=p.parent, prefix=".mapfuse-probe-"):
            pass
    except OSError as exc:
        raise UsageError(f"--out {p}: folder not writable: {exc.strerror or exc}") from None
    return p


# --------------------------------------------------------------------------- commands


def _progress(label: str, args: argparse.Namespace) -> Any:
    from mapfuse.progress import progress_bar

    return progress_bar(label, enabled=not args.quiet)


def _cmd_simulate(args: argparse.Namespace) -> int:
    from mapfuse.plotting import world_figure

    if args.seed is not None:
        check_seed(args.seed, "--seed")
    scenario = load_scenario(args.scenario)
    if args.plot_step is not None and args.plot_step < 0:
        raise UsageError(f"--plot-step must be >= 0, got {args.plot_step}")
    out = _check_out(args)
    t0 = time.perf_counter()
    result = simulate(
        scenario, seed=args.seed, progress=_progress("simulate", args), workers=default_workers()
    )
    elapsed = time.perf_counter() - t0
    log = result.log
    if args.plot_step is not None and args.plot_step >= log.n_steps:
        raise UsageError(f"--plot-step {args.plot_step} beyond the log's {log.n_steps} steps")
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
    _emit(
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
    return 0


def _log_from_args(args: argparse.Namespace, source: str, seed: int | None) -> MeasurementLog:
    """The measurement log a command works on: a .npz, a dataset or a simulation.

    A simulation extracts with the default pool: the command's main module is guarded.
    """
    from mapfuse.runner import prepare_log

    return prepare_log(
        source,
        seed=seed,
        progress=_progress("simulate", args),
        data_dir=getattr(args, "data", None),
        known_map=getattr(args, "known_map", None),
        workers=default_workers(),
    )


def _cmd_run(args: argparse.Namespace) -> int:
    from mapfuse.outputs import write_outputs
    from mapfuse.registry import resolve
    from mapfuse.runner import run as run_estimator

    estimator = resolve(args.backend)
    source = _source(args)
    _check_source(args, source, args.seed)
    flags = _check_graph_flags(args, [args.backend]).get(estimator.name, {})
    if args.steps is not None and args.steps < 1:
        raise UsageError(f"--steps must be >= 1, got {args.steps}")
    if args.export_graph and not estimator.capabilities.exports_graph:
        raise UsageError(f"--export-graph: the {args.backend} estimator holds no factor graph")
    out = _check_out(args)
    log = _log_from_args(args, source, args.seed)
    if args.steps is not None:
        log = log.head(args.steps)
    run = run_estimator(
        log, estimator, fusion=args.fusion, progress=_progress(args.backend, args), **flags
    )
    paths = write_outputs(run, out)
    _warn_runs([run])
    if args.export_graph:
        from mapfuse_graph.export import export_graph

        ex = export_graph(run.result, out)
        paths.update({"graph_g2o": str(ex.g2o), "graph_sidecar": str(ex.sidecar)})
        _note(ex.summary())
    _emit({"metrics": run.metrics.to_json(), "outputs": paths})
    return 0


def _cmd_compare(args: argparse.Namespace) -> int:
    from mapfuse.comparison import DEFAULT_ESTIMATORS, compare, write_comparison
    from mapfuse.progress import LabelledProgress
    from mapfuse.registry import resolve

    backends = list(DEFAULT_ESTIMATORS)
    if args.backends is not None:
        backends = [b.strip() for b in args.backends.split(",") if b.strip()]
        if not backends or len(set(backends)) != len(backends):
            raise UsageError(f"--backends needs distinct names, got {args.backends!r}")
    for b in backends:
        resolve(b)  # an unknown name fails before any work
    source = _source(args)
    _check_source(args, source, args.seed)
    overrides = _check_graph_flags(args, backends)
    fusions = (True, False) if args.fusion is None else (args.fusion,)
    beside = list(args.beside or ())
    for b in beside:
        if b.endswith(".npz") or _is_dataset(b):
            raise UsageError(f"--beside {b}: only simulated scenarios, not a log or dataset")
        load_scenario(b)  # ScenarioError names what is wrong
    out = _check_out(args)
    log = _log_from_args(args, source, args.seed)
    progress = LabelledProgress(not args.quiet)
    comparison = compare(
        log, progress=progress, estimators=backends, fusions=fusions, overrides=overrides
    )
    others: tuple[Any, ...] = ()
    if beside:
        from mapfuse.compare_beside import compare_beside

        others = compare_beside(beside, args.seed, backends, fusions, overrides, progress)
    progress.close()
    scenario = load_scenario(args.scenario) if _simulated(args.scenario) else None
    paths = write_comparison(comparison, out, scenario=scenario, beside=others)
    _warn_runs(comparison.runs, label=True)
    _emit({"outputs": paths})
    if not args.quiet:
        _note(f"Report: {paths['report']}")
    return 0


def _cmd_baseline_record(args: argparse.Namespace) -> int:
    from mapfuse.baseline import record_baselines, save_baseline
    from mapfuse.registry import resolve

    resolve(args.backend)
    _check_source(args, args.scenario, args.seed)
    out = _check_file_out(args.out)
    log = _log_from_args(args, args.scenario, args.seed)
    fusions = (True, False) if args.fusion is None else (args.fusion,)
    entries = record_baselines(log, estimators=(args.backend,), fusions=fusions, note=args.note)
    save_baseline(entries, out)
    _emit({"baseline": str(out), "entries": len(entries)})
    return 0


def _cmd_baseline_check(args: argparse.Namespace) -> int:
    from mapfuse.baseline import Tolerance, check_log_against_baseline, load_baseline

    if args.tolerance is not None and not args.tolerance > 0:
        raise UsageError(f"--tolerance must be > 0, got {args.tolerance}")
    entries = load_baseline(args.baseline)
    m0 = entries[0].metrics
    source = args.scenario or m0.scenario
    # A CARMEN log's seed is that of its simulated odometry (-1: raw odometry, none).
    keeps_seed = _simulated(source) or (_is_carmen(source) and m0.seed >= 0)
    seed = m0.seed if keeps_seed else None
    _check_source(args, source, seed)
    log = _log_from_args(args, source, seed)
    tolerances = None
    if args.tolerance is not None:
        tolerances = Tolerance(rel=args.tolerance)
    reports = check_log_against_baseline(log, entries, tolerances=tolerances)
    for r in reports:
        print(r.summary())
    return 0 if all(r.passed for r in reports) else 1


class _Formatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows every option's default, except where there is none to show."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default is None or action.default is argparse.SUPPRESS or action.nargs == 0:
            return action.help
        return super()._get_help_string(action)


def _sources() -> str:
    from mapfuse.runner import DATASETS

    return (
        f"built-in scenario ({', '.join(list_builtin_scenarios())}), a scenario .toml path, "
        f"a saved log .npz, a real dataset ({', '.join(DATASETS)}; needs --data), or a "
        "CARMEN laser log carmen:PATH.log[.gz] (carmen,odometry=raw|corrected:PATH states "
        "its kind)"
    )


def _add_common(
    p: argparse.ArgumentParser, *, seed: bool = True, data: bool = True, out: str | None = "dir"
) -> None:
    if seed:
        p.add_argument(
            "--seed",
            type=int,
            default=None,
            help="random seed of the simulation (default: the scenario's), or of a corrected "
            "CARMEN log's simulated odometry (default 0); not for a saved log or the car park "
            "and Victoria Park",
        )
    if data:
        p.add_argument(
            "--data",
            default=None,
            help="data directory of the real datasets (carpark, victoria-park)",
        )
    if out == "dir":
        p.add_argument("--out", required=True, help="output folder")
        p.add_argument(
            "--force",
            action="store_true",
            help="replace the files of another run in --out (without it such a folder is refused)",
        )
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def _add_fusion(p: argparse.ArgumentParser, default: bool | None, what: str) -> None:
    fusion = p.add_mutually_exclusive_group()
    fusion.add_argument(
        "--fusion",
        dest="fusion",
        action="store_true",
        default=default,
        help=f"{what} with map fusion only" if default is None else "fuse the known map (default)",
    )
    fusion.add_argument(
        "--no-fusion",
        dest="fusion",
        action="store_false",
        help=f"{what} without map fusion only" if default is None else "SLAM without map fusion",
    )


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
        help="graph backends only: the EKF's decisions (their default), simulation truth, "
        "or the graph's own χ²-gated nearest neighbour",
    )
    p.add_argument(
        "--robust",
        default=None,
        help="graph backends only: robust kernel on observations, huber[:k] or cauchy[:k] "
        "(default: none)",
    )


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="mapfuse",
        description="Map fusion SLAM toolkit: simulate, run the EKF reference or the GTSAM "
        "mirror, compare them, keep baselines.  Results are JSON on stdout; progress and "
        "messages go to stderr.",
        formatter_class=_Formatter,
    )
    p.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    sim = sub.add_parser(
        "simulate",
        help="simulate a scenario into a measurement log",
        description="Simulate SCENARIO and write OUT/log.npz and OUT/world.png.",
        formatter_class=_Formatter,
    )
    sim.add_argument(
        "scenario",
        help=f"built-in scenario ({', '.join(list_builtin_scenarios())}) or a .toml path",
    )
    _add_common(sim, data=False)
    sim.add_argument(
        "--plot-step",
        type=int,
        default=None,
        help="step whose scan world.png shows (default: the one with most features)",
    )
    sim.set_defaults(func=_cmd_simulate)

    run = sub.add_parser(
        "run",
        help="run an estimator on a scenario, a log or a dataset",
        description="Run BACKEND on SCENARIO and write OUT/metrics.json, the TUM "
        "trajectories (trajectory.tum, trajectory_known.tum, truth.tum, ...) and the "
        "error figures.",
        formatter_class=_Formatter,
    )
    run.add_argument("scenario", help=_sources())
    run.add_argument(
        "--backend",
        default="ekf",
        help="registered estimator (built-in: ekf, batch, isam2; plugins: entry points of "
        "the 'mapfuse.estimators' group)",
    )
    _add_graph_flags(run)
    _add_known_map(run)
    _add_odometry(run)
    _add_fusion(run, True, "run")
    run.add_argument("--steps", type=int, default=None, help="run only the log's first STEPS steps")
    run.add_argument(
        "--export-graph",
        action="store_true",
        help="graph backends: also write the solved graph, OUT/graph.g2o (poses and "
        "odometry) and OUT/graph.json (what g2o cannot hold, by name)",
    )
    _add_common(run)
    run.set_defaults(func=_cmd_run)

    cmp_ = sub.add_parser(
        "compare",
        help="several backends, with and without fusion, on one log",
        description="Run BACKENDS x {fusion, no fusion} on one measurement log (without "
        "fusion only, on a log without a known map) and write OUT/comparison.json, "
        "OUT/report.md, the paper's figures and each run's files in OUT/runs/.",
        formatter_class=_Formatter,
    )
    cmp_.add_argument("scenario", help=_sources())
    cmp_.add_argument(
        "--backends",
        default="ekf,batch,isam2",
        help="comma-separated registered estimators",
    )
    _add_fusion(cmp_, None, "compare")
    _add_graph_flags(cmp_)
    _add_known_map(cmp_)
    _add_odometry(cmp_)
    cmp_.add_argument(
        "--beside",
        action="append",
        metavar="SCENARIO",
        help="also compare the same backends on this simulated scenario, same seed, and "
        "put its table in the report (repeatable; e.g. loop600-sparse, the paper's regime)",
    )
    _add_common(cmp_)
    cmp_.set_defaults(func=_cmd_compare)

    from mapfuse.campaign.cli import add_montecarlo, add_world

    add_montecarlo(sub)
    add_world(sub)

    base = sub.add_parser(
        "baseline",
        help="record or check regression baselines",
        description="Record a backend's metrics as a baseline JSON file, or re-run and "
        "check against one.",
        formatter_class=_Formatter,
    )
    bsub = base.add_subparsers(dest="baseline_command", required=True, metavar="SUBCOMMAND")
    rec = bsub.add_parser(
        "record",
        help="record a backend's metrics as a baseline",
        description="Run BACKEND on SCENARIO (with and without fusion unless one is "
        "chosen) and write its metrics to the baseline file OUT.",
        formatter_class=_Formatter,
    )
    rec.add_argument("scenario", help=_sources())
    rec.add_argument("--backend", default="ekf", help="registered estimator")
    _add_fusion(rec, None, "record")
    rec.add_argument("--note", default="", help="free text stored with the baseline")
    rec.add_argument("--out", required=True, help="baseline JSON file to write")
    _add_common(rec, out=None)
    rec.set_defaults(func=_cmd_baseline_record)
    chk = bsub.add_parser(
        "check",
        help="re-run and compare against a stored baseline",
        description="Re-run the baseline's runs and compare their metrics; exit 1 when "
        "one is out of tolerance.",
        formatter_class=_Formatter,
    )
    chk.add_argument(
        "scenario", nargs="?", default=None, help="input to re-run (default: the baseline's)"
    )
    chk.add_argument("--baseline", required=True, help="baseline JSON file")
    chk.add_argument(
        "--tolerance",
        type=float,
        default=None,
        help="relative tolerance for every checked metric (default: per-metric defaults)",
    )
    _add_common(chk, seed=False, out=None)
    chk.set_defaults(func=_cmd_baseline_check)
    from mapfuse.spectrum import add_spectrum_parser

    add_spectrum_parser(sub)

    from mapfuse.changes_cli import add_parser as add_changes

    add_changes(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``mapfuse`` command.

    Exit status: 0 done, 1 a baseline check failed, 2 a usage or input error (one line
    on stderr), 130 interrupted by Ctrl-C.
    """
    args = _parser().parse_args(argv)
    with catching_sigint():
        try:
            code: int = args.func(args)
        except KeyboardInterrupt:
            from mapfuse.progress import close_all

            close_all()
            _note("mapfuse: interrupted")
            return EXIT_INTERRUPTED
        except (ScenarioError, ValueError, OSError) as exc:
            from mapfuse.progress import close_all

            close_all()
            _note(f"mapfuse: error: {exc}")
            return 2
    return code


if __name__ == "__main__":
    raise SystemExit(main())
