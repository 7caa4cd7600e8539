"""The ``mapfuse montecarlo`` and ``mapfuse world generate`` commands: argument parsing
and the calls of the campaign engine (:mod:`mapfuse.campaign`) and of the world
generator."""

from __future__ import annotations

import argparse
from typing import Any

__all__ = ["add_montecarlo", "add_world"]


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


def _check_input(args: argparse.Namespace, world: dict[str, Any] | None) -> None:
    """The campaign's input: a scenario at least ``--steps`` long (a generated world's
    length is checked by each run), or a corrected CARMEN log."""
    from pathlib import Path

    from mapfuse.carmen_input import is_carmen
    from mapfuse.cli_common import InputError, UsageError, checking
    from mapfuse_core.sim.scenario import load_scenario

    if is_carmen(args.scenario):
        raw = args.scenario.partition(":")[2]
        if raw and not Path(raw).exists():
            raise InputError(f"CARMEN log {raw} does not exist")
        with checking():
            _check_carmen_campaign(args.scenario, world)
        return
    if args.scenario.endswith(".npz") or args.scenario in ("carpark", "victoria-park"):
        raise UsageError(
            f"{args.scenario}: a campaign simulates each seed (a scenario, or a corrected "
            "CARMEN log), not a saved log or a dataset"
        )
    with checking():
        scenario = load_scenario(args.scenario)  # a bad scenario fails here, not on workers
    if world is None and args.steps is not None and args.steps > scenario.steps:
        raise UsageError(
            f"--steps {args.steps} is more than scenario {scenario.name!r} drives "
            f"({scenario.steps} steps)"
        )


def _check_campaign_out(args: argparse.Namespace, spec: Any) -> bool:
    """``--out``: a new folder, or this campaign's own (resumed); another campaign's or
    another command's files are refused without ``--force``, and with it removed.
    Returns whether the folder is resumed."""
    import json
    from pathlib import Path

    from mapfuse.campaign.spec import CampaignSpec
    from mapfuse.campaign.store import SPEC_FILE
    from mapfuse.cli_common import UsageError, check_out_dir, reading

    path = Path(args.out)
    stored = path / SPEC_FILE
    if stored.is_file() and not args.force:
        with reading():
            old = CampaignSpec.from_json(json.loads(stored.read_text()))
        diff = old.same_runs(spec)
        if diff:
            raise UsageError(
                f"--out {path} holds a campaign with other {', '.join(diff)} "
                f"({', '.join(f'{k}={old.to_json()[k]!r}' for k in diff)}); pass --force "
                "to replace it, or choose another folder"
            )
        return True
    check_out_dir(args)
    return False


def _cmd_montecarlo(args: argparse.Namespace) -> int:
    from mapfuse.campaign.engine import run_campaign
    from mapfuse.campaign.report import write_report
    from mapfuse.campaign.spec import CampaignSpec, parse_world_args
    from mapfuse.cli_args import fusions
    from mapfuse.cli_common import checking, emit, summary
    from mapfuse.outdir import prepare_output_dir
    from mapfuse.registry import resolve

    seeds = tuple(range(args.runs)) if args.runs is not None else args.seeds
    estimators = tuple(args.estimators)
    plugins = tuple(args.plugin or ())
    with checking():
        for e in estimators:
            resolve(e)  # an unknown name fails before any cluster starts (plug-ins: main)
        world = None if args.world_per_run is None else parse_world_args(args.world_per_run)
    _check_input(args, world)
    with checking():
        spec = CampaignSpec(
            scenario=args.scenario,
            seeds=seeds,
            estimators=estimators,
            fusions=fusions(args.fusion),
            steps=args.steps,
            world=world,
            plugins=plugins,
        )
    resumed = _check_campaign_out(args, spec)
    if not resumed:
        with checking():
            prepare_output_dir(args.out, force=args.force)
    result = run_campaign(
        spec,
        args.out,
        workers=args.workers,
        scheduler=args.scheduler,
        serial=args.serial,
        quiet=args.quiet,
        retry_failed=args.retry_failed,
    )
    paths = {} if args.no_report else write_report(args.out)
    emit(
        {
            "out": str(result.out),
            "ran": len(result.ran),
            "skipped": len(result.skipped),
            "failed_rows": result.failed_rows,
            "workers": result.workers,
            "wall_time_s": round(result.wall_time_s, 2),
            "outputs": paths,
        }
    )
    failed = f", {result.failed_rows} failed rows (runs.jsonl)" if result.failed_rows else ""
    where = paths.get("report", str(result.out))
    summary(
        args,
        f"montecarlo {args.scenario}: ran {len(result.ran)} seeds, skipped "
        f"{len(result.skipped)} finished{failed}, on {result.workers} workers in "
        f"{result.wall_time_s:.1f} s → {where}",
    )
    return 0


def add_montecarlo(sub: Any) -> None:
    """Add the ``montecarlo`` sub-command to a sub-parser set."""
    from mapfuse.cli_args import (
        Formatter,
        add_cluster,
        add_estimators,
        add_fusion,
        add_output,
        add_plugins,
        add_quiet,
        add_seeds,
        add_source,
        add_steps,
        positive_int,
    )

    mc = sub.add_parser(
        "montecarlo",
        help="Monte Carlo campaign: many seeds through every estimator, on dask",
        description="Simulate SCENARIO once per seed (for a corrected CARMEN log: draw its "
        "odometry from the reference once per seed) and run every estimator, with and "
        "without fusion, on each log; results go to OUT (campaign.json, runs.jsonl, "
        "arrays/, report.md and figures) as runs complete. A stopped campaign resumes "
        "into its own folder: finished seeds are skipped.",
        formatter_class=Formatter,
    )
    add_source(mc, kinds="simulated")
    which = mc.add_mutually_exclusive_group(required=True)
    which.add_argument("--runs", type=positive_int, metavar="N", help="seeds 0..N-1")
    add_seeds(which, default=None)
    add_estimators(mc, "ekf")
    add_fusion(mc, several=True)
    add_steps(mc)
    mc.add_argument(
        "--world-per-run",
        default=None,
        metavar="ARGS",
        help="a generated world per run from its seed: generator arguments as "
        "key=value,... (e.g. 'shape=figure8,trees=40'; '' for the defaults) (default: "
        "SCENARIO as it is)",
    )
    add_plugins(mc)
    add_cluster(mc, "the cores")
    mc.add_argument("--retry-failed", action="store_true", help="run failed seeds again")
    mc.add_argument("--no-report", action="store_true", help="do not write report.md and figures")
    add_output(
        mc,
        what="campaign folder (created, or resumed when it holds this campaign; --force "
        "starts it afresh)",
    )
    add_quiet(mc)
    mc.set_defaults(func=_cmd_montecarlo)


def _cmd_world_generate(args: argparse.Namespace) -> int:
    from mapfuse.cli_common import check_out_file, checking, emit, summary
    from mapfuse_core.sim.scenario import load_scenario
    from mapfuse_core.sim.worldgen import WorldParams, world_toml

    with checking():
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
        base = load_scenario(args.base)
    out = check_out_file(args)
    text = world_toml(params, base)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    sc = load_scenario(out)  # the loader re-validates what was written
    result = {
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
    emit(result)
    summary(
        args,
        f"generated {sc.name}: {sc.steps} steps, {result['walls']} walls, "
        f"{result['trees']} trees, {result['known_features']} known features → {out}",
    )
    return 0


def add_world(sub: Any) -> None:
    """Add the ``world`` sub-command (``world generate``) to a sub-parser set."""
    from mapfuse.cli_args import Formatter, add_output, add_quiet, seed_int
    from mapfuse_core.sim.worldgen import SHAPES, WorldParams

    d = WorldParams(seed=0)
    world = sub.add_parser(
        "world",
        help="generate random worlds (scenario TOML files)",
        description="Generate random worlds as scenario TOML files.",
        formatter_class=Formatter,
    )
    wsub = world.add_subparsers(dest="world_command", required=True, metavar="SUBCOMMAND")
    gen = wsub.add_parser(
        "generate",
        help="write a random world as a scenario TOML",
        description="Draw a closed drive with walls and trees beside it from SEED and "
        "write it as a scenario the loader validates.",
        formatter_class=Formatter,
    )
    gen.add_argument("--seed", type=seed_int, required=True, metavar="N", help="seed of the layout")
    gen.add_argument("--walls", type=int, metavar="N", default=d.walls, help="wall segments")
    gen.add_argument("--trees", type=int, metavar="N", default=d.trees, help="trees")
    gen.add_argument(
        "--laser-range",
        type=float,
        metavar="M",
        default=d.laser_range_m,
        help="laser range, m",
    )
    gen.add_argument(
        "--loop-length",
        type=float,
        metavar="M",
        default=d.loop_length_m,
        help="drive length, m",
    )
    gen.add_argument("--shape", choices=SHAPES, default=d.shape, help="shape of the drive")
    gen.add_argument(
        "--known-fraction",
        type=float,
        metavar="F",
        default=d.known_fraction,
        help="fraction of the features in the known map",
    )
    gen.add_argument(
        "--changes",
        type=float,
        metavar="F",
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
        "--base",
        default="loop600",
        metavar="SCENARIO",
        help="scenario whose vehicle, laser and map noise to use",
    )
    add_output(gen, kind="file", what="scenario TOML file to write")
    add_quiet(gen)
    gen.set_defaults(func=_cmd_world_generate)
