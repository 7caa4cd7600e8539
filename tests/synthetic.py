"""Small synthetic measurement logs with exactly Gaussian observations (no laser).

They isolate the estimators from the extraction front end: every observation is
the true feature in the sensor frame plus noise drawn from its stated covariance.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from mapfuse_core.geometry.features import FeatureKind, canonical_line, express_in
from mapfuse_core.geometry.se2 import compose, relative, wrap_angle
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog
from mapfuse_core.sensor import LaserParams
from mapfuse_core.sim.clutter import ClutterParams, spurious_feature


def ring_world(
    n_circles: int = 24, n_lines: int = 6, radius: float = 30.0, seed: int = 7
) -> KnownMapArrays:
    """Circles and lines scattered around a ring of the given radius (irregular)."""
    rng = np.random.default_rng(seed)
    params, kinds = [], []
    for i in range(n_circles):
        a = 2 * math.pi * i / n_circles + rng.uniform(-0.1, 0.1)
        d = radius + rng.choice([-1, 1]) * rng.uniform(6, 14)
        params.append([d * math.cos(a), d * math.sin(a), rng.uniform(0.3, 0.9)])
        kinds.append(int(FeatureKind.CIRCLE))
    for i in range(n_lines):
        a = 2 * math.pi * (i + 0.5) / n_lines
        d = radius + 18 + rng.uniform(0, 5)
        th = a + math.pi / 2 + rng.uniform(-0.3, 0.3)
        params.append([d * math.cos(a), d * math.sin(a), float(wrap_angle(th))])
        kinds.append(int(FeatureKind.LINE))
    n = len(params)
    ext = np.full((n, 2), np.nan)
    ext[np.array(kinds) == FeatureKind.LINE] = [-8.0, 8.0]
    return KnownMapArrays(
        ids=np.arange(100, 100 + n, dtype=np.int64),
        kinds=np.array(kinds, dtype=np.int8),
        params=np.array(params, dtype=float),
        covs=np.zeros((n, 3, 3)),
        extents=ext,
    )


def synthetic_log(
    steps: int = 400,
    seed: int = 0,
    world: KnownMapArrays | None = None,
    radius: float = 30.0,
    start: tuple[float, float, float] = (-29.0, -11.0, math.pi / 3),
    max_range: float = 25.0,
    sigma_odo: tuple[float, float, float] = (0.01, 0.005, 0.002),
    sigma_circle: float = 0.03,
    sigma_line: tuple[float, float] = (0.02, 0.005),
    known_fraction: float = 0.7,
    known_sigma: tuple[float, float, float] = (0.1, 0.1, 0.05),
) -> MeasurementLog:
    """A vehicle driving a circle of ``radius`` around the world's centre.

    The world is given in ``W``; the trajectory is placed so that its first pose is
    ``start`` in ``W``.  The known map holds ``known_fraction`` of the features, with
    noise drawn from ``known_sigma`` (xy, radius, line angle).
    """
    rng = np.random.default_rng(seed)
    world = world if world is not None else ring_world(radius=radius)
    # Centre the world on the circle the vehicle drives (it turns left from start).
    centre = np.array(
        [start[0] - radius * math.sin(start[2]), start[1] + radius * math.cos(start[2])]
    )
    shifted = world.params.copy()
    shifted[:, :2] += centre
    world = KnownMapArrays(world.ids, world.kinds, shifted, world.covs, world.extents)
    step_len = 2 * math.pi * radius / max(steps, 1) * 0.999
    dth = step_len / radius
    true_inc = np.array([radius * math.sin(dth), radius * (1 - math.cos(dth)), dth])
    # Place the circle so that pose 0 = start and the path circles the origin.
    s0 = np.array(start)
    poses = np.zeros((steps, 3))
    poses[0] = s0
    Q = np.diag(np.square(sigma_odo))
    odo = np.zeros((steps, 3))
    odo_cov = np.zeros((steps, 3, 3))
    for k in range(1, steps):
        poses[k] = compose(poses[k - 1], true_inc)
        odo[k] = true_inc + rng.multivariate_normal(np.zeros(3), Q)
        odo_cov[k] = Q
    f_step, f_kind, f_params, f_cov, f_true, f_ext = [], [], [], [], [], []
    for k in range(steps):
        for j in range(len(world)):
            kind = FeatureKind(int(world.kinds[j]))
            z, _, _ = express_in(kind, poses[k], world.params[j])
            if kind == FeatureKind.CIRCLE:
                if math.hypot(z[0], z[1]) > max_range or z[0] < 0:
                    continue
                cov = np.diag([sigma_circle**2, sigma_circle**2, (sigma_circle / 2) ** 2])
                zn = z + rng.multivariate_normal(np.zeros(3), cov)
                ext = (math.nan, math.nan)
            else:
                lateral = relative(z, np.zeros(3))[0][1]
                if abs(lateral) > max_range or math.hypot(z[0], z[1]) > max_range + 8:
                    continue
                z = canonical_line(z)
                # Noise on (lateral, angle) in the line's own frame, none along it.
                d = np.array([0.0, rng.normal(0, sigma_line[0]), rng.normal(0, sigma_line[1])])
                zn = compose(z, d)
                c, s = math.cos(zn[2]), math.sin(zn[2])
                Rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
                cov = Rot @ np.diag([4.0, sigma_line[0] ** 2, sigma_line[1] ** 2]) @ Rot.T
                ext = (-8.0, 8.0)
            f_step.append(k)
            f_kind.append(int(kind))
            f_params.append(zn)
            f_cov.append(cov)
            f_true.append(int(world.ids[j]))
            f_ext.append(ext)
    m = len(f_step)
    n_known = max(1, round(known_fraction * len(world)))
    pick = np.sort(rng.choice(len(world), size=n_known, replace=False))
    kcov = []
    kpar = []
    for j in pick:
        if world.kinds[j] == FeatureKind.CIRCLE:
            c = np.diag([known_sigma[0] ** 2, known_sigma[0] ** 2, known_sigma[1] ** 2])
        else:
            c = np.diag([known_sigma[0] ** 2, known_sigma[0] ** 2, known_sigma[2] ** 2])
        kcov.append(c)
        kpar.append(world.params[j] + rng.multivariate_normal(np.zeros(3), c))
    known = KnownMapArrays(
        ids=world.ids[pick].copy(),
        kinds=world.kinds[pick].copy(),
        params=np.array(kpar),
        covs=np.array(kcov),
        extents=None if world.extents is None else world.extents[pick].copy(),
    )
    return MeasurementLog(
        scenario="synthetic-ring",
        seed=seed,
        timestamps=np.arange(steps) * 0.125,
        odometry=odo,
        odometry_cov=odo_cov,
        feat_step=np.array(f_step, dtype=np.int64),
        feat_kind=np.array(f_kind, dtype=np.int8),
        feat_params=np.array(f_params).reshape(m, 3),
        feat_cov=np.array(f_cov).reshape(m, 3, 3),
        feat_true_id=np.array(f_true, dtype=np.int64),
        feat_n_points=np.full(m, 10, dtype=np.int64),
        feat_extent=np.array(f_ext, dtype=float).reshape(m, 2),
        known_map=known,
        world=world,
        true_poses=poses,
    )


def with_known(log: MeasurementLog, keep: list[int]) -> MeasurementLog:
    """``log`` with its known map cut to the features at indices ``keep``."""
    k = log.known_map
    sel = np.array(keep, dtype=np.int64)
    known = KnownMapArrays(
        k.ids[sel],
        k.kinds[sel],
        k.params[sel].reshape(-1, 3),
        k.covs[sel].reshape(-1, 3, 3),
        None if k.extents is None else k.extents[sel].reshape(-1, 2),
    )
    return dataclasses.replace(log, known_map=known)


def with_clutter(log: MeasurementLog, per_step: int, seed: int = 0) -> MeasurementLog:
    """``log`` with ``per_step`` spurious detections added to every scan, drawn by the
    simulator's clutter model (``mapfuse_core.sim.clutter``; true id −1)."""
    rng = np.random.default_rng(seed)
    laser, clutter = LaserParams(), ClutterParams(features_per_scan=per_step)
    steps, kinds, params, covs, exts, npts = [], [], [], [], [], []
    for k in range(log.n_steps):
        for _ in range(per_step):
            f = spurious_feature(rng, laser, clutter)
            kinds.append(int(f.kind))
            params.append(f.params)
            covs.append(f.cov)
            exts.append(f.extent)
            npts.append(f.n_points)
            steps.append(k)
    n = len(steps)
    step = np.concatenate([log.feat_step, np.array(steps, dtype=np.int64)])
    order = np.argsort(step, kind="stable")

    def cat(a: np.ndarray, b: object, dtype: object) -> np.ndarray:
        return np.concatenate([a, np.asarray(b, dtype=dtype).reshape((n, *a.shape[1:]))])[order]

    return dataclasses.replace(
        log,
        feat_step=step[order],
        feat_kind=cat(log.feat_kind, kinds, np.int8),
        feat_params=cat(log.feat_params, params, float),
        feat_cov=cat(log.feat_cov, covs, float),
        feat_gate_cov=None if log.feat_gate_cov is None else cat(log.feat_gate_cov, covs, float),
        feat_true_id=cat(log.feat_true_id, np.full(n, -1), np.int64),
        feat_n_points=cat(log.feat_n_points, npts, np.int64),
        feat_extent=cat(log.feat_extent, exts, float),
    )
