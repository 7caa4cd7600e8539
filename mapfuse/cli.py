"""The ``mapfuse`` command line: parses arguments, calls the library, prints results."""

from __future__ import annotations

import os

# Before numpy loads: the estimators work on small dense matrices, where threaded BLAS
# on this project's 2-core machines only adds contention (docs/performance.md).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from mapfuse_core.measlog import MeasurementLog, save_log
from mapfuse_core.scenario import ScenarioError, list_builtin_scenarios, load_scenario
from mapfuse_core.simulate import simulate

__all__ = ["main"]


class _Progress:
    """A one-line progress indicator on stderr, silent when not a terminal or ``--quiet``."""

    def __init__(self, label: str, enabled: bool) -> None:
        self.label = label
        self.enabled = enabled and sys.stderr.isatty()
        self._last = -1

    def __call__(self, k: int, n: int) -> None:
        if not self.enabled:
            return
        pct = 100 * k // max(n, 1)
        if pct != self._last:
            self._last = pct
            end = "\n" if k >= n else ""
            print(f"\r{self.label}: {pct:3d}% ({k}/{n})", end=end, file=sys.stderr, flush=True)


def _cmd_simulate(args: argparse.Namespace) -> int:
    from mapfuse.plotting import world_figure

    scenario = load_scenario(args.scenario)
    t0 = time.perf_counter()
    result = simulate(scenario, seed=args.seed, progress=_Progress("simulate", not args.quiet))
    elapsed = time.perf_counter() - t0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log = result.log
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
    summary = {
        "scenario": log.scenario,
        "seed": log.seed,
        "steps": log.n_steps,
        "features": log.n_features,
        "rejected": log.rejected,
        "log": str(log_path),
        "figure": str(fig_path),
        "wall_time_s": round(elapsed, 3),
    }
    print(json.dumps(summary, indent=2))
    return 0


def _log_from_args(args: argparse.Namespace, source: str, seed: int | None) -> MeasurementLog:
    """The measurement log a command works on: a .npz, a dataset or a simulation."""
    from mapfuse.run import prepare_log

    return prepare_log(
        source,
        seed=seed,
        progress=_Progress("simulate", not args.quiet),
        data_dir=getattr(args, "data", None),
    )


def _graph_flags(args: argparse.Namespace, estimator: object) -> dict[str, object]:
    """``--association`` / ``--robust`` as option overrides, when given; only an
    estimator that consumes another's decisions (the graph backends) takes them."""
    flags: dict[str, object] = {}
    given = [f for f in ("association", "robust") if getattr(args, f) is not None]
    if given and getattr(estimator, "consumes", None) is None:
        names = " and ".join(f"--{f}" for f in given)
        raise ValueError(f"{names}: only for the graph backends (batch, isam2), not {args.backend}")
    if args.association is not None:
        flags["association"] = args.association
    if args.robust is not None:
        flags["robust"] = args.robust
    return flags


def _cmd_run(args: argparse.Namespace) -> int:
    from mapfuse.outputs import write_outputs
    from mapfuse.run import resolve
    from mapfuse.run import run as run_estimator

    estimator = resolve(args.backend)
    log = _log_from_args(args, args.scenario, args.seed)
    if args.steps is not None:
        if args.steps < 1:
            raise ValueError(f"--steps must be >= 1, got {args.steps}")
        log = log.head(args.steps)
    run = run_estimator(
        log,
        estimator,
        fusion=args.fusion,
        progress=_Progress(args.backend, not args.quiet),
        **_graph_flags(args, estimator),
    )
    paths = write_outputs(run, args.out)
    print(json.dumps({"metrics": run.metrics, "outputs": paths}, indent=2))
    return 0


class _LabelledProgress:
    """Adapts ``progress(label, k, n)`` callbacks to one :class:`_Progress` per label."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self._bars: dict[str, _Progress] = {}

    def __call__(self, label: str, k: int, n: int) -> None:
        bar = self._bars.setdefault(label, _Progress(label, self.enabled))
        bar(k, n)


def _cmd_compare(args: argparse.Namespace) -> int:
    from mapfuse.compare import compare, write_comparison
    from mapfuse.run import resolve

    backends = None
    if args.backends is not None:
        backends = [b.strip() for b in args.backends.split(",") if b.strip()]
        for b in backends:
            resolve(b)  # an unknown name fails before any simulation
    log = _log_from_args(args, args.scenario, args.seed)
    comparison = compare(log, progress=_LabelledProgress(not args.quiet), backends=backends)
    simulated = not (args.scenario.endswith(".npz") or args.data)
    scenario = load_scenario(args.scenario) if simulated else None
    paths = write_comparison(comparison, args.out, scenario=scenario)
    print(json.dumps({"outputs": paths}, indent=2))
    print(f"Report: {paths['report']}")
    return 0


def _cmd_baseline_record(args: argparse.Namespace) -> int:
    from mapfuse.baseline import record_baselines, save_baseline

    log = _log_from_args(args, args.scenario, args.seed)
    fusions = (True, False) if args.fusion is None else (args.fusion,)
    entries = record_baselines(log, backends=(args.backend,), fusions=fusions, note=args.note)
    save_baseline(entries, args.out)
    print(json.dumps({"baseline": str(args.out), "entries": len(entries)}))
    return 0


def _cmd_baseline_check(args: argparse.Namespace) -> int:
    from mapfuse.baseline import Tolerance, check_log_against_baseline, load_baseline

    entries = load_baseline(args.baseline)
    m0 = entries[0]["metrics"]
    source = args.scenario or m0["scenario"]
    log = _log_from_args(args, source, m0["seed"])
    tolerances = None
    if args.tolerance is not None:
        tolerances = Tolerance(rel=args.tolerance)
    reports = check_log_against_baseline(log, entries, tolerances=tolerances)
    for r in reports:
        print(r.summary())
    return 0 if all(r.passed for r in reports) else 1


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="mapfuse",
        description="Map fusion SLAM toolkit: simulate, run the EKF reference or the GTSAM mirror.",
    )
    sub = p.add_subparsers(dest="command", required=True)
    sim = sub.add_parser(
        "simulate",
        help="simulate a scenario into a measurement log",
        description="Simulate SCENARIO (built-in name or TOML path) and write "
        "OUT/log.npz and OUT/world.png.",
    )
    sim.add_argument(
        "scenario",
        help=f"built-in scenario ({', '.join(list_builtin_scenarios())}) or a .toml path",
    )
    sim.add_argument("--seed", type=int, default=None, help="random seed (default: the scenario's)")
    sim.add_argument("--out", required=True, help="output directory")
    sim.add_argument("--plot-step", type=int, default=None, help="step whose scan world.png shows")
    sim.add_argument("--quiet", action="store_true", help="no progress output")
    sim.set_defaults(func=_cmd_simulate)

    run = sub.add_parser(
        "run",
        help="run an estimator on a scenario or a log",
        description="Run BACKEND on SCENARIO (built-in name, TOML path, or a log.npz) and "
        "write OUT/metrics.json, OUT/trajectory.tum and OUT/errors.png.",
    )
    run.add_argument(
        "scenario", help="built-in scenario, .toml path, log .npz, carpark or victoria-park"
    )
    run.add_argument(
        "--backend",
        default="ekf",
        help="registered estimator (built-in: ekf, batch, isam2; plugins: entry points of "
        "the 'mapfuse.estimators' group)",
    )
    run.add_argument(
        "--association",
        default=None,
        choices=["ekf", "truth", "own"],
        help="graph backends: the EKF's saved decisions (default), simulation truth, or "
        "the graph's own χ²-gated nearest neighbour",
    )
    run.add_argument(
        "--robust", default=None, help="robust kernel on observations: huber[:k] or cauchy[:k]"
    )
    fusion = run.add_mutually_exclusive_group()
    fusion.add_argument(
        "--fusion",
        dest="fusion",
        action="store_true",
        default=True,
        help="fuse the known map (default)",
    )
    fusion.add_argument(
        "--no-fusion", dest="fusion", action="store_false", help="SLAM without map fusion"
    )
    run.add_argument("--seed", type=int, default=None, help="random seed for simulation")
    run.add_argument("--steps", type=int, default=None, help="run only the log's first STEPS steps")
    run.add_argument("--data", default=None, help="data directory for carpark / victoria-park")
    run.add_argument("--out", required=True, help="output directory")
    run.add_argument("--quiet", action="store_true", help="no progress output")
    run.set_defaults(func=_cmd_run)

    cmp_ = sub.add_parser(
        "compare",
        help="EKF, batch and iSAM2 (or --backends), with and without fusion, on one log",
        description="Run {ekf, batch, isam2} (or --backends) x {fusion, no fusion} on one "
        "measurement log (no "
        "fusion only, on a log without a known map) and write OUT/comparison.json, "
        "OUT/report.md and the paper's figures.",
    )
    cmp_.add_argument("scenario", help="built-in scenario, .toml path, or log .npz")
    cmp_.add_argument("--seed", type=int, default=None, help="random seed for simulation")
    cmp_.add_argument(
        "--backends",
        default=None,
        help="comma-separated registered estimators (default: ekf,batch,isam2)",
    )
    cmp_.add_argument("--data", default=None, help="data directory for carpark / victoria-park")
    cmp_.add_argument("--out", required=True, help="output directory")
    cmp_.add_argument("--quiet", action="store_true", help="no progress bar")
    cmp_.set_defaults(func=_cmd_compare)

    base = sub.add_parser("baseline", help="record or check regression baselines")
    bsub = base.add_subparsers(dest="baseline_command", required=True)
    rec = bsub.add_parser("record", help="record a backend's metrics as a baseline")
    rec.add_argument("scenario", help="built-in scenario, .toml path, or log .npz")
    rec.add_argument("--backend", default="ekf", help="registered estimator")
    rec.add_argument("--seed", type=int, default=None)
    fz = rec.add_mutually_exclusive_group()
    fz.add_argument("--fusion", dest="fusion", action="store_true", default=None)
    fz.add_argument("--no-fusion", dest="fusion", action="store_false")
    rec.add_argument("--note", default="", help="free text stored with the baseline")
    rec.add_argument("--out", required=True, help="baseline JSON file to write")
    rec.add_argument("--quiet", action="store_true")
    rec.set_defaults(func=_cmd_baseline_record)
    chk = bsub.add_parser("check", help="re-run and compare against a stored baseline")
    chk.add_argument("scenario", nargs="?", default=None, help="default: the baseline's")
    chk.add_argument("--baseline", required=True, help="baseline JSON file")
    chk.add_argument(
        "--tolerance",
        type=float,
        default=None,
        help="relative tolerance for every checked metric (default: per-metric defaults)",
    )
    chk.add_argument("--quiet", action="store_true")
    chk.set_defaults(func=_cmd_baseline_check)

    from mapfuse.changes_cli import add_parser as add_changes

    add_changes(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``mapfuse`` command."""
    args = _parser().parse_args(argv)
    try:
        code: int = args.func(args)
    except (ScenarioError, ValueError, OSError) as exc:
        print(f"mapfuse: error: {exc}", file=sys.stderr)
        return 2
    return code


if __name__ == "__main__":
    raise SystemExit(main())
