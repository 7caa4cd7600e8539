"""Whitened errors of the extractor's circles and lines, by range and size, against the truth.

Every extracted feature labelled with a world id is compared with the true feature in
the sensor frame, and each component of the error is divided by the standard deviation
the extractor states for it:

* circles, in the line-of-sight frame of the true centre: ``along`` (positive: centre
  too far), ``across`` (counter-clockwise) and ``radius``;
* lines, as the estimators use them (:func:`mapfuse_core.models.line.line_residual`
  with the true line as target): ``lateral`` (offset of the observed segment's
  midpoint from the true line) and ``angle``.

Per bin and component the output gives the number of samples, the mean with its 95 %
interval (± 1.96 s/√n) and the variance with its 95 % interval (± 1.96 √((m₄ − s⁴)/n),
which does not assume normal errors), and the mean NEES per degree of freedom of the
full covariance.  A consistent extractor has means of 0 and variances of 1.

Scans come from two sources (``--source``):

* ``single``: controlled scenes.  Circles: three trees per scan (bearings −60°, 0°,
  +60°; radius uniform in 0.2–1 m, centre 1.2 r + 1 m to 20 r away, log-uniform),
  half of the scans with a wall 3–20 m behind each tree (a silhouette against a farther
  return), the others against empty space.  Lines: one wall per scan, length 3–40 m,
  its midpoint 2–78 m away (log-uniform) at an incidence of 0–85°.  A small random
  heading puts the beams at a random phase.
* ``worlds``: generated worlds (``--world``, the generator's keywords; by default the
  long, sparse loop: 583 m, 10 walls, 45 trees, 80 m laser), scanned from
  the true poses of a simulated drive, every ``--stride``-th step.

Bins: circles by range (distance to the true centre) × true radius, and by range in
radii (the silhouette's width, which decides detection: trunks are tried as circles up to
about 17 radii, ``min_circle_snr``); lines by range
(distance to the observed midpoint) × incidence (between that line of sight and the
wall's normal), and by range × observed length.  Seeded; prints one JSON document.

    PYTHONPATH=. python benchmarks/extraction_whitened.py --source single --scans 12000
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from mapfuse.campaign.spec import parse_world_args
from mapfuse_core.geometry.features import FeatureKind, express_in
from mapfuse_core.models.line import line_residual, line_residual_cov
from mapfuse_core.perception.extraction import ExtractionParams, extract_features
from mapfuse_core.sim.laser import LaserParams, simulate_scan
from mapfuse_core.sim.scenario import load_scenario
from mapfuse_core.sim.vehicle import simulate_motion
from mapfuse_core.sim.world import CircleObstacle, WallSegment, World
from mapfuse_core.sim.worldgen import WorldParams, generate_scenario

DEFAULT_WORLD = "shape=loop,loop_length_m=583,walls=10,trees=45,laser_range_m=80"

CIRCLE_DOFS = ("along", "across", "radius")
LINE_DOFS = ("lateral", "angle")
CIRCLE_RANGE_BINS = (0.0, 4.0, 7.0, 11.0, 16.0, 30.0)
CIRCLE_RADIUS_BINS = (0.2, 0.4, 0.6, 0.8, 1.0)
CIRCLE_RADII_BINS = (0.0, 6.0, 10.0, 13.0, 15.0, 17.0, 30.0)
LINE_RANGE_BINS = (0.0, 10.0, 20.0, 40.0, 80.0)
LINE_INCIDENCE_BINS_DEG = (0.0, 30.0, 55.0, 70.0, 90.0)
LINE_LENGTH_BINS = (2.5, 6.0, 12.0, 25.0, 80.0)


@dataclass(frozen=True)
class Sample:
    """One scored feature."""

    kind: FeatureKind
    """Line or circle."""
    rng_m: float
    """Range to the true centre (circles) or to the observed midpoint (lines) (m)."""
    size: float
    """True radius (circles, m) or incidence at the observed midpoint (lines, degrees)."""
    length_m: float
    """Observed length (lines, m); NaN for circles."""
    radii: float
    """Range in radii (circles: range / true radius; the detection limit is near 17);
    NaN for lines."""
    z: tuple[float, ...]
    """Whitened error components (:data:`CIRCLE_DOFS` or :data:`LINE_DOFS`)."""
    nees: float
    """NEES with the full stated covariance."""


def score(world: World, pose: np.ndarray, features: Any) -> list[Sample]:
    """Samples of every feature of ``features`` labelled with a world id of its own kind."""
    out: list[Sample] = []
    for f in features:
        if f.true_id < 0:
            continue
        kind, true_w = world.feature(f.true_id)
        if kind != f.kind:
            continue
        truth = express_in(kind, pose, true_w)[0]
        if kind == FeatureKind.CIRCLE:
            d = float(np.hypot(truth[0], truth[1]))
            u = truth[:2] / d
            R = np.array([[u[0], u[1], 0.0], [-u[1], u[0], 0.0], [0.0, 0.0, 1.0]])
            e = R @ (f.params - truth)
            S = R @ f.cov @ R.T
            z = e / np.sqrt(np.diag(S))
            nees = float(e @ np.linalg.solve(S, e))
            r = float(truth[2])
            out.append(Sample(kind, d, r, math.nan, d / r, tuple(z.tolist()), nees))
        else:
            e, _, _ = line_residual(truth, f.params)
            S = line_residual_cov(truth, f.params, f.cov)
            z = e / np.sqrt(np.diag(S))
            nees = float(e @ np.linalg.solve(S, e))
            mid = f.params[:2]
            rng_m = float(np.hypot(mid[0], mid[1]))
            # Angle between the line of sight and the wall's normal (θ + π/2), in [0°, 90°].
            los = math.atan2(mid[1], mid[0])
            inc = math.degrees(math.acos(min(1.0, abs(math.sin(los - float(truth[2]))))))
            length = float(f.extent[1] - f.extent[0])
            out.append(Sample(kind, rng_m, inc, length, math.nan, tuple(z.tolist()), nees))
    return out


def _circle_scene(rng: np.random.Generator) -> tuple[World, np.ndarray]:
    """Three trees at −60°, 0°, +60°, each against empty space or a wall behind it."""
    trees, walls = [], []
    behind = bool(rng.random() < 0.5)
    for k, bearing in enumerate((-math.pi / 3, 0.0, math.pi / 3)):
        r = float(rng.uniform(0.2, 1.0))
        # Beyond about 20 radii the arc is too short for a circle (``min_circle_snr``).
        lo, hi = 1.2 * r + 1.0, 20.0 * r
        d = float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
        b = bearing + float(rng.uniform(-0.05, 0.05))
        c = (d * math.cos(b), d * math.sin(b))
        trees.append(CircleObstacle(100 + k, c, r))
        if behind:
            w = d + r + float(rng.uniform(3.0, 20.0))
            # A wall across the line of sight, wider than the tree seen from the sensor.
            half = 0.3 * w
            m = np.array([w * math.cos(b), w * math.sin(b)])
            t = np.array([-math.sin(b), math.cos(b)]) * half
            walls.append(WallSegment(10 + k, tuple((m - t).tolist()), tuple((m + t).tolist())))
    pose = np.array([0.0, 0.0, float(rng.uniform(-0.01, 0.01))])
    return World(tuple(walls), tuple(trees)), pose


def _line_scene(rng: np.random.Generator) -> tuple[World, np.ndarray]:
    """One wall: length 3–40 m, midpoint 2–78 m away, incidence 0–85°."""
    length = float(rng.uniform(3.0, 40.0))
    d = float(math.exp(rng.uniform(math.log(2.0), math.log(78.0))))
    b = float(rng.uniform(-1.2, 1.2))
    inc = float(rng.uniform(-math.radians(85.0), math.radians(85.0)))
    m = np.array([d * math.cos(b), d * math.sin(b)])
    normal = b + inc
    t = np.array([-math.sin(normal), math.cos(normal)]) * 0.5 * length
    wall = WallSegment(1, tuple((m - t).tolist()), tuple((m + t).tolist()))
    pose = np.array([0.0, 0.0, float(rng.uniform(-0.01, 0.01))])
    return World((wall,), ()), pose


def single_samples(
    n_scans: int,
    seed: int,
    laser: LaserParams,
    params: ExtractionParams,
    kinds: tuple[str, ...] = ("circle", "line"),
) -> Iterator[Sample]:
    """Samples of ``n_scans`` circle scenes and ``n_scans`` line scenes (of ``kinds``);
    each kind's scenes draw from a stream of their own."""
    for kind, scene in (("circle", _circle_scene), ("line", _line_scene)):
        if kind not in kinds:
            continue
        rng = np.random.default_rng(np.random.SeedSequence([seed, 43, len(kind)]))
        for _ in range(n_scans):
            world, pose = scene(rng)
            scan = simulate_scan(world, pose, laser, rng)
            yield from score(world, pose, extract_features(scan, laser, params).features)


def world_samples(
    world_args: dict[str, Any], seeds: range, stride: int, params: ExtractionParams
) -> Iterator[Sample]:
    """Samples along the drive of each generated world, every ``stride``-th true pose."""
    base = load_scenario("loop600")
    for seed in seeds:
        sc = generate_scenario(WorldParams(seed=seed, **world_args), base=base)
        rng = np.random.default_rng(np.random.SeedSequence([seed, 4343]))
        motion = simulate_motion(sc.start, sc.waypoints, sc.steps, sc.vehicle, rng)
        for pose in motion.true_poses[::stride]:
            scan = simulate_scan(sc.world, pose, sc.laser, rng)
            feats = extract_features(scan, sc.laser, params).features
            yield from score(sc.world, pose, feats)


def _dof_stats(z: np.ndarray) -> dict[str, Any]:
    """Mean and variance of ``z`` with 95 % intervals (normal approximation)."""
    n = z.size
    mean = float(z.mean())
    var = float(z.var(ddof=1)) if n > 1 else math.nan
    se_mean = float(z.std(ddof=1) / math.sqrt(n)) if n > 1 else math.nan
    m4 = float(np.mean((z - mean) ** 4))
    se_var = math.sqrt(max(m4 - var * var, 0.0) / n) if n > 1 else math.nan
    return {
        "mean": round(mean, 3),
        "mean_ci": [round(mean - 1.96 * se_mean, 3), round(mean + 1.96 * se_mean, 3)],
        "var": round(var, 3),
        "var_ci": [round(var - 1.96 * se_var, 3), round(var + 1.96 * se_var, 3)],
    }


def table(
    samples: list[Sample],
    dofs: tuple[str, ...],
    key_x: str,
    bins_x: tuple[float, ...],
    key_y: str,
    bins_y: tuple[float, ...],
    min_n: int,
) -> list[dict[str, Any]]:
    """Per (x bin, y bin) with at least ``min_n`` samples: n, NEES per dof, each dof's stats."""
    x = np.array([getattr(s, key_x) for s in samples])
    y = np.array([getattr(s, key_y) for s in samples])
    Z = np.array([s.z for s in samples]).reshape(-1, len(dofs))
    nees = np.array([s.nees for s in samples])
    rows = []
    for i in range(len(bins_x) - 1):
        for j in range(len(bins_y) - 1):
            sel = (x >= bins_x[i]) & (x < bins_x[i + 1]) & (y >= bins_y[j]) & (y < bins_y[j + 1])
            n = int(sel.sum())
            if n < min_n:
                continue
            rows.append(
                {
                    key_x: [bins_x[i], bins_x[i + 1]],
                    key_y: [bins_y[j], bins_y[j + 1]],
                    "n": n,
                    "nees_per_dof": round(float(nees[sel].mean()) / len(dofs), 3),
                    **{d: _dof_stats(Z[sel, k]) for k, d in enumerate(dofs)},
                }
            )
    return rows


def _worst(rows: list[dict[str, Any]], dofs: tuple[str, ...]) -> dict[str, float]:
    """Largest |mean| and largest |variance − 1| over the rows."""
    means = [abs(r[d]["mean"]) for r in rows for d in dofs]
    vars_ = [abs(r[d]["var"] - 1.0) for r in rows for d in dofs]
    return {
        "max_abs_mean": max(means, default=math.nan),
        "max_abs_var_minus_1": round(max(vars_, default=math.nan), 3),
    }


def summarise(samples: list[Sample], min_n: int) -> dict[str, Any]:
    """The tables of circles and lines."""
    circles = [s for s in samples if s.kind == FeatureKind.CIRCLE]
    lines = [s for s in samples if s.kind == FeatureKind.LINE]
    c_rows = table(
        circles, CIRCLE_DOFS, "rng_m", CIRCLE_RANGE_BINS, "size", CIRCLE_RADIUS_BINS, min_n
    )
    c_all = table(circles, CIRCLE_DOFS, "rng_m", (0.0, 1e9), "size", (0.0, 1e9), 1)
    c_radii = table(circles, CIRCLE_DOFS, "radii", CIRCLE_RADII_BINS, "size", (0.0, 1e9), min_n)
    l_inc = table(
        lines, LINE_DOFS, "rng_m", LINE_RANGE_BINS, "size", LINE_INCIDENCE_BINS_DEG, min_n
    )
    l_len = table(lines, LINE_DOFS, "rng_m", LINE_RANGE_BINS, "length_m", LINE_LENGTH_BINS, min_n)
    l_all = table(lines, LINE_DOFS, "rng_m", (0.0, 1e9), "size", (0.0, 1e9), 1)
    return {
        "circle": {
            "all": c_all,
            "by_range_radius": c_rows,
            "by_range_in_radii": c_radii,
            "worst": _worst(c_rows, CIRCLE_DOFS),
        },
        "line": {
            "all": l_all,
            "by_range_incidence": l_inc,
            "by_range_length": l_len,
            "worst": _worst(l_inc + l_len, LINE_DOFS),
        },
    }


def _cell(d: dict[str, Any]) -> str:
    return f"{d['mean']:+.2f} [{d['mean_ci'][0]:+.2f}, {d['mean_ci'][1]:+.2f}] / " + (
        f"{d['var']:.2f} [{d['var_ci'][0]:.2f}, {d['var_ci'][1]:.2f}]"
    )


def _markdown_table(
    rows: list[dict[str, Any]], key_y: str, dofs: tuple[str, ...], key_x: str = "rng_m"
) -> list[str]:
    head = f"| {key_x} | {key_y} | n | NEES/dof | " + " | ".join(dofs) + " |"
    out = [head, "|" + "---|" * (4 + len(dofs))]
    for r in rows:
        x, y = r[key_x], r[key_y]
        cells = " | ".join(_cell(r[d]) for d in dofs)
        head = f"| {x[0]:g}–{x[1]:g} | {y[0]:g}–{y[1]:g} | {r['n']} | {r['nees_per_dof']:.2f}"
        out.append(f"{head} | {cells} |")
    return out


def markdown(out: dict[str, Any]) -> str:
    """The tables of :func:`summarise` in Markdown: mean [95 %] / variance [95 %]."""
    c, ln = out["circle"], out["line"]
    lines = ["Circles (along, across, radius): mean [95 %] / variance [95 %]", ""]
    lines += _markdown_table(c["all"] + c["by_range_radius"], "size", CIRCLE_DOFS)
    lines += ["", "Circles by range in radii (first column)", ""]
    lines += _markdown_table(c["by_range_in_radii"], "size", CIRCLE_DOFS, "radii")
    lines += ["", "Lines by incidence (°)", ""]
    lines += _markdown_table(ln["all"] + ln["by_range_incidence"], "size", LINE_DOFS)
    lines += ["", "Lines by length (m)", ""]
    lines += _markdown_table(ln["by_range_length"], "length_m", LINE_DOFS)
    lines += ["", f"circle worst: {c['worst']}; line worst: {ln['worst']}"]
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--source", choices=("single", "worlds"), default="single")
    p.add_argument("--scans", type=int, default=12000, help="single: scans per feature kind")
    p.add_argument(
        "--kinds", default="circle,line", help="single: scenes of these kinds (circle, line)"
    )
    p.add_argument("--seed", type=int, default=0, help="single: seed of the scenes and noise")
    p.add_argument("--world", default=DEFAULT_WORLD, help="worlds: generator keywords")
    p.add_argument("--seeds", type=int, nargs=2, default=(1, 5), help="worlds: first, end")
    p.add_argument("--stride", type=int, default=2, help="worlds: every n-th pose")
    p.add_argument("--min-n", type=int, default=200, help="smallest bin reported")
    p.add_argument("--markdown", action="store_true", help="print tables instead of JSON")
    args = p.parse_args()
    params = ExtractionParams()
    t0 = time.perf_counter()
    if args.source == "single":
        kinds = tuple(args.kinds.split(","))
        samples = list(single_samples(args.scans, args.seed, LaserParams(), params, kinds))
        setup: dict[str, Any] = {
            "source": "single",
            "scans": args.scans,
            "kinds": list(kinds),
            "seed": args.seed,
        }
    else:
        world = parse_world_args(args.world)
        samples = list(world_samples(world, range(*args.seeds), args.stride, params))
        setup = {"source": "worlds", "world": world, "seeds": args.seeds, "stride": args.stride}
    out = {**setup, **summarise(samples, args.min_n), "wall_s": round(time.perf_counter() - t0, 1)}
    print(markdown(out) if args.markdown else json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
