"""Observations the fused EKF pairs with a known feature of another world feature, with
the known-wall ends rule on and off (``AssociationConfig.known_wall_ends``).

For every seed a world is generated (``--world``, the generator's keywords; by default
loop600's density, the ``dense`` regime of ``benchmarks/consistency_regimes.py``), or a
named scenario taken (``--scenario``), and simulated once; the EKF with fusion runs on
it with the rule on and off.  Per run: the mean NEES over the steps, the observations
paired with a known feature, those of them whose world id is not the known feature's
(*wrong*), grouped by (observed id → known id) with their first and last step, and the
known-map gate's rejections and un-fused known features
(``EKFConfig.known_map_gating``; nothing in these worlds moved, so every un-fused
feature is a false alarm).

Output: one JSON line per seed (``--out``, appended to; a seed already there is
skipped), then a JSON summary on stdout: per setting the worlds, the mean of the runs'
mean NEES with its 95 % interval, the observations paired with known features, the
wrong ones and the worlds with any, the gate's rejections and un-fused features.

    PYTHONPATH=. python benchmarks/known_wall_ends.py --seeds 0 80 --out /tmp/kwe.jsonl
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np

from benchmarks.consistency_regimes import REGIMES
from benchmarks.world_runs import append_rows, read_rows, world_logs
from mapfuse.campaign.spec import parse_world_args
from mapfuse.campaign.stats import mean_interval
from mapfuse.figures import run_errors
from mapfuse.runner import run
from mapfuse_core.measlog import MeasurementLog

DEFAULT_WORLD = REGIMES["dense"]
SETTINGS = {"on": True, "off": False}


def wrong_known_pairings(log: MeasurementLog, obs_known_id: np.ndarray) -> dict[str, Any]:
    """Observations paired with a known feature, and those whose world id differs."""
    kid = np.asarray(obs_known_id)
    lab = np.asarray(log.feat_true_id)
    judged = (kid >= 0) & (lab >= 0)
    wrong = judged & (kid != lab)
    groups: dict[str, list[int]] = {}
    for j in np.flatnonzero(wrong).tolist():
        groups.setdefault(f"{lab[j]}->{kid[j]}", []).append(int(log.feat_step[j]))
    return {
        "known_obs": int(judged.sum()),
        "wrong": int(wrong.sum()),
        "groups": {k: [len(v), min(v), max(v)] for k, v in groups.items()},
    }


def run_seed(log: MeasurementLog, seed: int) -> dict[str, Any]:
    """The fused EKF with the rule on and off on one log."""
    row: dict[str, Any] = {"seed": seed}
    for name, on in SETTINGS.items():
        r = run(log, "ekf", fusion=True, data_association={"known_wall_ends": on})
        _, nees = run_errors(r)
        decisions = r.result.decisions
        assert decisions is not None  # the EKF always returns its decisions
        gating = decisions.known_gating
        row[name] = {
            "nees_mean": float(np.nanmean(nees)),
            **wrong_known_pairings(log, decisions.obs_known_id),
            "rejections": 0 if gating is None else int(sum(gating.rejected.values())),
            "unfused": 0 if gating is None else len(gating.unfused),
        }
    return row


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per setting, over the rows: worlds, mean NEES with its interval, the pairings."""
    out: dict[str, Any] = {"worlds": len(rows)}
    for name in SETTINGS:
        m = mean_interval([r[name]["nees_mean"] for r in rows])
        out[name] = {
            "nees_mean": m.value,
            "nees_mean_interval": [m.low, m.high],
            "known_obs": sum(r[name]["known_obs"] for r in rows),
            "wrong": sum(r[name]["wrong"] for r in rows),
            "worlds_with_wrong": [r["seed"] for r in rows if r[name]["wrong"]],
            "rejections": sum(r[name]["rejections"] for r in rows),
            "unfused": sum(r[name]["unfused"] for r in rows),
        }
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs=2, default=(0, 20), help="first, end (exclusive)")
    p.add_argument("--world", default=DEFAULT_WORLD, help="generator keywords, key=value,...")
    p.add_argument("--scenario", help="a named scenario instead of generated worlds (loop600)")
    p.add_argument("--out", required=True, help="JSON lines, appended to (resumes by seed)")
    args = p.parse_args()
    world = parse_world_args(args.world)
    rows = read_rows(args.out)
    for seed, log in world_logs(
        world, range(*args.seeds), {r["seed"] for r in rows}, args.scenario
    ):
        row = run_seed(log, seed)
        append_rows(args.out, [row])
        rows.append(row)
    wanted = set(range(*args.seeds))
    print(json.dumps(summary([r for r in rows if r["seed"] in wanted]), indent=1))


if __name__ == "__main__":
    main()
