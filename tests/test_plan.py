"""One planner for every command: consumed runs first, made once, fusion where it can be.

The estimators here are stand-ins registered for the test: only their capabilities
matter to the planner, and the executor runs them on a tiny synthetic log.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from mapfuse import registry
from mapfuse.estimator import Capabilities
from mapfuse.plan import RunRequest, execute, plan_runs
from mapfuse_core.estimate import EstimatorResult, MapEstimate, PoseTrack
from mapfuse_core.measlog import MeasurementLog
from tests.synthetic import synthetic_log


@dataclass(frozen=True)
class _Options:
    shift: float = 0.0
    """Added to every pose's x (tells runs with different options apart)."""
    fail: bool = False
    """Raise instead of returning."""


def _make(name: str, caps: Capabilities) -> Any:
    class Stub:
        options_type = _Options
        capabilities = caps

        def run(
            self,
            log: MeasurementLog,
            options: _Options,
            *,
            fusion: bool,
            upstream: EstimatorResult | None = None,
            progress: Any = None,
        ) -> EstimatorResult:
            if options.fail:
                raise RuntimeError(f"{name} failed on purpose")
            n = log.n_steps
            poses = np.zeros((n, 3))
            poses[:, 0] = options.shift
            return EstimatorResult(
                estimator=name,
                scenario=log.scenario,
                seed=log.seed,
                fusion=fusion,
                timestamps=log.timestamps,
                step_time_s=np.zeros(n),
                map=MapEstimate.empty(),
                filtered=PoseTrack(poses, np.tile(np.eye(3), (n, 1, 1))),
                upstream=upstream,
            )

    Stub.name = name
    return Stub


@pytest.fixture
def stubs() -> Iterator[dict[str, Any]]:
    made = {
        "pf": _make("pf", Capabilities()),
        "pg": _make("pg", Capabilities(tracks=frozenset({"smoothed"}), consumes="pf")),
        "ph": _make("ph", Capabilities(consumes="pg")),
        "pn": _make("pn", Capabilities(fuses=False)),
    }
    for cls in made.values():
        registry.register(cls)
    yield made
    for name in made:
        registry.unregister(name)


def test_a_consumer_gets_its_upstream_first_and_once(stubs: dict[str, Any]) -> None:
    plan = plan_runs([RunRequest("pg", True), RunRequest("pf", True)], True)
    assert [(p.estimator, p.fusion, p.reported) for p in plan] == [
        ("pf", True, True),
        ("pg", True, True),
    ]
    assert plan[1].upstream == 0


def test_an_upstream_not_asked_for_is_made_and_not_reported(stubs: dict[str, Any]) -> None:
    plan = plan_runs([RunRequest("ph", False)], True)
    assert [(p.estimator, p.reported, p.upstream) for p in plan] == [
        ("pf", False, None),
        ("pg", False, 0),
        ("ph", True, 1),
    ]


def test_each_fusion_setting_has_its_own_upstream(stubs: dict[str, Any]) -> None:
    plan = plan_runs([RunRequest("pg", f) for f in (True, False)], True)
    assert [(p.estimator, p.fusion, p.upstream) for p in plan] == [
        ("pf", True, None),
        ("pg", True, 0),
        ("pf", False, None),
        ("pg", False, 2),
    ]


def test_without_a_known_map_or_the_capability_nothing_fuses(stubs: dict[str, Any]) -> None:
    no_map = plan_runs([RunRequest("pf", f) for f in (True, False)], False)
    assert [(p.estimator, p.fusion) for p in no_map] == [("pf", False)]
    cannot = plan_runs([RunRequest("pn", f) for f in (True, False)], True)
    assert [(p.estimator, p.fusion) for p in cannot] == [("pn", False)]


def test_overrides_make_distinct_runs_sharing_the_upstream(stubs: dict[str, Any]) -> None:
    plan = plan_runs(
        [
            RunRequest("pg", True, {"shift": 1.0}, label="one"),
            RunRequest("pg", True, {"shift": 2.0}, label="two"),
        ],
        True,
    )
    assert [(p.label, p.upstream) for p in plan] == [
        ("pf with fusion", None),
        ("one", 0),
        ("two", 0),
    ]


def test_a_consumption_loop_is_refused(stubs: dict[str, Any]) -> None:
    loop_a = _make("la", Capabilities(consumes="lb"))
    loop_b = _make("lb", Capabilities(consumes="la"))
    registry.register(loop_a)
    registry.register(loop_b)
    try:
        with pytest.raises(ValueError, match="loop: la -> lb"):
            plan_runs([RunRequest("la", True)], True)
    finally:
        registry.unregister("la")
        registry.unregister("lb")


def test_execute_hands_each_consumer_its_upstream(stubs: dict[str, Any]) -> None:
    log = synthetic_log(steps=20, seed=1)
    plan = plan_runs([RunRequest("ph", True, {"shift": 3.0})], len(log.known_map) > 0)
    done = execute(plan, log)
    assert [d.result.estimator for d in done if d.result is not None] == ["pf", "pg", "ph"]
    ph = done[-1].result
    assert ph is not None
    assert ph.upstream is done[1].result
    np.testing.assert_array_equal(ph.poses[:, 0], 3.0)


def test_recorded_errors_fail_the_consumers_too(stubs: dict[str, Any]) -> None:
    log = synthetic_log(steps=20, seed=1)
    plan = plan_runs([RunRequest("pf", True, {"fail": True})], True)
    plan = (*plan, dataclasses.replace(plan[0], estimator="pg", upstream=0, label="pg"))
    done = execute(plan, log, errors="record")
    assert done[0].result is None
    assert done[0].error is not None
    assert "pf failed on purpose" in done[0].error
    assert done[1].result is None
    assert done[1].error is not None
    assert done[1].error.startswith("its upstream pf with fusion failed")
    with pytest.raises(RuntimeError, match="pf failed on purpose"):
        execute(plan, log)


def test_capabilities_refuse_an_unknown_track() -> None:
    with pytest.raises(ValueError, match="'filtered' and/or 'smoothed'"):
        Capabilities(tracks=frozenset({"final"}))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="'filtered' and/or 'smoothed'"):
        Capabilities(tracks=frozenset())


def test_an_estimator_without_capabilities_is_refused() -> None:
    class NoCaps:
        name = "nocaps"
        options_type = _Options

        def run(self, *a: Any, **k: Any) -> None: ...

    with pytest.raises(TypeError, match="needs name, options_type, capabilities"):
        registry.register(NoCaps)


def test_no_harness_module_tests_an_estimator_name() -> None:
    # The harness knows estimators through the registry and their capabilities: a
    # comparison with a built-in name would single one out.  (``association`` values
    # name where a graph's decisions come from, an option, not an estimator test.)
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "mapfuse"
    pattern = re.compile(r"""(==|!=|\bin\b)\s*\(?\s*["'](ekf|batch|isam2|fixedlag)["']""")
    offenders = [
        f"{p.relative_to(root)}:{i}"
        for p in root.rglob("*.py")
        if p.parent.name != "estimators"
        for i, line in enumerate(p.read_text().splitlines(), 1)
        if pattern.search(line) and "association" not in line
    ]
    assert offenders == []
