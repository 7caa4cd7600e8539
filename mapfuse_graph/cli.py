"""The ``mapfuse`` command line: parses arguments, calls the library, prints results."""

from __future__ import annotations

import os

# Before numpy loads: the estimators work on small dense matrices, where threaded BLAS
# on this project's 2-core machines only adds contention (measured ~4x slower).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from mapfuse_core.measlog import save_log
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
    from mapfuse_core.plotting import world_figure

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


def _cmd_run(args: argparse.Namespace) -> int:
    from mapfuse_graph.runner import prepare_log, run_backend, write_outputs

    log = prepare_log(args.scenario, seed=args.seed, progress=_Progress("simulate", not args.quiet))
    run = run_backend(
        log,
        args.backend,
        fusion=args.fusion,
        association=args.association,
        robust=args.robust,
        progress=_Progress(args.backend, not args.quiet),
    )
    paths = write_outputs(run, args.out)
    print(json.dumps({"metrics": run.metrics, "outputs": paths}, indent=2))
    return 0


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
    run.add_argument("scenario", help="built-in scenario, .toml path, or log .npz")
    run.add_argument(
        "--backend", default="ekf", choices=["ekf", "batch", "isam2"], help="estimator"
    )
    run.add_argument(
        "--association",
        default="ekf",
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
    run.add_argument("--out", required=True, help="output directory")
    run.add_argument("--quiet", action="store_true", help="no progress output")
    run.set_defaults(func=_cmd_run)
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
