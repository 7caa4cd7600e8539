"""Random worlds for Monte Carlo campaigns: :func:`world_toml` and :func:`generate_scenario`.

A world is a closed drive of a chosen shape and length with walls and trees beside
it, all drawn from one seed, written as a scenario TOML that
:func:`mapfuse_core.sim.scenario.load_scenario` validates like any other.  The vehicle,
the laser (but for its range) and the known map's noise come from a base scenario
(loop600 by default), so a generated world differs from it only in layout.

Shapes (the path before scaling to ``loop_length_m``):

* ``loop`` — a closed curve ``r(φ) = 1 + a₂ cos(2φ + p₂) + a₃ cos(3φ + p₃)`` with
  random ``|aᵢ| ≤ 0.12`` and aspect ratio 1–1.6;
* ``figure8`` — a lemniscate of Gerono with lobes 0.5–0.8 times as tall as half
  its width (the drive crosses itself once);
* ``corridor`` — a long, thin stadium: two straights joined by half circles of 12 m.

Placement: a tree's radius is drawn from ``[tree_radius_min_m, tree_radius_max_m]``
and the gap between its trunk and the path point it is placed beside from
``[tree_clearance_min_m + 0.5, tree_clearance_max_m]``, both uniformly; no trunk is
nearer any point of the path than ``tree_clearance_min_m``, nor 1.5 m from another
trunk (by default radii 0.3–0.8 m and gaps 4.1–14.6 m with a clearance of 3.6 m:
loop600's trees).  Every wall is at least 4 m from the path and 1 m from other walls
and trees.  The known map holds every feature within 40 m of the start (so a match
can be made early), then random others up to ``known_fraction`` of all features.

Changes (``changes``, a fraction of the known map, drawn from a stream of its own so
the layout does not depend on it): half of them moved by 0.3–5 m in a random
direction (walls also turned by 0.05–0.3 rad about their midpoint), a quarter
removed from the world (the map keeps them, ``[known_map.removed]``), the rest added
since the map was made (in the world, ``[known_map] added``), as
:func:`mapfuse_core.sim.map_changes.with_changes` draws them.  They are
drawn from the whole known map, the features near the start included.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.sim.scenario import Scenario, ScenarioError, load_scenario, scenario_from_toml

__all__ = ["SHAPES", "WorldParams", "generate_scenario", "world_toml"]

#: Path shapes the generator draws.
SHAPES = ("loop", "figure8", "corridor")

_MIN_TREE_CLEARANCE_M = 1.0
_TREE_GAP_MARGIN_M = 0.5
_WALL_CLEARANCE_M = 4.0
_KNOWN_RADIUS_M = 40.0
_MIN_TURN_RADIUS_M = 8.0
_CORRIDOR_RADIUS_M = 12.0


@dataclass(frozen=True)
class WorldParams:
    """What the generator draws; every random choice derives from :attr:`seed`."""

    seed: int
    """Seed of the layout (and the scenario's default simulation seed)."""
    walls: int = 12
    """Number of wall segments."""
    trees: int = 45
    """Number of trees (circles)."""
    laser_range_m: float = 80.0
    """Laser maximum range (m)."""
    loop_length_m: float = 600.0
    """Length of the drive (m)."""
    shape: str = "loop"
    """One of :data:`SHAPES`."""
    known_fraction: float = 0.5
    """Fraction of the features in the known map (at least those near the start)."""
    changes: float = 0.0
    """Fraction of the known map changed since it was made (moved, removed, added)."""
    tree_radius_min_m: float = 0.3
    """Smallest trunk radius (m)."""
    tree_radius_max_m: float = 0.8
    """Largest trunk radius (m)."""
    tree_clearance_min_m: float = 3.6
    """No trunk is nearer the path than this (m), at least 1 m: the vehicle drives
    beside the trees, not through them."""
    tree_clearance_max_m: float = 14.6
    """Largest gap between a trunk and the path point it is placed beside (m), at least
    0.5 m more than :attr:`tree_clearance_min_m`."""

    def __post_init__(self) -> None:
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed must be an integer >= 0, got {self.seed!r}")
        for name in ("walls", "trees"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ValueError(f"{name} must be an integer >= 0, got {v!r}")
        if self.walls + self.trees == 0:
            raise ValueError("a world needs at least one wall or tree")
        if not (math.isfinite(self.laser_range_m) and self.laser_range_m > 0):
            raise ValueError(f"laser_range_m must be > 0, got {self.laser_range_m}")
        if not (math.isfinite(self.loop_length_m) and self.loop_length_m >= 60.0):
            raise ValueError(f"loop_length_m must be >= 60 m, got {self.loop_length_m}")
        if self.shape not in SHAPES:
            raise ValueError(f"shape must be one of {', '.join(SHAPES)}, got {self.shape!r}")
        if not 0.0 <= self.known_fraction <= 1.0:
            raise ValueError(f"known_fraction must be in [0, 1], got {self.known_fraction}")
        if not (math.isfinite(self.changes) and 0.0 <= self.changes <= 1.0):
            raise ValueError(f"changes must be in [0, 1], got {self.changes}")
        self._check_range("tree_radius", 0.0, False, 0.0)
        self._check_range("tree_clearance", _MIN_TREE_CLEARANCE_M, True, _TREE_GAP_MARGIN_M)
        if self.shape == "corridor" and self.loop_length_m <= 2 * math.pi * _CORRIDOR_RADIUS_M:
            raise ValueError(
                f"a corridor needs loop_length_m > {2 * math.pi * _CORRIDOR_RADIUS_M:.0f} m "
                f"(its two {_CORRIDOR_RADIUS_M:.0f} m turns), got {self.loop_length_m}"
            )

    def _check_range(self, name: str, floor: float, floor_allowed: bool, margin: float) -> None:
        """``{name}_min_m + margin ≤ {name}_max_m``, both finite and above ``floor``."""
        lo, hi = getattr(self, f"{name}_min_m"), getattr(self, f"{name}_max_m")
        for key, v in ((f"{name}_min_m", lo), (f"{name}_max_m", hi)):
            ok = isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
            if not ok or v < floor or (v == floor and not floor_allowed):
                bound = ">=" if floor_allowed else ">"
                raise ValueError(f"{key} must be a finite number {bound} {floor:g}, got {v!r}")
        if lo + margin > hi:
            more = f" + {margin:g}" if margin else ""
            raise ValueError(f"{name}_max_m ({hi}) must be >= {name}_min_m ({lo}){more}")


def _unit_curve(params: WorldParams, rng: np.random.Generator, n: int) -> FloatArray:
    """(n, 2) closed curve of the shape, any scale, starting at index 0."""
    u = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    if params.shape == "loop":
        a2, a3 = rng.uniform(-0.12, 0.12, 2)
        p2, p3 = rng.uniform(0, 2 * math.pi, 2)
        r = 1.0 + a2 * np.cos(2 * u + p2) + a3 * np.cos(3 * u + p3)
        aspect = rng.uniform(1.0, 1.6)
        xy = np.column_stack([aspect * r * np.cos(u), r * np.sin(u)])
    elif params.shape == "figure8":
        # Lobe height a in [0.5, 0.8] of the half-width: the tightest turn then has a
        # radius of about 0.047 of the whole length (taller lobes turn tighter).
        a = rng.uniform(0.5, 0.8)
        xy = np.column_stack([np.sin(u), a * np.sin(u) * np.cos(u)])
    else:
        R = _CORRIDOR_RADIUS_M
        straight = (params.loop_length_m - 2 * math.pi * R) / 2
        s = u / (2 * math.pi) * params.loop_length_m
        xy = np.zeros((n, 2))
        for i, si in enumerate(s):
            if si < straight:
                xy[i] = (si, -R)
            elif si < straight + math.pi * R:
                a = (si - straight) / R - math.pi / 2
                xy[i] = (straight + R * math.cos(a), R * math.sin(a))
            elif si < 2 * straight + math.pi * R:
                xy[i] = (straight - (si - straight - math.pi * R), R)
            else:
                a = (si - 2 * straight - math.pi * R) / R + math.pi / 2
                xy[i] = (R * math.cos(a), R * math.sin(a))
    theta = rng.uniform(0, 2 * math.pi)
    c, s_ = math.cos(theta), math.sin(theta)
    out: FloatArray = xy @ np.array([[c, s_], [-s_, c]])
    return out


def _arc(xy: FloatArray) -> FloatArray:
    d = np.diff(np.vstack([xy, xy[:1]]), axis=0)
    return np.concatenate([[0.0], np.cumsum(np.hypot(d[:, 0], d[:, 1]))])


def _min_radius(xy: FloatArray) -> float:
    """Smallest radius of curvature of a closed polyline, from consecutive triples."""
    a, b, c = xy, np.roll(xy, -1, axis=0), np.roll(xy, -2, axis=0)
    ab, bc, ca = (np.hypot(*(q - p).T) for p, q in ((a, b), (b, c), (c, a)))
    cross = np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
    with np.errstate(divide="ignore"):
        radius = np.where(cross > 0, ab * bc * ca / (2 * np.maximum(cross, 1e-300)), np.inf)
    return float(radius.min())


def _path(params: WorldParams, rng: np.random.Generator) -> FloatArray:
    """(n, 2) closed path of length ``loop_length_m``, sampled about every 0.1 m.

    A draw that turns tighter than the vehicle follows well (8 m) is drawn again, up
    to 50 times, so a campaign's generated worlds do not fail on an unlucky shape.
    """
    n = max(2000, int(params.loop_length_m / 0.1))
    tightest = np.inf
    for _ in range(50):
        xy = _unit_curve(params, rng, n)
        xy *= params.loop_length_m / _arc(xy)[-1]
        r = _min_radius(xy)
        if r >= _MIN_TURN_RADIUS_M:
            return xy
        tightest = min(tightest, r)
    raise ValueError(
        f"a {params.shape} of {params.loop_length_m:g} m turns on a {tightest:.1f} m "
        f"radius or less, below {_MIN_TURN_RADIUS_M:g} m: make the loop longer"
    )


def _dist_to(points: FloatArray, path: FloatArray) -> FloatArray:
    """(P,) distance of each point to the nearest path sample."""
    out = np.empty(points.shape[0])
    for i, p in enumerate(points):
        out[i] = np.sqrt(np.min(np.sum((path - p) ** 2, axis=1)))
    return out


def _segment_points(p1: FloatArray, p2: FloatArray, spacing: float = 0.5) -> FloatArray:
    n = max(2, math.ceil(float(np.hypot(*(p2 - p1))) / spacing) + 1)
    return p1 + np.linspace(0.0, 1.0, n)[:, None] * (p2 - p1)


def _place(
    params: WorldParams, rng: np.random.Generator, path: FloatArray
) -> tuple[list[tuple[FloatArray, FloatArray]], list[tuple[FloatArray, float]]]:
    """Walls ``(p1, p2)`` and trees ``(centre, radius)`` beside ``path``."""
    tangent = np.roll(path, -1, axis=0) - np.roll(path, 1, axis=0)
    tangent /= np.hypot(tangent[:, 0], tangent[:, 1])[:, None]
    normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    walls: list[tuple[FloatArray, FloatArray]] = []
    wall_pts: list[FloatArray] = []
    for _ in range(params.walls):
        for _attempt in range(400):
            i = int(rng.integers(path.shape[0]))
            side = rng.choice([-1.0, 1.0])
            length = rng.uniform(10.0, 35.0)
            centre = path[i] + side * rng.uniform(6.0, 20.0) * normal[i]
            ang = math.atan2(tangent[i, 1], tangent[i, 0]) + rng.normal(0.0, 0.6)
            half = 0.5 * length * np.array([math.cos(ang), math.sin(ang)])
            p1, p2 = centre - half, centre + half
            pts = _segment_points(p1, p2)
            if _dist_to(pts, path).min() < _WALL_CLEARANCE_M:
                continue
            if any(np.min(np.hypot(*(q[:, None] - pts[None]).T)) < 1.0 for q in wall_pts):
                continue
            walls.append((p1, p2))
            wall_pts.append(pts)
            break
        else:
            raise ValueError(
                f"could not place wall {len(walls) + 1} of {params.walls} beside the "
                f"{params.shape}: ask for fewer walls or a longer loop"
            )
    trees: list[tuple[FloatArray, float]] = []
    all_wall_pts = np.vstack(wall_pts) if wall_pts else np.zeros((0, 2))
    for _ in range(params.trees):
        for _attempt in range(400):
            i = int(rng.integers(path.shape[0]))
            r = float(rng.uniform(params.tree_radius_min_m, params.tree_radius_max_m))
            lo, hi = params.tree_clearance_min_m, params.tree_clearance_max_m
            d = lo + r + float(rng.uniform(_TREE_GAP_MARGIN_M, hi - lo))
            c = path[i] + rng.choice([-1.0, 1.0]) * d * normal[i]
            # Nearer another stretch of the path than the clearance: draw again.
            if _dist_to(c[None], path)[0] < lo + r:
                continue
            if any(np.hypot(*(c - q)) < r + rq + 1.5 for q, rq in trees):
                continue
            if all_wall_pts.size and np.min(np.hypot(*(all_wall_pts - c).T)) < r + 1.0:
                continue
            trees.append((c, r))
            break
        else:
            raise ValueError(
                f"could not place tree {len(trees) + 1} of {params.trees} beside the "
                f"{params.shape}: ask for fewer trees or a longer loop"
            )
    return walls, trees


def _known_ids(
    params: WorldParams,
    rng: np.random.Generator,
    start: FloatArray,
    features: list[tuple[int, FloatArray]],
) -> list[int]:
    """Ids of the known map: every feature within 40 m of the start, then random ones."""
    near = [fid for fid, pts in features if _dist_to(pts, start[None]).min() <= _KNOWN_RADIUS_M]
    rest = [fid for fid, _ in features if fid not in near]
    want = max(0, round(params.known_fraction * len(features)) - len(near))
    chosen = list(rng.choice(rest, size=min(want, len(rest)), replace=False)) if rest else []
    return sorted([*near, *(int(x) for x in chosen)])


@dataclass(frozen=True)
class _Changes:
    """The known-map changes drawn for a world."""

    moved: dict[int, tuple[float, float, float]]
    """Feature id → ``(dx, dy, dθ)`` (m, m, rad; ``dθ`` 0 for trees)."""
    removed: tuple[int, ...]
    """Ids taken out of the world (the map keeps them)."""
    added: tuple[int, ...]
    """Ids in the world the map does not hold."""


def _draw_changes(params: WorldParams, known: list[int], tree_ids: set[int]) -> _Changes:
    """Half moved, a quarter removed, the rest added, of ``changes × len(known)``."""
    rng = np.random.default_rng(np.random.SeedSequence([params.seed, 0x6D617066, 1]))
    n = min(len(known), round(params.changes * len(known)))
    order = [int(i) for i in rng.permutation(known)[:n]]
    n_mv = (n + 1) // 2
    n_rm = (n - n_mv) // 2
    moved = {}
    for fid in order[:n_mv]:
        d = float(rng.uniform(0.3, 5.0))
        a = float(rng.uniform(-math.pi, math.pi))
        dth = 0.0 if fid in tree_ids else float(rng.choice([-1.0, 1.0]) * rng.uniform(0.05, 0.3))
        moved[fid] = (d * math.cos(a), d * math.sin(a), dth)
    return _Changes(
        moved=moved,
        removed=tuple(sorted(order[n_mv : n_mv + n_rm])),
        added=tuple(sorted(order[n_mv + n_rm :])),
    )


def _change_lines(
    ch: _Changes,
    walls: dict[int, tuple[FloatArray, FloatArray]],
    trees: dict[int, tuple[FloatArray, float]],
) -> list[str]:
    """``[known_map]`` keys (``moved``, ``added``) and ``[known_map.removed]`` of ``ch``."""
    out = []
    if ch.moved:
        out.append("moved = [")
        for fid, (dx, dy, dth) in sorted(ch.moved.items()):
            turn = f", dtheta = {dth:.6f}" if fid in walls else ""
            out.append(f"    {{ id = {fid}, dx = {_fmt(dx)}, dy = {_fmt(dy)}{turn} }},")
        out.append("]")
    if ch.added:
        out.append(f"added = [{', '.join(str(i) for i in ch.added)}]")
    if ch.removed:
        out += ["", "[known_map.removed]", "segments = ["]
        out += [
            f"    {{ id = {i}, p1 = [{_fmt(walls[i][0][0])}, {_fmt(walls[i][0][1])}], "
            f"p2 = [{_fmt(walls[i][1][0])}, {_fmt(walls[i][1][1])}] }},"
            for i in ch.removed
            if i in walls
        ]
        out += ["]", "circles = ["]
        out += [
            f"    {{ id = {i}, centre = [{_fmt(trees[i][0][0])}, {_fmt(trees[i][0][1])}], "
            f"radius = {trees[i][1]:.3f} }},"
            for i in ch.removed
            if i in trees
        ]
        out.append("]")
    return out


def _fmt(x: float) -> str:
    return f"{x:.3f}"


def world_toml(params: WorldParams, base: Scenario | None = None) -> str:
    """The scenario TOML of the world ``params`` draws (vehicle, laser and known-map
    noise from ``base``, default loop600)."""
    base = load_scenario("loop600") if base is None else base
    rng = np.random.default_rng(np.random.SeedSequence([params.seed, 0x6D617066]))
    path = _path(params, rng)
    walls, trees = _place(params, rng, path)
    veh, las, km = base.vehicle, base.laser, base.known_map
    step_m = veh.speed_mps * veh.dt_s
    steps = math.ceil(params.loop_length_m / step_m) + 1
    # Waypoints every 10 m, and 20 m past the start again, so the drive closes.
    arc = _arc(path)[:-1]
    marks = np.arange(0.0, params.loop_length_m + 20.0, 10.0)
    idx = [int(np.argmin(np.abs(arc - (m % params.loop_length_m)))) for m in marks]
    wps = path[idx]
    heading = math.atan2(*(path[5] - path[0])[::-1])
    wall_ids = list(range(1, len(walls) + 1))
    tree_ids = list(range(1001, 1001 + len(trees)))
    feats: list[tuple[int, FloatArray]] = [
        (i, _segment_points(p1, p2)) for i, (p1, p2) in zip(wall_ids, walls, strict=True)
    ] + [(i, c[None]) for i, (c, _) in zip(tree_ids, trees, strict=True)]
    known = _known_ids(params, rng, path[0], feats)
    ch = _draw_changes(params, known, set(tree_ids))
    wall_of = dict(zip(wall_ids, walls, strict=True))
    tree_of = dict(zip(tree_ids, trees, strict=True))
    gone = set(ch.removed)
    held = [i for i in known if i not in gone and i not in set(ch.added)]
    vehicle_lines = [f"{f.name} = {_value(getattr(veh, f.name))}" for f in fields(veh) if f.init]
    laser_values = {f.name: getattr(las, f.name) for f in fields(las) if f.init}
    laser_values["max_range_m"] = params.laser_range_m
    laser_lines = [f"{k} = {_value(v)}" for k, v in laser_values.items()]
    lines = [
        f"# Generated by mapfuse_core.sim.worldgen: {params}.",
        f"# Vehicle, laser and known-map noise of {base.name}; "
        f"laser range {params.laser_range_m:g} m.",
        "",
        "[scenario]",
        f'name = "world-{params.shape}-{params.seed}"',
        f'description = "generated {params.shape}, {params.loop_length_m:g} m, '
        f'{len(walls)} walls, {len(trees)} trees"',
        f"seed = {params.seed}",
        "",
        "[trajectory]",
        f"start = [{_fmt(path[0, 0])}, {_fmt(path[0, 1])}, {heading:.6f}]",
        f"steps = {steps}",
        "waypoints = [",
        *(f"    [{_fmt(p[0])}, {_fmt(p[1])}]," for p in wps),
        "]",
        "",
        "[vehicle]",
        *vehicle_lines,
        "",
        "[laser]",
        *laser_lines,
        "",
        "[known_map]",
        "frame = [0.0, 0.0, 0.0]",
        f"sigma_xy_m = {km.sigma_xy_m!r}",
        f"sigma_r_m = {km.sigma_r_m!r}",
        f"sigma_theta_rad = {km.sigma_theta_rad!r}",
        f"ids = [{', '.join(str(i) for i in held)}]",
        *_change_lines(ch, wall_of, tree_of),
        "",
        "[world]",
        "segments = [",
        *(
            f"    {{ id = {i}, p1 = [{_fmt(p1[0])}, {_fmt(p1[1])}], "
            f"p2 = [{_fmt(p2[0])}, {_fmt(p2[1])}] }},"
            for i, (p1, p2) in zip(wall_ids, walls, strict=True)
            if i not in gone
        ),
        "]",
        "circles = [",
        *(
            f"    {{ id = {i}, centre = [{_fmt(c[0])}, {_fmt(c[1])}], radius = {r:.3f} }},"
            for i, (c, r) in zip(tree_ids, trees, strict=True)
            if i not in gone
        ),
        "]",
        "",
    ]
    return "\n".join(lines)


def _value(v: object) -> str:
    if isinstance(v, tuple | list):
        return "[" + ", ".join(repr(float(x)) for x in v) + "]"
    return repr(float(v)) if isinstance(v, float) else repr(v)


def generate_scenario(params: WorldParams, base: Scenario | None = None) -> Scenario:
    """The world of ``params`` as a validated :class:`Scenario` (parsed from
    :func:`world_toml` by the scenario loader)."""
    text = world_toml(params, base)
    try:
        return scenario_from_toml(text, f"<world seed {params.seed}>", f"world-{params.seed}")
    except ScenarioError as e:  # pragma: no cover - the generator writes valid scenarios
        raise ValueError(f"the generator wrote an invalid scenario: {e}") from e
