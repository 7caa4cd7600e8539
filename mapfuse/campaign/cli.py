"""The ``mapfuse montecarlo`` and ``mapfuse world generate`` commands: argument parsing
and the calls of the engine and of the world generator."""

from __future__ import annotations

import argparse
import json
from typing import Any

from mapfuse_core.sim.scenario import list_builtin_scenarios

__all__ = ["add_montecarlo", "add_world", "parse_world_args"]


_KIND_NAMES = {int: "an integer", float: "a number", str: "text"}


def parse_world_args(text: str) -> dict[str, Any]:
    """``--world-per-run`` arguments, ``"walls=6,trees=40,shape=figure8"``, as the
    generator's keywords (numbers converted; the seed comes from each run)."""
    from mapfuse_core.sim.worldgen import WorldParams

    out: dict[str, Any] = {}
    if not text.strip():
        return out
    fields = WorldParams.__dataclass_fields__
    for part in text.split(","):
        key, eq, value = (s.strip() for s in part.partition("="))
        key = key.replace("-", "_")
        if not eq or not key:
            raise ValueError(f"--world-per-run: expected key=value items, got {part!r}")
        if key == "seed":
            raise ValueError("--world-per-run: the seed of each world is the run's seed")
        if key not in fields:
            raise ValueError(
                f"--world-per-run: unknown generator argument {key!r} "
                f"(known: {', '.join(k for k in fields if k != 'seed')})"
            )
        kind = type(getattr(WorldParams(seed=0), key))
        try:
            out[key] = kind(value)
        except ValueError:
            raise ValueError(
                f"--world-per-run: {key} must be "
                f"{_KIND_NAMES.get(kind, kind.__name__)}, got {value!r}"
            ) from None
    WorldParams(seed=0, **out)  # validates the values now, not on the workers
    return out


def _check_carmen_campaign(source: str, world: dict[str, Any] | None) -> None:
    """A CARMEN log as a campaign's input: a corrected one (its reference is the truth,
    each seed draws its simulated odometry), without generated worlds."""
    from mapfuse.carmen_input import carmen_log_kind

    if world is not None:
        raise ValueError("--world-per-run generates simulated worlds; not with a CARMEN log")
    if carmen_log_kind(source) != "corrected":
        raise ValueError(
            f"{source}: a campaign needs a reference trajectory, and this CARMEN log's "
            "poses are raw odometry (state carmen,odometry=corrected:PATH if they are "
            "corrected ones)"
        )


def _cmd_montecarlo(args: argparse.Namespace) -> int:
    from mapfuse.campaign.engine import run_campaign
    from mapfuse.campaign.report import write_report
    from mapfuse.campaign.spec import CampaignSpec, parse_fusion, parse_seeds
    from mapfuse.campaign.task import plugins_registered
    from mapfuse.carmen_input import is_carmen
    from mapfuse.registry import resolve
    from mapfuse_core.sim.scenario import load_scenario

    if args.runs is not None:
        if args.runs < 1:
            raise ValueError(f"--runs must be >= 1, got {args.runs}")
        seeds = tuple(range(args.runs))
    else:
        seeds = parse_seeds(args.seeds)
    estimators = tuple(e.strip() for e in args.estimators.split(",") if e.strip())
    plugins = tuple(args.plugin or ())
    with plugins_registered(plugins):
        for e in estimators:
            resolve(e)  # an unknown name fails before any cluster starts
    world = None if args.world_per_run is None else parse_world_args(args.world_per_run)
    if is_carmen(args.scenario):
        _check_carmen_campaign(args.scenario, world)
    else:
        load_scenario(args.scenario)  # a bad scenario fails here, not on every worker
    spec = CampaignSpec(
        scenario=args.scenario,
        seeds=seeds,
        estimators=estimators,
        fusions=parse_fusion(args.fusion),
        steps=args.steps,
        world=world,
        plugins=plugins,
    )
    summary = run_campaign(
        spec,
        args.out,
        workers=args.workers,
        scheduler=args.scheduler,
        serial=args.serial,
        quiet=args.quiet,
        retry_failed=args.retry_failed,
    )
    paths = {} if args.no_report else write_report(args.out)
    print(
        json.dumps(
            {
                "out": str(summary.out),
                "ran": len(summary.ran),
                "skipped": len(summary.skipped),
                "failed_rows": summary.failed_rows,
                "workers": summary.workers,
                "wall_time_s": round(summary.wall_time_s, 2),
                "outputs": paths,
            },
            indent=2,
        )
    )
    return 0


def add_montecarlo(sub: Any) -> None:
    """Add the ``montecarlo`` sub-command to a sub-parser set."""
    mc = sub.add_parser(
        "montecarlo",
        help="Monte Carlo campaign: many seeds through every estimator, on dask",
        description="Simulate SCENARIO once per seed (for a corrected CARMEN log: draw its "
        "odometry from the reference once per seed) and run every estimator, with and "
        "without fusion, on each log; results go to OUT (runs.jsonl, arrays/, "
        "report.md and figures) as runs complete. A stopped campaign resumes: finished "
        "seeds are skipped.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    mc.add_argument(
        "scenario",
        help=f"built-in scenario ({', '.join(list_builtin_scenarios())}), a .toml path, or "
        "a corrected CARMEN log carmen:PATH (carmen,odometry=corrected:PATH states its kind)",
    )
    which = mc.add_mutually_exclusive_group(required=True)
    which.add_argument("--runs", type=int, help="seeds 0..N-1")
    which.add_argument("--seeds", help="seeds, e.g. 0-39 or 0,3,7")
    mc.add_argument("--estimators", default="ekf", help="comma-separated registered estimators")
    mc.add_argument(
        "--fusion", default="both", choices=["on", "off", "both"], help="fusion settings to run"
    )
    mc.add_argument("--out", required=True, help="campaign directory (created or resumed)")
    mc.add_argument(
        "--workers", type=int, default=None, help="local worker processes (default: cores)"
    )
    mc.add_argument("--scheduler", default=None, help="address of a running dask scheduler")
    mc.add_argument("--serial", action="store_true", help="run in this process, without dask")
    mc.add_argument(
        "--steps", type=int, default=None, help="only the first STEPS steps of each log"
    )
    mc.add_argument(
        "--world-per-run",
        default=None,
        metavar="ARGS",
        help="a generated world per run from its seed: generator arguments as "
        "key=value,... (e.g. 'shape=figure8,trees=40'; '' for the defaults)",
    )
    mc.add_argument(
        "--plugin",
        action="append",
        metavar="MODULE:ATTR",
        help="an estimator each worker registers before running (repeatable)",
    )
    mc.add_argument("--retry-failed", action="store_true", help="run failed seeds again")
    mc.add_argument("--no-report", action="store_true", help="do not write report.md and figures")
    mc.add_argument("--quiet", action="store_true", help="no progress bar")
    mc.set_defaults(func=_cmd_montecarlo)


def _cmd_world_generate(args: argparse.Namespace) -> int:
    from pathlib import Path

    from mapfuse_core.sim.scenario import load_scenario
    from mapfuse_core.sim.worldgen import WorldParams, world_toml

    params = WorldParams(
        seed=args.seed,
        walls=args.walls,
        trees=args.trees,
        laser_range_m=args.laser_range,
        loop_length_m=args.loop_length,
        shape=args.shape,
        known_fraction=args.known_fraction,
        changes=args.changes,
        tree_radius_min_m=args.tree_radius[0],
        tree_radius_max_m=args.tree_radius[1],
        tree_clearance_min_m=args.tree_clearance[0],
        tree_clearance_max_m=args.tree_clearance[1],
    )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(world_toml(params, load_scenario(args.base)))
    sc = load_scenario(out)  # the loader re-validates what was written
    summary = {
        "scenario": str(out),
        "name": sc.name,
        "steps": sc.steps,
        "walls": len(sc.world.segments),
        "trees": len(sc.world.circles),
        "known_features": len(sc.known_map.world_ids),
        "moved": len(sc.known_map.moved),
        "removed": len(sc.known_map.removed),
        "added": len(sc.known_map.added),
    }
    print(json.dumps(summary, indent=2))
    return 0


def add_world(sub: Any) -> None:
    """Add the ``world`` sub-command (``world generate``) to a sub-parser set."""
    from mapfuse_core.sim.worldgen import SHAPES, WorldParams

    d = WorldParams(seed=0)
    world = sub.add_parser(
        "world",
        help="generate random worlds (scenario TOML files)",
        description="Generate random worlds as scenario TOML files.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    wsub = world.add_subparsers(dest="world_command", required=True)
    gen = wsub.add_parser(
        "generate",
        help="write a random world as a scenario TOML",
        description="Draw a closed drive with walls and trees beside it from SEED and "
        "write it as a scenario the loader validates.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    gen.add_argument("--seed", type=int, required=True, help="seed of the layout")
    gen.add_argument("--walls", type=int, default=d.walls, help="wall segments")
    gen.add_argument("--trees", type=int, default=d.trees, help="trees")
    gen.add_argument(
        "--laser-range",
        type=float,
        default=d.laser_range_m,
        help="laser range, m",
    )
    gen.add_argument(
        "--loop-length",
        type=float,
        default=d.loop_length_m,
        help="drive length, m",
    )
    gen.add_argument("--shape", choices=SHAPES, default=d.shape, help="shape of the drive")
    gen.add_argument(
        "--known-fraction",
        type=float,
        default=d.known_fraction,
        help="fraction of the features in the known map",
    )
    gen.add_argument(
        "--changes",
        type=float,
        default=d.changes,
        help="fraction of the known map changed since it was made: half moved, a "
        "quarter removed, a quarter added (seeded by --seed)",
    )
    gen.add_argument(
        "--tree-radius",
        type=float,
        nargs=2,
        metavar=("MIN", "MAX"),
        default=(d.tree_radius_min_m, d.tree_radius_max_m),
        help="range of the trunk radii, m",
    )
    gen.add_argument(
        "--tree-clearance",
        type=float,
        nargs=2,
        metavar=("MIN", "MAX"),
        default=(d.tree_clearance_min_m, d.tree_clearance_max_m),
        help="no trunk nearer the drive than MIN; the gap to where it is placed is drawn "
        "in [MIN + 0.5, MAX], m",
    )
    gen.add_argument(
        "--base", default="loop600", help="scenario whose vehicle, laser and map noise to use"
    )
    gen.add_argument("--out", required=True, help="TOML file to write")
    gen.set_defaults(func=_cmd_world_generate)
