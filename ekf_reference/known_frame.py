"""The known map in a frame centred on its features, poses taken back to its own, and
its features as EKF map elements."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ekf_reference.state import Element, ElementKind, Role, bind_line_cov
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.measlog import KnownMapArrays


def centred_known_map(known: KnownMapArrays) -> tuple[KnownMapArrays, FloatArray]:
    """``known`` in the frame ``Wknown'``: ``Wknown`` translated to the centroid ``c`` of
    the feature positions, and ``c``.

    The anchor joins ``Wknown`` to the vehicle's frames.  A surveyed map comes in
    UTM-like coordinates (10⁶–10⁷ m): the anchor's translation and the features'
    positions are then both huge and cancel in every prediction, and the lever arm of
    the anchor's angle turns its variance into metre-sized position terms that
    round-off destroys (the innovation covariance stops being positive definite).
    In ``Wknown'`` both are of the size of the map.  A translation leaves angles,
    extents and covariances unchanged; results are reported back in ``Wknown``
    (:func:`uncentred`).
    """
    if len(known) == 0:
        return known, np.zeros(2)
    c = np.asarray(known.params[:, :2], dtype=np.float64).mean(axis=0)
    params = np.array(known.params, dtype=np.float64, copy=True)
    params[:, :2] -= c
    return replace(known, params=params), c


def uncentred(x_known_centred: FloatArray, c: FloatArray) -> FloatArray:
    """A pose in ``Wknown'`` as a pose in ``Wknown``: ``(c, 0) ⊕ x`` (Jacobian: identity)."""
    out = np.array(x_known_centred, dtype=np.float64, copy=True)
    out[:2] += c
    return out


def known_element(
    known: KnownMapArrays, j: int, track: int
) -> tuple[Element, FloatArray, FloatArray]:
    """Known feature ``j`` as a static map element in the known frame (track ``track``),
    its mean and its surveyed covariance (a line's with the along-line part projected
    out)."""
    kind = ElementKind.of_feature(int(known.kinds[j]))
    cov = known.covs[j]
    extent = (math.nan, math.nan)
    extent_sd = 0.0
    if kind == ElementKind.LINE:
        u = np.array([math.cos(known.params[j, 2]), math.sin(known.params[j, 2])])
        extent_sd = math.sqrt(max(float(u @ cov[:2, :2] @ u), 0.0))
        cov = bind_line_cov(known.params[j], cov)
        if known.extents is not None:
            extent = (float(known.extents[j, 0]), float(known.extents[j, 1]))
    element = Element(
        kind,
        Role.KNOWN,
        moving=False,
        track=track,
        extent=extent,
        extent_sd=extent_sd,
        true_id=int(known.ids[j]),
    )
    return element, known.params[j], cov
