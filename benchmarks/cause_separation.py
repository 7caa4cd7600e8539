"""Where the estimators' overconfidence on generated worlds comes from: the observations,
the association or the estimator.

For every seed a world is generated (``--world``, the generator's keywords; by default
a long, thin, sparse loop: a 583 m corridor, 10 walls, 45 trees, 80 m laser, where
the estimators are least consistent) and simulated once.  Each variant then runs on
that log:

========================  =========  ======  ============  ==================================
variant                   estimator  fusion  association   observations
========================  =========  ======  ============  ==================================
``ekf``                   EKF        on/off  its own       as extracted
``batch``                 batch      on/off  the EKF's     as extracted
``batch_truth``           batch      off     true ids      as extracted
``batch_truth_redrawn``   batch      off     true ids      every one redrawn (below)
``batch_truth_circles``   batch      off     true ids      circles redrawn, lines as extracted
``batch_truth_lines``     batch      off     true ids      lines redrawn, circles as extracted
``batch_lines_only``      batch      off     true ids      lines only, as extracted
``batch_circles_only``    batch      off     true ids      circles only, as extracted
``ekf_redrawn``           EKF        on/off  its own       every one redrawn
``ekf_lines``             EKF        on/off  its own       lines redrawn
``ekf_circles``           EKF        on/off  its own       circles redrawn
``ekf_exact_map``         EKF        on      its own       as extracted; the known map exact
``batch_redrawn``         batch      on/off  the EKF's     every one redrawn
``batch_circles``         batch      on/off  the EKF's     circles redrawn
``batch_lines``           batch      on/off  the EKF's     lines redrawn
``batch_exact_map``       batch      on      the EKF's     as extracted; the known map exact
========================  =========  ======  ============  ==================================

The batch variants on the EKF's association take its decisions (observation to
landmark, and the match) from the EKF run on the log as extracted, so a redrawn or
exact-map batch row differs from ``batch`` only in what it is given.

*Redrawn*: an observation of a world feature is replaced by the true feature in the
sensor frame plus noise drawn from the observation's own stated covariance (seeded by
the run's seed): a line's lateral offset and angle from the 2×2 covariance the
estimators use (:func:`mapfuse_core.models.line.line_residual_cov`), its midpoint kept
where it was along the line and its covariance turned with it; a circle from its 3×3
covariance (a draw with a radius ≤ 0 is drawn again).  Unlabelled detections are left
as they are.  A redrawn log is exactly as the estimators' models assume, so what
remains of an excess there is the estimator's (linearisation, association).  *The known
map exact*: the known features replaced by the true ones they were drawn around, stated
to ``EXACT_MAP_SIGMA`` (the known map's share of the anchor's error and covariance gone).

Output: one JSON line per seed and variant (``--out``, appended to; a seed already
there is skipped), then a JSON summary on stdout: per variant and fusion the ANEES over
the runs with its two-sided 95 % bounds, the fraction of steps inside them, the mean of
the runs' mean NEES with its interval, the anchor ANEES with its bounds, and for the
fused EKF the anchor ANEES as the anchors stood when fused (the EKF run again on the
log up to that step) and the mean NEES from its anchor on in the known map's frame and
in ``Wglobal``; and per variant, fusion setting and stretch of steps (``--stretches``),
the paired difference of the runs' mean NEES from the EKF's with its interval
(:func:`paired_stretches`).  The summary covers the seeds of ``--seeds`` found in
``--out``
(``--world`` takes any generator keywords: the dense regime of
``benchmarks/consistency_regimes.py`` is where the fused EKF is pessimistic).

    PYTHONPATH=. python benchmarks/cause_separation.py --seeds 1 9 --out /tmp/cs.jsonl
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from benchmarks.world_runs import append_rows, read_rows, truth_in_sensor, world_logs
from mapfuse.campaign.spec import parse_world_args
from mapfuse.campaign.stats import anees_bounds, anees_series, mean_interval
from mapfuse.figures import run_errors
from mapfuse.runner import run
from mapfuse_core.evaluation import nees_series, pose_errors
from mapfuse_core.geometry.features import FeatureKind, express_in
from mapfuse_core.geometry.se2 import compose, inverse, wrap_scalar
from mapfuse_core.measlog import MeasurementLog
from mapfuse_core.models.line import line_residual_cov

DEFAULT_WORLD = "shape=corridor,loop_length_m=583,walls=10,trees=45,laser_range_m=80"


def _redrawn_line(
    truth: np.ndarray, z: np.ndarray, cov: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """``truth`` moved by a lateral offset and an angle drawn from ``z``'s stated noise,
    with its reference point where ``z``'s midpoint projects and oriented like ``z``;
    and ``z``'s covariance turned with it.

    The covariance holds the along-line pseudo-variance ``L²/12`` along ``z``'s
    direction: left as it is under a redrawn angle, ``(L²/12) sin²Δθ`` of it would show
    as lateral noise to the estimators (four times the lateral variance for a 20 m wall
    turned by 0.01 rad).
    """
    c, s = math.cos(truth[2]), math.sin(truth[2])
    g = 1.0 if math.cos(z[2] - truth[2]) >= 0.0 else -1.0
    along = c * (z[0] - truth[0]) + s * (z[1] - truth[1])
    lat, ang = rng.multivariate_normal(np.zeros(2), line_residual_cov(truth, z, cov))
    theta = wrap_scalar(truth[2] + (0.0 if g > 0 else math.pi) + ang)
    params = np.array(
        [truth[0] + along * c - g * lat * s, truth[1] + along * s + g * lat * c, theta]
    )
    turn = wrap_scalar(theta - z[2])
    R = np.array(
        [[math.cos(turn), -math.sin(turn), 0.0], [math.sin(turn), math.cos(turn), 0.0], [0, 0, 1.0]]
    )
    return params, R @ cov @ R.T


def redrawn(log: MeasurementLog, seed: int, kinds: tuple[FeatureKind, ...]) -> MeasurementLog:
    """``log`` with every observation of a world feature of ``kinds`` redrawn from the
    truth with its stated covariance (see the module docstring)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 7, *[int(k) for k in kinds]]))
    params = np.array(log.feat_params, copy=True)
    covs = np.array(log.feat_cov, copy=True)
    drawn = np.zeros(log.n_features, dtype=bool)
    for j in range(log.n_features):
        kind = FeatureKind(int(log.feat_kind[j]))
        if kind not in kinds:
            continue
        truth = truth_in_sensor(log, j)
        if truth is None:
            continue
        drawn[j] = True
        cov = log.feat_cov[j]
        if kind == FeatureKind.LINE:
            params[j], covs[j] = _redrawn_line(truth, log.feat_params[j], cov, rng)
            continue
        draw = rng.multivariate_normal(truth, cov)
        while draw[2] <= 0.0:  # a radius must stay positive: redraw (truncated tail)
            draw = rng.multivariate_normal(truth, cov)
        params[j] = draw
    if log.feat_gate_cov is None:
        return dataclasses.replace(log, feat_params=params, feat_cov=covs)
    # A redrawn observation errs by its covariance alone, independently of the others.
    gate = np.array(log.feat_gate_cov, copy=True)
    gate[drawn] = covs[drawn]
    return dataclasses.replace(log, feat_params=params, feat_cov=covs, feat_gate_cov=gate)


#: Standard deviation (m and rad) the exact known map states: small, not zero, so that
#: every covariance stays invertible.
EXACT_MAP_SIGMA = 1e-4


def exact_known_map(log: MeasurementLog) -> MeasurementLog:
    """``log`` with its known map replaced by the true features it was drawn around
    (the world's, in the known map's frame), stated to ``EXACT_MAP_SIGMA``; the scans
    and everything else unchanged (the known map never reaches the sensor)."""
    assert log.world is not None
    km = log.known_map
    frame = np.zeros(3) if log.known_frame is None else log.known_frame
    rows = [int(np.flatnonzero(log.world.ids == i)[0]) for i in km.ids.tolist()]
    params = np.array(
        [
            express_in(FeatureKind(int(log.world.kinds[r])), frame, log.world.params[r])[0]
            for r in rows
        ]
    ).reshape(-1, 3)
    covs = np.broadcast_to(np.eye(3) * EXACT_MAP_SIGMA**2, (len(rows), 3, 3)).copy()
    known = dataclasses.replace(km, params=params, covs=covs)
    return dataclasses.replace(log, known_map=known)


def only(log: MeasurementLog, kind: FeatureKind) -> MeasurementLog:
    """``log`` with the observations of ``kind`` only."""
    return with_observations(log, log.feat_kind == int(kind))


def with_observations(log: MeasurementLog, keep: np.ndarray) -> MeasurementLog:
    """``log`` with the observations where the (M,) mask ``keep`` is true only."""
    return dataclasses.replace(
        log,
        feat_step=log.feat_step[keep],
        feat_kind=log.feat_kind[keep],
        feat_params=log.feat_params[keep],
        feat_cov=log.feat_cov[keep],
        feat_gate_cov=None if log.feat_gate_cov is None else log.feat_gate_cov[keep],
        feat_true_id=log.feat_true_id[keep],
        feat_n_points=log.feat_n_points[keep],
        feat_extent=log.feat_extent[keep],
    )


def _redraw(*kinds: FeatureKind) -> Callable[[MeasurementLog, int], MeasurementLog]:
    """The log of a variant whose observations of ``kinds`` are redrawn."""
    return lambda log, s: redrawn(log, s, kinds)


def _as_extracted(log: MeasurementLog, seed: int) -> MeasurementLog:
    """The log of a variant that runs on the observations as extracted."""
    return log


_ALL = (FeatureKind.LINE, FeatureKind.CIRCLE)
_BOTH = (True, False)

#: variant → (estimator, fusion settings, association, the log it runs on).
VARIANTS: dict[
    str, tuple[str, tuple[bool, ...], str, Callable[[MeasurementLog, int], MeasurementLog]]
] = {
    "ekf": ("ekf", _BOTH, "own", _as_extracted),
    "batch": ("batch", _BOTH, "ekf", _as_extracted),
    "batch_truth": ("batch", (False,), "truth", _as_extracted),
    "batch_truth_redrawn": ("batch", (False,), "truth", _redraw(*_ALL)),
    "batch_truth_circles": ("batch", (False,), "truth", _redraw(FeatureKind.CIRCLE)),
    "batch_truth_lines": ("batch", (False,), "truth", _redraw(FeatureKind.LINE)),
    "batch_lines_only": ("batch", (False,), "truth", lambda log, s: only(log, FeatureKind.LINE)),
    "batch_circles_only": (
        "batch",
        (False,),
        "truth",
        lambda log, s: only(log, FeatureKind.CIRCLE),
    ),
    "ekf_redrawn": ("ekf", _BOTH, "own", _redraw(*_ALL)),
    "ekf_lines": ("ekf", _BOTH, "own", _redraw(FeatureKind.LINE)),
    "ekf_circles": ("ekf", _BOTH, "own", _redraw(FeatureKind.CIRCLE)),
    "ekf_exact_map": ("ekf", (True,), "own", lambda log, s: exact_known_map(log)),
    "batch_redrawn": ("batch", _BOTH, "ekf", _redraw(*_ALL)),
    "batch_circles": ("batch", _BOTH, "ekf", _redraw(FeatureKind.CIRCLE)),
    "batch_lines": ("batch", _BOTH, "ekf", _redraw(FeatureKind.LINE)),
    "batch_exact_map": ("batch", (True,), "ekf", lambda log, s: exact_known_map(log)),
}


def _nees_in_known(log: MeasurementLog, r: Any) -> list[float] | None:
    """The fused EKF's NEES of its poses in the known map's frame, from the step of
    its anchor on (``None`` for other runs)."""
    details = r.result.details
    poses = getattr(details, "poses_in_known", None)
    if poses is None or log.true_poses is None:
        return None
    held = np.flatnonzero(np.all(np.isfinite(poses), axis=1))
    if held.size == 0:
        return None
    to_known = inverse(np.zeros(3) if log.known_frame is None else log.known_frame)
    truth = np.array([compose(to_known, x) for x in log.true_poses[held]])
    d = pose_errors(poses[held], truth)
    return [float(v) for v in nees_series(d.dx, details.covs_in_known[held])]


def _anchor_nees_at_fusion(log: MeasurementLog, r: Any) -> float | None:
    """NEES of the EKF's anchor as it stood when fused: the EKF run again on the log up
    to that step (the same decisions up to there), its anchor against the truth."""
    anchor = r.result.anchor
    if r.result.estimator != "ekf" or anchor is None:
        return None
    assert log.true_poses is not None
    cut = run(log.head(anchor.accepted_at_step + 1), "ekf", fusion=True).metrics.anchor
    return None if cut is None else cut.nees


def _row(log: MeasurementLog, r: Any, seed: int, variant: str, fusion: bool, t0: float) -> dict:
    assert log.true_poses is not None
    _, nees = run_errors(r)
    anchor_nees = None if r.metrics.anchor is None else r.metrics.anchor.nees
    return {
        "seed": seed,
        "variant": variant,
        "fusion": fusion,
        "nees": nees.tolist(),
        "nees_mean": float(np.nanmean(nees)),
        "anchor_nees": anchor_nees,
        "nees_known": _nees_in_known(log, r),
        "anchor_nees_at_fusion": _anchor_nees_at_fusion(log, r),
        "wall_s": round(time.perf_counter() - t0, 1),
    }


def run_seed(log: MeasurementLog, seed: int, variants: list[str]) -> list[dict]:
    """Rows of every variant on the log of one seed."""
    out = []
    ekf_runs: dict[bool, Any] = {}
    for variant in variants:
        est, fusions, association, make = VARIANTS[variant]
        vlog = make(log, seed)
        for fusion in fusions:
            t0 = time.perf_counter()
            if est == "ekf":
                r = run(vlog, "ekf", fusion=fusion)
                if variant == "ekf":
                    ekf_runs[fusion] = r.result
            elif association == "ekf":
                upstream = ekf_runs.get(fusion)
                if upstream is None:
                    upstream = run(log, "ekf", fusion=fusion).result
                    ekf_runs[fusion] = upstream
                r = run(vlog, est, fusion=fusion, upstream=upstream)
            else:
                r = run(vlog, est, fusion=fusion, association=association)
            # The variant's own log: the anchor at fusion is found again on it.
            out.append(_row(vlog, r, seed, variant, fusion, t0))
    return out


def summarise(rows: list[dict]) -> list[dict]:
    """ANEES statistics per (variant, fusion)."""
    out = []
    for variant, fusion in sorted({(r["variant"], r["fusion"]) for r in rows}):
        sel = [r for r in rows if (r["variant"], r["fusion"]) == (variant, fusion)]
        steps = min(len(r["nees"]) for r in sel)
        a = anees_series(np.array([r["nees"][:steps] for r in sel]))
        anchors = [r["anchor_nees"] for r in sel if r["anchor_nees"] is not None]
        bounds = (
            [math.nan, math.nan]
            if not anchors
            else [float(np.ravel(b)[0]) for b in anees_bounds(np.array([len(anchors)]), 3, 0.95)]
        )
        m = mean_interval([r["nees_mean"] for r in sel])
        known = [v for r in sel for v in (r.get("nees_known") or [])]
        at_fusion = [r["anchor_nees_at_fusion"] for r in sel if r.get("anchor_nees_at_fusion")]
        after = [v for r in sel if r.get("nees_known") for v in r["nees"][-len(r["nees_known"]) :]]
        out.append(
            {
                "variant": variant,
                "fusion": fusion,
                "runs": len(sel),
                "anees": round(a.overall, 3),
                "anees_bounds": [round(float(a.lower[-1]), 3), round(float(a.upper[-1]), 3)],
                "steps_inside": round(a.fraction_inside, 3),
                "steps_above": round(a.fraction_above, 3),
                "run_nees_mean": [round(m.value, 3), round(m.low, 3), round(m.high, 3)],
                "anchor_anees": round(float(np.mean(anchors)), 3) if anchors else None,
                "anchor_bounds": [round(b, 3) for b in bounds],
                "anchor_runs": len(anchors),
                # From each fused EKF run's anchor on: its poses' mean NEES in the known
                # map's frame and in Wglobal, over the same steps.
                "anchor_anees_at_fusion": round(float(np.mean(at_fusion)), 3)
                if at_fusion
                else None,
                "nees_known_after_anchor": round(float(np.mean(known)), 3) if known else None,
                "nees_global_after_anchor": round(float(np.nanmean(after)), 3) if after else None,
            }
        )
    return out


def paired_stretches(rows: list[dict], bounds: list[int]) -> list[dict]:
    """Per variant and fusion setting other than the EKF's own, and per stretch of steps
    ``bounds[i] … bounds[i+1]`` (the last runs to the end): the mean NEES of the EKF and
    of the variant over the worlds both ran, and their paired difference (the EKF's
    minus the variant's, per world) with its 95 % Student-t interval over the worlds.

    A stretch shows where along the drive a difference arises: an excess that follows
    the observations is there from the start, one of the filter's linearisation grows
    with the distance driven and jumps where a loop closes."""
    by_key = {(r["seed"], r["variant"], r["fusion"]): r for r in rows}
    out = []
    for variant, fusion in sorted({(r["variant"], r["fusion"]) for r in rows}):
        if variant == "ekf":
            continue
        seeds = sorted(s for s, v, f in by_key if (v, f) == (variant, fusion))
        seeds = [s for s in seeds if (s, "ekf", fusion) in by_key]
        if not seeds:
            continue
        pairs = [
            (by_key[(s, "ekf", fusion)]["nees"], by_key[(s, variant, fusion)]["nees"])
            for s in seeds
        ]
        steps = min(min(len(a), len(b)) for a, b in pairs)
        edges = [b for b in bounds if b < steps] + [steps]
        for lo, hi in itertools.pairwise(edges):
            e = np.array([np.nanmean(np.asarray(a[lo:hi], dtype=float)) for a, _ in pairs])
            v = np.array([np.nanmean(np.asarray(b[lo:hi], dtype=float)) for _, b in pairs])
            d = mean_interval(e - v)
            out.append(
                {
                    "variant": variant,
                    "fusion": fusion,
                    "worlds": len(seeds),
                    "steps": [lo, hi],
                    "ekf": round(float(np.mean(e)), 3),
                    "variant_nees": round(float(np.mean(v)), 3),
                    "difference": [round(d.value, 3), round(d.low, 3), round(d.high, 3)],
                }
            )
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--seeds", type=int, nargs=2, default=(1, 9), help="first, end (exclusive)")
    p.add_argument("--world", default=DEFAULT_WORLD, help="generator keywords, key=value,...")
    p.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated")
    p.add_argument("--out", required=True, help="JSON lines, appended to (resumes by seed)")
    p.add_argument(
        "--stretches",
        type=lambda v: [int(x) for x in v.split(",")],
        default=[0],
        help="first steps of the stretches the paired differences are given for, e.g. "
        "0,600,1600,2340 (default: the whole run)",
    )
    args = p.parse_args()
    world = parse_world_args(args.world)
    variants = args.variants.split(",")
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise SystemExit(f"unknown variants {unknown}; known: {', '.join(VARIANTS)}")
    rows = read_rows(args.out)
    for seed, log in world_logs(world, range(*args.seeds), {r["seed"] for r in rows}):
        new = run_seed(log, seed, variants)
        append_rows(args.out, new)
        rows += new
    wanted = set(range(*args.seeds))
    rows = [r for r in rows if r["seed"] in wanted]
    report = {
        "world": world,
        "seeds": sorted(wanted),
        "groups": summarise(rows),
        "paired": paired_stretches(rows, args.stretches),
    }
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
