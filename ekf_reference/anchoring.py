"""Fusing a CCDA match into a copy of the global map: the anchor and the known map
enter, and the pairings fix the anchor by an iterated update (:func:`fuse_match`), or
the anchor enters as CCDA estimated it (:func:`insert_ccda_estimate`, the paper's eq.
15; ``EKFConfig.anchor_entry``).

The pipeline fuses on a copy so that a match the joint test refuses
(:attr:`~mapfuse_core.matching.AssociationConfig.match_joint_test`) leaves its map as
it was; the copy's new known features get their tracks only once the match is kept.
:func:`vet_match` gives the verdict of both tests and, when one pairing fails its own,
which one: the pipeline can then match again without that feature.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np

from ekf_reference.association import IteratedUpdate, apply_iterated, element_pairings
from ekf_reference.final_map import feature_in_global
from ekf_reference.known_frame import known_element
from ekf_reference.state import Element, ElementKind, GaussianMap, Role
from mapfuse_core.geometry.se2 import compose_jacobians
from mapfuse_core.matching import AssociationConfig, chi2_gate
from mapfuse_core.matching.ccda import CCDAResult
from mapfuse_core.measlog import KnownMapArrays

TieAt = Literal["observed", "target"]
"""Where a tie of two lines measures its lateral residual
(``EKFConfig.line_tie_residual_at``)."""

__all__ = [
    "JOINTLY_INCONSISTENT",
    "PAIRING_INCONSISTENT",
    "Vetted",
    "fuse_match",
    "insert_ccda_estimate",
    "match_arrays",
    "match_arrays_in_global",
    "vet_match",
    "worst_pairing",
]

JOINTLY_INCONSISTENT = "jointly inconsistent"
"""Refusal reason of a match whose pairings fail the joint test
(:attr:`~mapfuse_core.matching.AssociationConfig.match_joint_test`)."""
PAIRING_INCONSISTENT = "a pairing inconsistent with the others"
"""Refusal reason of a match one of whose pairings fails its own test
(:attr:`~mapfuse_core.matching.AssociationConfig.match_pairing_test`)."""


def match_arrays(g: GaussianMap, feats: list[int]) -> KnownMapArrays:
    """The features ``feats`` of ``g`` as CCDA's first map (ids: their indices in ``g``)."""
    return KnownMapArrays(
        ids=np.array(feats, dtype=np.int64),
        kinds=np.array([int(g.elements[i].kind.feature_kind()) for i in feats], dtype=np.int8),
        params=g.mean[feats].copy(),
        covs=np.stack([g.block(i) for i in feats]),
        extents=np.array([g.elements[i].extent for i in feats], dtype=np.float64),
    )


def match_arrays_in_global(g: GaussianMap, feats: list[int]) -> KnownMapArrays:
    """:func:`match_arrays` with the features in ``Wglobal`` (``⊖x^Wlocal_Wglobal ⊕
    x^Wlocal_F``, each with its covariance there): CCDA's transform is then the paper's
    ``x^Wglobal_Wknown`` (§3.2, eq. 12)."""
    out = match_arrays(g, feats)
    for r, i in enumerate(feats):
        out.params[r], out.covs[r] = feature_in_global(g, i)
    return out


def _add_known_map(trial: GaussianMap, known: KnownMapArrays) -> dict[int, int]:
    """Append every known feature to ``trial`` (track −1, uncorrelated); returns the
    index of each in it."""
    known_index: dict[int, int] = {}
    for j in range(len(known)):
        element, mean, cov = known_element(known, j, -1)
        known_index[j] = trial.add(element, mean, cov)
    return known_index


def fuse_match(
    g: GaussianMap,
    feats: list[int],
    known: KnownMapArrays,
    res: CCDAResult,
    assoc: AssociationConfig,
    tie_at: TieAt = "observed",
) -> tuple[GaussianMap, dict[int, int], IteratedUpdate]:
    """A copy of ``g`` with the anchor at CCDA's value under the loose prior
    ``assoc.anchor_prior_sigma``, every known feature (track −1), and the pairings of
    ``res`` (indices into ``feats`` and ``known``) applied by :func:`apply_iterated`
    (a line pairing's lateral residual measured ``tie_at``).

    Returns the copy, the index of each known feature in it, and the update's outcome.
    """
    trial = g.copy()
    sig = np.array(assoc.anchor_prior_sigma)
    trial.add(
        Element(ElementKind.POSE, Role.ANCHOR, moving=False, track=-1),
        res.x_A_B,
        np.diag(sig**2),
    )
    known_index = _add_known_map(trial, known)
    pairs = [(feats[ia], known_index[jb]) for ia, jb in res.pairings]
    # The anchor's prior is flat: iterate, or the anchor depends on where the pairings
    # happened to be linearised (CCDA's estimate).
    upd = apply_iterated(trial, lambda state: element_pairings(state, pairs, tie_at))
    return trial, known_index, upd


def insert_ccda_estimate(
    g: GaussianMap, res: CCDAResult, known: KnownMapArrays | None
) -> tuple[GaussianMap, dict[int, int]]:
    """A copy of ``g`` with the anchor inserted as the paper does (§3.3.1, eqs. 13–16),
    and ``known``'s features when given (track −1, uncorrelated).

    ``res`` is CCDA's match of the map in ``Wglobal`` (:func:`match_arrays_in_global`):
    ``x^Wglobal_Wknown`` with covariance ``C``.  The anchor is
    ``x^Wlocal_Wknown = x^Wlocal_Wglobal ⊕ x^Wglobal_Wknown`` (eq. 13), with covariance
    ``G diag(C, P) Gᵀ`` with the map (eqs. 15–16: ``G = [[J_g, J_X], [0, I]]``, ``J_g``
    and ``J_X`` the Jacobians of eq. 13 w.r.t. CCDA's estimate and the map ``P``, which
    it reads through the base only): CCDA's estimate is taken as independent of the
    map.  The anchor's ``x^Wknown_Wglobal`` is then CCDA's, with CCDA's covariance.
    Returns the copy and the index of each known feature in it.
    """
    trial = g.copy()
    b = trial.find(Role.BASE)
    x, J_X, J_g = compose_jacobians(trial.mean[b], res.x_A_B)
    rows = trial.cov[3 * b : 3 * b + 3, :]
    cov = J_X @ rows[:, 3 * b : 3 * b + 3] @ J_X.T + J_g @ res.cov @ J_g.T
    anchor = Element(ElementKind.POSE, Role.ANCHOR, moving=False, track=-1)
    trial.add(anchor, x, cov, J_X @ rows)
    return trial, {} if known is None else _add_known_map(trial, known)


def worst_pairing(
    g: GaussianMap,
    feats: list[int],
    known: KnownMapArrays,
    res: CCDAResult,
    assoc: AssociationConfig,
    upd: IteratedUpdate,
    tie_at: TieAt = "observed",
) -> tuple[int, float, int] | None:
    """The pairing of ``res`` that fails its own test against the others, if any.

    For each pairing, the match is fused again without it: the NIS it adds,
    ``upd.nis`` less that of the rest, is its χ² given the others (exactly so for a
    linear problem), with its own dimension as the degrees of freedom.  Returns
    ``(index in res.pairings, χ², dof)`` of the largest failure of the
    ``assoc.gate_prob`` quantile, or ``None`` when every pairing passes.
    """
    worst: tuple[int, float, int] | None = None
    worst_ratio = 1.0
    for p in range(len(res.pairings)):
        rest = res.pairings[:p] + res.pairings[p + 1 :]
        if not rest:
            continue
        trimmed = dataclasses.replace(res, pairings=rest)
        _, _, without = fuse_match(g, feats, known, trimmed, assoc, tie_at)
        dof = upd.dims - without.dims
        delta = upd.nis - without.nis
        ratio = delta / chi2_gate(assoc.gate_prob, dof)
        if ratio > worst_ratio:
            worst, worst_ratio = (p, float(delta), dof), ratio
    return worst


@dataclasses.dataclass(frozen=True, eq=False)
class Vetted:
    """A CCDA match fused on a copy of the map, and the verdict of its tests."""

    trial: GaussianMap
    """The copy with the match fused (:func:`fuse_match`)."""
    known_index: dict[int, int]
    """Index in :attr:`trial` of each known feature."""
    update: IteratedUpdate
    """Outcome of the iterated update of all the pairings."""
    refusal: str | None
    """``None`` when the match passes, else :data:`JOINTLY_INCONSISTENT` or
    :data:`PAIRING_INCONSISTENT`."""
    chi2: float
    """The failed statistic (the joint one, or the worst pairing's own); the joint one
    when the match passes."""
    dof: int
    """Its degrees of freedom."""
    culprit: int | None
    """Index in the match's pairings of the pairing that fails its own test by the
    largest ratio to its gate (with the pairing test on), whether the match failed that
    test or the joint one; ``None`` when no pairing fails its own."""


def vet_match(
    g: GaussianMap,
    feats: list[int],
    known: KnownMapArrays,
    res: CCDAResult,
    assoc: AssociationConfig,
    culprit_if_joint_fails: bool = True,
    tie_at: TieAt = "observed",
) -> Vetted:
    """Fuse ``res`` on a copy of ``g`` and test it: jointly (χ² of every pairing, the
    anchor's 3 dimensions less) and, with ``assoc.match_pairing_test``, each pairing
    against the others (:func:`worst_pairing`).  ``culprit_if_joint_fails=False``
    skips the per-pairing fuses when the joint test already refuses the match and no
    culprit is wanted.  ``tie_at``: where a line pairing measures its lateral residual."""
    trial, known_index, upd = fuse_match(g, feats, known, res, assoc, tie_at)
    dof = upd.dims - 3
    if not assoc.match_joint_test:
        return Vetted(trial, known_index, upd, None, upd.nis, dof, None)
    joint_fails = dof > 0 and upd.nis > chi2_gate(assoc.gate_prob, dof)
    bad = None
    if assoc.match_pairing_test and (culprit_if_joint_fails or not joint_fails):
        bad = worst_pairing(g, feats, known, res, assoc, upd, tie_at)
    culprit = None if bad is None else bad[0]
    if joint_fails:
        return Vetted(trial, known_index, upd, JOINTLY_INCONSISTENT, upd.nis, dof, culprit)
    if bad is not None:
        return Vetted(trial, known_index, upd, PAIRING_INCONSISTENT, bad[1], bad[2], culprit)
    return Vetted(trial, known_index, upd, None, upd.nis, dof, None)
