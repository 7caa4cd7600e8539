"""The known map a scenario specifies: its true features (moves applied) drawn with
the specified noise and expressed in the map's frame."""

from __future__ import annotations

import numpy as np

from mapfuse_core.geometry.features import FeatureKind, express_in
from mapfuse_core.geometry.se2 import FloatArray, wrap_angle
from mapfuse_core.sim.scenario.types import KnownMap, KnownMapSpec, Scenario
from mapfuse_core.sim.world import WallSegment, World


def _true_map_feature(spec: KnownMapSpec, world: World, fid: int) -> tuple[FeatureKind, FloatArray]:
    """Kind and world-frame parameters of map feature ``fid``, with its move applied."""
    removed = {f.id: f for f in spec.removed}
    if fid in removed:
        f = removed[fid]
        kind, p = (
            (FeatureKind.LINE, f.spmap())
            if isinstance(f, WallSegment)
            else (FeatureKind.CIRCLE, f.params())
        )
    else:
        kind, p = world.feature(fid)
    p = p.copy()
    for m in spec.moved:
        if m.id == fid:
            p[0] += m.dx
            p[1] += m.dy
            if kind == FeatureKind.LINE:
                p[2] = float(wrap_angle(p[2] + m.dtheta))
            else:
                p[2] += m.dr
    return kind, p


def build_known_map(scenario: Scenario, rng: np.random.Generator) -> KnownMap:
    """Realise the scenario's known map with one seeded draw of its noise.

    For every held id (sorted): take the world feature (or the removed one), apply the
    deliberate ``moved`` change, express it in the map frame (``⊖frame ⊕ f``); those are
    ``true_params``.  Then add ``N(0, diag σ²)`` drawn from ``rng`` (one ``(M, 3)`` draw,
    so the map depends on the seed only).  See :class:`KnownMap`.
    """
    spec = scenario.known_map
    ids = np.array(spec.ids, dtype=np.int64)
    m = ids.shape[0]
    kinds = np.zeros(m, dtype=np.int8)
    true_params = np.zeros((m, 3))
    sig = np.zeros((m, 3))
    for i, fid in enumerate(spec.ids):
        kind, p_W = _true_map_feature(spec, scenario.world, fid)
        true_params[i] = express_in(kind, spec.frame, p_W)[0]
        kinds[i] = int(kind)
        third = spec.sigma_theta_rad if kind == FeatureKind.LINE else spec.sigma_r_m
        sig[i] = (spec.sigma_xy_m, spec.sigma_xy_m, third)
    params = true_params + sig * rng.normal(size=(m, 3))
    lines = kinds == int(FeatureKind.LINE)
    params[lines, 2] = wrap_angle(params[lines, 2])
    # Redraw non-positive radii (truncated normal): a circle must keep r > 0.
    while True:
        bad = np.nonzero(~lines & (params[:, 2] <= 0.0))[0]
        if bad.size == 0:
            break
        params[bad, 2] = true_params[bad, 2] + sig[bad, 2] * rng.normal(size=bad.size)
    covs = np.zeros((m, 3, 3))
    covs[:, [0, 1, 2], [0, 1, 2]] = sig**2
    for a in (ids, kinds, params, covs, true_params):
        a.setflags(write=False)
    return KnownMap(
        ids=ids,
        kinds=kinds,
        params=params,
        covs=covs,
        true_params=true_params,
        frame=np.array(spec.frame),
    )


# --------------------------------------------------------------------------- drive
