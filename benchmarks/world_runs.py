"""Benchmarks over generated worlds: a world per seed, simulated once, and the rows of
each seed appended to a JSON-lines file that a rerun resumes from (a seed already there
is skipped)."""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from mapfuse_core.geometry.features import FeatureKind, express_in
from mapfuse_core.measlog import MeasurementLog
from mapfuse_core.sim.scenario import load_scenario
from mapfuse_core.sim.simulate import simulate
from mapfuse_core.sim.worldgen import WorldParams, generate_scenario


def read_rows(path: str | Path) -> list[dict[str, Any]]:
    """The rows already in ``path`` (none when it does not exist)."""
    try:
        with open(path) as f:
            return [json.loads(line) for line in f]
    except FileNotFoundError:
        return []


def append_rows(path: str | Path, rows: list[dict[str, Any]]) -> None:
    """Append ``rows`` to ``path``, one JSON line each."""
    with open(path, "a") as f:
        for r in rows:
            f.write(json.dumps(r) + "\n")


def world_logs(
    world: Mapping[str, Any],
    seeds: range,
    done: set[int],
    scenario: str | None = None,
) -> Iterator[tuple[int, MeasurementLog]]:
    """``(seed, log)`` for every seed not in ``done``: the world the generator draws from
    that seed with ``world``'s keywords (loop600's vehicle, laser and known-map noise),
    or the named ``scenario`` itself, simulated with that seed on one worker."""
    base = load_scenario(scenario or "loop600")
    for seed in seeds:
        if seed in done:
            continue
        sc = base if scenario else generate_scenario(WorldParams(seed=seed, **world), base=base)
        yield seed, simulate(sc, seed=seed, workers=1).log


def truth_in_sensor(log: MeasurementLog, j: int) -> np.ndarray | None:
    """The world feature behind observation ``j`` in the sensor frame at the true pose,
    or ``None`` (no world feature, or one of another kind)."""
    assert log.world is not None
    assert log.true_poses is not None
    hit = np.flatnonzero(log.world.ids == log.feat_true_id[j])
    if hit.size == 0 or int(log.world.kinds[hit[0]]) != int(log.feat_kind[j]):
        return None
    pose = log.true_poses[int(log.feat_step[j])]
    out: np.ndarray = express_in(
        FeatureKind(int(log.feat_kind[j])), pose, log.world.params[hit[0]]
    )[0]
    return out
