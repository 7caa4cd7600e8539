"""Summarise ``benchmarks/changes_mc.py`` output (``docs/results/changes.md``).

Move significance is re-derived from the regenerated changes (lines: across the
line or turned), so it matches :meth:`ChangeTruth.significant_move`.

    PYTHONPATH=. python benchmarks/changes_summary.py /tmp/changes.jsonl --steps 600

Several files, one per world, are summarised together with one ``--scenario`` each, in
the same order (generated worlds: ``--scenario w1.toml --scenario w2.toml ...``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from typing import Any

import numpy as np

from benchmarks.changes_mc import change_rng
from mapfuse.campaign.stats import AneesSeries, anees_series
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.sim.map_changes import with_changes
from mapfuse_core.sim.scenario import Scenario, load_scenario


def _pr(tp: int, fp: int, fn: int, beyond: int = 0) -> str:
    """Precision and recall; ``beyond``: right calls outside the recall's population
    (removed features found out of view), counted for precision only."""
    p = f"{(tp + beyond) / (tp + beyond + fp):.3f}" if tp + beyond + fp else "–"
    r = f"{tp / (tp + fn):.3f}" if tp + fn else "–"
    extra = f", {beyond} found out of view" if beyond else ""
    return f"P {p} R {r} (tp {tp}, fp {fp}, fn {fn}{extra})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("jsonl", nargs="+")
    ap.add_argument(
        "--scenario",
        action="append",
        help="the benchmark's --scenario (default loop600), once per file or once for all",
    )
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--moved", type=float, default=0.15)
    ap.add_argument("--removed", type=float, default=0.05)
    ap.add_argument("--added", type=float, default=0.05)
    ap.add_argument("--min-scans", type=int, default=None, help="re-score missing with this K")
    ap.add_argument("--move-m", default="0.3,5.0", help="the benchmark's --move-m")
    a = ap.parse_args()
    scenarios = a.scenario or ["loop600"]
    if len(scenarios) == 1:
        scenarios = scenarios * len(a.jsonl)
    if len(scenarios) != len(a.jsonl):
        ap.error(f"{len(a.jsonl)} files but {len(scenarios)} --scenario: give one, or one each")
    rows: list[dict[str, Any]] = []
    bases: list[Scenario] = []
    for path, name in zip(a.jsonl, scenarios, strict=True):
        base = dataclasses.replace(load_scenario(name), steps=a.steps)
        by_seed: dict[int, dict[str, Any]] = {}
        with open(path) as f:
            for line in f:
                r = json.loads(line)
                if r["seed"] in by_seed:
                    print(f"{path}: seed {r['seed']} appears again; its last row is used")
                r["file"] = path
                by_seed[r["seed"]] = r
        rows += by_seed.values()
        bases += [base] * len(by_seed)
    size = []  # (significance measure, kind, detected)
    mtp = mfn = 0
    split = {True: [0, 0], False: [0, 0]}  # surveyed place in view → [detected, missed]
    mfp = {"unchanged": 0, "changed": 0}
    rem = {"unchanged": [0, 0, 0], "changed": [0, 0, 0]}
    beyond = {"unchanged": 0, "changed": 0}
    add = {"unchanged": [0, 0, 0], "changed": [0, 0, 0]}
    for r, base in zip(rows, bases, strict=True):
        sc = with_changes(
            base,
            change_rng(r["seed"], r.get("change_salt")),
            moved=a.moved,
            removed=a.removed,
            added=a.added,
            move_m=tuple(float(v) for v in a.move_m.split(",")),  # type: ignore[arg-type]
        )
        for pre in ("unchanged", "changed"):
            if f"{pre}_score" not in r:
                continue
            s = r[f"{pre}_score"]
            mfp[pre] += s["moved"]["fp"]
            add[pre] = [add[pre][i] + s["added"][k] for i, k in enumerate(("tp", "fp", "fn"))]
            if a.min_scans is not None and f"{pre}_missing_or_removed" in r:
                for d in r[f"{pre}_missing_or_removed"]:
                    called = d["status"] == "missing" and d["scans_in_view"] >= a.min_scans
                    if called and d["removed_in_view"]:
                        rem[pre][0] += 1
                    elif called and d["removed"]:
                        beyond[pre] += 1
                    elif called:
                        rem[pre][1] += 1
                    elif d["removed_in_view"]:
                        rem[pre][2] += 1
            else:
                rem[pre] = [rem[pre][i] + s["removed"][k] for i, k in enumerate(("tp", "fp", "fn"))]
                beyond[pre] += s["removed"].get("beyond_view_tp", 0)
        for m in r.get("changed_moves", []):
            move = next(x for x in sc.known_map.moved if x.id == m["id"])
            kind, p = sc.world.feature(m["id"])
            if kind == FeatureKind.LINE:
                lat = abs(-math.sin(p[2]) * move.dx + math.cos(p[2]) * move.dy)
                sig = lat >= 0.5 or abs(move.dtheta) >= 0.1
                measure = lat
            else:
                measure = math.hypot(move.dx, move.dy)
                sig = measure >= 0.5
            det = m["status"] == "moved"
            if m["observed"]:
                size.append((measure, kind.name.lower(), abs(move.dtheta), det))
                if sig:
                    mtp += det
                    mfn += not det
                    if "surveyed_in_view" in m:
                        split[bool(m["surveyed_in_view"])][0 if det else 1] += 1
    print(
        f"seeds: {len(rows)}; changed runs with an anchor: "
        f"{sum(bool(r.get('changed_anchor')) for r in rows)}"
    )
    print(
        "moved (significant):",
        _pr(mtp, mfp["changed"], mfn),
        "| false moves on unchanged maps:",
        mfp["unchanged"],
    )
    for in_view, (tp, fn) in sorted(split.items(), reverse=True):
        if tp + fn:
            where = "came into view" if in_view else "never came into view"
            print(f"  significant moves whose surveyed place {where}: {tp} of {tp + fn} detected")
    for pre in ("changed", "unchanged"):
        print(f"removed in view ({pre}):", _pr(*rem[pre], beyond=beyond[pre]))
        print(f"added ({pre}):", _pr(*add[pre]))
    for lo, hi in ((0.0, 0.3), (0.3, 0.5), (0.5, 1.0), (1.0, 2.0), (2.0, 99.0)):
        s = [x for x in size if lo <= x[0] < hi]
        print(
            f"  observed moves {lo}-{hi} m (circle distance, line lateral): {len(s)}, "
            f"detected {sum(x[3] for x in s)}; missed: "
            f"{[(k, round(d, 2), round(t, 2)) for d, k, t, det in s if not det]}"
        )
    ok = [r for r in rows if r.get("changed_anchor") and r.get("unchanged_anchor")]
    u = np.array([r["unchanged_rmse_m"] for r in ok])
    c = np.array([r["changed_rmse_m"] for r in ok])
    print(
        f"RMSE over {len(ok)} seeds: unchanged mean {u.mean():.4f} m, changed {c.mean():.4f} m, "
        f"ratio of means {c.mean() / u.mean():.3f}, worst seed ratio {np.max(c / u):.3f}"
    )
    print(
        f"NEES mean: unchanged {np.mean([r['unchanged_nees_mean'] for r in ok]):.2f}, "
        f"changed {np.mean([r['changed_nees_mean'] for r in ok]):.2f}"
    )

    _gate_table(rows)
    _variants_table(rows)
    _anees_table(rows)
    _after_anchor(rows)
    _oracle_table(rows)
    _graph_table(rows)


def _variants_table(rows: list[dict[str, Any]]) -> None:
    """The same runs classified with each ``changes_mc.py --variant`` (keys
    ``<map>_TAG_score``), next to the default classification: every class as the
    score counts it (moves by :meth:`ChangeTruth.significant_move`)."""
    keys = {k for r in rows for k in r if k.startswith("changed_") and k.endswith("_score")}
    tags = sorted({k[len("changed_") : -len("_score")] for k in keys} - {"", "graph"})
    if not tags:
        return
    print("\nclassification variants (the same runs):")
    print(
        "| variant | moved | R, surveyed place in view | false moves, unchanged maps "
        "| removed in view | false missing, unchanged maps | added |"
    )
    print("|---|---|---|---|---|---|---|")
    for tag in ["default", *tags]:
        key = "{}_score" if tag == "default" else f"{{}}_{tag}_score"
        got = [r for r in rows if key.format("changed") in r]
        tot: dict[str, list[int]] = {c: [0, 0, 0] for c in ("moved", "removed", "added")}
        view = [0, 0]
        false_moves = false_missing = beyond = 0
        for r in got:
            s = r[key.format("changed")]
            for c in tot:
                tot[c] = [tot[c][i] + s[c][f] for i, f in enumerate(("tp", "fp", "fn"))]
            beyond += s["removed"].get("beyond_view_tp", 0)
            v = s.get("moved_surveyed_in_view", {"tp": 0, "fn": 0})
            view = [view[0] + v["tp"], view[1] + v["fn"]]
            u = r.get(key.format("unchanged"))
            if u is not None:
                false_moves += u["moved"]["fp"]
                false_missing += u["removed"]["fp"]
        in_view = f"{view[0] / sum(view):.3f}" if sum(view) else "–"
        print(
            f"| {tag} | {_pr(*tot['moved'])} | {in_view} | {false_moves} "
            f"| {_pr(*tot['removed'], beyond=beyond)} | {false_missing} | {_pr(*tot['added'])} |"
        )


def _anees_table(rows: list[dict[str, Any]]) -> None:
    """ANEES over the seeds per step, with its two-sided 95 % bounds (rows that hold
    the per-step NEES of both maps)."""
    ok = [r for r in rows if r.get("changed_anchor") and r.get("unchanged_anchor")]
    ok = [r for r in ok if "changed_nees" in r and "unchanged_nees" in r]
    if not ok:
        return
    print(f"\nANEES over {len(ok)} seeds with an anchor on both maps:")
    print("| map | gate | ANEES | steps inside the bounds | above |")
    print("|---|---|---|---|---|")
    for pre, gate, key in (
        ("unchanged", "on", "unchanged_nees"),
        ("changed", "on", "changed_nees"),
        ("changed", "off", "changed_off_nees"),
    ):
        a = _anees(ok, key)
        print(
            f"| {pre} | {gate} | {a.overall:.3f} | {a.fraction_inside:.3f} "
            f"| {a.fraction_above:.3f} |"
        )


def _anees(rows: list[dict[str, Any]], key: str) -> AneesSeries:
    """ANEES over the rows' per-step NEES lists under ``key`` (None: undefined), cut to
    the shortest run."""
    n = min(len(r[key]) for r in rows)
    x = np.array([[np.nan if v is None else v for v in r[key][:n]] for r in rows])
    return anees_series(x)


def _after_anchor(rows: list[dict[str, Any]]) -> None:
    """The EKF's RMSE ratio split at the later of the two runs' anchor steps: what the
    changed map costs by anchoring later, and what it costs once both are anchored."""
    ok = [r for r in rows if "changed_anchor_step" in r and "unchanged_anchor_step" in r]
    ok = [r for r in ok if "changed_pos_err_mm" in r]
    if not ok:
        return
    rng = np.random.default_rng(0)
    delay = np.array([r["changed_anchor_step"] - r["unchanged_anchor_step"] for r in ok])
    after = []
    for r in ok:
        k = max(r["changed_anchor_step"], r["unchanged_anchor_step"])
        u = np.asarray(r["unchanged_pos_err_mm"][k:], dtype=float)
        c = np.asarray(r["changed_pos_err_mm"][k:], dtype=float)
        n = min(u.size, c.size)
        if n:
            after.append(math.sqrt(np.mean(c[:n] ** 2)) / math.sqrt(np.mean(u[:n] ** 2)))
    print(
        f"\nEKF anchor step, changed minus unchanged, over {len(ok)} seeds: median "
        f"{int(np.median(delay))}, later on {int(np.sum(delay > 0))}, earlier on "
        f"{int(np.sum(delay < 0))}, max {int(delay.max())}"
    )
    if after:
        a = np.array(after)
        print(
            f"EKF RMSE ratio after both anchors: {_ci(a, rng)}, within 10 % on "
            f"{int(np.sum(a <= 1.10))}/{a.size}"
        )


def _oracle_table(rows: list[dict[str, Any]]) -> None:
    """The changed map's run against the same log with the changed features struck
    from the map (``changes_mc.py --oracle``): how much of the RMSE ratio is the
    information the changed features took away, and how much is their being wrong."""
    ok = [r for r in rows if r.get("oracle_anchor") and r.get("unchanged_anchor")]
    ok = [r for r in ok if r.get("changed_anchor")]
    if not ok:
        return
    rng = np.random.default_rng(0)
    u = np.array([r["unchanged_rmse_m"] for r in ok])
    c = np.array([r["changed_rmse_m"] for r in ok])
    o = np.array([r["oracle_rmse_m"] for r in ok])
    print(f"\nEKF with the changed features struck from the map, {len(ok)} seeds:")
    print(
        f"struck per seed {np.mean([r['oracle_struck'] for r in ok]):.1f}; RMSE struck "
        f"{_ci(o, rng)} m; struck/unchanged per seed {_ci(o / u, rng)}, within 10 % on "
        f"{int(np.sum(o / u <= 1.10))}/{len(ok)}; changed/struck per seed "
        f"{_ci(c / o, rng)}, within 10 % on {int(np.sum(c / o <= 1.10))}/{len(ok)}"
    )
    steps = [(r["oracle_anchor_step"], r["changed_anchor_step"]) for r in ok]
    print(
        "anchor step struck vs changed: same on "
        f"{sum(a == b for a, b in steps)}, struck earlier on {sum(a < b for a, b in steps)}, "
        f"later on {sum(a > b for a, b in steps)}"
    )
    if all("oracle_graph_rmse_m" in r and "changed_graph_rmse_m" in r for r in ok):
        gu = np.array([r["unchanged_graph_rmse_m"] for r in ok])
        gc = np.array([r["changed_graph_rmse_m"] for r in ok])
        go = np.array([r["oracle_graph_rmse_m"] for r in ok])
        print(
            f"graph: struck/unchanged {_ci(go / gu, rng)}, within 10 % on "
            f"{int(np.sum(go / gu <= 1.10))}/{len(ok)}; changed/struck {_ci(gc / go, rng)}, "
            f"within 10 % on {int(np.sum(gc / go <= 1.10))}/{len(ok)}"
        )


def _graph_table(rows: list[dict[str, Any]]) -> None:
    """The graph backend run on the gated EKF's decisions (``changes_mc.py --graph``)."""
    ok = [r for r in rows if "changed_graph_rmse_m" in r and "unchanged_graph_rmse_m" in r]
    ok = [r for r in ok if r.get("changed_anchor") and r.get("unchanged_anchor")]
    if not ok:
        return
    rng = np.random.default_rng(0)
    u = np.array([r["unchanged_graph_rmse_m"] for r in ok])
    c = np.array([r["changed_graph_rmse_m"] for r in ok])
    ratio = c / u
    print(f"\ngraph on the EKF's decisions, {len(ok)} seeds with an anchor on both maps:")
    print(
        f"RMSE unchanged {_ci(u, rng)} m, changed {_ci(c, rng)} m; ratio per seed "
        f"{_ci(ratio, rng)}, median {np.median(ratio):.3f}, worst {ratio.max():.3f}, "
        f"within 10 % on {int(np.sum(ratio <= 1.10))}/{ratio.size}; ratio of means "
        f"{c.mean() / u.mean():.3f}"
    )
    for pre in ("unchanged", "changed"):
        key = f"{pre}_graph_nees"
        if all(key in r for r in ok):
            a = _anees(ok, key)
            print(
                f"{pre}: ANEES {a.overall:.3f}, steps inside the bounds "
                f"{a.fraction_inside:.3f}, above {a.fraction_above:.3f}"
            )
    for pre in ("changed", "unchanged"):
        scores = [r[f"{pre}_graph_score"] for r in ok if f"{pre}_graph_score" in r]
        for cls in ("moved", "removed", "added"):
            tp, fp, fn = (sum(s[cls][k] for s in scores) for k in ("tp", "fp", "fn"))
            b = sum(s[cls].get("beyond_view_tp", 0) for s in scores)
            print(f"graph {cls} ({pre}):", _pr(tp, fp, fn, beyond=b))


def _ci(x: np.ndarray, rng: np.random.Generator) -> str:
    """Mean and its 95 % bootstrap interval over the seeds."""
    boots = [rng.choice(x, x.size).mean() for _ in range(2000)]
    lo, hi = np.percentile(boots, [2.5, 97.5])
    return f"{x.mean():.4f} [{lo:.4f}, {hi:.4f}]"


def _gate_table(rows: list[dict[str, Any]]) -> None:
    """The known-map gate on and off (rows of ``changes_mc.py`` that hold both)."""
    ok = [
        r
        for r in rows
        if r.get("changed_anchor") and r.get("unchanged_anchor") and "changed_off_rmse_m" in r
    ]
    if not ok:
        return
    rng = np.random.default_rng(0)
    print(f"\nknown-map gate on/off over {len(ok)} seeds with an anchor on both maps:")
    print("| map | gate | RMSE mean [95 % CI] (m) | NEES mean [95 % CI] |")
    print("|---|---|---|---|")
    for pre in ("unchanged", "changed"):
        for gate, key in (("on", ""), ("off", "_off")):
            rm = np.array([r[f"{pre}{key}_rmse_m"] for r in ok])
            ne = np.array([r[f"{pre}{key}_nees_mean"] for r in ok])
            print(f"| {pre} | {gate} | {_ci(rm, rng)} | {_ci(ne, rng)} |")
    for gate, key in (("on", ""), ("off", "_off")):
        ratio = np.array([r[f"changed{key}_rmse_m"] / r[f"unchanged{key}_rmse_m"] for r in ok])
        within = int(np.sum(ratio <= 1.10))
        print(
            f"gate {gate}: RMSE ratio changed/unchanged per seed {_ci(ratio, rng)}, "
            f"worst {ratio.max():.3f}, within 10 % on {within}/{ratio.size} seeds"
        )
    band = np.percentile([r["unchanged_nees_mean"] for r in ok], [2.5, 97.5])
    inside = sum(band[0] <= r["changed_nees_mean"] <= band[1] for r in ok)
    print(
        f"NEES: unchanged-map runs' 95 % band over the seeds [{band[0]:.2f}, {band[1]:.2f}]; "
        f"changed-map runs (gate on) inside it: {inside}/{len(ok)}"
    )
    for pre in ("unchanged", "changed"):
        g = [r[f"{pre}_gate"] for r in rows if f"{pre}_gate" in r]
        print(
            f"{pre}: un-fused changed {sum(len(x['unfused_changed']) for x in g)}, "
            f"un-fused unchanged {sum(len(x['unfused_unchanged']) for x in g)}, "
            f"changed features fused at least once {sum(len(x['fused_changed']) for x in g)}, "
            f"observations fused after un-fusing {sum(x['fused_after_unfuse'] for x in g)}, "
            f"rejections {sum(x['rejected'] for x in g)}, "
            f"anchors refuted {sum(bool(x['anchor_refuted']) for x in g)}"
        )
    kept = []
    for r in rows:
        gate_row = r.get("changed_gate")
        if gate_row is None:
            continue
        moved = {m["id"] for m in r.get("changed_moves", []) if m["status"] == "moved"}
        kept += [
            (r["file"], r["seed"], k)
            for k in moved & set(gate_row["fused_changed"]) - set(gate_row["unfused_changed"])
        ]
    print(f"classified moved after the run but still fused by the gate (file, seed, id): {kept}")


if __name__ == "__main__":
    main()
