"""Scenarios with a wrong known map, for tests and benchmarks: :func:`with_changes`.

Draws, from the features the known map holds, disjoint sets that are moved (centre
or midpoint by a distance in ``move_m``, in a random direction; lines also turned by
an angle in ``turn_rad``), removed from the world (the map keeps them), or dropped
from the map (added since it was made); optionally the whole map is shifted and
rotated, which is a change of its frame (``[known_map] frame``).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray, compose, inverse
from mapfuse_core.sim.scenario import FeatureMove, Scenario
from mapfuse_core.sim.world import CircleObstacle, WallSegment, World

__all__ = ["with_changes"]


def _count(fraction: float, n: int, name: str) -> int:
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"{name} must be in [0, 1], got {fraction}")
    return round(fraction * n)


def with_changes(
    scenario: Scenario,
    rng: np.random.Generator,
    moved: float = 0.0,
    removed: float = 0.0,
    added: float = 0.0,
    move_m: tuple[float, float] = (0.3, 5.0),
    turn_rad: tuple[float, float] = (0.05, 0.3),
    shift: FloatArray | None = None,
) -> Scenario:
    """``scenario`` with the given fractions of its known map changed.

    ``moved``/``removed``/``added``: fractions of the held features (disjoint sets,
    rounded); ``shift``: ``(dx, dy, dθ)`` applied to the whole map (its frame).
    """
    spec = scenario.known_map
    held = [i for i in spec.world_ids if i not in {m.id for m in spec.moved}]
    n = len(held)
    nm, nr, na = (
        _count(moved, n, "moved"),
        _count(removed, n, "removed"),
        _count(added, n, "added"),
    )
    if nm + nr + na > n:
        raise ValueError(f"{nm + nr + na} changes asked of a known map of {n} held features")
    order = rng.permutation(held).tolist()
    mv, rm, ad = order[:nm], order[nm : nm + nr], order[nm + nr : nm + nr + na]
    for lo_hi, name in ((move_m, "move_m"), (turn_rad, "turn_rad")):
        if not 0.0 <= lo_hi[0] <= lo_hi[1]:
            raise ValueError(f"{name} must be (low, high) with 0 <= low <= high, got {lo_hi}")
    moves = list(spec.moved)
    for fid in mv:
        kind, _ = scenario.world.feature(fid)
        d = float(rng.uniform(*move_m))
        a = float(rng.uniform(-math.pi, math.pi))
        dth = 0.0
        if kind == FeatureKind.LINE:
            dth = float(rng.choice([-1.0, 1.0]) * rng.uniform(*turn_rad))
        moves.append(FeatureMove(fid, d * math.cos(a), d * math.sin(a), dth, 0.0))
    gone = set(rm)
    world = World(
        segments=tuple(s for s in scenario.world.segments if s.id not in gone),
        circles=tuple(c for c in scenario.world.circles if c.id not in gone),
    )
    removed_f: tuple[WallSegment | CircleObstacle, ...] = (
        *(s for s in scenario.world.segments if s.id in gone),
        *(c for c in scenario.world.circles if c.id in gone),
    )
    frame = np.asarray(spec.frame, dtype=float)
    if shift is not None:
        T = np.asarray(shift, dtype=float)
        if T.shape != (3,) or not np.all(np.isfinite(T)):
            raise ValueError(f"shift must be a finite (dx, dy, dθ), got {shift!r}")
        # Every feature moved by T: ⊖F ⊕ (T ⊕ f) = ⊖(⊖T ⊕ F) ⊕ f.
        frame = compose(inverse(T), frame)
    frame.setflags(write=False)
    new_spec = dataclasses.replace(
        spec,
        world_ids=tuple(sorted(i for i in spec.world_ids if i not in gone and i not in set(ad))),
        moved=tuple(moves),
        removed=spec.removed + removed_f,
        added=tuple(sorted((*spec.added, *ad))),
        frame=frame,
    )
    return dataclasses.replace(
        scenario,
        name=f"{scenario.name}+changes",
        world=world,
        known_map=new_spec,
    )
