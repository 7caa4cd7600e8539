"""Change detection and fused accuracy over seeds (``docs/results/changes.md``).

For every seed: loop600 cut to ``--steps`` steps, once with its known map and once
with ``--moved``/``--removed``/``--added`` of it changed (moves 0.3–5 m, lines turned
0.05–0.3 rad; drawn from ``1000 + seed`` and ``--change-salt``); the EKF runs with
fusion on both, with the known-map gate (``EKFConfig.known_map_gating``) on and off;
the gated runs are classified and scored, and every run's position RMSE, error per
step and mean NEES are recorded, with the gate's rejections and un-fused features
(which ones were truly changed, and whether any observation was fused into one after
its un-fuse step).  ``--map-sigma`` replaces the known map's σ (a better survey: a
change smaller than the map's own noise cannot be told from it).  The ungated run is
made only when the gate un-fused something: until then the two runs are the same.
``--assoc`` changes the EKF's association settings (the match's tests and re-runs,
``docs/results/changes-worlds.md``).  ``--oracle`` also runs the changed map's
log with its changed features struck from the known map: the RMSE a fusion that knew
which entries are wrong would reach.  ``--graph NAME`` also runs that graph backend
(``batch``, ``isam2``, ``fixedlag``) on each gated EKF run's decisions and records its
RMSE, NEES and change scores under ``<map>_graph_*``.  One JSON line per
seed is appended to ``--out``.

    PYTHONPATH=. python benchmarks/changes_mc.py --seeds 0 20 --out /tmp/changes.jsonl
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import json
from collections.abc import Mapping
from typing import Any

import numpy as np

from mapfuse.changes import detect_changes
from mapfuse.figures import run_errors
from mapfuse.runner import Run, run
from mapfuse_core.changes import ChangeParams
from mapfuse_core.estimate import EstimatorResult
from mapfuse_core.evaluation.change_truth import change_truth, score_changes
from mapfuse_core.matching import AssociationConfig
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog
from mapfuse_core.sim.map_changes import with_changes
from mapfuse_core.sim.scenario import Scenario, load_scenario
from mapfuse_core.sim.simulate import simulate


def _base(args: argparse.Namespace) -> Scenario:
    """The scenario cut to ``--steps``, with the known map's σ of ``--map-sigma``."""
    base = dataclasses.replace(load_scenario(args.scenario), steps=args.steps)
    if args.map_sigma is None:
        return base
    xy, r, theta = (float(v) for v in args.map_sigma.split(","))
    km = dataclasses.replace(base.known_map, sigma_xy_m=xy, sigma_r_m=r, sigma_theta_rad=theta)
    return dataclasses.replace(base, known_map=km)


def _one(seed: int, args: argparse.Namespace) -> dict[str, object]:
    base = _base(args)
    changed = with_changes(
        base,
        change_rng(seed, args.change_salt),
        moved=args.moved,
        removed=args.removed,
        added=args.added,
        move_m=_range(args.move_m),
    )
    params = ChangeParams(
        level=args.level,
        missing_radius_sigmas=args.missing_radius_sigmas,
        link_unviewed_lines=not args.no_link_unviewed_lines,
    ).with_sensor(base.laser)
    row: dict[str, object] = {"seed": seed, "change_salt": args.change_salt}
    for name, sc in (("unchanged", base), ("changed", changed)):
        log = simulate(sc, seed=seed, workers=1).log
        assoc = args.assoc
        r = run(log, "ekf", fusion=True, known_map_gating=True, data_association=assoc)
        row[f"{name}_rmse_m"] = _rmse(r)
        row[f"{name}_nees_mean"] = _nees_mean(r)
        row[f"{name}_nees"] = _nees(r)
        row[f"{name}_pos_err_mm"] = _pos_err_mm(r)
        kg = r.metrics.known_map_rejections
        changed_ids = _changed_ids(sc)
        if kg is not None:
            row[f"{name}_gate"] = _gate_summary(kg, changed_ids, r.result, log)
        ungated = r
        if kg is not None and kg["known_unfused"]:
            ungated = run(log, "ekf", fusion=True, known_map_gating=False, data_association=assoc)
        row[f"{name}_off_rmse_m"] = _rmse(ungated)
        row[f"{name}_off_nees_mean"] = _nees_mean(ungated)
        row[f"{name}_off_nees"] = _nees(ungated)
        if r.result.anchor is None:
            row[f"{name}_anchor"] = False
            continue
        row[f"{name}_anchor"] = True
        row[f"{name}_anchor_step"] = r.result.anchor.accepted_at_step
        rep = detect_changes(r.result, log, params)
        truth = change_truth(sc, log, params)
        row[f"{name}_counts"] = rep.counts()
        row[f"{name}_score"] = score_changes(rep, truth).as_dict()
        moves = []
        for c in rep.known:
            if c.known_id in truth.moved:
                dx, dy, dth, _ = truth.moved[c.known_id]
                moves.append(
                    {
                        "id": c.known_id,
                        "kind": c.kind.name.lower(),
                        "true_m": float(np.hypot(dx, dy)),
                        "true_rad": float(dth),
                        "status": c.status.value,
                        "observed": c.known_id in truth.observed,
                        "surveyed_in_view": c.known_id in truth.moved_surveyed_in_view,
                    }
                )
        row[f"{name}_moves"] = moves
        if args.oracle and name == "changed":
            _oracle(row, log, sc, args)
        if args.graph:
            g = run(log, args.graph, fusion=True, upstream=r.result)
            row[f"{name}_graph_rmse_m"] = _rmse(g)
            row[f"{name}_graph_nees_mean"] = _nees_mean(g)
            row[f"{name}_graph_nees"] = _nees(g)
            if g.result.anchor is not None:
                rep_g = detect_changes(g.result, log, params)
                row[f"{name}_graph_counts"] = rep_g.counts()
                row[f"{name}_graph_score"] = score_changes(rep_g, truth).as_dict()
        for tag, fields in args.variant:
            rep_v = detect_changes(r.result, log, dataclasses.replace(params, **fields))
            row[f"{name}_{tag}_counts"] = rep_v.counts()
            row[f"{name}_{tag}_score"] = score_changes(rep_v, truth).as_dict()
        row[f"{name}_missing_or_removed"] = [
            {
                "id": c.known_id,
                "status": c.status.value,
                "scans_in_view": c.scans_in_view,
                "removed": c.known_id in truth.removed,
                "removed_in_view": c.known_id in truth.removed_in_view,
            }
            for c in rep.known
            if c.status.value == "missing" or c.known_id in truth.removed
        ]
    return row


# ChangeParams fields the truth is built from: a variant may not change them, or it
# would be scored against another truth than its own.
_TRUTH_FIELDS = ("min_obs", "min_scans", "view_stride")


def _variant(spec: str) -> tuple[str, dict[str, object]]:
    """``'TAG:field=value;field=value'`` → ``(TAG, {field: value})``, values as Python
    literals; checked against :class:`ChangeParams` before anything is simulated."""
    tag, sep, body = spec.partition(":")
    if not sep or not tag.isidentifier():
        raise argparse.ArgumentTypeError(f"{spec!r}: expected 'TAG:field=value;...'")
    if tag == "graph":
        raise argparse.ArgumentTypeError(f"{spec!r}: the tag 'graph' names the --graph run's keys")
    fields: dict[str, object] = {}
    for item in filter(None, (x.strip() for x in body.split(";"))):
        key, eq, value = item.partition("=")
        key = key.strip()
        if not eq or not key:
            raise argparse.ArgumentTypeError(f"{spec!r}: {item!r} is not field=value")
        if key in _TRUTH_FIELDS:
            raise argparse.ArgumentTypeError(
                f"{spec!r}: {key} sets what the truth counts, vary it in its own run"
            )
        try:
            fields[key] = ast.literal_eval(value.strip())
        except (ValueError, SyntaxError) as e:
            raise argparse.ArgumentTypeError(f"{spec!r}: {value!r} is not a literal") from e
    if not fields:
        raise argparse.ArgumentTypeError(f"{spec!r}: no field=value given")
    try:
        dataclasses.replace(ChangeParams(), **fields)  # type: ignore[arg-type]
    except (TypeError, ValueError) as e:
        raise argparse.ArgumentTypeError(f"{spec!r}: {e}") from e
    return tag, fields


def _assoc(spec: str) -> AssociationConfig:
    """``'field=value;...'`` → the default :class:`AssociationConfig` with those fields."""
    fields: dict[str, object] = {}
    for item in filter(None, (x.strip() for x in spec.split(";"))):
        key, eq, value = item.partition("=")
        if not eq or not key.strip():
            raise argparse.ArgumentTypeError(f"{spec!r}: {item!r} is not field=value")
        try:
            fields[key.strip()] = ast.literal_eval(value.strip())
        except (ValueError, SyntaxError) as e:
            raise argparse.ArgumentTypeError(f"{spec!r}: {value!r} is not a literal") from e
    try:
        return dataclasses.replace(AssociationConfig(), **fields)  # type: ignore[arg-type]
    except (TypeError, ValueError) as e:
        raise argparse.ArgumentTypeError(f"{spec!r}: {e}") from e


def change_rng(seed: int, salt: int | None) -> np.random.Generator:
    """The generator of a seed's changes: ``1000 + seed``, with ``salt`` beside it when
    given (one per world, so that worlds do not share their draws of the moves)."""
    return np.random.default_rng(1000 + seed if salt is None else [1000 + seed, salt])


def _range(text: str) -> tuple[float, float]:
    lo, hi = (float(v) for v in text.split(","))
    return lo, hi


def _rmse(r: Run) -> float | None:
    """The run's position RMSE (m), ``None`` without a reference."""
    err = r.metrics.position_error
    return None if err is None else err.rmse


def _nees_mean(r: Run) -> float | None:
    """The run's mean vehicle NEES, ``None`` without truth and covariances."""
    nees = r.metrics.nees
    return None if nees is None else nees.mean


def _nees(r: Run) -> list[float | None]:
    """The run's vehicle NEES per step (None where undefined), for the ANEES over seeds."""
    return [None if not np.isfinite(v) else round(float(v), 4) for v in run_errors(r)[1]]


def _oracle(row: dict[str, object], log: MeasurementLog, sc: Scenario, args: Any) -> None:
    """The changed map's run again with the changed features struck from the known map:
    what the unchanged part of the map alone gives, the best a robust fusion can do."""
    wrong = _changed_ids(sc)
    km = log.known_map
    keep = np.array([int(i) not in wrong for i in km.ids.tolist()], dtype=bool)
    struck = KnownMapArrays(
        ids=km.ids[keep],
        kinds=km.kinds[keep],
        params=km.params[keep],
        covs=km.covs[keep],
        extents=None if km.extents is None else km.extents[keep],
    )
    olog = dataclasses.replace(log, known_map=struck)
    o = run(olog, "ekf", fusion=True, known_map_gating=True, data_association=args.assoc)
    row["oracle_struck"] = int(np.count_nonzero(~keep))
    row["oracle_rmse_m"] = _rmse(o)
    row["oracle_nees_mean"] = _nees_mean(o)
    row["oracle_nees"] = _nees(o)
    row["oracle_pos_err_mm"] = _pos_err_mm(o)
    row["oracle_anchor"] = o.result.anchor is not None
    if o.result.anchor is not None:
        row["oracle_anchor_step"] = o.result.anchor.accepted_at_step
    if args.graph:
        g = run(olog, args.graph, fusion=True, upstream=o.result)
        row["oracle_graph_rmse_m"] = _rmse(g)
        row["oracle_graph_nees_mean"] = _nees_mean(g)


def _pos_err_mm(r: Run) -> list[int]:
    """The run's position error per step in mm (the RMSE after a given step)."""
    dx = run_errors(r)[0]
    return [round(1000.0 * float(v)) for v in np.hypot(dx[:, 0], dx[:, 1])]


def _changed_ids(sc: Scenario) -> set[int]:
    km = sc.known_map
    return {m.id for m in km.moved} | {f.id for f in km.removed}


def _gate_summary(
    kg: Mapping[str, Any], changed: set[int], result: EstimatorResult, log: MeasurementLog
) -> dict[str, object]:
    """The gate's counts, split by whether the feature was truly changed, and the
    observations fused into an un-fused feature after its un-fuse step (0 by design)."""
    per = kg["per_feature"]
    unfused = {int(k): v["unfused_at_step"] for k, v in per.items() if v["unfused_at_step"] >= 0}
    assert result.decisions is not None
    _, kn = result.decisions.arrays
    late = 0
    for kid, step in unfused.items():
        late += int(np.count_nonzero((kn == kid) & (log.feat_step > step)))
    return {
        "rejected": kg["known_rejected"],
        "unfused_changed": sorted(k for k in unfused if k in changed),
        "unfused_unchanged": sorted(k for k in unfused if k not in changed),
        "fused_changed": sorted(
            int(k) for k, v in per.items() if v["accepted"] and int(k) in changed
        ),
        "fused_after_unfuse": late,
        "anchor_refuted": kg["anchor_refuted"],
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--scenario", default="loop600")
    p.add_argument("--steps", type=int, default=600)
    p.add_argument("--seeds", type=int, nargs=2, default=(0, 20))
    p.add_argument("--moved", type=float, default=0.15)
    p.add_argument("--removed", type=float, default=0.05)
    p.add_argument("--added", type=float, default=0.0)
    p.add_argument("--level", type=float, default=0.999)
    p.add_argument("--move-m", default="0.3,5.0", help="range of the moves 'low,high' (m)")
    p.add_argument(
        "--map-sigma",
        default=None,
        help="known map's σ 'xy,r,θ' (m, m, rad) instead of the scenario's",
    )
    p.add_argument(
        "--missing-radius-sigmas",
        type=float,
        default=None,
        help="ChangeParams.missing_radius_sigmas (default: from --level)",
    )
    p.add_argument(
        "--no-link-unviewed-lines",
        action="store_true",
        help="ChangeParams.link_unviewed_lines off: walls are linked to a move only "
        "from a surveyed place predicted in view",
    )
    p.add_argument(
        "--variant",
        type=_variant,
        action="append",
        default=[],
        help="also classify each run with other ChangeParams, 'TAG:field=value;...' "
        "(values as Python literals; keys '<map>_TAG_counts' and '<map>_TAG_score')",
    )
    p.add_argument(
        "--assoc",
        type=_assoc,
        default=AssociationConfig(),
        help="the EKF's AssociationConfig with these fields changed, 'field=value;...' "
        "(e.g. 'match_exclusions=0' or 'match_pairing_test=False')",
    )
    p.add_argument(
        "--graph",
        default=None,
        choices=("batch", "isam2", "fixedlag"),
        help="also run this graph backend on each gated EKF run's decisions",
    )
    p.add_argument(
        "--change-salt",
        type=int,
        default=None,
        help="drawn beside the seed for the changes (give each world its own)",
    )
    p.add_argument(
        "--oracle",
        action="store_true",
        help="also run the changed map's log with the changed features struck from its "
        "known map (keys 'oracle_*')",
    )
    p.add_argument("--out", required=True)
    args = p.parse_args()
    if args.change_salt is not None and args.change_salt < 0:
        p.error(f"--change-salt must be >= 0, got {args.change_salt}")
    tags = [tag for tag, _ in args.variant]
    if len(set(tags)) != len(tags):
        p.error(f"--variant tags must differ, got {tags}")
    for seed in range(*args.seeds):
        row = _one(seed, args)
        with open(args.out, "a") as f:
            f.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
