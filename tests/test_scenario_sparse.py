"""The built-in ``loop600-sparse``: loop600's drive, sensor and noise in a sparser
world (a subset of loop600's features), valid for the loader and seen at every step."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mapfuse_core.sim.scenario import (
    Scenario,
    check_visibility,
    list_builtin_scenarios,
    load_scenario,
    simulate_drive,
)


@pytest.fixture(scope="module")
def dense() -> Scenario:
    return load_scenario("loop600")


@pytest.fixture(scope="module")
def sparse() -> Scenario:
    return load_scenario("loop600-sparse")


def test_loop600_sparse_is_builtin_and_loads_by_path_too(sparse: Scenario) -> None:
    assert "loop600-sparse" in list_builtin_scenarios()
    assert sparse.name == "loop600-sparse"
    assert Path(sparse.source).name == "loop600-sparse.toml"
    by_path = load_scenario(Path(sparse.source))
    assert by_path.world == sparse.world
    assert by_path.known_map.ids == sparse.known_map.ids


def test_same_drive_sensor_and_noise_as_loop600(sparse: Scenario, dense: Scenario) -> None:
    assert sparse.steps == dense.steps == 2400
    np.testing.assert_array_equal(sparse.start, dense.start)
    np.testing.assert_array_equal(sparse.waypoints, dense.waypoints)
    assert sparse.vehicle == dense.vehicle
    assert sparse.laser == dense.laser
    km, kd = sparse.known_map, dense.known_map
    assert (km.sigma_xy_m, km.sigma_r_m, km.sigma_theta_rad) == (
        kd.sigma_xy_m,
        kd.sigma_r_m,
        kd.sigma_theta_rad,
    )
    np.testing.assert_array_equal(km.frame, kd.frame)
    assert km.moved == km.removed == km.added == ()


def test_world_is_a_sparser_subset_of_loop600(sparse: Scenario, dense: Scenario) -> None:
    ws, wd = sparse.world, dense.world
    # Every feature is loop600's, unchanged; at most a third of its walls and half its trees.
    assert set(ws.segments) <= set(wd.segments)
    assert set(ws.circles) <= set(wd.circles)
    assert 3 <= len(ws.segments) <= len(wd.segments) / 3
    assert 3 <= len(ws.circles) <= len(wd.circles) / 2
    km = sparse.known_map
    assert set(km.ids) <= set(ws.ids)
    kinds = {s.id: "wall" for s in ws.segments} | {c.id: "tree" for c in ws.circles}
    assert {kinds[i] for i in km.ids} == {"wall", "tree"}


def test_every_sampled_step_sees_a_feature(sparse: Scenario) -> None:
    motion = simulate_drive(sparse, np.random.default_rng(np.random.SeedSequence(0).spawn(3)[0]))
    counts = check_visibility(sparse, motion, stride=40)
    # Sparse, but never blind: some feature is in view at every sampled step.
    assert counts.min() >= 1
