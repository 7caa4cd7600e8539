"""The EKF with the paper's method (``EKFConfig.paper()``) against its default.

The default goes beyond the paper in the settings ``EKFConfig.extensions()`` lists.
All but one are about the fusion with the known map; ``line_tie_residual_at`` also
measures the join's line ties (eq. 5), so without fusion the two differ there
(``tests/test_ekf_paper_preset.py``).  Each log is run four times: fused with
``paper`` and with ``default``, and without fusion with each (``paper-plain``,
``plain``).  With ``--ablation`` it is also run with the default less one extension
at a time (``default-no-<name>``, :data:`ABLATIONS`: that extension at the paper's
value); ``--ablation a,b`` runs only those.

Groups of logs (``--groups``):

* ``loop600``: the paper's simulation, one log per seed of ``--loop600-seeds``;
* ``worlds``: one generated world per seed of ``--world-seeds`` (``--world``, the
  generator's keywords), simulated with that seed;
* ``changed``: the same worlds with ``--changes`` of their known map out of date
  (moved, removed, added), where the match's tests and the known-map gate are meant
  to act;
* ``survey``: the generator's default worlds (a 600 m loop, 12 walls, 45 trees, an
  80 m laser) with ``--changes`` of the known map out of date, one per seed of
  ``--survey-seeds``: the conditions of ``docs/results/changes-worlds.md`` (its world seeds,
  simulated here with the world's seed).

Per run: position RMSE and maximum, the NEES of every step, the anchor's error, NEES
and pairings (a pairing is wrong when the landmark's observations are mostly of
another feature), and the observations fused into a known feature: of another
feature (``wrong_fused_obs``), or of a feature the world moved or removed
(``changed_fused_obs``).  One JSON line per log is appended to ``--out`` (logs
One JSON line per run (log and configuration) is appended to ``--out``; runs already
there are skipped, so a campaign resumes and ``--ablation`` adds to one.  Then the
summary per group and configuration is printed as JSON: means with Student-t 95 %
intervals, the paired difference of each configuration less ``default``, the ANEES
over the runs with its two-sided 95 % bounds and the fraction of steps inside them, and
counts with Clopper–Pearson intervals.

    OPENBLAS_NUM_THREADS=1 nice -n 10 python benchmarks/ekf_paper_vs_default.py \\
        --out /tmp/paper_vs_default.jsonl
    python benchmarks/ekf_paper_vs_default.py --summarise /tmp/paper_vs_default.jsonl
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from ekf_reference import EKFConfig, run_ekf
from mapfuse.campaign.stats import (
    anees_bounds,
    anees_series,
    mean_interval,
    proportion_interval,
    stack_runs,
)
from mapfuse_core.evaluation import (
    CHI2_3_95,
    anchor_truth,
    nees_series,
    pose_errors,
    truth_in_global,
)
from mapfuse_core.measlog import MeasurementLog
from mapfuse_core.sim.scenario import Scenario, load_scenario
from mapfuse_core.sim.simulate import simulate
from mapfuse_core.sim.worldgen import WorldParams, generate_scenario

GROUPS = ("loop600", "worlds", "changed", "survey")
CONFIGS = ("paper", "default", "plain", "paper-plain")

ABLATIONS: dict[str, tuple[str, ...]] = {
    "min_pairings": ("data_association.ccda.min_pairings",),
    "min_obs_for_matching": ("data_association.min_obs_for_matching",),
    "ccda_acceptance": (
        "data_association.ccda.redundant_pairings",
        "data_association.ccda.ambiguity_margin",
    ),
    "match_tests": (
        "data_association.match_joint_test",
        "data_association.match_pairing_test",
        "data_association.match_exclusions",
    ),
    "known_map_gating": ("known_map_gating",),
    "anchor_entry": ("anchor_entry",),
    "known_map_in_local_maps": ("known_map_in_local_maps",),
    "line_tie_residual_at": ("line_tie_residual_at",),
    "odometry_linearisation": ("odometry_linearisation",),
}
"""The extensions, grouped where one needs another (the pairing test runs with the
joint test, the re-runs after a failed pairing test), for ``--ablation``."""
DEFAULT_WORLD = "shape=figure8,laser_range_m=40,walls=22,trees=50,loop_length_m=400"


def _seeds(text: str) -> list[int]:
    """``"0-19"`` or ``"0,3,7"`` (or both, comma-separated) as a list."""
    out: list[int] = []
    for part in text.split(","):
        lo, dash, hi = (s.strip() for s in part.partition("-"))
        if not lo.isdigit() or (dash and not hi.isdigit()):
            raise argparse.ArgumentTypeError(f"seeds look like 0-19 or 0,3,7; got {text!r}")
        out += list(range(int(lo), int(hi) + 1)) if dash else [int(lo)]
    return out


def _world(text: str) -> dict[str, Any]:
    """Generator keywords ``key=value,...`` (numbers converted by the field's type)."""
    out: dict[str, Any] = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        key, eq, value = (s.strip() for s in part.partition("="))
        if not eq or key not in WorldParams.__dataclass_fields__ or key in ("seed", "changes"):
            raise argparse.ArgumentTypeError(f"--world: bad item {part!r}")
        out[key] = type(getattr(WorldParams(seed=0), key))(value)
    return out


def _changed_ids(sc: Scenario) -> set[int]:
    """Known-map ids the world moved or removed."""
    return {m.id for m in sc.known_map.moved} | {f.id for f in sc.known_map.removed}


def _run(log: MeasurementLog, name: str, changed: set[int]) -> dict[str, Any]:
    """The figures of one EKF run, configuration ``name`` (see the module docstring)."""
    assert log.true_poses is not None
    t0 = time.perf_counter()
    res = run_ekf(log, config_of(name), fusion=not name.endswith("plain"))
    wall = time.perf_counter() - t0
    assert res.decisions is not None
    e = pose_errors(res.poses, truth_in_global(log.true_poses))
    err = e.position
    nees = nees_series(e.dx, res.covs)
    nees[0] = np.nan  # step 0 is the frame's origin, exactly known
    kid, tid = res.decisions.obs_known_id, log.feat_true_id
    fused = kid >= 0
    row: dict[str, Any] = {
        "rmse_m": float(np.sqrt(np.mean(err**2))),
        "max_m": float(err.max()),
        "nees": [round(float(v), 4) if math.isfinite(v) else None for v in nees],
        "nees_within_chi2_95": float(np.mean(nees[1:] <= CHI2_3_95)),
        "fused_obs": int(fused.sum()),
        "wrong_fused_obs": int(np.sum(fused & (tid >= 0) & (kid != tid))),
        "changed_fused_obs": int(np.sum(fused & np.isin(kid, sorted(changed)))),
        "ccda_attempts": 0 if res.matching is None else res.matching.attempts,
        "ccda_reasons": {} if res.matching is None else dict(res.matching.reasons),
        "wall_s": round(wall, 2),
        "anchor": None,
    }
    a = res.anchor
    if a is not None:
        truth = anchor_truth(log.true_poses, log.known_frame)
        e = pose_errors(a.x_Wknown_Wglobal[None], truth[None])
        row["anchor"] = {
            "step": a.accepted_at_step,
            "pairings": len(a.pairings),
            "wrong_pairings": sum(1 for t, k in a.pairings if t != k),
            "changed_pairings": sum(1 for _, k in a.pairings if k in changed),
            "error_m": float(e.position[0]),
            "error_rad": float(e.heading[0]),
            "nees": float(nees_series(e.dx, a.cov[None])[0]),
            "sd_m": float(np.sqrt(np.trace(a.cov[:2, :2]) / 2)),
        }
    return row


def _with_paper(config: Any, paper: Any, path: str) -> Any:
    """``config`` with the setting at dotted ``path`` taken from ``paper``."""
    head, _, rest = path.partition(".")
    if not rest:
        return dataclasses.replace(config, **{head: getattr(paper, head)})
    inner = _with_paper(getattr(config, head), getattr(paper, head), rest)
    return dataclasses.replace(config, **{head: inner})


def config_of(name: str) -> EKFConfig:
    """The configuration a run name stands for (``plain``: the default, run without
    fusion; ``paper-plain``: the paper's, without fusion)."""
    if name in ("paper", "paper-plain"):
        return EKFConfig.paper()
    if name in ("default", "plain"):
        return EKFConfig()
    cfg = EKFConfig()
    for path in ABLATIONS[name.removeprefix("default-no-")]:
        cfg = _with_paper(cfg, EKFConfig.paper(), path)
    return cfg


def _check_ablations() -> None:
    """Every extension is in exactly one ablation (a new one must be placed)."""
    listed = sorted(p for paths in ABLATIONS.values() for p in paths)
    ext = sorted(EKFConfig.extensions())
    if listed != ext:
        raise SystemExit(f"ABLATIONS lists {listed}, EKFConfig.extensions() {ext}")


def _scenario(group: str, seed: int, world: dict[str, Any], changes: float) -> Scenario:
    base = load_scenario("loop600")
    if group == "loop600":
        sc = base
    elif group == "survey":
        sc = generate_scenario(WorldParams(seed=seed, changes=changes), base=base)
    else:
        frac = changes if group == "changed" else 0.0
        sc = generate_scenario(WorldParams(seed=seed, changes=frac, **world), base=base)
    return sc


def run_log(
    group: str, seed: int, configs: list[str], world: dict[str, Any], changes: float
) -> list[dict[str, Any]]:
    """Simulate one log of ``group`` and run ``configs`` on it: one line per run."""
    sc = _scenario(group, seed, world, changes)
    log = simulate(sc, seed=seed, workers=1).log
    changed = _changed_ids(sc)
    head = {"group": group, "seed": seed, "steps": log.n_steps}
    return [{**head, "config": c, **_run(log, c, changed)} for c in configs]


def _interval(values: list[float], digits: int = 4) -> list[float] | None:
    iv = mean_interval(values)
    if iv.n == 0:
        return None
    return [round(v, digits) for v in (iv.value, iv.low, iv.high)]


def _count(successes: int, n: int) -> dict[str, Any]:
    iv = proportion_interval(successes, n)
    return {"runs": successes, "of": n, "ci95": [round(iv.low, 3), round(iv.high, 3)]}


def _summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """One configuration's figures over the runs of a group."""
    a = anees_series(_nees_matrix(runs))
    anchors = [r["anchor"] for r in runs if r["anchor"] is not None]
    out: dict[str, Any] = {
        "runs": len(runs),
        "rmse_m": _interval([r["rmse_m"] for r in runs]),
        "max_m": _interval([r["max_m"] for r in runs]),
        "anees": round(a.overall, 3),
        # Every run has every step (one log length per group): one pair of bounds.
        "anees_bounds": [round(float(a.lower[-1]), 3), round(float(a.upper[-1]), 3)],
        "steps_inside": round(a.fraction_inside, 3),
        "steps_above": round(a.fraction_above, 3),
        "run_nees_within_chi2_95": _interval([r["nees_within_chi2_95"] for r in runs], 3),
        "anchored": _count(len(anchors), len(runs)),
        "fused_obs": sum(r["fused_obs"] for r in runs),
        "wrong_fused_obs": sum(r["wrong_fused_obs"] for r in runs),
        "runs_with_wrong_fused_obs": _count(sum(r["wrong_fused_obs"] > 0 for r in runs), len(runs)),
        "changed_fused_obs": sum(r["changed_fused_obs"] for r in runs),
        "wall_s": _interval([r["wall_s"] for r in runs], 2),
    }
    if anchors:
        nees = [x["nees"] for x in anchors]
        # Two-sided 95 % bounds of the mean of len(nees) consistent 3-dof NEES.
        bounds = [round(float(np.ravel(b)[0]), 3) for b in anees_bounds(len(nees), 3, 0.95)]
        out |= {
            "anchor_step_median": float(np.median([x["step"] for x in anchors])),
            "anchor_error_m": _interval([x["error_m"] for x in anchors]),
            "anchor_error_rad": _interval([x["error_rad"] for x in anchors], 5),
            "anchor_anees": round(float(np.mean(nees)), 3),
            "anchor_sd_m": _interval([x["sd_m"] for x in anchors if "sd_m" in x]),
            "anchor_anees_bounds": bounds,
            "wrong_pairings": sum(x["wrong_pairings"] for x in anchors),
            "runs_with_wrong_pairing": _count(
                sum(x["wrong_pairings"] > 0 for x in anchors), len(runs)
            ),
            "changed_pairings": sum(x["changed_pairings"] for x in anchors),
        }
    return out


def _nees_matrix(runs: list[dict[str, Any]]) -> np.ndarray:
    """(runs, steps) NEES of one configuration's runs (NaN where none)."""
    return stack_runs([np.array([np.nan if v is None else v for v in r["nees"]]) for r in runs])


def _inside_difference(
    rows: list[dict[str, Any]], name: str, base: str = "default", draws: int = 2000
) -> list[float]:
    """``name`` − ``base`` of the fraction of steps whose ANEES is inside its bounds,
    with a 95 % interval from a paired bootstrap over the logs (seeded: the same rows
    give the same interval)."""
    x, d = (_nees_matrix([r[c] for r in rows]) for c in (name, base))
    # A resample keeps the number of runs at every step, so the bounds stay as they are.
    a = anees_series(d)
    lo, hi = a.lower, a.upper

    def inside(m: np.ndarray) -> float:
        v = np.nansum(m, axis=0) / np.maximum(a.runs, 1)
        return float(np.mean(((v >= lo) & (v <= hi))[a.valid]))

    diff = anees_series(x).fraction_inside - a.fraction_inside
    rng = np.random.default_rng(0)
    boot = []
    for _ in range(draws):
        i = rng.integers(0, len(rows), len(rows))
        boot.append(inside(x[i]) - inside(d[i]))
    q = np.quantile(boot, [0.025, 0.975])
    return [round(float(v), 3) for v in (diff, *q)]


def _paired(rows: list[dict[str, Any]], name: str, base: str = "default") -> dict[str, Any]:
    """``name`` − ``base``, per log, with Student-t 95 % intervals (a bootstrap one for
    the steps inside the ANEES bounds)."""
    x, d = [r[name] for r in rows], [r[base] for r in rows]
    rmse = [a["rmse_m"] - b["rmse_m"] for a, b in zip(x, d, strict=True)]
    ratio = [math.log(a["rmse_m"] / b["rmse_m"]) for a, b in zip(x, d, strict=True)]
    within = [
        a["nees_within_chi2_95"] - b["nees_within_chi2_95"] for a, b in zip(x, d, strict=True)
    ]
    both = [
        (a["anchor"], b["anchor"]) for a, b in zip(x, d, strict=True) if a["anchor"] and b["anchor"]
    ]
    iv = mean_interval(ratio)
    return {
        "rmse_m": _interval(rmse),
        "rmse_ratio_geomean": [round(math.exp(v), 3) for v in (iv.value, iv.low, iv.high)],
        "run_nees_within_chi2_95": _interval(within, 3),
        "anees_steps_inside": _inside_difference(rows, name, base),
        "anchor_nees": _interval([a["nees"] - b["nees"] for a, b in both], 3),
        "anchor_error_m": _interval([a["error_m"] - b["error_m"] for a, b in both]),
        "anchor_step": _interval([a["step"] - b["step"] for a, b in both], 1),
        "logs_lower_rmse": sum(v < -1e-9 for v in rmse),
        "logs_higher_rmse": sum(v > 1e-9 for v in rmse),
        "logs_identical": sum(a["rmse_m"] == b["rmse_m"] for a, b in zip(x, d, strict=True)),
    }


def _by_log(lines: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The run lines gathered per log: ``{"group", "seed", <config>: <run>, ...}``."""
    logs: dict[tuple[str, int], dict[str, Any]] = {}
    for line in lines:
        row = logs.setdefault(
            (line["group"], line["seed"]), {"group": line["group"], "seed": line["seed"]}
        )
        row[line["config"]] = line
    return list(logs.values())


def summarise(lines: list[dict[str, Any]]) -> dict[str, Any]:
    """Per group: each configuration's figures (over the logs that have every
    configuration run) and each one's paired difference with the default."""
    out: dict[str, Any] = {}
    rows = _by_log(lines)
    for group in GROUPS:
        sel = sorted((r for r in rows if r["group"] == group), key=lambda r: r["seed"])
        configs = [c for c in _all_configs() if sel and all(c in r for r in sel)]
        if "default" not in configs:
            continue
        out[group] = {
            "seeds": [r["seed"] for r in sel],
            **{c: _summary([r[c] for r in sel]) for c in configs},
            **{
                f"{c}_minus_{_base_of(c)}": _paired(sel, c, _base_of(c))
                for c in configs
                if c not in ("default", "plain")
            },
        }
    return out


def _base_of(name: str) -> str:
    """The run a configuration is compared with: the default, fused or not."""
    return "plain" if name == "paper-plain" else "default"


def _all_configs() -> list[str]:
    return [*CONFIGS, *(f"default-no-{a}" for a in ABLATIONS)]


def _ablations(text: str) -> list[str]:
    """``--ablation``'s value: ``all`` or comma-separated names of :data:`ABLATIONS`."""
    names = list(ABLATIONS) if text == "all" else [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in ABLATIONS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(
            f"--ablation: choose from {', '.join(ABLATIONS)} (got {text!r})"
        )
    return names


def _read(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError as e:
            raise SystemExit(f"{path}:{n}: not a JSON line ({e})") from None
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--groups", default=",".join(GROUPS), help="comma-separated, of %(default)s")
    ap.add_argument("--loop600-seeds", type=_seeds, default=_seeds("0-19"))
    ap.add_argument("--world-seeds", type=_seeds, default=_seeds("1-20"))
    ap.add_argument("--survey-seeds", type=_seeds, default=_seeds("101-110"))
    ap.add_argument("--world", type=_world, default=_world(DEFAULT_WORLD))
    ap.add_argument("--changes", type=float, default=0.2, help="fraction for 'changed'")
    ap.add_argument(
        "--ablation",
        type=_ablations,
        nargs="?",
        const="all",
        default=[],
        help="also the default less each extension (or only those named, comma-separated)",
    )
    ap.add_argument("--out", type=Path, help="JSON lines, one per log (appended, resumed)")
    ap.add_argument("--summarise", type=Path, metavar="FILE", help="only summarise FILE")
    args = ap.parse_args()
    if args.summarise is not None:
        print(json.dumps(summarise(_read(args.summarise)), indent=1))
        return
    groups = [g.strip() for g in args.groups.split(",") if g.strip()]
    if not groups or not set(groups) <= set(GROUPS):
        raise SystemExit(f"--groups: choose from {', '.join(GROUPS)}")
    if not 0.0 < args.changes <= 1.0:
        raise SystemExit(f"--changes must be in (0, 1], got {args.changes}")
    _check_ablations()
    configs = [*CONFIGS, *(f"default-no-{a}" for a in args.ablation)]
    lines = _read(args.out) if args.out else []
    done = {(r["group"], r["seed"], r["config"]) for r in lines}
    seeds = {"loop600": args.loop600_seeds, "survey": args.survey_seeds}
    wanted = [(g, s) for g in groups for s in seeds.get(g, args.world_seeds)]
    for group, seed in wanted:
        todo = [c for c in configs if (group, seed, c) not in done]
        if not todo:
            continue
        new = run_log(group, seed, todo, args.world, args.changes)
        lines += new
        if args.out:
            with args.out.open("a") as f:
                f.writelines(json.dumps(r) + "\n" for r in new)
    keep = set(wanted)
    print(json.dumps(summarise([r for r in lines if (r["group"], r["seed"]) in keep]), indent=1))


if __name__ == "__main__":
    main()
