"""The observation update with the step's odometry increment as a state, iterated.

The robotcentric prediction (:func:`~ekf_reference.maps.predict`) composes every
element with the increment ``u`` linearised at its measured value; the update then
corrects the heading change through cross-covariances that are tangent to the
rotation by ``u``, so a feature at distance ``d`` leaves its arc by about ``d·δ²/2`` for a
heading correction ``δ``, in the same direction at every step.  With the increments of a
laser log (heading σ of 0.02–0.03 rad a step) that drift reaches decimetres over a local
map while the covariance, to first order, does not see it (``docs/results/carmen.md``,
the EKF's own part).

Here the update runs on ``[x^R'_E…, u]``: the local map before the prediction (``R'``
the previous vehicle frame) and the increment with its covariance, uncorrelated.  The
pairings are evaluated on ``⊖u ⊕ x`` and chained to that state; the Gauss–Newton
iterations of :func:`~ekf_reference.association.apply_iterated` relinearise the
composition at the updated increment; the map is then composed with the updated
increment (``EKFConfig.odometry_linearisation = "iterated"``).  Without pairings the
result is the prediction's exactly.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ekf_reference.association import Candidate, IteratedUpdate, apply_iterated
from ekf_reference.maps import Motion, apply_motion, motion
from ekf_reference.state import Element, ElementKind, GaussianMap, Role
from mapfuse_core.geometry.se2 import FloatArray

__all__ = ["Increment", "update_through_increment"]

RELATIVE_TOLERANCE = 1e-3
"""Largest mean step of a converged iteration, as a fraction of the element's prior σ:
a step that small moves no NEES by more than a few tenths of a per cent (on Intel, seed
0, absolute steps of 1e-4 to 1e-7 m give the same NEES to four digits)."""
MAX_ITERATIONS = 10
"""Linearisations before the last iterate is kept (``converged`` false)."""


@dataclass(frozen=True)
class Increment:
    """A step's odometry increment and the local map it moves."""

    before: GaussianMap
    """The local map before the prediction (a copy), in the previous vehicle frame."""
    u: FloatArray
    """The measured increment ``x^R'_R``."""
    Q: FloatArray
    """Its covariance (3, 3)."""


def _chained(c: Candidate, mo: Motion, at: dict[int, int], ui: int) -> Candidate:
    """``c`` (linearised in the moved frame) as a pairing of the elements before the
    motion and the increment ``ui``: each moving element's block through the motion
    (``mo`` covers the elements ``at`` maps to their rows)."""
    blocks, HU = [], np.zeros((c.residual.size, 3))
    for j, e in enumerate(c.indices):
        Hb = c.H[:, 3 * j : 3 * j + 3]
        r = at[e]
        if mo.moving[r]:
            blocks.append(Hb @ mo.rotation)
            HU += Hb @ mo.increment_jacobian[3 * r : 3 * r + 3]
        else:
            blocks.append(Hb)
    H = np.hstack([*blocks, HU])
    return Candidate(c.target, c.residual, [*c.indices, ui], H, c.R, c.d2, c.R_gate)


def update_through_increment(
    predicted: GaussianMap,
    inc: Increment,
    pairings: Callable[[GaussianMap], list[Candidate]],
    first: list[Candidate] | None = None,
) -> IteratedUpdate:
    """Update ``predicted`` (``inc.before`` moved by ``inc.u``) with ``pairings``
    relinearised through the increment, and leave it moved by the updated increment.

    ``pairings(state)`` evaluates the step's pairings on a map of ``predicted``'s
    elements at ``state.mean`` (its covariance is the prediction's: it serves their
    Mahalanobis distance only); ``first``, when given, is what it returns on
    ``predicted`` as it comes (the association's candidates), the first
    linearisation.  ``predicted`` must hold the same elements as ``inc.before``.
    """
    n = len(predicted)
    if len(inc.before) != n:
        raise ValueError(
            f"the predicted map has {n} elements and the map before the prediction "
            f"{len(inc.before)}: elements were added in between"
        )
    # ``add`` makes new arrays: the joint state shares nothing it changes with ``inc``.
    joint = GaussianMap()
    joint.elements = list(inc.before.elements)
    joint.mean, joint.cov = inc.before.mean, inc.before.cov
    ui = joint.add(Element(ElementKind.POSE, Role.BASE, moving=False, track=-1), inc.u, inc.Q)

    def moved(state: GaussianMap, elems: list[int]) -> Motion:
        view = GaussianMap()
        view.elements = [state.elements[i] for i in elems]
        view.mean = state.mean[elems]
        return motion(view, state.mean[ui])

    # The pairings read the elements they tie only: move those at each iteration.
    pending: list[Candidate] | None = first if first is not None else pairings(predicted)
    involved = sorted({i for c in pending or [] for i in c.indices})
    at = {e: r for r, e in enumerate(involved)}

    def chained(state: GaussianMap) -> list[Candidate]:
        nonlocal pending
        mo = moved(state, involved)
        if pending is None:
            predicted.mean[involved] = mo.mean
            out = pairings(predicted)
        else:
            # The first linearisation is at the prediction: the pairings as they came.
            out, pending = pending, None
        return [_chained(c, mo, at, ui) for c in out]

    upd = apply_iterated(joint, chained, MAX_ITERATIONS, 0.0, RELATIVE_TOLERANCE)
    # Moved by the updated increment, its covariance with the map included.
    m = 3 * n
    predicted.cov = joint.cov[:m, :m].copy()
    apply_motion(predicted, moved(joint, list(range(n))), joint.cov[m:, m:], joint.cov[:m, m:])
    return upd
