"""Loading scenarios: built-in names, TOML files and strings, parsed into a
:class:`~mapfuse_core.sim.scenario.types.Scenario` with every section validated."""

from __future__ import annotations

import math
import tomllib
from collections.abc import Iterator, Mapping
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray, wrap_angle
from mapfuse_core.sensor import LaserParams
from mapfuse_core.sim.limits import MAX_SEED, MAX_STEPS, check_steps
from mapfuse_core.sim.scenario.reader import _join, _Reader
from mapfuse_core.sim.scenario.types import (
    ControlSegment,
    FeatureMove,
    KnownMapSpec,
    Scenario,
    ScenarioError,
)
from mapfuse_core.sim.vehicle import VehicleParams
from mapfuse_core.sim.world import CircleObstacle, WallSegment, World


def list_builtin_scenarios() -> list[str]:
    """Names of the scenarios shipped in ``mapfuse_core/sim/scenarios``."""
    folder = resources.files("mapfuse_core.sim") / "scenarios"
    return sorted(
        p.name[: -len(".toml")]
        for p in folder.iterdir()
        if p.name.endswith(".toml") and p.is_file()
    )


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load and validate a built-in scenario by name (``"loop600"``) or a TOML file by path.

    A string is a built-in name unless it ends in ``.toml`` or contains a path
    separator.  Raises :class:`ScenarioError` for every problem.
    """
    is_path = isinstance(name_or_path, Path) or (
        name_or_path.endswith(".toml") or "/" in name_or_path or "\\" in name_or_path
    )
    if is_path:
        path = Path(name_or_path)
        source = str(path)
        try:
            raw = path.read_bytes()
        except FileNotFoundError:
            raise ScenarioError(source, "", "file not found") from None
        except OSError as e:
            raise ScenarioError(source, "", f"cannot read the file: {e}") from None
        stem = path.stem
    else:
        name = str(name_or_path)
        builtins = list_builtin_scenarios()
        if name not in builtins:
            raise ScenarioError(
                name,
                "",
                f"no built-in scenario of that name (built-ins: {', '.join(builtins)}); "
                "give a path to a .toml file instead",
            )
        res = resources.files("mapfuse_core.sim") / "scenarios" / f"{name}.toml"
        source = str(res)
        raw = res.read_bytes()
        stem = name
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ScenarioError(source, "", f"not UTF-8 text: {e}") from None
    return scenario_from_toml(text, source, stem)


def scenario_from_toml(text: str, source: str = "<string>", stem: str = "scenario") -> Scenario:
    """Parse and validate a scenario from TOML text, as :func:`load_scenario` does a
    file (``source`` names it in errors; ``stem`` is the name when it gives none)."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ScenarioError(source, "", f"invalid TOML: {e}") from None
    return _parse(doc, source, stem)


_SEGMENT_KEYS = ("id", "p1", "p2")
_CIRCLE_KEYS = ("id", "centre", "radius")


def _segments(r: _Reader, value: object, key: str) -> Iterator[tuple[str, WallSegment]]:
    for i, item in enumerate(r.array(value, key)):
        k = f"{key}[{i}]"
        t = r.table(item, k, required=_SEGMENT_KEYS)
        fid = r.feature_id(t["id"], f"{k}.id")
        p1 = r.vector(t["p1"], f"{k}.p1", 2)
        p2 = r.vector(t["p2"], f"{k}.p2", 2)
        if math.hypot(p2[0] - p1[0], p2[1] - p1[1]) <= 1e-6:
            raise r.fail(f"{k}.p2", "zero-length segment: p2 equals p1")
        yield f"{k}.id", WallSegment(id=fid, p1=(p1[0], p1[1]), p2=(p2[0], p2[1]))


def _circles(r: _Reader, value: object, key: str) -> Iterator[tuple[str, CircleObstacle]]:
    for i, item in enumerate(r.array(value, key)):
        k = f"{key}[{i}]"
        t = r.table(item, k, required=_CIRCLE_KEYS)
        fid = r.feature_id(t["id"], f"{k}.id")
        c = r.vector(t["centre"], f"{k}.centre", 2)
        radius = r.number(t["radius"], f"{k}.radius", positive=True)
        yield f"{k}.id", CircleObstacle(id=fid, centre=(c[0], c[1]), radius=radius)


def _features(
    r: _Reader, t: dict[str, Any], key: str
) -> tuple[list[WallSegment], list[CircleObstacle], dict[int, str]]:
    """Segments and circles of a ``{segments, circles}`` table; ids unique within it."""
    seen: dict[int, str] = {}
    segs: list[WallSegment] = []
    circs: list[CircleObstacle] = []

    def note(id_key: str, fid: int) -> None:
        if fid in seen:
            raise r.fail(id_key, f"duplicate id {fid} (also {seen[fid]})")
        seen[fid] = id_key

    for id_key, s in _segments(r, t.get("segments", []), _join(key, "segments")):
        note(id_key, s.id)
        segs.append(s)
    for id_key, c in _circles(r, t.get("circles", []), _join(key, "circles")):
        note(id_key, c.id)
        circs.append(c)
    return segs, circs, seen


def _params_from(
    r: _Reader, value: object, key: str, cls: type[VehicleParams] | type[LaserParams]
) -> Any:
    """Build ``cls`` from a table of overrides of its fields (defaults for the rest).

    Every value is type-checked here and then tried alone in ``cls`` so that the
    class's own validation is reported against the right key.
    """
    defaults = cls()
    t = r.table(value, key, optional=list(cls.__dataclass_fields__))
    kwargs: dict[str, Any] = {}
    for name, raw in t.items():
        k = _join(key, name)
        default = getattr(defaults, name)
        angle = name.endswith("_rad") or name == "sigma_phi"
        if isinstance(default, int) and not isinstance(default, bool):
            v: Any = r.integer(raw, k)
        elif isinstance(default, tuple):
            v = tuple(r.vector(raw, k, len(default), angle_last=True))
            for j, x in enumerate(v):
                if x <= 0.0:
                    raise r.fail(f"{k}[{j}]", f"must be > 0, got {x}")
        else:
            v = r.number(raw, k, positive=True, angle=angle)
        try:
            cls(**{name: v})
        except ValueError as e:
            raise r.fail(k, str(e)) from None
        kwargs[name] = v
    try:
        return cls(**kwargs)
    except ValueError as e:
        raise r.fail(key, str(e)) from None


def _parse(doc: dict[str, Any], source: str, stem: str) -> Scenario:
    r = _Reader(source)
    top = r.table(
        doc,
        "",
        required=("scenario", "trajectory", "world", "known_map"),
        optional=("vehicle", "laser"),
    )

    meta = r.table(
        top["scenario"], "scenario", required=("seed",), optional=("name", "description")
    )
    name = r.string(meta["name"], "scenario.name") if "name" in meta else stem
    if not name.strip():
        raise r.fail("scenario.name", "must not be empty")
    description = (
        r.string(meta["description"], "scenario.description") if "description" in meta else ""
    )
    seed = r.integer(meta["seed"], "scenario.seed", minimum=0, maximum=MAX_SEED, what="2**63 - 1")

    start, steps, waypoints, controls = _parse_trajectory(r, top["trajectory"])
    vehicle: VehicleParams = _params_from(r, top.get("vehicle", {}), "vehicle", VehicleParams)
    laser: LaserParams = _params_from(r, top.get("laser", {}), "laser", LaserParams)
    try:
        check_steps(steps, laser.n_beams, "steps")
    except ValueError as e:
        raise r.fail("trajectory.steps", str(e)) from None
    for i, c in enumerate(controls):
        if abs(c.steer_rad) > vehicle.max_steer_rad:
            raise r.fail(
                f"trajectory.controls[{i}][1]",
                f"steering {c.steer_rad:.6g} rad is beyond the vehicle's steering limit "
                f"vehicle.max_steer_rad = {vehicle.max_steer_rad:.6g}",
            )

    wt = r.table(top["world"], "world", optional=("segments", "circles"))
    segs, circs, world_keys = _features(r, wt, "world")
    if not segs and not circs:
        raise r.fail("world", "the world is empty: give at least one segment or circle")
    try:
        world = World(segments=tuple(segs), circles=tuple(circs))
    except ValueError as e:  # pragma: no cover - every World check is done above
        raise r.fail("world", str(e)) from None
    known = _parse_known_map(r, top["known_map"], world, world_keys)
    return Scenario(
        name=name,
        description=description,
        source=source,
        seed=seed,
        world=world,
        start=start,
        steps=steps,
        waypoints=waypoints,
        controls=controls,
        vehicle=vehicle,
        laser=laser,
        known_map=known,
    )


def _parse_trajectory(
    r: _Reader, value: object
) -> tuple[FloatArray, int, FloatArray, tuple[ControlSegment, ...]]:
    """Start, number of poses, waypoints and controls of ``[trajectory]`` (one of the two
    given, the other empty); the steering limit is checked once the vehicle is known."""
    key = "trajectory"
    traj = r.table(value, key, required=("start",), optional=("steps", "waypoints", "controls"))
    start = np.array(r.vector(traj["start"], f"{key}.start", 3, angle_last=True))
    start[2] = float(wrap_angle(start[2]))
    start.setflags(write=False)
    if "waypoints" in traj and "controls" in traj:
        raise r.fail(f"{key}.controls", "give either waypoints or controls, not both")
    if "controls" not in traj:
        if "waypoints" not in traj:
            raise r.fail(
                key,
                "no drive: give waypoints = [[x, y], ...] (with steps) "
                "or controls = [[v, phi, n], ...]",
            )
        if "steps" not in traj:
            raise r.fail(f"{key}.steps", "missing required key")
        steps = r.integer(traj["steps"], f"{key}.steps", minimum=2, maximum=MAX_STEPS)
        wp_items = r.array(traj["waypoints"], f"{key}.waypoints")
        if len(wp_items) < 2:
            raise r.fail(f"{key}.waypoints", f"needs at least 2 waypoints, got {len(wp_items)}")
        waypoints = np.array(
            [r.vector(w, f"{key}.waypoints[{i}]", 2) for i, w in enumerate(wp_items)]
        )
        for i in range(1, waypoints.shape[0]):
            if np.hypot(*(waypoints[i] - waypoints[i - 1])) <= 1e-6:
                raise r.fail(f"{key}.waypoints[{i}]", "repeats the previous waypoint")
        waypoints.setflags(write=False)
        return start, steps, waypoints, ()

    rows = r.array(traj["controls"], f"{key}.controls")
    if not rows:
        raise r.fail(f"{key}.controls", "needs at least one control [v, phi, n]")
    controls: list[ControlSegment] = []
    driven = 0
    for i, row in enumerate(rows):
        k = f"{key}.controls[{i}]"
        items = r.array(row, k)
        if len(items) != 3:
            raise r.fail(k, f"must be [v, phi, n] (3 entries), got {len(items)} entries")
        controls.append(
            ControlSegment(
                speed_mps=r.number(items[0], f"{k}[0]"),
                steer_rad=r.number(items[1], f"{k}[1]", angle=True),
                steps=r.integer(items[2], f"{k}[2]", minimum=1, maximum=MAX_STEPS - 1),
            )
        )
        driven += controls[-1].steps
        if driven + 1 > MAX_STEPS:
            raise r.fail(
                f"{k}[2]",
                f"the controls drive {driven} steps so far, above the maximum of "
                f"{MAX_STEPS:,} poses",
            )
    steps = driven + 1
    if "steps" in traj:
        given = r.integer(traj["steps"], f"{key}.steps", minimum=2)
        if given != steps:
            raise r.fail(
                f"{key}.steps",
                f"is {given} but the controls drive {driven} steps, i.e. {steps} poses with "
                "the start (leave steps out to take it from the controls)",
            )
    waypoints = np.zeros((0, 2))
    waypoints.setflags(write=False)
    return start, steps, waypoints, tuple(controls)


def _parse_known_map(
    r: _Reader,
    value: object,
    world: World,
    world_keys: Mapping[int, str],
) -> KnownMapSpec:
    key = "known_map"
    t = r.table(
        value,
        key,
        required=("ids", "sigma_xy_m", "sigma_r_m", "sigma_theta_rad"),
        optional=("frame", "moved", "removed", "added"),
    )
    sigma_xy = r.sigma(t["sigma_xy_m"], f"{key}.sigma_xy_m")
    sigma_r = r.sigma(t["sigma_r_m"], f"{key}.sigma_r_m")
    sigma_th = r.sigma(t["sigma_theta_rad"], f"{key}.sigma_theta_rad", angle=True)
    frame = np.array(r.vector(t.get("frame", [0.0, 0.0, 0.0]), f"{key}.frame", 3, True))
    frame[2] = float(wrap_angle(frame[2]))
    frame.setflags(write=False)

    added: list[int] = []
    for i, v in enumerate(r.array(t.get("added", []), f"{key}.added")):
        k = f"{key}.added[{i}]"
        fid = r.feature_id(v, k)
        if fid not in world_keys:
            raise r.fail(k, f"id {fid} is not in the world (added features are world features)")
        if fid in added:
            raise r.fail(k, f"duplicate id {fid}")
        added.append(fid)

    ids_value = t["ids"]
    if isinstance(ids_value, str):
        if ids_value != "all":
            raise r.fail(f"{key}.ids", f'must be an array of ids or "all", got {ids_value!r}')
        held = [fid for fid in world_keys if fid not in added]
    else:
        held = []
        for i, v in enumerate(r.array(ids_value, f"{key}.ids")):
            k = f"{key}.ids[{i}]"
            fid = r.feature_id(v, k)
            if fid not in world_keys:
                raise r.fail(k, f"id {fid} is not in the world")
            if fid in held:
                raise r.fail(k, f"duplicate id {fid}")
            if fid in added:
                raise r.fail(k, f"id {fid} is also listed in {key}.added (new since the map)")
            held.append(fid)

    removed: list[WallSegment | CircleObstacle] = []
    kinds = {fid: world.feature(fid)[0] for fid in held}
    if "removed" in t:
        rt = r.table(t["removed"], f"{key}.removed", optional=("segments", "circles"))
        segs, circs, rkeys = _features(r, rt, f"{key}.removed")
        for fid, k in rkeys.items():
            if fid in world_keys:
                raise r.fail(
                    k,
                    f"id {fid} is in the world ({world_keys[fid]}); removed features are "
                    "gone from the world and need ids of their own",
                )
        removed = [*segs, *circs]
        kinds |= {s.id: FeatureKind.LINE for s in segs}
        kinds |= {c.id: FeatureKind.CIRCLE for c in circs}
    if not kinds:
        raise r.fail(f"{key}.ids", "the known map holds no feature")

    radii = {c.id: c.radius for c in (*world.circles, *removed) if isinstance(c, CircleObstacle)}
    moves: list[FeatureMove] = []
    moved_ids: set[int] = set()
    for i, item in enumerate(r.array(t.get("moved", []), f"{key}.moved")):
        k = f"{key}.moved[{i}]"
        mt = r.table(item, k, required=("id",), optional=("dx", "dy", "dtheta", "dr"))
        fid = r.feature_id(mt["id"], f"{k}.id")
        if fid not in kinds:
            raise r.fail(f"{k}.id", f"id {fid} is not in the known map")
        if fid in moved_ids:
            raise r.fail(f"{k}.id", f"id {fid} is moved twice")
        moved_ids.add(fid)
        kind = kinds[fid]
        if kind == FeatureKind.LINE and "dr" in mt:
            raise r.fail(f"{k}.dr", f"feature {fid} is a line: it has no radius")
        if kind == FeatureKind.CIRCLE and "dtheta" in mt:
            raise r.fail(f"{k}.dtheta", f"feature {fid} is a circle: it has no angle")
        move = FeatureMove(
            id=fid,
            dx=r.number(mt.get("dx", 0.0), f"{k}.dx"),
            dy=r.number(mt.get("dy", 0.0), f"{k}.dy"),
            dtheta=r.number(mt.get("dtheta", 0.0), f"{k}.dtheta", angle=True),
            dr=r.number(mt.get("dr", 0.0), f"{k}.dr"),
        )
        if kind == FeatureKind.CIRCLE:
            radius = radii[fid]
            if radius + move.dr <= 0.0:
                raise r.fail(
                    f"{k}.dr", f"moves the radius {radius:g} m to {radius + move.dr:.6g} m <= 0"
                )
        moves.append(move)

    return KnownMapSpec(
        world_ids=tuple(sorted(held)),
        sigma_xy_m=sigma_xy,
        sigma_r_m=sigma_r,
        sigma_theta_rad=sigma_th,
        frame=frame,
        moved=tuple(moves),
        removed=tuple(removed),
        added=tuple(sorted(added)),
    )
