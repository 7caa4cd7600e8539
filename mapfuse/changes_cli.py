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
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["add_parser"]


def add_parser(sub: Any) -> None:
    """Add the ``changes`` sub-command to the CLI's sub-parsers."""
    p = sub.add_parser(
        "changes",
        help="classify the known map's features (confirmed, moved, missing, unobserved, new)",
        description="Run BACKEND with fusion on SCENARIO (built-in name, TOML, log .npz, "
        "carpark, carmen:PATH) and write OUT/changes.json and OUT/changes.png.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument(
        "scenario", help="built-in scenario, .toml path, log .npz, carpark or carmen:PATH"
    )
    p.add_argument("--backend", default="ekf", help="registered estimator (ekf, batch, isam2)")
    p.add_argument("--seed", type=int, default=None, help="random seed for simulation")
    p.add_argument("--steps", type=int, default=None, help="simulate/run only STEPS steps")
    p.add_argument("--data", default=None, help="data directory for carpark")
    p.add_argument("--level", type=float, default=None, help="χ² test probability (0.999)")
    p.add_argument("--moved", type=float, default=0.0, help="simulation: fraction moved")
    p.add_argument("--removed", type=float, default=0.0, help="simulation: fraction removed")
    p.add_argument("--added", type=float, default=0.0, help="simulation: fraction added")
    p.add_argument(
        "--shift", default=None, help="simulation: 'dx,dy,dθ' applied to the whole known map"
    )
    p.add_argument("--change-seed", type=int, default=0, help="seed of the perturbation")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=_cmd_changes)


def _cmd_changes(args: argparse.Namespace) -> int:
    import dataclasses

    from mapfuse.carmen_input import carmen_change_params, is_carmen
    from mapfuse.changes import change_section, detect_changes
    from mapfuse.changes_figure import changes_figure
    from mapfuse.runner import DATASETS, prepare_log
    from mapfuse.runner import run as run_estimator
    from mapfuse_core.changes import ChangeParams
    from mapfuse_core.evaluation.change_truth import change_truth
    from mapfuse_core.sim.map_changes import with_changes
    from mapfuse_core.sim.scenario import load_scenario
    from mapfuse_core.sim.simulate import default_workers, simulate

    carmen = is_carmen(args.scenario)
    simulated = not (args.scenario.endswith(".npz") or args.scenario in DATASETS or carmen)
    perturbed = args.moved or args.removed or args.added or args.shift
    if perturbed and not simulated:
        raise ValueError("--moved/--removed/--added/--shift perturb a simulated scenario only")
    if args.steps is not None and args.steps < 2:
        raise ValueError(f"--steps must be >= 2, got {args.steps}")
    params = ChangeParams() if args.level is None else ChangeParams(level=args.level)
    scenario = truth = None
    if simulated:
        scenario = load_scenario(args.scenario)
        if args.steps is not None:
            scenario = dataclasses.replace(scenario, steps=args.steps)
        if perturbed:
            shift = None
            if args.shift is not None:
                try:
                    shift = np.array([float(v) for v in args.shift.split(",")])
                except ValueError:
                    raise ValueError(f"--shift must be 'dx,dy,dθ', got {args.shift!r}") from None
            scenario = with_changes(
                scenario,
                np.random.default_rng(args.change_seed),
                moved=args.moved,
                removed=args.removed,
                added=args.added,
                shift=shift,
            )
        log = simulate(scenario, seed=args.seed, workers=default_workers()).log
        params = params.with_sensor(scenario.laser)
        truth = change_truth(scenario, log, params)
    else:
        log = prepare_log(args.scenario, seed=args.seed, data_dir=args.data)
        if args.steps is not None:
            log = log.head(args.steps)
        if carmen:
            params = carmen_change_params(log, params)
    run = run_estimator(log, args.backend, fusion=True)
    report = detect_changes(run.result, log, params)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
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
    summary = {"counts": report.counts(), "outputs": {"json": str(json_path), "png": str(png_path)}}
    if "score" in section:
        summary["score"] = section["score"]
    print(json.dumps(summary, indent=2))
    return 0
