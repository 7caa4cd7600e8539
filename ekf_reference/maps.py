"""Robotcentric local maps, their joining into the global map, and known-map fusion.

Frames (docs/method.md §1): ``R`` the vehicle, ``Wlocal`` the base of the current local
map, ``Wglobal`` the vehicle at step 0, ``Wknown`` the known map.

* Local map (paper eq. 1, 17): ``[x^R_Wlocal, (x^R_Wknown, x^Wknown_E…), x^R_F…]``.
  Prediction moves every element expressed in ``R``; known features stay in
  ``Wknown``.
* Global map (eq. 2, 14): ``[x^Wlocal_Wglobal, (x^Wlocal_Wknown, x^Wknown_E…), x^Wlocal_G…]``.

How the anchor and the known map reach a local map is
``EKFConfig.known_map_in_local_maps``.  By default (``"shared"``) known-map
information is counted once: the anchor and the known features are *shared* between
the global map and the local map started from it (conditionally independent local
maps, Piniés and Tardós 2008; :func:`new_local_map`): a local map starts with the
global marginal of the shared elements, and at the join the global-only elements are
corrected through their correlation with the shared ones.  The structure of
Algorithm 1 (translation vector in every local map, constrained local update at every
step, translation-vector update at every join) is the paper's.  ``"copied"`` is the
paper's bookkeeping (:func:`copied_local_map`): every local map gets a copy of the
anchor and of the known map, independent of the global map, and the join fuses the
anchor's copy back (eqs. 22–24); that counts the same information again at every
join.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg import block_diag

from ekf_reference.known_frame import known_element
from ekf_reference.state import Element, ElementKind, GaussianMap, Role, bind_line_cov
from mapfuse_core.geometry.features import express_in, transform_feature
from mapfuse_core.geometry.se2 import (
    FloatArray,
    compose_jacobians,
    inverse_jacobian,
    relative,
    wrap_angle,
)
from mapfuse_core.measlog import KnownMapArrays

__all__ = [
    "CIContext",
    "Motion",
    "apply_motion",
    "bind_line_cov",
    "copied_local_map",
    "motion",
    "new_global_map",
    "new_local_map",
    "predict",
    "rotate_moving",
    "tie_anchor_copy",
    "vehicle_in_global",
]


@dataclass
class CIContext:
    """What a fused local map remembers of the global map it was started from."""

    shared_global: list[int]
    """Global-map indices of the shared elements: the anchor, the known features, then
    the carried features (``EKFConfig.carry_seen_steps``)."""
    shared_local: list[int]
    """Local-map indices of the same elements, in the same order."""
    moving: list[int]
    """Positions (into the two lists above) of the shared elements the local map holds
    in the vehicle frame ``R``: the anchor and carried features, globally
    ``⊖x^R_Wlocal ⊕ x``.  The others (known features) are held as the global map holds
    them, static in ``Wknown``."""
    mu_s: FloatArray
    """(k, 3) global mean of the shared elements when the local map started."""
    A: FloatArray
    """``P_gs P_ss⁺`` over all global dofs (3n × 3k): how global elements follow the shared."""
    angle_dofs: np.ndarray
    """Flat indices (into ``3k``) of the shared elements' angles, wrapped in differences."""
    base_mean: FloatArray
    """``x^Wlocal_Wglobal`` of the global map (it does not change during a local map)."""
    base_cond_cov: FloatArray
    """Its covariance given the shared elements, ``P_bb − A_b P_sb``: constant too, so
    :func:`vehicle_in_global` does not redo it at every step."""


def new_global_map() -> GaussianMap:
    """The global map before the first join: ``x^Wglobal_Wglobal = 0`` exactly."""
    g = GaussianMap()
    g.add(
        Element(ElementKind.POSE, Role.BASE, moving=False, track=-1), np.zeros(3), np.zeros((3, 3))
    )
    return g


def new_local_map(
    global_map: GaussianMap, carry: Sequence[int] = ()
) -> tuple[GaussianMap, CIContext | None]:
    """A local map based at the current vehicle pose, with the shared part of the global map.

    Shared are the anchor and the known features (fusion), and the global features
    ``carry`` (indices into ``global_map``).  A new local map starts at the frame the
    global map has just been expressed in, so a carried feature's ``x^R_F`` starts
    equal to its global ``x^Wlocal_F``; it then moves with the vehicle like a local
    feature, and the join takes it back through the base.
    """
    loc = GaussianMap()
    loc.add(
        Element(ElementKind.POSE, Role.BASE, moving=True, track=-1), np.zeros(3), np.zeros((3, 3))
    )
    shared = []
    if global_map.has(Role.ANCHOR):
        shared = [global_map.find(Role.ANCHOR), *global_map.indices(Role.KNOWN)]
    for gi in carry:
        if global_map.elements[gi].role != Role.FEATURE:
            raise AssertionError(f"only estimated features are carried, not element {gi}")
    shared += list(carry)
    if not shared:
        return loc, None
    Pss = global_map.marginal(shared)
    first = len(loc)
    moving = [global_map.elements[gi].role != Role.KNOWN for gi in shared]
    # Filled in one go: GaussianMap.add reallocates the covariance per element.
    loc.elements += [
        replace(e, moving=mv, n_obs=e.n_obs if e.role == Role.FEATURE else 0, in_local=False)
        for e, mv in zip((global_map.elements[gi] for gi in shared), moving, strict=True)
    ]
    loc.mean = np.vstack([loc.mean, global_map.mean[shared]])
    cov = np.zeros((3 * len(loc), 3 * len(loc)))
    cov[3 * first :, 3 * first :] = Pss
    loc.cov = cov
    s_dofs = global_map.dofs(shared)
    A = global_map.cov[:, s_dofs] @ psd_pinv(Pss)
    gb = global_map.find(Role.BASE)
    P_sb = global_map.cov[s_dofs, 3 * gb : 3 * gb + 3]
    kinds = [global_map.elements[i].kind for i in shared]
    ctx = CIContext(
        shared_global=shared,
        shared_local=list(range(first, len(loc))),
        moving=[r for r, mv in enumerate(moving) if mv],
        mu_s=global_map.mean[shared].copy(),
        A=A,
        angle_dofs=_angle_dofs(kinds),
        base_mean=global_map.mean[gb].copy(),
        base_cond_cov=global_map.block(gb) - A[3 * gb : 3 * gb + 3] @ P_sb,
    )
    return loc, ctx


def copied_local_map(
    global_map: GaussianMap, known: KnownMapArrays, known_tracks: Mapping[int, int]
) -> GaussianMap:
    """A local map based at the current vehicle pose with its own copy of the anchor
    and of the known map (the paper, §3.3.1–3.3.2, eqs. 17–19).

    ``[x^R_Wlocal, x^R_Wknown, x^Wknown_E…]``: the base at zero with zero covariance;
    the anchor at the global map's ``x^Wlocal_Wknown`` (the local map starts at
    ``Wlocal``) with its global marginal covariance, uncorrelated with the base (eqs.
    17–18); every known feature static in ``Wknown`` with its surveyed covariance,
    uncorrelated with both (eq. 19), on track ``known_tracks[j]``.  Nothing is
    correlated with the global map: the local map counts this information as if it
    were new.
    """
    loc = GaussianMap()
    a = global_map.find(Role.ANCHOR)
    loc.elements = [
        Element(ElementKind.POSE, Role.BASE, moving=True, track=-1),
        Element(ElementKind.POSE, Role.ANCHOR, moving=True, track=-1),
    ]
    means = [np.zeros(3), global_map.mean[a]]
    blocks = [np.zeros((3, 3)), global_map.block(a)]
    for j in range(len(known)):
        element, mean, cov = known_element(known, j, known_tracks[j])
        loc.elements.append(element)
        means.append(mean)
        blocks.append(cov)
    # Filled in one go: GaussianMap.add reallocates the covariance per element.
    loc.mean = np.array(means, dtype=np.float64).reshape(-1, 3)
    loc.cov = block_diag(*blocks)
    loc.symmetrise()
    return loc


def psd_pinv(P: FloatArray, rcond: float = 1e-10) -> FloatArray:
    """Pseudo-inverse of a symmetric positive semi-definite matrix (bound lines make
    the shared covariance singular).

    The symmetric eigensolver is the fast path.  numpy's (LAPACK ``syevd``) can fail
    to converge on a finite PSD matrix: it did on loop600 seed 11's 192 ×
    192 shared covariance at step 1519, whose entries span 1e-2 to 1e-55.  The SVD
    gives the same pseudo-inverse there and is the fallback.
    """
    try:
        out = np.linalg.pinv(P, rcond=rcond, hermitian=True)
    except np.linalg.LinAlgError:
        out = np.linalg.pinv(P, rcond=rcond, hermitian=False)
    return np.asarray(out, dtype=np.float64)


def _seen_from_base(loc: GaussianMap, lb: int, i: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``⊖x^R_Wlocal ⊕ x^R_i`` (``lb`` the base) with Jacobians (base, element)."""
    e = loc.elements[i]
    if e.kind == ElementKind.POSE:
        return relative(loc.mean[lb], loc.mean[i])
    return express_in(e.kind.feature_kind(), loc.mean[lb], loc.mean[i])


@dataclass(frozen=True)
class Motion:
    """Where an odometry increment ``u`` takes the elements expressed in ``R``:
    ``⊖u ⊕ x`` for each moving element, first order in ``u``."""

    mean: FloatArray
    """(n, 3) the elements' means after the motion (static ones unchanged)."""
    rotation: FloatArray
    """(3, 3) ``∂(⊖u ⊕ x)/∂x``, the same for every kind (a static element's is I)."""
    increment_jacobian: FloatArray
    """(3n, 3) ``∂(⊖u ⊕ x)/∂u`` stacked over the elements (zero for a static one),
    with the along-line component of a line's reference point projected out: the
    rotation keeps a bound line bound (its direction turns with it); only the
    increment's noise would add along-line variance (SPmap binding, see state.py)."""
    moving: np.ndarray
    """(n,) bool: the elements that move."""


def motion(loc: GaussianMap, u: FloatArray) -> Motion:
    """The :class:`Motion` of ``loc``'s moving elements by the increment ``u``."""
    moving = np.array([e.moving for e in loc.elements], dtype=bool)
    c, s = math.cos(u[2]), math.sin(u[2])
    m = loc.mean
    dx, dy = m[:, 0] - u[0], m[:, 1] - u[1]
    lx = c * dx + s * dy
    ly = -s * dx + c * dy
    kinds = loc.kinds_roles()[0]
    is_circle = kinds == int(ElementKind.CIRCLE)
    n = len(loc)
    Ju = np.zeros((n, 3, 3))
    Ju[:, 0, 0], Ju[:, 0, 1], Ju[:, 0, 2] = -c, -s, ly
    Ju[:, 1, 0], Ju[:, 1, 1], Ju[:, 1, 2] = s, -c, -lx
    Ju[:, 2, 2] = np.where(is_circle, 0.0, -1.0)
    new = m.copy()
    new[moving, 0] = lx[moving]
    new[moving, 1] = ly[moving]
    rot = moving & ~is_circle
    new[rot, 2] = wrap_angle(m[rot, 2] - u[2])
    lines = moving & (kinds == int(ElementKind.LINE))
    if lines.any():
        ux, uy = np.cos(new[lines, 2]), np.sin(new[lines, 2])
        along = ux[:, None] * Ju[lines, 0, :] + uy[:, None] * Ju[lines, 1, :]
        Ju[lines, 0, :] -= ux[:, None] * along
        Ju[lines, 1, :] -= uy[:, None] * along
    G = np.where(moving[:, None, None], Ju, 0.0).reshape(3 * n, 3)
    R = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    return Motion(new, R, G, moving)


def predict(loc: GaussianMap, u: FloatArray, Q: FloatArray) -> None:
    """Move every element expressed in ``R`` by the odometry increment ``u`` (cov ``Q``)."""
    if not any(e.moving for e in loc.elements):
        return
    apply_motion(loc, motion(loc, u), Q)


def apply_motion(
    loc: GaussianMap, mo: Motion, P_uu: FloatArray, P_xu: FloatArray | None = None
) -> None:
    """Set ``loc`` (its mean and covariance those before the motion) to the moved map,
    first order in the increment whose covariance is ``P_uu`` and whose covariance with
    ``loc``'s elements is ``P_xu`` (3n × 3; ``None``: uncorrelated, the prediction):
    ``P = F P Fᵀ + C Gᵀ + G Cᵀ + G P_uu Gᵀ``, ``F`` the block rotation, ``G`` the
    increment's Jacobian and ``C = F P_xu``."""
    rotate_moving(loc, mo.rotation, mo.moving)
    G = mo.increment_jacobian
    cov = loc.cov + G @ P_uu @ G.T
    if P_xu is not None:
        C = P_xu.reshape(-1, 3, 3).copy()
        C[mo.moving] = mo.rotation @ C[mo.moving]
        GC = G @ C.reshape(-1, 3).T
        cov += GC + GC.T
    loc.cov = cov
    loc.mean = mo.mean
    loc.symmetrise()


def rotate_moving(loc: GaussianMap, Jx: FloatArray, moving: np.ndarray) -> None:
    """``P ← F P Fᵀ`` with ``F = blockdiag(Jx on moving elements, I on static)``.

    One GEMM per side instead of a per-block einsum: the prediction's hot spot.
    """
    n = len(loc)
    P4 = loc.cov.reshape(n, 3, n, 3)
    sel = np.nonzero(moving)[0]
    k = sel.size
    rows = P4[sel].transpose(1, 0, 2, 3).reshape(3, -1)
    P4[sel] = (Jx @ rows).reshape(3, k, n, 3).transpose(1, 0, 2, 3)
    cols = P4[:, :, sel].reshape(-1, 3)
    P4[:, :, sel] = (cols @ Jx.T).reshape(n, 3, k, 3)
    loc.cov = P4.reshape(3 * n, 3 * n)


def vehicle_in_global(
    global_map: GaussianMap, loc: GaussianMap, ctx: CIContext | None
) -> tuple[FloatArray, FloatArray]:
    """Filtered ``x^Wglobal_R`` and its covariance at the current step.

    ``x^Wglobal_R = ⊖(x^R_Wlocal ⊕ x^Wlocal_Wglobal)``.  With a fused local map the
    global base is first corrected by what the local map has learnt about the shared
    elements, and its correlation with ``x^R_Wlocal`` is carried through them.
    """
    gb = global_map.find(Role.BASE)
    lb = loc.find(Role.BASE)
    Pb_l = np.zeros((3, 3))
    if ctx is None:
        b = global_map.mean[gb].copy()
        Pbb = global_map.block(gb).copy()
    else:
        # shared_in_global_frame without its dense Jacobian: only the moving elements'
        # rows mix elements (with the base), so M = A_b Js is assembled from them.
        s_L = loc.mean[ctx.shared_local].copy()
        A_b = ctx.A[3 * gb : 3 * gb + 3]
        M = np.zeros((3, 3 * (len(ctx.shared_local) + 1)))
        M[:, 3:] = A_b
        for r in ctx.moving:
            s_L[r], Jb, Je = _seen_from_base(loc, lb, ctx.shared_local[r])
            Ab_r = A_b[:, 3 * r : 3 * r + 3]
            M[:, 0:3] += Ab_r @ Jb
            M[:, 3 * r + 3 : 3 * r + 6] = Ab_r @ Je
        d = _wrap_flat((s_L - ctx.mu_s).reshape(-1), ctx.angle_dofs)
        dofs = _leading_dofs([lb, *ctx.shared_local])
        P_L = loc.cov[:dofs, :dofs]
        b = ctx.base_mean + A_b @ d
        b[2] = float(wrap_angle(b[2]))
        Pbb = ctx.base_cond_cov + M @ P_L @ M.T
        Pb_l = M @ loc.cov[:dofs, 3 * lb : 3 * lb + 3]
    y, J1, J2 = compose_jacobians(loc.mean[lb], b)
    P_joint = np.block([[loc.block(lb), Pb_l.T], [Pb_l, Pbb]])
    Jy = np.hstack([J1, J2])
    Py = Jy @ P_joint @ Jy.T
    x, Ji = inverse_jacobian(y)
    P = Ji @ Py @ Ji.T
    return x, 0.5 * (P + P.T)


def _leading_dofs(idx: list[int]) -> int:
    """Dof count of the leading elements ``idx`` (the order new_local_map creates)."""
    if idx != list(range(len(idx))):
        raise AssertionError(f"shared elements are not the leading block: {idx}")
    return 3 * len(idx)


def _angle_dofs(kinds: Sequence[ElementKind]) -> np.ndarray:
    """Flat indices of the angles among the parameters of elements of ``kinds``."""
    return np.array(
        [3 * k + 2 for k, kind in enumerate(kinds) if kind != ElementKind.CIRCLE], dtype=np.int64
    )


def _wrap_flat(d: FloatArray, angle_dofs: np.ndarray) -> FloatArray:
    out = d.copy()
    out[angle_dofs] = wrap_angle(out[angle_dofs])
    return out


def _wrap_diff(d: FloatArray, kinds: Sequence[ElementKind]) -> FloatArray:
    """Flattened parameter differences of elements of ``kinds``, angles wrapped."""
    return _wrap_flat(d, _angle_dofs(kinds))


def shared_in_global_frame(
    loc: GaussianMap, ctx: CIContext
) -> tuple[FloatArray, FloatArray, list[int]]:
    """Shared elements of a local map as the global map holds them.

    A moving element (the anchor ``x^R_Wknown``, a carried feature ``x^R_F``) is
    ``⊖x^R_Wlocal ⊕ x`` globally; known features are identical.  Returns their values
    (k, 3), the Jacobian w.r.t. the local elements ``[base, shared…]`` and those local
    indices.
    """
    lb = loc.find(Role.BASE)
    idx = [lb, *ctx.shared_local]
    k = len(ctx.shared_local)
    J = np.zeros((3 * k, 3 * (k + 1)))
    J[:, 3:] = np.eye(3 * k)
    vals = loc.mean[ctx.shared_local].copy()
    for r in ctx.moving:
        vals[r], Jb, Je = _seen_from_base(loc, lb, ctx.shared_local[r])
        J[3 * r : 3 * r + 3, 0:3] = Jb
        J[3 * r : 3 * r + 3, 3 * r + 3 : 3 * r + 6] = Je
    return vals, J, idx


def extend_line(
    e: Element,
    line: FloatArray,
    seg: FloatArray,
    seg_extent: tuple[float, float],
    seg_end_sd: float,
) -> None:
    """Extend line element ``e`` (mean ``line``) by a collinear segment ``seg`` seen on
    ``seg_extent``: its extent becomes the union of both, in the line's frame, and its
    :attr:`~ekf_reference.state.Element.extent_sd` the larger of its own and
    ``seg_end_sd``."""
    if not all(math.isfinite(v) for v in seg_extent):
        return
    u = np.array([math.cos(line[2]), math.sin(line[2])])
    uq = np.array([math.cos(seg[2]), math.sin(seg[2])])
    s = [float((seg[:2] + t * uq - line[:2]) @ u) for t in seg_extent]
    if all(math.isfinite(v) for v in e.extent):
        s += list(e.extent)
    e.extent = (min(s), max(s))
    e.extent_sd = max(e.extent_sd, seg_end_sd)


def tie_anchor_copy(joint: GaussianMap) -> None:
    """At a join with a copied known map (the paper's eqs. 22–24): tie the local map's
    anchor ``x^R_Wknown`` (the second anchor of ``joint``) to the global map's
    ``x^R_Wlocal ⊕ x^Wlocal_Wknown`` (the first, already composed into the new frame)
    by a hard constraint, then drop it.

    The local anchor is a state of the stacked system (eq. 24's ``H^local = I``), so
    the observation noise ``w_known`` of eq. 22 is its own uncertainty and the tie adds
    none.
    """
    a_g, a_l = joint.indices(Role.ANCHOR)
    r = joint.mean[a_l] - joint.mean[a_g]
    r[2] = wrap_angle(r[2])
    H = np.hstack([-np.eye(3), np.eye(3)])
    joint.update([a_g, a_l], r, H, np.zeros((3, 3)))
    joint.remove([a_l])


def compose_into(state: GaussianMap, base: int, frame_elements: list[int]) -> None:
    """Re-express ``frame_elements`` (given in the frame ``state[base]`` is given in)
    through ``state[base]``: ``x ← base ⊕ x``.  Exact mean, first-order covariance."""
    if not frame_elements:
        return
    n = len(state)
    xb = state.mean[base].copy()
    sel = np.asarray(frame_elements, dtype=np.int64)
    Jx = np.zeros((sel.size, 3, 3))
    Jb = np.zeros((sel.size, 3, 3))
    for r, i in enumerate(frame_elements):
        fk = state.elements[i].kind.feature_kind()
        state.mean[i], Jb[r], Jx[r] = transform_feature(fk, xb, state.mean[i])
    # Rows of the transformed elements become Jx_i P_i + Jb_i P_base; others stay.
    P4 = state.cov.reshape(n, 3, n, 3)
    rows = np.einsum("iab,ibjc->iajc", Jx, P4[sel]) + np.einsum("iab,bjc->iajc", Jb, P4[base])
    new = P4.copy()
    new[sel] = rows
    # Columns likewise; the (sel, sel) block then gets both transforms.
    cols = np.einsum("iajc,jdc->iajd", new[:, :, sel], Jx) + np.einsum(
        "iac,jdc->iajd", new[:, :, base], Jb
    )
    new[:, :, sel] = cols
    state.cov = new.reshape(3 * n, 3 * n)
    state.symmetrise()
