"""The EKF's final map as a :class:`~mapfuse_core.estimate.MapEstimate`: :func:`final_map`.

Every feature is given in ``Wglobal`` with its marginal covariance.  When the map was
matched, each feature the EKF kept apart from the known map is also given in
``Wknown``, with the covariance computed from its joint marginal with the anchor.
Composed from the two marginals separately, that covariance would count twice what
the match taught both at once: after the match a landmark seen long before it is
placed by the known features around it, while its place in ``Wglobal`` and the
anchor each keep the whole unanchored drift, in opposite directions.
"""

from __future__ import annotations

import numpy as np

from ekf_reference.known_frame import uncentred
from ekf_reference.state import GaussianMap, Role
from ekf_reference.tracks import Tracks
from mapfuse_core.estimate import MapEstimate
from mapfuse_core.geometry.features import express_in, transform_feature
from mapfuse_core.geometry.se2 import FloatArray, inverse_jacobian

__all__ = ["feature_in_global", "final_map"]


def final_map(
    g: GaussianMap, tracks: Tracks, known_centre: FloatArray, obs_known_id: np.ndarray
) -> MapEstimate:
    """The final map of global map ``g``; ``tracks`` merge the landmarks' track ids,
    ``known_centre`` is the offset of the centred known frame the filter works in.

    A known feature's ``n_obs`` is the number of logged observations associated with
    it (``obs_known_id``, the known id of every observation's landmark), as the graph's
    landmarks count theirs: the filter's own count misses those absorbed into it by a
    hard constraint.  An estimated feature tied to a known one and kept
    (``EKFConfig.known_map_in_local_maps="copied"``) has that known id and its own count.
    """
    feats = [i for i, e in enumerate(g.elements) if e.role in (Role.FEATURE, Role.KNOWN)]
    gb = g.find(Role.BASE)
    a = g.find(Role.ANCHOR) if g.has(Role.ANCHOR) else None
    n = len(feats)
    params = np.zeros((n, 3))
    covs = np.zeros((n, 3, 3))
    params_known = np.full((n, 3), np.nan)
    covs_known = np.full((n, 3, 3), np.nan)
    # Final map in Wglobal: x^Wglobal_F = ⊖x^Wlocal_Wglobal ⊕ x^Wlocal_F (known ones via anchor).
    inv_b, Jinv = inverse_jacobian(g.mean[gb])
    for r, i in enumerate(feats):
        e = g.elements[i]
        fk = e.kind.feature_kind()
        if e.role == Role.KNOWN:
            # Known features enter the map with the anchor, so it is there.
            assert a is not None
            f_wl, Ja, Je = transform_feature(fk, g.mean[a], g.mean[i])
            val, J1, J2 = transform_feature(fk, inv_b, f_wl)
            J = np.hstack([J1 @ Jinv, J2 @ Ja, J2 @ Je])
            P = g.marginal([gb, a, i])
        else:
            val, J, P = _feature_in_global(g, gb, i, inv_b, Jinv)
            if a is not None:
                # x^Wknown'_F = ⊖x^Wlocal_Wknown' ⊕ x^Wlocal_F, then uncentred.
                fk_val, Ka, Kf = express_in(fk, g.mean[a], g.mean[i])
                K = np.hstack([Ka, Kf])
                params_known[r] = uncentred(fk_val, known_centre)
                covs_known[r] = K @ g.marginal([a, i]) @ K.T
        params[r] = val
        covs[r] = J @ P @ J.T
    known_ids = np.array(
        [
            g.elements[i].true_id
            if g.elements[i].role == Role.KNOWN
            else tracks.known.get(tracks.root(g.elements[i].track), -1)
            if g.elements[i].track >= 0
            else -1
            for i in feats
        ],
        dtype=np.int64,
    )
    return MapEstimate(
        kinds=np.array([int(g.elements[i].kind.feature_kind()) for i in feats], dtype=np.int8),
        params=params,
        covs=covs,
        known_ids=known_ids,
        true_ids=np.array([g.elements[i].true_id for i in feats], dtype=np.int64),
        n_obs=_n_obs(
            np.array([g.elements[i].n_obs for i in feats], dtype=np.int64),
            np.where([g.elements[i].role == Role.KNOWN for i in feats], known_ids, -1),
            obs_known_id,
        ),
        tracks=np.array(
            [
                tracks.root(int(g.elements[i].track)) if g.elements[i].track >= 0 else -1
                for i in feats
            ],
            dtype=np.int64,
        ),
        params_known=params_known,
        covs_known=covs_known,
    )


def feature_in_global(g: GaussianMap, i: int) -> tuple[FloatArray, FloatArray]:
    """Estimated feature ``i`` of global map ``g`` in ``Wglobal``, ``⊖x^Wlocal_Wglobal ⊕
    x^Wlocal_F``, and its covariance (from its joint marginal with the base)."""
    gb = g.find(Role.BASE)
    inv_b, Jinv = inverse_jacobian(g.mean[gb])
    val, J, P = _feature_in_global(g, gb, i, inv_b, Jinv)
    return val, J @ P @ J.T


def _feature_in_global(
    g: GaussianMap, gb: int, i: int, inv_b: FloatArray, Jinv: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Feature ``i`` through the inverted base ``inv_b`` (``Jinv``: its Jacobian), the
    Jacobian w.r.t. ``[base, feature]`` and their joint marginal."""
    fk = g.elements[i].kind.feature_kind()
    val, J1, J2 = transform_feature(fk, inv_b, g.mean[i])
    return val, np.hstack([J1 @ Jinv, J2]), g.marginal([gb, i])


def _n_obs(n_obs: np.ndarray, known_ids: np.ndarray, obs_known_id: np.ndarray) -> np.ndarray:
    """``n_obs`` with each known feature's count taken from the observations' known ids
    (``known_ids``: −1 for every entry that keeps its own count)."""
    out = np.array(n_obs, dtype=np.int64, copy=True)
    known = known_ids >= 0
    if np.any(known):
        ids, counts = np.unique(obs_known_id[obs_known_id >= 0], return_counts=True)
        per_id = dict(zip(ids.tolist(), counts.tolist(), strict=True))
        out[known] = [per_id.get(int(i), 0) for i in known_ids[known]]
    return out
