"""Map matching on hostile worlds, end to end: what every CCDA call decided, over seeds.

Each case simulates a scenario, runs the EKF with fusion (and, for clutter, the
iSAM2 graph with ``association="own"``), and records every :func:`ccda_match` call
the estimators make: the estimators' own module attribute is wrapped for the run
(whatever CCDA's internals are), so the script measures any CCDA version.

Cases (``--case``, comma-separated, default all):

* ``manhattan`` — 72 axis-aligned walls: 6 × 3 square blocks of 28 m every 40 m
  (12 m streets); the known map holds the 48 walls of the four middle columns.
  Each seed drives a different route: 60 m along an inner street, a turn, 40 m
  along the cross street.
* ``trees`` — 72 identical trees (r 0.8 m) on a 12 × 6 grid, 10 m apart; the known
  map holds the 48 of the eight middle columns.  Routes as above, in the aisles.
* ``clutter`` — loop600 with 5 spurious features per scan (half circles, half
  lines) and 10 % of the real observations moved by 2–10 m
  (:mod:`mapfuse_core.sim.clutter`); the EKF and the graph with ``own`` association.
* ``shifts`` — loop600 with its world, route and known map moved by 0, 10³, 10⁶ and
  10⁷ m along x and y: every CCDA call must decide the same and pair the same
  features, and the anchor must move with the world.
* ``worlds`` — a generated 600 m world per seed (the generator's defaults,
  :mod:`mapfuse_core.sim.worldgen`, simulated with the seed, as ``mapfuse montecarlo
  --world-per-run ''``): late matches on a map that drifted unfused.  Besides the CCDA
  record (whose columns judge every match CCDA accepted, those the EKF then refused
  included), every match the EKF fused is judged (the anchor it kept, and those its
  anchor watch undid), with the matches refused by its joint tests before fusion and
  the anchors undone after it (the second table).

A call is judged against the true anchor (:func:`mapfuse_core.evaluation.anchor_truth`
with the log's ``known_frame``): an accepted match is *wrong* when its anchor is more
than 1 m or 0.05 rad off.  Its pairings are judged by true ids (the world id of each
matched feature's first observation against the known feature's id).  After the
match, every observation merged with a known feature of another id (clutter
included, true id −1) is a *wrong known observation*, unless it lies where that
feature truly is (within 1 m, lines also 0.05 rad): a spurious detection on top of a
real feature is counted as *coincident* instead.

    python benchmarks/matching_mc.py --seeds 20 --case manhattan,trees,clutter,shifts
    python benchmarks/matching_mc.py --seeds 40 --case worlds    # about 1 min a seed
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from types import FrameType
from typing import Any

import numpy as np

import mapfuse_core.matching.ccda as ccda_pkg
from ekf_reference import EKFConfig, run_ekf
from ekf_reference.anchor_watch import AnchorWatchParams
from mapfuse.runner import simulate as simulate_run
from mapfuse_core.estimate import EstimatorResult
from mapfuse_core.evaluation import anchor_truth
from mapfuse_core.geometry.features import FeatureKind, transform_feature
from mapfuse_core.geometry.se2 import compose, inverse, wrap_angle
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog
from mapfuse_core.sim.clutter import ClutterParams
from mapfuse_core.sim.scenario import Scenario, load_scenario
from mapfuse_core.sim.simulate import simulate
from mapfuse_core.sim.world import CircleObstacle, WallSegment, World
from mapfuse_core.sim.worldgen import WorldParams, generate_scenario

CASES = ("manhattan", "trees", "clutter", "shifts", "worlds")
#: Default steps per case (a seed takes a few seconds; a world, its whole drive).
STEPS = {"manhattan": 420, "trees": 400, "clutter": 160, "shifts": 200, "worlds": 2401}
#: ``matching.reasons`` keys of a match the EKF refused before fusing it.
REFUSED_BEFORE_FUSION = ("jointly inconsistent", "a pairing inconsistent with the others")
#: ``matching.reasons`` key of an anchor the EKF undid after fusing it.
UNDONE_AFTER_FUSION = "anchor contradicted"
SHIFTS_M = (0.0, 1e3, 1e6, 1e7)
#: An accepted anchor this far from the truth is a wrong match.
WRONG_XY_M = 1.0
WRONG_THETA_RAD = 0.05
#: Keys of :func:`judge_fused`, summed over the seeds of a case that has them.
FUSED_KEYS = (
    "fused_right",
    "fused_right_undone",
    "fused_wrong_kept",
    "fused_wrong_undone",
    "refused_before_fusion",
    "undone_after_fusion",
)
CLUTTER = ClutterParams(features_per_scan=5, circle_fraction=0.5, outlier_fraction=0.1)


# --------------------------------------------------------------------------- recording


@dataclass(frozen=True)
class Call:
    """One :func:`ccda_match` call made by an estimator."""

    reason: str
    """The result's reason."""
    accepted: bool
    """Whether the match was accepted."""
    seconds: float
    """Wall time of the call."""
    cpu_seconds: float
    """CPU time of this process during the call (the machine's load does not count)."""
    search_work: int
    """Work units of the clique search (``CCDAResult.search_work``, 0 if absent)."""
    n_hypotheses: int
    """Hypotheses fitted (``CCDAResult.n_hypotheses``, 0 if absent)."""
    n_a: int
    """Features of the estimator's map."""
    pairings: tuple[tuple[int, int], ...]
    """The result's pairings as (true id of the map feature or −2 if unknown, known id)."""
    x_Wknown_Wglobal: tuple[float, float, float] | None
    """The anchor the call implies, ``None`` when no transform was fitted or the
    caller's frame is unknown."""


def _caller_context(
    frame: FrameType | None, map_a: KnownMapArrays
) -> tuple[list[int] | None, np.ndarray | None]:
    """What the estimator that called CCDA knows about ``map_a``: the true world id of
    each row, and the pose of ``Wglobal`` in ``map_a``'s frame.

    The EKF's global map is expressed in the frame of its last local map (its
    ``BASE`` element is ``x^Wlocal_Wglobal``; the rows are its elements); the graph's
    landmarks are in ``Wglobal`` (the rows are ``feats``, landmarks whose first
    observation holds the true id).  ``(None, None)`` for any other caller."""
    if frame is None:
        return None, None
    loc = frame.f_locals
    obj: Any = loc.get("self")
    try:
        if hasattr(obj, "global_map"):
            g = obj.global_map
            els = g.elements
            base = [i for i, e in enumerate(els) if e.role.name == "BASE"]
            x = np.asarray(g.mean[base[0]], dtype=float) if base else np.zeros(3)
            return [int(els[int(i)].true_id) for i in map_a.ids], x
        if hasattr(obj, "landmarks") and "feats" in loc:
            tid = obj.log.feat_true_id
            return [int(tid[obj.landmarks[i].first_obs]) for i in loc["feats"]], np.zeros(3)
    except (AttributeError, IndexError, TypeError, KeyError):
        pass
    return None, None


@contextmanager
def recording(calls: list[Call]) -> Iterator[None]:
    """Record every call of ``ccda_match`` made through a loaded module's attribute."""
    original = ccda_pkg.ccda_match

    def wrapper(map_a: KnownMapArrays, map_b: KnownMapArrays, *args: Any, **kw: Any) -> Any:
        t0, c0 = time.perf_counter(), time.process_time()
        res = original(map_a, map_b, *args, **kw)
        dt, cpu = time.perf_counter() - t0, time.process_time() - c0
        ids, x_a_global = _caller_context(sys._getframe(1), map_a)
        pairs = tuple(
            (-2 if ids is None else ids[ia], int(map_b.ids[jb])) for ia, jb in res.pairings
        )
        x = np.asarray(res.x_A_B, dtype=float)
        anchor = None
        if x_a_global is not None and np.all(np.isfinite(x)):
            # x^Wknown_Wglobal = ⊖x^A_Wknown ⊕ x^A_Wglobal
            est = compose(inverse(x), x_a_global)
            # The EKF matches the known map in a frame centred on its features
            # (ekf_reference/known_frame.py): take the pose back to the map's frame.
            centre = getattr(sys._getframe(1).f_locals.get("self"), "known_centre", None)
            if centre is not None:
                est[:2] += np.asarray(centre, dtype=float)
            anchor = tuple(float(v) for v in est)
        calls.append(
            Call(
                reason=str(res.reason),
                accepted=bool(res.accepted),
                seconds=dt,
                cpu_seconds=cpu,
                search_work=int(getattr(res, "search_work", 0)),
                n_hypotheses=int(getattr(res, "n_hypotheses", 0)),
                n_a=len(map_a),
                pairings=pairs,
                x_Wknown_Wglobal=anchor,  # type: ignore[arg-type]
            )
        )
        return res

    patched = [
        m
        for m in list(sys.modules.values())
        if m is not None and getattr(m, "ccda_match", None) is original and m is not ccda_pkg
    ]
    for m in patched:
        m.ccda_match = wrapper  # type: ignore[attr-defined]
    try:
        yield
    finally:
        for m in patched:
            m.ccda_match = original  # type: ignore[attr-defined]


# --------------------------------------------------------------------------- worlds


def _route(
    rng: np.random.Generator,
    streets_y: list[float],
    cross_x: list[float],
    x_range: tuple[float, float],
) -> np.ndarray:
    """Waypoints: 60 m along a street (starting inside ``x_range``), a rounded turn at
    cross street ``X``, 40 m along it."""
    y = float(rng.choice(streets_y))
    d = 1.0 if rng.random() < 0.5 else -1.0
    X = float(rng.choice([x for x in cross_x if x_range[0] <= x - d * 60.0 <= x_range[1]]))
    turn = 1.0 if rng.random() < 0.5 else -1.0
    r = 6.0
    pts = [(X - d * 60.0, y), (X - d * 30.0, y), (X - d * r, y)]
    for a in np.linspace(0.0, math.pi / 2, 5)[1:]:
        pts.append((X - d * r + d * r * math.sin(a), y + turn * r * (1.0 - math.cos(a))))
    pts += [(X, y + turn * 20.0), (X, y + turn * 40.0)]
    return np.array(pts)


def _scenario(
    name: str, seed: int, world: World, known: list[int], waypoints: np.ndarray, steps: int
) -> Scenario:
    """loop600's vehicle, laser and known-map noise on another world and route."""
    base = load_scenario("loop600")
    start = waypoints[0]
    heading = math.atan2(*(waypoints[1] - waypoints[0])[::-1])
    s = np.array([start[0], start[1], heading])
    wps = np.array(waypoints, dtype=float)
    for a in (s, wps):
        a.setflags(write=False)
    return dataclasses.replace(
        base,
        name=name,
        description=f"{name} (benchmarks/matching_mc.py)",
        source=f"<{name} seed {seed}>",
        seed=seed,
        world=world,
        start=s,
        steps=steps,
        waypoints=wps,
        controls=(),
        known_map=dataclasses.replace(base.known_map, world_ids=tuple(sorted(known))),
    )


def manhattan(seed: int, steps: int) -> Scenario:
    """6 × 3 blocks of 28 m every 40 m, 72 walls; known: the four middle columns."""
    walls: list[WallSegment] = []
    known: list[int] = []
    for ix in range(6):
        for iy in range(3):
            x0, y0, s = 40.0 * ix, 40.0 * iy, 28.0
            corners = [(x0, y0), (x0 + s, y0), (x0 + s, y0 + s), (x0, y0 + s)]
            for c in range(4):
                wid = len(walls) + 1
                walls.append(WallSegment(wid, corners[c], corners[(c + 1) % 4]))
                if 1 <= ix <= 4:
                    known.append(wid)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x6D616E]))
    wps = _route(rng, [34.0, 74.0], [34.0 + 40.0 * i for i in range(5)], (-6.0, 234.0))
    return _scenario("manhattan", seed, World(tuple(walls), ()), known, wps, steps)


def trees(seed: int, steps: int) -> Scenario:
    """12 × 6 identical trees 10 m apart; known: the eight middle columns."""
    circles: list[CircleObstacle] = []
    known: list[int] = []
    for ix in range(12):
        for iy in range(6):
            cid = 1001 + len(circles)
            circles.append(CircleObstacle(cid, (10.0 * ix, 10.0 * iy), 0.8))
            if 2 <= ix <= 9:
                known.append(cid)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x747265]))
    wps = _route(rng, [15.0, 25.0, 35.0], [5.0 + 10.0 * i for i in range(11)], (0.0, 110.0))
    return _scenario("trees", seed, World((), tuple(circles)), known, wps, steps)


def shifted_loop600(shift_m: float, steps: int) -> Scenario:
    """loop600 with its world, route and known map moved by ``(shift, shift)``."""
    base = load_scenario("loop600")
    d = (shift_m, shift_m)

    def mv(p: tuple[float, float]) -> tuple[float, float]:
        return (p[0] + d[0], p[1] + d[1])

    world = World(
        tuple(WallSegment(s.id, mv(s.p1), mv(s.p2)) for s in base.world.segments),
        tuple(CircleObstacle(c.id, mv(c.centre), c.radius) for c in base.world.circles),
    )
    start = base.start + np.array([d[0], d[1], 0.0])
    wps = base.waypoints + np.array(d)
    for a in (start, wps):
        a.setflags(write=False)
    return dataclasses.replace(base, world=world, start=start, waypoints=wps, steps=steps)


# --------------------------------------------------------------------------- judging


def _anchor_error(x: tuple[float, float, float], truth: np.ndarray) -> tuple[float, float]:
    return math.hypot(x[0] - truth[0], x[1] - truth[1]), abs(float(wrap_angle(x[2] - truth[2])))


def _coincides(log: MeasurementLog, j: int, known_id: int) -> bool:
    """Whether observation ``j``, placed in the world with the true pose, lies where
    world feature ``known_id`` is (circles: centres within 1 m; lines: angle within
    0.05 rad modulo π and the observed midpoint within 1 m of the wall's line): then
    it is physically that feature (a spurious detection on top of it), not a wrong
    pairing that any test could refuse."""
    assert log.true_poses is not None
    assert log.world is not None
    rows = np.nonzero(log.world.ids == known_id)[0]
    if rows.size == 0:
        return False
    w = log.world.params[rows[0]]
    kind = FeatureKind(int(log.feat_kind[j]))
    f = transform_feature(kind, log.true_poses[int(log.feat_step[j])], log.feat_params[j])[0]
    if kind == FeatureKind.CIRCLE:
        return math.hypot(f[0] - w[0], f[1] - w[1]) <= WRONG_XY_M
    d_th = abs(float(wrap_angle(2.0 * (f[2] - w[2])))) / 2.0
    lateral = abs(-math.sin(w[2]) * (f[0] - w[0]) + math.cos(w[2]) * (f[1] - w[1]))
    return d_th <= WRONG_THETA_RAD and lateral <= WRONG_XY_M


def judge(calls: list[Call], log: MeasurementLog, result: EstimatorResult | str) -> dict[str, Any]:
    """One run's CCDA record: outcome, calls by reason, work, time, wrong pairings.

    ``result`` is the estimator's result, or the one-line error that ended the run
    (then the outcome is ``"error"`` and the error is reported)."""
    assert log.true_poses is not None
    truth = anchor_truth(log.true_poses, log.known_frame)
    by: Counter[str] = Counter()
    suspects: list[int] = []  # known ids paired with a landmark of another first id
    outcome = "none:no call"
    for c in calls:
        key = c.reason
        if c.accepted:
            key = "accepted, frame unknown"
            if c.x_Wknown_Wglobal is not None:
                e_xy, e_th = _anchor_error(c.x_Wknown_Wglobal, truth)
                key = "wrong" if e_xy > WRONG_XY_M or e_th > WRONG_THETA_RAD else "right"
            suspects.extend(k for t, k in c.pairings if t != k)
            outcome = key if outcome.startswith("none") else outcome
        elif outcome.startswith("none"):
            outcome = f"none:{c.reason}"
        by[key] += 1
    error = result if isinstance(result, str) else None
    wrong_obs, coincident, anchor = 0, 0, None
    if not isinstance(result, str):
        dec = result.decisions
        kn = np.asarray(dec.obs_known_id if dec is not None else [], dtype=np.int64)
        tid = np.asarray(log.feat_true_id[: kn.size], dtype=np.int64)
        bad = np.nonzero((kn >= 0) & (kn != tid))[0]
        near = [_coincides(log, int(j), int(kn[j])) for j in bad]
        coincident = int(sum(near))
        wrong_obs = len(near) - coincident
        anchor = None if result.anchor is None else result.anchor.x_Wknown_Wglobal
    # A landmark's first observation can be clutter (a spurious detection where a real
    # feature is): a pairing with known feature k is wrong unless more than half of all
    # the log's observations associated with k (those of no feature included) are of k.
    wrong_pairings = 0
    for k in suspects:
        if isinstance(result, str) or result.decisions is None:
            wrong_pairings += 1
            continue
        kn = np.asarray(result.decisions.obs_known_id, dtype=np.int64)
        ids = np.asarray(log.feat_true_id[: kn.size], dtype=np.int64)[kn == k]
        wrong_pairings += int(ids.size == 0 or np.count_nonzero(ids == k) * 2 <= ids.size)
    return {
        "outcome": "error" if error else outcome,
        "error": error,
        "calls": len(calls),
        "by_reason": dict(by),
        "wrong_pairings": wrong_pairings,
        "first_observation_mismatches": len(suspects) - wrong_pairings,
        "wrong_known_obs": wrong_obs,
        "coincident_known_obs": coincident,
        "max_call_s": max((c.seconds for c in calls), default=0.0),
        "max_call_cpu_s": max((c.cpu_seconds for c in calls), default=0.0),
        "search_work": sum(c.search_work for c in calls),
        "max_call_work": max((c.search_work for c in calls), default=0),
        "n_hypotheses": sum(c.n_hypotheses for c in calls),
        "anchor_error": None if anchor is None else list(_anchor_error(tuple(anchor), truth)),
    }


def judge_fused(log: MeasurementLog, result: EstimatorResult | str) -> dict[str, Any]:
    """Every match the EKF fused, judged: the anchor it kept and those its anchor watch
    undid (``EKFDetails.anchors_undone``), each wrong when more than 1 m or 0.05 rad
    off or when one of its pairings is (by label); and the matches its joint tests
    refused before fusion, the anchors undone after it."""
    out: dict[str, Any] = {"fused_right": 0, "fused_wrong_kept": 0, "fused_wrong_undone": 0}
    out.update(fused_right_undone=0, refused_before_fusion=0, undone_after_fusion=0)
    if isinstance(result, str):
        return out
    assert log.true_poses is not None
    truth = anchor_truth(log.true_poses, log.known_frame)
    fused: list[tuple[Any, tuple[tuple[int, int], ...], str]] = [
        (u.x_Wknown_Wglobal, u.pairings, "undone")
        for u in getattr(result.details, "anchors_undone", ())
    ]
    if result.anchor is not None:
        fused.append((result.anchor.x_Wknown_Wglobal, result.anchor.pairings, "kept"))
    for x, pairings, fate in fused:
        e_xy, e_th = _anchor_error(tuple(float(v) for v in x), truth)  # type: ignore[arg-type]
        wrong = e_xy > WRONG_XY_M or e_th > WRONG_THETA_RAD or any(t != k for t, k in pairings)
        if wrong:
            out["fused_wrong_kept" if fate == "kept" else "fused_wrong_undone"] += 1
        else:
            out["fused_right" if fate == "kept" else "fused_right_undone"] += 1
    reasons = {} if result.matching is None else dict(result.matching.reasons)
    out["refused_before_fusion"] = sum(int(reasons.get(k, 0)) for k in REFUSED_BEFORE_FUSION)
    out["undone_after_fusion"] = int(reasons.get(UNDONE_AFTER_FUSION, 0))
    return out


def _guarded(fn: Callable[[], EstimatorResult]) -> EstimatorResult | str:
    """``fn()``, or the one-line error that ended it: a run that fails is counted."""
    try:
        return fn()
    except Exception as e:  # every failure is reported, none hidden
        return f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"[:200]


_WATCHED = EKFConfig(anchor_watch=AnchorWatchParams())
"""The EKF with its joint tests before fusion and the anchor watch after it."""


def _run_ekf(log: MeasurementLog) -> tuple[list[Call], EstimatorResult | str]:
    calls: list[Call] = []
    with recording(calls):
        res = _guarded(lambda: run_ekf(log, _WATCHED, fusion=True))
    return calls, res


def _run_graph_own(log: MeasurementLog) -> tuple[list[Call], EstimatorResult | str]:
    import mapfuse_graph.own_association  # noqa: F401  (loads gtsam; patched below)
    from mapfuse.execution import estimate

    calls: list[Call] = []
    with recording(calls):
        # No planning: the graph decides alone, no EKF runs first (its calls would be
        # recorded as the graph's).
        res = _guarded(lambda: estimate(log, "isam2", fusion=True, association="own"))
    return calls, res


# --------------------------------------------------------------------------- cases


def run_case(case: str, seed: int, steps: int | None = None) -> dict[str, Any]:
    """One seed of ``case``: per estimator, :func:`judge`'s record (shifts: invariance)."""
    n = STEPS[case] if steps is None else steps
    if case in ("manhattan", "trees"):
        sc = manhattan(seed, n) if case == "manhattan" else trees(seed, n)
        log = simulate(sc, seed=seed, workers=1).log
        calls, res = _run_ekf(log)
        return {"seed": seed, "ekf": judge(calls, log, res)}
    if case == "clutter":
        sc = dataclasses.replace(load_scenario("loop600"), steps=n)
        log = simulate(sc, seed=seed, workers=1, clutter=CLUTTER).log
        row: dict[str, Any] = {"seed": seed}
        calls, res = _run_ekf(log)
        row["ekf"] = judge(calls, log, res)
        calls, res = _run_graph_own(log)
        row["graph_own"] = judge(calls, log, res)
        return row
    if case == "shifts":
        return _shift_row(seed, n)
    if case == "worlds":
        sc = generate_scenario(WorldParams(seed=seed), base=load_scenario("loop600"))
        log = simulate_run(sc, seed, steps=min(n, sc.steps), workers=1)
        calls, res = _run_ekf(log)
        return {"seed": seed, "ekf": {**judge(calls, log, res), **judge_fused(log, res)}}
    raise ValueError(f"unknown case {case!r}; choose from {', '.join(CASES)}")


def _moved_diff(x: Any, ref: Any, shift: float) -> tuple[float, float]:
    """``x`` against ``ref`` moved by ``(shift, shift)``: position difference relative
    to ``max(1, |shift|)``, and the angle difference (rad)."""
    d = np.asarray(x[:2], dtype=float) - (np.asarray(ref[:2], dtype=float) + shift)
    rel = float(np.hypot(*d)) / max(1.0, math.hypot(shift, shift))
    return rel, abs(float(wrap_angle(float(x[2]) - float(ref[2]))))


def _shift_row(seed: int, steps: int) -> dict[str, Any]:
    """Every shift against shift 0: the same CCDA decisions and pairings call by call,
    each call's transform and the EKF's final anchor moved with the world (largest
    relative position difference ``|Δ| / max(1, |shift|)`` and angle difference)."""
    ref_calls: list[Call] = []
    ref_anchor: np.ndarray | None = None
    out: dict[str, Any] = {"seed": seed, "same_decisions": True, "errors": {}}
    out.update(max_rel_diff=0.0, max_angle_diff_rad=0.0, max_ccda_rel_diff=0.0)
    for shift in SHIFTS_M:
        log = simulate(shifted_loop600(shift, steps), seed=seed, workers=1).log
        calls, res = _run_ekf(log)
        anchor = None
        if isinstance(res, str):
            out["errors"][f"{shift:g}"] = res
        elif res.anchor is not None:
            anchor = np.asarray(res.anchor.x_Wknown_Wglobal)
            assert log.true_poses is not None
            e = _anchor_error(tuple(anchor), anchor_truth(log.true_poses, log.known_frame))
            out.setdefault("anchor_error", {})[f"{shift:g}"] = list(e)
        if shift == 0.0:
            out["ekf"] = judge(calls, log, res)
            ref_calls, ref_anchor = calls, anchor
            continue
        same = [(c.reason, c.pairings) for c in calls] == [
            (c.reason, c.pairings) for c in ref_calls
        ]
        out["same_decisions"] = out["same_decisions"] and same
        for c, r in zip(calls, ref_calls, strict=False):
            if c.x_Wknown_Wglobal is not None and r.x_Wknown_Wglobal is not None:
                rel, _ = _moved_diff(c.x_Wknown_Wglobal, r.x_Wknown_Wglobal, shift)
                out["max_ccda_rel_diff"] = max(out["max_ccda_rel_diff"], rel)
        if anchor is not None and ref_anchor is not None:
            rel, da = _moved_diff(anchor, ref_anchor, shift)
            out["max_rel_diff"] = max(out["max_rel_diff"], rel)
            out["max_angle_diff_rad"] = max(out["max_angle_diff_rad"], da)
        elif (anchor is None) != (ref_anchor is None):
            out["same_anchor_presence"] = False
    return out


def summarise(case: str, rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per estimator: run outcomes, calls by reason, wrong pairings, time and work."""
    out: dict[str, Any] = {"case": case, "seeds": len(rows)}
    for est in ("ekf", "graph_own"):
        recs = [r[est] for r in rows if est in r]
        if not recs:
            continue
        outcomes: Counter[str] = Counter(r["outcome"] for r in recs)
        reasons: Counter[str] = Counter()
        for r in recs:
            reasons.update(r["by_reason"])
        out[est] = {
            "runs": dict(sorted(outcomes.items())),
            "calls": dict(sorted(reasons.items())),
            "wrong_pairings_accepted": sum(r["wrong_pairings"] for r in recs),
            "wrong_known_obs": sum(r["wrong_known_obs"] for r in recs),
            "coincident_known_obs": sum(r["coincident_known_obs"] for r in recs),
            "max_call_s": round(max(r["max_call_s"] for r in recs), 3),
            "max_call_cpu_s": round(max(r.get("max_call_cpu_s", math.nan) for r in recs), 3),
            "search_work": sum(r["search_work"] for r in recs),
            "max_call_work": max(r["max_call_work"] for r in recs),
            "n_hypotheses": sum(r["n_hypotheses"] for r in recs),
            "final_anchor_wrong": sum(
                r["anchor_error"] is not None
                and (r["anchor_error"][0] > WRONG_XY_M or r["anchor_error"][1] > WRONG_THETA_RAD)
                for r in recs
            ),
            "errors": sum(r["error"] is not None for r in recs),
            **{key: sum(r[key] for r in recs) for key in FUSED_KEYS if all(key in r for r in recs)},
            "wrong_seeds": [
                r["seed"] for r, x in zip(rows, recs, strict=False) if x["wrong_pairings"]
            ],
        }
    if case == "shifts":
        out["same_decisions"] = all(r["same_decisions"] for r in rows)
        out["same_anchor_presence"] = all(r.get("same_anchor_presence", True) for r in rows)
        for key in ("max_rel_diff", "max_angle_diff_rad", "max_ccda_rel_diff"):
            out[key] = max(r[key] for r in rows)
        errors: Counter[str] = Counter()
        for r in rows:
            errors.update(r["errors"].keys())
        out["ekf_errors_by_shift"] = dict(errors)
        worst: dict[str, list[float]] = {}
        for r in rows:
            for k, (e_xy, e_th) in r.get("anchor_error", {}).items():
                w = worst.setdefault(k, [0.0, 0.0])
                worst[k] = [max(w[0], e_xy), max(w[1], e_th)]
        out["max_final_anchor_error_by_shift"] = worst
        out["ekf_error_examples"] = sorted({e for r in rows for e in r["errors"].values()})[:3]
    return out


def markdown(report: dict[str, Any]) -> str:
    """The summaries of a report (this script's JSON) as a markdown table."""
    head = (
        "| case | estimator | seeds | runs: right / wrong / none (last refusal) | "
        "wrong pairings | wrong known obs (coincident) | CCDA calls by outcome | "
        "max call s, wall (CPU) | max call work | total work | hypotheses |"
    )
    lines = [head, "|" + "---|" * 11]
    for case, summ in report["cases"].items():
        for est in ("ekf", "graph_own"):
            if est not in summ:
                continue
            e = summ[est]
            runs = e["runs"]
            none = {k.split(":", 1)[1]: v for k, v in runs.items() if k.startswith("none")}
            none_txt = ", ".join(f"{v} {k}" for k, v in sorted(none.items())) or "0"
            errors = f", {e['errors']} errors" if e.get("errors") else ""
            calls = ", ".join(f"{v} {k}" for k, v in sorted(e["calls"].items()))
            lines.append(
                f"| {case} | {est} | {summ['seeds']} | {runs.get('right', 0)} / "
                f"{runs.get('wrong', 0)} / {none_txt}{errors} | {e['wrong_pairings_accepted']} | "
                f"{e['wrong_known_obs']} ({e.get('coincident_known_obs', 0)}) | {calls} | "
                f"{e['max_call_s']} ({e.get('max_call_cpu_s', '–')}) | "
                f"{e['max_call_work']:,} | {e['search_work']:,} | {e['n_hypotheses']} |"
            )
    fused = [
        (case, summ)
        for case, summ in report["cases"].items()
        if all(k in summ.get("ekf", {}) for k in FUSED_KEYS)
    ]
    if fused:
        lines += [
            "",
            "| case | seeds | matches fused: right kept / right undone / wrong undone / "
            "wrong kept | refused before fusion (joint tests) | anchors undone after fusion |",
            "|" + "---|" * 5,
        ]
        for case, summ in fused:
            e = summ["ekf"]
            lines.append(
                f"| {case} | {summ['seeds']} | {e['fused_right']} / {e['fused_right_undone']} / "
                f"{e['fused_wrong_undone']} / {e['fused_wrong_kept']} | "
                f"{e['refused_before_fusion']} | {e['undone_after_fusion']} |"
            )
    return "\n".join(lines)


def _parse_seeds(text: str) -> list[int]:
    """``20`` (seeds 0–19), ``5-9`` or ``0,3,7``."""
    if text.strip().isdigit() and "," not in text:
        return list(range(int(text)))
    seeds: list[int] = []
    for part in text.split(","):
        lo, dash, hi = part.partition("-")
        if not lo.strip().isdigit() or (dash and not hi.strip().isdigit()):
            raise argparse.ArgumentTypeError(
                f"seeds must look like 20, 0-19 or 0,3,7; got {text!r}"
            )
        seeds += list(range(int(lo), int(hi) + 1)) if dash else [int(lo)]
    return seeds


def main(argv: list[str] | None = None, echo: Callable[[str], None] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", type=_parse_seeds, default=_parse_seeds("20"))
    ap.add_argument("--case", default=",".join(CASES), help="comma-separated (default: all)")
    ap.add_argument("--steps", type=int, help="steps per run (default: per case, STEPS)")
    ap.add_argument("--detail", action="store_true", help="also print every seed's row")
    ap.add_argument("--rows", help="append every seed's row to this file (JSON lines)")
    ap.add_argument(
        "--markdown", nargs="+", metavar="REPORT", help="print these JSON reports as a table"
    )
    args = ap.parse_args(argv)
    if args.markdown:
        merged: dict[str, Any] = {"cases": {}}
        for path in args.markdown:
            with open(path) as f:
                merged["cases"].update(json.load(f)["cases"])
        print(markdown(merged))
        return
    cases = [c.strip() for c in args.case.split(",") if c.strip()]
    bad = [c for c in cases if c not in CASES]
    if bad or not cases:
        raise SystemExit(
            f"--case: unknown {', '.join(bad) or 'empty'}; choose from {', '.join(CASES)}"
        )
    if args.steps is not None and args.steps < 2:
        raise SystemExit(f"--steps must be >= 2, got {args.steps}")
    say = echo or (lambda s: print(s, file=sys.stderr, flush=True))
    report: dict[str, Any] = {"seeds": args.seeds, "steps": args.steps or STEPS, "cases": {}}
    for case in cases:
        rows = []
        for seed in args.seeds:
            t0 = time.perf_counter()
            rows.append(run_case(case, seed, args.steps))
            if args.rows:
                with open(args.rows, "a") as f:
                    f.write(json.dumps({"case": case, **rows[-1]}) + "\n")
            say(f"{case} seed {seed}: {time.perf_counter() - t0:.1f} s")
        report["cases"][case] = summarise(case, rows)
        if args.detail:
            report["cases"][case]["rows"] = rows
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
