"""The world generator (mapfuse_core.sim.worldgen) and ``mapfuse world generate``."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from mapfuse.cli import main
from mapfuse_core.sim import worldgen
from mapfuse_core.sim.scenario import load_scenario
from mapfuse_core.sim.worldgen import SHAPES, WorldParams, generate_scenario, world_toml

SMALL = {"walls": 4, "trees": 12, "laser_range_m": 30.0}


@pytest.mark.parametrize(
    ("shape", "length"), [("loop", 150.0), ("figure8", 250.0), ("corridor", 300.0)]
)
def test_generated_world_is_a_valid_scenario_of_the_asked_size(shape: str, length: float) -> None:
    sc = generate_scenario(WorldParams(seed=2, shape=shape, loop_length_m=length, **SMALL))
    assert (len(sc.world.segments), len(sc.world.circles)) == (4, 12)
    assert sc.laser.max_range_m == 30.0
    # 0.25 m per step over the whole length, the start pose included.
    assert sc.steps == math.ceil(length / 0.25) + 1
    assert set(sc.known_map.world_ids) <= {s.id for s in sc.world.segments} | {
        c.id for c in sc.world.circles
    }


def test_same_seed_gives_the_same_world_and_another_seed_another() -> None:
    p = dict(loop_length_m=150.0, **SMALL)
    assert world_toml(WorldParams(seed=5, **p)) == world_toml(WorldParams(seed=5, **p))
    assert world_toml(WorldParams(seed=5, **p)) != world_toml(WorldParams(seed=6, **p))


def test_features_keep_their_clearance_from_the_path() -> None:
    params = WorldParams(seed=0, walls=6, trees=20, loop_length_m=300.0)
    rng = np.random.default_rng(1)
    path = worldgen._path(params, rng)
    walls, trees = worldgen._place(params, rng, path)
    for c, r in trees:
        assert worldgen._dist_to(c[None], path)[0] >= 3.6 + r
    for p1, p2 in walls:
        assert worldgen._dist_to(worldgen._segment_points(p1, p2), path).min() >= 4.0


def test_trees_take_the_asked_radii_and_clearances() -> None:
    # Large trunks close to the drive: every radius and every gap to the path within
    # the asked ranges (the gap to the nearest path point: another stretch of the path
    # may be nearer than where the tree was placed, never nearer than the minimum).
    params = WorldParams(
        seed=1,
        walls=4,
        trees=30,
        loop_length_m=300.0,
        tree_radius_min_m=0.6,
        tree_radius_max_m=1.2,
        tree_clearance_min_m=1.5,
        tree_clearance_max_m=4.0,
    )
    rng = np.random.default_rng(2)
    path = worldgen._path(params, rng)
    _, trees = worldgen._place(params, rng, path)
    radii = np.array([r for _, r in trees])
    gaps = np.array([worldgen._dist_to(c[None], path)[0] - r for c, r in trees])
    assert np.all((radii >= 0.6) & (radii <= 1.2))
    assert np.all((gaps >= 1.5) & (gaps <= 4.0 + 0.05))
    # The defaults are loop600's trees, drawn as before the ranges were arguments.
    d = WorldParams(seed=0)
    assert (d.tree_radius_min_m, d.tree_radius_max_m) == (0.3, 0.8)
    assert (d.tree_clearance_min_m, d.tree_clearance_max_m) == (3.6, 14.6)


def test_known_fraction_holds_features_near_the_start_and_about_the_asked_share() -> None:
    sc = generate_scenario(WorldParams(seed=3, loop_length_m=600.0, known_fraction=0.5))
    assert len(sc.known_map.world_ids) >= round(0.5 * 57)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"shape": "spiral"}, "shape must be one of"),
        ({"walls": -1}, "walls must be"),
        ({"known_fraction": 1.5}, "known_fraction"),
        ({"loop_length_m": 30.0}, "loop_length_m must be"),
        ({"walls": 0, "trees": 0}, "at least one"),
        ({"tree_radius_min_m": 0.0}, "tree_radius_min_m must be"),
        ({"tree_radius_min_m": 1.0, "tree_radius_max_m": 0.9}, "tree_radius_max_m"),
        ({"tree_clearance_min_m": 0.5}, "tree_clearance_min_m must be"),
        ({"tree_clearance_min_m": 4.0, "tree_clearance_max_m": 4.2}, r"\+ 0.5"),
        ({"tree_clearance_max_m": math.inf}, "tree_clearance_max_m must be"),
    ],
)
def test_bad_generator_arguments_are_named(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        WorldParams(seed=0, **kwargs)  # type: ignore[arg-type]


def test_too_short_a_figure8_is_refused_with_the_reason() -> None:
    with pytest.raises(ValueError, match="make the loop longer"):
        generate_scenario(WorldParams(seed=0, shape="figure8", loop_length_m=100.0, **SMALL))


def test_cli_world_generate_writes_a_file_the_loader_reads(tmp_path: Path) -> None:
    out = tmp_path / "w.toml"
    code = main(
        ["world", "generate", "--seed", "4", "--shape", "corridor", "--loop-length", "300",
         "--walls", "3", "--trees", "10", "--out", str(out)]
    )  # fmt: skip
    assert code == 0
    sc = load_scenario(out)
    assert sc.name == "world-corridor-4"
    assert len(sc.world.circles) == 10


def test_cli_world_generate_takes_the_tree_ranges(tmp_path: Path) -> None:
    out = tmp_path / "w.toml"
    args = ["world", "generate", "--seed", "2", "--walls", "3", "--trees", "10"]
    args += ["--tree-radius", "1.0", "1.5", "--tree-clearance", "2", "3", "--out", str(out)]
    assert main(args) == 0
    radii = [c.radius for c in load_scenario(out).world.circles]
    assert len(radii) == 10
    assert min(radii) >= 1.0
    assert max(radii) <= 1.5


def test_every_shape_is_listed() -> None:
    assert SHAPES == ("loop", "figure8", "corridor")


def test_changes_option_moves_removes_and_adds_the_asked_share_of_the_known_map() -> None:
    p = dict(loop_length_m=150.0, known_fraction=1.0, **SMALL)
    plain = generate_scenario(WorldParams(seed=4, **p))
    sc = generate_scenario(WorldParams(seed=4, changes=0.25, **p))
    n = len(plain.known_map.world_ids)  # 16 features, all known
    km = sc.known_map
    # round(0.25 · 16) = 4 changes: 2 moved, 1 removed, 1 added.
    assert (len(km.moved), len(km.removed), len(km.added)) == (2, 1, 1)
    assert len(km.world_ids) == n - 2  # removed and added ones are no longer held
    removed = km.removed[0].id
    world_ids = {s.id for s in sc.world.segments} | {c.id for c in sc.world.circles}
    assert removed not in world_ids
    assert km.added[0] in world_ids
    assert {m.id for m in km.moved} <= set(km.world_ids)
    for m in km.moved:
        assert 0.3 <= math.hypot(m.dx, m.dy) <= 5.0
    # The layout is drawn before, and apart from, the changes.
    assert [c.centre for c in sc.world.circles] == [
        c.centre for c in plain.world.circles if c.id != removed
    ]
    assert world_toml(WorldParams(seed=4, changes=0.25, **p)) == world_toml(
        WorldParams(seed=4, changes=0.25, **p)
    )


def test_changes_fraction_outside_zero_one_is_refused() -> None:
    with pytest.raises(ValueError, match="changes must be in"):
        WorldParams(seed=0, changes=1.5)


def test_world_generate_cli_writes_the_changes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "w.toml"
    args = ["world", "generate", "--seed", "1", "--walls", "4", "--trees", "12"]
    args += ["--loop-length", "150", "--known-fraction", "1", "--changes", "0.5"]
    assert main([*args, "--out", str(out)]) == 0
    text = out.read_text()
    for key in ("moved = [", "added = [", "[known_map.removed]"):
        assert key in text
    summary = json.loads(capsys.readouterr().out)
    assert (summary["moved"], summary["removed"], summary["added"]) == (4, 2, 2)
