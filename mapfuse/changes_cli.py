"""``mapfuse changes``: classify a known map's changes after one fused run.

Writes ``OUT/changes.json`` (every known feature's class and evidence, the new
features, the run's rejection counters, and in simulation the truth and the
precision/recall) and ``OUT/changes.png`` (:func:`mapfuse.changes_figure.changes_figure`).
``--moved/--removed/--added/--shift`` perturb a simulated scenario's known map first
(:func:`mapfuse_core.sim.map_changes.with_changes`).
"""

from __future__ import annotations

import argparse
import json
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from mapfuse_core.sim.scenario import Scenario

__all__ = ["add_parser"]


def add_parser(sub: Any) -> None:
    """Add the ``changes`` sub-command to the CLI's sub-parsers."""
    from mapfuse.cli_args import (
        Formatter,
        add_data,
        add_estimator,
        add_output,
        add_plugins,
        add_quiet,
        add_seed,
        add_source,
        add_steps,
        seed_int,
    )
    from mapfuse_core.changes import ChangeParams

    p = sub.add_parser(
        "changes",
        help="classify the known map's features (confirmed, moved, missing, unobserved, new)",
        description="Run ESTIMATOR with fusion on SCENARIO (a scenario, a log .npz, "
        "carpark or a CARMEN log: an input with a known map) and write OUT/changes.json "
        "and OUT/changes.png.",
        formatter_class=Formatter,
    )
    add_source(p)
    add_estimator(p)
    add_seed(p)
    add_steps(p, minimum=2)
    add_data(p)
    p.add_argument(
        "--level",
        type=float,
        metavar="P",
        default=ChangeParams().level,
        help="probability of the χ² tests that classify a feature",
    )
    for name in ("moved", "removed", "added"):
        p.add_argument(
            f"--{name}",
            type=float,
            default=0.0,
            metavar="FRACTION",
            help=f"simulation only: fraction of the known map {name} before the run",
        )
    p.add_argument(
        "--shift",
        default=None,
        metavar="DX,DY,DTHETA",
        help="simulation only: a rigid shift of the whole known map (m, m, rad) (default: none)",
    )
    p.add_argument(
        "--change-seed",
        type=seed_int,
        default=0,
        metavar="N",
        help="seed of the known-map perturbation",
    )
    add_plugins(p)
    add_output(p)
    add_quiet(p)
    p.set_defaults(func=_cmd_changes)


def _perturbed(args: argparse.Namespace, scenario: Scenario) -> Scenario:
    """The scenario with ``--moved/--removed/--added/--shift`` applied to its known map."""
    from mapfuse_core.sim.map_changes import with_changes

    shift = None
    if args.shift is not None:
        try:
            shift = np.array([float(v) for v in args.shift.split(",")])
        except ValueError:
            raise ValueError(f"--shift must be 'dx,dy,dθ', got {args.shift!r}") from None
        if shift.shape != (3,) or not np.all(np.isfinite(shift)):
            raise ValueError(f"--shift must be three finite numbers 'dx,dy,dθ', got {args.shift!r}")
    return with_changes(
        scenario,
        np.random.default_rng(args.change_seed),
        moved=args.moved,
        removed=args.removed,
        added=args.added,
        shift=shift,
    )


def _cmd_changes(args: argparse.Namespace) -> int:
    import dataclasses

    from mapfuse.carmen_input import carmen_change_params
    from mapfuse.changes import NoChangeEvidenceError, change_section, detect_changes
    from mapfuse.changes_figure import changes_figure
    from mapfuse.cli_common import (
        InputError,
        UsageError,
        check_out_dir,
        check_source,
        checking,
        emit,
        load_source,
        progress_bar,
        run_with_bars,
        source_kind,
        summary,
        warn_runs,
    )
    from mapfuse.outdir import prepare_output_dir
    from mapfuse.registry import resolve
    from mapfuse.runner import simulate
    from mapfuse_core.changes import ChangeParams
    from mapfuse_core.evaluation.change_truth import change_truth
    from mapfuse_core.sim.simulate import default_workers

    with checking():
        estimator = resolve(args.estimator).name
        params = ChangeParams(level=args.level)
    perturbed = args.moved or args.removed or args.added or args.shift
    if perturbed and source_kind(args.scenario) != "scenario":
        raise UsageError("--moved/--removed/--added/--shift perturb a simulated scenario only")
    src = check_source(args)
    scenario = truth = None
    if src.scenario is not None:
        scenario = src.scenario
        if args.steps is not None and not scenario.controls:
            scenario = dataclasses.replace(scenario, steps=args.steps)
        if perturbed:
            with checking():
                scenario = _perturbed(args, scenario)
    check_out_dir(args)
    if scenario is not None:
        log = simulate(
            scenario,
            args.seed,
            steps=args.steps,
            progress=progress_bar(args, "simulate"),
            workers=default_workers(),
        )
        params = params.with_sensor(scenario.laser)
        truth = change_truth(scenario, log, params)
    else:
        log = load_source(args, src)
        if src.kind == "carmen":
            params = carmen_change_params(log, params)
    if len(log.known_map) == 0:
        raise UsageError(f"{args.scenario}: the log has no known map, so nothing can change")
    run = run_with_bars(args, log, estimator, True)
    warn_runs([run.metrics])
    try:
        report = detect_changes(run.result, log, params)
    except NoChangeEvidenceError as exc:
        raise InputError(f"{args.scenario}: {exc}") from None
    with checking():
        out = prepare_output_dir(args.out, force=args.force)
    section: dict[str, Any] = {
        "backend": run.result.estimator,
        "scenario": log.scenario,
        "seed": log.seed,
        **change_section(report, truth),
        "warnings": list(run.metrics.warnings),
        "known_map_rejections": dict(run.metrics.known_map_rejections or {}),
    }
    json_path = out / "changes.json"
    json_path.write_text(json.dumps(section, indent=2) + "\n")
    fig = changes_figure(report, log, run.result.poses, scenario, truth)
    png_path = out / "changes.png"
    fig.savefig(png_path, dpi=110)
    counts = report.counts()
    verdict = "conclusive" if report.conclusive else "inconclusive"
    result: dict[str, Any] = {
        "verdict": verdict,
        "consistency": None if report.consistency is None else report.consistency.as_dict(),
        "counts": counts,
        "outputs": {"json": str(json_path), "png": str(png_path)},
    }
    if "score" in section:
        result["score"] = section["score"]
    emit(result)
    said = ", ".join(f"{v} {k}" for k, v in counts.items())
    summary(
        args,
        f"changes of {log.scenario}'s known map ({estimator}): {said}, {verdict} → {json_path}",
    )
    return 0
