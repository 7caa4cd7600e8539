"""Fuzzing of the two inputs, scenario TOML and measurement logs: every mutated input
either loads and runs (a valid result) or is refused with a one-line
:class:`ScenarioError` / :class:`MeasurementLogError` naming the file (and the key);
never another exception, never a hang (docs/results/input-validation.md).

Each case is bounded in time twice: hypothesis's ``deadline`` and a ``SIGALRM`` timer
that interrupts a case that does not return at all.  A case is a parse (milliseconds),
a simulation of at most :data:`RUN_STEPS` steps of a 5-feature world (about 0.1 s) and
an EKF run over them (about 0.1 s), measured on this project's 2-core machine; the
bound :data:`CASE_SECONDS` leaves a factor of 20 for a loaded machine.  The examples
are derandomized, so the same cases run every time.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
import signal
import tempfile
import threading
import time
import tomllib
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import timedelta
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from ekf_reference.config import EKFConfig
from ekf_reference.pipeline import run_ekf
from mapfuse_core.measlog import MeasurementLog, MeasurementLogError, load_log, save_log
from mapfuse_core.sim.scenario import ScenarioError, scenario_from_toml
from mapfuse_core.sim.simulate import simulate

#: Longest a case may take (s): see the module docstring.
CASE_SECONDS = 5.0
#: Steps simulated and run per case: a valid scenario may ask for up to the documented
#: maximum, which is a long run but not a hang; the fuzz checks the load of every
#: value and a short run of what loads.
RUN_STEPS = 12
SOURCE = "fuzz.toml"

BASE: dict[str, Any] = {
    "scenario": {"name": "fuzz", "seed": 3},
    "trajectory": {
        "start": [0.0, 0.0, 0.0],
        "steps": 30,
        "waypoints": [[0.0, 0.0], [20.0, 0.0]],
    },
    "vehicle": {"sigma_v": 0.1, "slip_sigma": [0.002, 0.002, 0.0002]},
    "laser": {"n_beams": 181, "max_range_m": 30.0, "sigma_range_m": 0.05},
    "world": {
        "segments": [
            {"id": 1, "p1": [5.0, 6.0], "p2": [15.0, 6.0]},
            {"id": 2, "p1": [25.0, -5.0], "p2": [25.0, 5.0]},
        ],
        "circles": [
            {"id": 10, "centre": [8.0, -4.0], "radius": 0.5},
            {"id": 11, "centre": [14.0, -5.0], "radius": 0.4},
            {"id": 12, "centre": [18.0, 4.0], "radius": 0.3},
        ],
    },
    "known_map": {
        "ids": [1, 2, 10, 12],
        "sigma_xy_m": 0.1,
        "sigma_r_m": 0.08,
        "sigma_theta_rad": 0.05,
    },
}

#: Replacement values: wrong types, boundaries, huge, tiny, negative and non-finite.
VALUES: list[Any] = [
    0, -1, 1, 2, 3, 1.5, -0.5, 1e-300, 1e300, -1e300, 2**63 - 1, 2**63, 2**64, 10**13,
    math.nan, math.inf, -math.inf, "x", "pi/3", "all", True, [], [0.0], [1.0, 2.0],
    [1.0, 2.0, 3.0], [[0.0, 0.0], [0.0, 0.0]], {}, {"id": 1},
]  # fmt: skip


def _paths(node: Any, prefix: tuple[Any, ...] = ()) -> Iterator[tuple[Any, ...]]:
    """Every key path of ``node`` (tables and arrays, leaves included)."""
    if isinstance(node, dict):
        for k, v in node.items():
            yield (*prefix, k)
            yield from _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield (*prefix, i)
            yield from _paths(v, (*prefix, i))


PATHS = sorted(_paths(BASE), key=repr)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return (
            "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
        )
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return "{" + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + "}"


def to_toml(doc: dict[str, Any]) -> str:
    """TOML text of ``doc``: top-level tables as sections, the rest inline."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in doc.items() if not isinstance(v, dict)]
    for k, v in doc.items():
        if isinstance(v, dict):
            lines.append(f"[{k}]")
            lines += [f"{kk} = {_toml_value(vv)}" for kk, vv in v.items()]
    return "\n".join(lines) + "\n"


def test_the_serializer_gives_back_the_base_scenario() -> None:
    assert tomllib.loads(to_toml(BASE)) == BASE
    assert scenario_from_toml(to_toml(BASE), SOURCE).steps == 30


def _mutate(doc: dict[str, Any], path: tuple[Any, ...], action: str, value: Any) -> None:
    parent: Any = doc
    for p in path[:-1]:
        in_table = isinstance(parent, dict) and p in parent
        in_array = isinstance(parent, list) and isinstance(p, int) and p < len(parent)
        if not (in_table or in_array):
            return  # an earlier mutation removed this path
        parent = parent[p]
    last = path[-1]
    present = (isinstance(parent, dict) and last in parent) or (
        isinstance(parent, list) and isinstance(last, int) and last < len(parent)
    )
    if not present:
        return
    if action == "drop":
        del parent[last]
    elif action == "replace":
        parent[last] = copy.deepcopy(value)
    elif action == "unknown_key" and isinstance(parent[last], dict):
        parent[last]["surprise"] = copy.deepcopy(value)


@contextmanager
def time_bound(seconds: float) -> Iterator[None]:
    """Fail a case that does not return within ``seconds`` (a hang).  Signals reach the
    main thread only; elsewhere hypothesis's deadline is the bound."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def expired(signum: int, frame: object) -> None:
        raise TimeoutError(f"a fuzz case ran over {seconds} s")

    old = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        signal.signal(signal.SIGALRM, old)


def test_the_time_bound_stops_a_case_that_does_not_return() -> None:
    t0 = time.perf_counter()
    with pytest.raises(TimeoutError, match=r"ran over 0\.05 s"), time_bound(0.05):
        time.sleep(5.0)
    assert time.perf_counter() - t0 < 1.0


def _short_run(log: MeasurementLog) -> None:
    """A few EKF steps (with local-map joins and the known-map match): a valid result."""
    head = log.head(RUN_STEPS)
    result = run_ekf(head, EKFConfig(local_map_steps=5))
    assert np.all(np.isfinite(result.poses)), "the EKF gave a non-finite pose"
    assert np.all(np.isfinite(result.covs)), "the EKF gave a non-finite pose covariance"


def _one_line(message: str, source: str) -> None:
    assert "\n" not in message, message
    assert message.startswith(f"{source}: ") or message.startswith(source), message


FUZZ = settings(
    max_examples=int(os.environ.get("MAPFUSE_FUZZ_EXAMPLES", "150")),
    derandomize=True,
    deadline=timedelta(seconds=CASE_SECONDS),
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
    database=None,
)

MUTATION = st.tuples(
    st.sampled_from(PATHS),
    st.sampled_from(["drop", "replace", "replace", "unknown_key"]),
    st.sampled_from(VALUES),
)


@FUZZ
@given(
    mutations=st.lists(MUTATION, min_size=1, max_size=3),
    cut=st.sampled_from([None] * 4 + list(range(0, 900, 7))),
)
def test_mutated_scenario_loads_and_runs_or_is_refused_cleanly(
    mutations: list[tuple[tuple[Any, ...], str, Any]], cut: int | None
) -> None:
    doc = tomllib.loads(to_toml(BASE))
    for path, action, value in mutations:
        _mutate(doc, path, action, value)
    text = to_toml(doc)
    _load_and_run_scenario(text if cut is None else text[:cut])


def _load_and_run_scenario(text: str) -> None:
    """Load ``text``; a clean refusal, or a short simulation whose log saves and loads
    back, and an EKF run over it."""
    with time_bound(CASE_SECONDS):
        try:
            scenario = scenario_from_toml(text, SOURCE)
            scenario = dataclasses.replace(scenario, steps=min(scenario.steps, RUN_STEPS))
            log = simulate(scenario, workers=1).log
            refused: ScenarioError | None = None
        except ScenarioError as exc:
            refused = exc
        if refused is not None:
            assert refused.file == SOURCE
            _one_line(str(refused), SOURCE)
            event(f"refused: {refused.key or 'file'}")
            return
        with tempfile.TemporaryDirectory() as folder:
            back = load_log(save_log(log, Path(folder) / "log.npz"))
        assert back.seed == log.seed
        _short_run(back)
        event("loaded and ran")


def _numeric(path: tuple[Any, ...]) -> bool:
    node: Any = BASE
    for p in path:
        node = node[p]
    return isinstance(node, int | float) and not isinstance(node, bool)


NUMERIC_PATHS = [p for p in PATHS if _numeric(p)]
#: Extreme numbers, valid ones among them (1e9 is the documented maximum magnitude).
NUMBERS: list[Any] = [
    0, 0.0, -0.0, 1e-300, 1e-150, 1e-12, 1e-9, -1e-9, 1e-3, 0.999, 1e6, 1e9, -1e9,
    1.0000001e9, 1e300, 2**31, 2**53 + 1, 2**63 - 1, 2**63, -(2**63), 10**13, math.nan,
]  # fmt: skip


@FUZZ
@given(
    mutations=st.lists(
        st.tuples(st.sampled_from(NUMERIC_PATHS), st.sampled_from(NUMBERS)),
        min_size=1,
        max_size=2,
    )
)
def test_scenario_with_extreme_numbers_loads_and_runs_or_is_refused_cleanly(
    mutations: list[tuple[tuple[Any, ...], Any]],
) -> None:
    doc = tomllib.loads(to_toml(BASE))
    for path, value in mutations:
        _mutate(doc, path, "replace", value)
    _load_and_run_scenario(to_toml(doc))


@cache
def _base_log_arrays() -> dict[str, np.ndarray]:
    """The arrays of the base scenario's log, as :func:`save_log` writes them."""
    scenario = scenario_from_toml(to_toml(BASE), SOURCE)
    with tempfile.TemporaryDirectory() as folder:
        path = save_log(simulate(scenario, workers=1).log, Path(folder) / "base.npz")
        with np.load(path, allow_pickle=False) as npz:
            return {k: npz[k] for k in npz.files}


#: Changes to one array of a log.
ARRAY_ACTIONS = [
    "drop", "as_str", "as_bool", "as_complex", "as_float32", "as_int8", "as_uint64",
    "add_dim", "flatten", "shorten", "scalar", "nan", "inf", "huge", "negative",
    "zero", "not_psd", "transpose",
]  # fmt: skip


def _change(a: np.ndarray, action: str, where: int) -> np.ndarray | None:
    """``a`` changed by ``action`` at flat index ``where`` (``None``: drop the array)."""
    if action == "drop":
        return None
    casts = {"as_str": np.str_, "as_bool": np.bool_, "as_complex": np.complex128}
    casts |= {"as_float32": np.float32, "as_int8": np.int8, "as_uint64": np.uint64}
    if action in casts:
        if a.dtype.kind == "U" and action != "as_str":
            return a  # text does not convert to numbers
        with np.errstate(all="ignore"):
            return a.astype(casts[action])
    if action == "add_dim":
        return a[None]
    if action == "flatten":
        return a.reshape(-1)
    if action == "shorten":
        return a[:-1] if a.ndim else a
    if action == "scalar":
        return a.reshape(-1)[:1].reshape(()) if a.size else np.array(0)
    if action == "transpose":
        return a.T
    if a.dtype.kind not in "fiu" or a.size == 0:
        return a
    b = a.astype(np.float64) if action in ("nan", "inf", "huge") else a.copy()
    flat = b.reshape(-1)
    i = where % flat.size
    if action == "nan":
        flat[i] = np.nan
    elif action == "inf":
        flat[i] = np.inf
    elif action == "huge":
        flat[i] = 1e300
    elif action == "negative":
        flat[i] = -abs(flat[i]) - 1
    elif action == "zero":
        flat[:] = 0
    elif action == "not_psd" and b.ndim == 3 and b.shape[1:] == (3, 3):
        b[where % b.shape[0]] = np.array([[0.01, 0, 0], [0, 0.01, 0.0032], [0, 0.0032, 0.0006]])
    return b


@FUZZ
@given(
    changes=st.lists(
        st.tuples(st.integers(0, 10**6), st.sampled_from(ARRAY_ACTIONS), st.integers(0, 10**6)),
        min_size=1,
        max_size=2,
    )
)
def test_mutated_log_loads_and_runs_or_is_refused_cleanly(
    tmp_path_factory: pytest.TempPathFactory,
    changes: list[tuple[int, str, int]],
) -> None:
    base = _base_log_arrays()
    names = sorted(base)
    arrays = dict(base)
    for pick, action, where in changes:
        name = names[pick % len(names)]
        if name not in arrays:
            continue
        changed = _change(arrays[name], action, where)
        if changed is None:
            del arrays[name]
        else:
            arrays[name] = changed
    path = tmp_path_factory.mktemp("case") / "log.npz"
    np.savez(path, **arrays)  # type: ignore[arg-type]
    with time_bound(CASE_SECONDS):
        try:
            log = load_log(path)
        except MeasurementLogError as exc:
            _one_line(str(exc), str(path))
            event("refused")
            return
        _short_run(log)
        event("loaded and ran")
