"""One map reduced to what matching needs: validated arrays, floors, line perturbations.

A line enters matching only through the 2×2 covariance of its SPmap perturbation
``(e_lat, e_θ)``; its along-line pseudo-variance is never used.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.matching.ccda.params import CCDAParams
from mapfuse_core.measlog import KnownMapArrays

IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

#: Information below this (1/m², 1/rad²) is treated as none: the direction is free.
_INFO_FLOOR = 1e-12

_LINE = int(FeatureKind.LINE)
_CIRCLE = int(FeatureKind.CIRCLE)


@dataclass(frozen=True)
class _Prep:
    """One map reduced to what matching needs, in its own frame."""

    kinds: NDArray[np.int8]
    """(n,) feature kinds."""
    params: FloatArray
    """(n, 3) raw parameters."""
    covs: FloatArray
    """(n, 3, 3) covariances, with the variance floor added (circles only)."""
    circ: IntArray
    """Indices of the circles."""
    line: IntArray
    """Indices of the lines."""
    p: FloatArray
    """(n, 2) circle centres / line origins."""
    Sp: FloatArray
    """(n, 2, 2) covariance of the circle centres (unused for lines)."""
    vr: FloatArray
    """(n,) variance of the circle radii (unused for lines)."""
    th: FloatArray
    """(n,) line angles (unused for circles)."""
    C: FloatArray
    """(n, 2, 2) covariance of a line's ``(e_lat, e_θ)`` perturbation (unused for
    circles)."""
    ext: FloatArray
    """(n, 2) along-line interval of each line's segment relative to its origin, in
    the direction of its angle; NaN where unknown (circles, maps without extents)."""

    @property
    def n(self) -> int:
        """Number of features."""
        return int(self.kinds.shape[0])


def _check_finite(name: str, a: FloatArray) -> None:
    bad = np.argwhere(~np.isfinite(a))
    if bad.size:
        idx = tuple(int(v) for v in bad[0])
        where = ", ".join(str(v) for v in idx)
        raise ValueError(f"{name}[{where}] is not finite ({a[idx]})")


def _prepare(m: KnownMapArrays, name: str, params: CCDAParams) -> _Prep:
    """Validate a map (errors name ``name``) and reduce it to :class:`_Prep`."""
    kinds = np.asarray(m.kinds)
    n = int(kinds.shape[0]) if kinds.ndim == 1 else -1
    if n < 0:
        raise ValueError(f"{name}.kinds must be one-dimensional, got shape {kinds.shape}")
    P = np.asarray(m.params, dtype=np.float64)
    S = np.asarray(m.covs, dtype=np.float64)
    if P.shape != (n, 3):
        raise ValueError(f"{name}.params has shape {P.shape}, expected ({n}, 3)")
    if S.shape != (n, 3, 3):
        raise ValueError(f"{name}.covs has shape {S.shape}, expected ({n}, 3, 3)")
    bad_kind = np.nonzero((kinds != _LINE) & (kinds != _CIRCLE))[0]
    if bad_kind.size:
        i = int(bad_kind[0])
        raise ValueError(f"{name}.kinds[{i}] = {kinds[i]} is not a feature kind")
    _check_finite(f"{name}.params", P)
    _check_finite(f"{name}.covs", S)
    kinds = kinds.astype(np.int8)
    circ = np.nonzero(kinds == _CIRCLE)[0].astype(np.int64)
    line = np.nonzero(kinds == _LINE)[0].astype(np.int64)
    ext = np.full((n, 2), np.nan)
    if m.extents is not None:
        E = np.asarray(m.extents, dtype=np.float64)
        if E.shape != (n, 2):
            raise ValueError(f"{name}.extents has shape {E.shape}, expected ({n}, 2)")
        ok = np.all(np.isfinite(E), axis=1) & (E[:, 0] <= E[:, 1])
        ext[ok] = E[ok]
        ext[circ] = np.nan
    vm, va = params.var_floor_m**2, params.var_floor_rad**2

    covs = S.copy()
    covs[circ] += np.diag([vm, vm, vm])
    p = P[:, :2].copy()
    Sp = covs[:, :2, :2].copy()
    vr = covs[:, 2, 2].copy()
    th = P[:, 2].copy()
    # (e_lat, e_θ) covariance of a line: project the position block on the normal
    # only, so the along-line pseudo-variance never enters.
    nrm = np.stack([-np.sin(th), np.cos(th)], axis=1)
    C = np.zeros((n, 2, 2))
    C[:, 0, 0] = np.einsum("ni,nij,nj->n", nrm, S[:, :2, :2], nrm) + vm
    C[:, 0, 1] = C[:, 1, 0] = np.einsum("ni,ni->n", nrm, S[:, :2, 2])
    C[:, 1, 1] = S[:, 2, 2] + va
    return _Prep(
        kinds=kinds,
        params=P,
        covs=covs,
        circ=circ,
        line=line,
        p=p,
        Sp=Sp,
        vr=vr,
        th=th,
        C=C,
        ext=ext,
    )


def _centred(P: _Prep) -> tuple[_Prep, FloatArray]:
    """``P`` in a frame translated to the centroid of its feature positions, and that
    centroid (the pose ``(c, 0)`` of the new frame in the old one).

    Matching is then independent of where the map's origin is: invariants, gates and
    the transform fit see coordinates of the size of the map, not of its distance
    from the origin (surveyed maps come in UTM-like coordinates, 10⁶–10⁷ m, where
    the lever arm of the transform's angle would swamp its position, and rounding
    would swamp the features' metre-level geometry).  A translation leaves angles
    and covariances unchanged.
    """
    if P.n == 0:
        return P, np.zeros(2)
    c = P.p.mean(axis=0)
    params = P.params.copy()
    params[:, :2] -= c
    return replace(P, params=params, p=P.p - c), c


def _pairing_arrays(
    A: _Prep, B: _Prep, pairings: Sequence[tuple[int, int]]
) -> tuple[IntArray, IntArray]:
    arr = np.asarray(list(pairings), dtype=np.int64).reshape(-1, 2)
    ii, jj = arr[:, 0], arr[:, 1]
    for name, idx, n in (("map_a", ii, A.n), ("map_b", jj, B.n)):
        bad = np.nonzero((idx < 0) | (idx >= n))[0]
        if bad.size:
            raise ValueError(
                f"pairing {int(bad[0])} indexes {name}[{int(idx[bad[0]])}], outside 0..{n - 1}"
            )
    mism = np.nonzero(A.kinds[ii] != B.kinds[jj])[0]
    if mism.size:
        m = int(mism[0])
        raise ValueError(
            f"pairing {m} pairs map_a[{int(ii[m])}] and map_b[{int(jj[m])}] of different kinds"
        )
    return ii, jj
