"""Covariances of the graph's solutions: GTSAM's body-tangent Pose2 covariances in
absolute ``(x, y, θ)`` (:func:`body_to_abs_cov`) and every marginal of a linear system in
one pass down its Bayes tree (:func:`tree_marginals`, :func:`bayes_tree_marginals`)."""

from __future__ import annotations

import math
from typing import Any

import gtsam
import numpy as np

from mapfuse_core.geometry.se2 import FloatArray

__all__ = ["bayes_tree_marginals", "body_to_abs_cov", "tree_marginals"]


def _body_to_abs(thetas: FloatArray) -> FloatArray:
    """(k, 3, 3) ``G`` of each heading: a body-tangent perturbation is ``G δ`` absolute."""
    G = np.zeros((thetas.size, 3, 3))
    c, s = np.cos(thetas), np.sin(thetas)
    G[:, 0, 0], G[:, 0, 1], G[:, 1, 0], G[:, 1, 1], G[:, 2, 2] = c, -s, s, c, 1.0
    return G


def body_to_abs_cov(P_body: FloatArray, theta: float) -> FloatArray:
    """Pose2 covariance in GTSAM's body tangent → absolute ``(x, y, θ)``: ``G P Gᵀ`` with
    ``G = blockdiag(R(θ), 1)``, written out (it runs once per filtered step)."""
    c, s = math.cos(theta), math.sin(theta)
    (p00, p01, p02), (p10, p11, p12), (p20, p21, p22) = np.asarray(P_body, dtype=float).tolist()
    # Symmetrised first, as G P Gᵀ of the symmetric part.
    p01 = 0.5 * (p01 + p10)
    p02 = 0.5 * (p02 + p20)
    p12 = 0.5 * (p12 + p21)
    xx = c * c * p00 - 2.0 * c * s * p01 + s * s * p11
    yy = s * s * p00 + 2.0 * c * s * p01 + c * c * p11
    xy = c * s * (p00 - p11) + (c * c - s * s) * p01
    xt = c * p02 - s * p12
    yt = s * p02 + c * p12
    return np.array([[xx, xy, xt], [xy, yy, yt], [xt, yt, p22]])


def _key_dims(values: gtsam.Values) -> list[tuple[int, int]]:
    zero = values.zeroVectors()
    return [(int(k), int(zero.at(k).shape[0])) for k in list(values.keys())]


def tree_marginals(lin: gtsam.GaussianFactorGraph, dims: dict[int, int]) -> dict[int, FloatArray]:
    """Marginal covariance of every variable of the linear system ``lin`` (tangent space).

    ``dims`` maps each key to its tangent dimension.  One multifrontal elimination, then
    one pass down the Bayes tree: a clique's conditional ``R δ_F + S δ_S = d`` (whitened)
    and the joint covariance ``Σ_SS`` of its separator, taken from its parent's joint
    covariance, give ``Σ_FS = −R⁻¹ S Σ_SS`` and ``Σ_FF = R⁻¹ R⁻ᵀ − Σ_FS (R⁻¹ S)ᵀ``.
    Exact, like ``gtsam.Marginals``, but each clique is handled once: asking GTSAM for
    every variable's ``marginalCovariance`` re-eliminates the clique's conditional with
    its separator marginal for each variable, which costs an order of magnitude more
    where separators reach a few hundred dimensions (Victoria Park;
    ``docs/results/performance.md``).
    """
    return bayes_tree_marginals(lin.eliminateMultifrontal(), dims)


def bayes_tree_marginals(
    bt: gtsam.GaussianBayesTree, dims: dict[int, int]
) -> dict[int, FloatArray]:
    """:func:`tree_marginals` of a system already eliminated into the Bayes tree ``bt``
    (a caller that also solves the system eliminates it once)."""
    out: dict[int, FloatArray] = {}
    roots = bt.roots()
    # (clique, offset of each key in the parent's joint covariance, that covariance)
    stack: list[tuple[Any, dict[int, int], FloatArray]] = [
        (roots[i], {}, np.zeros((0, 0))) for i in range(len(roots))
    ]
    while stack:
        clique, parent_at, parent_cov = stack.pop()
        cond = clique.conditional()
        keys = list(map(int, cond.keys()))
        Ab = np.asarray(cond.augmentedJacobian())  # whitened [R S d]
        nf = Ab.shape[0]  # R is square: one row per frontal dimension
        Rinv = np.linalg.inv(Ab[:, :nf])
        n_front, width = 0, 0
        while width < nf:
            width += dims[keys[n_front]]
            n_front += 1
        seps = keys[n_front:]
        n_children = clique.nrChildren()
        # Leaves need their frontal block only; parents the whole joint for their children.
        size = Ab.shape[1] - 1 if n_children else nf
        joint = np.empty((size, size))
        if seps:
            idx = [i for k in seps for i in range(parent_at[k], parent_at[k] + dims[k])]
            cov_ss = parent_cov[idx][:, idx]
            G = Rinv @ Ab[:, nf:-1]
            cov_fs = -G @ cov_ss
            joint[:nf, :nf] = Rinv @ Rinv.T - cov_fs @ G.T
            if n_children:
                joint[:nf, nf:] = cov_fs
                joint[nf:, :nf] = cov_fs.T
                joint[nf:, nf:] = cov_ss
        else:
            joint[:nf, :nf] = Rinv @ Rinv.T
        at = 0
        for k in keys[:n_front]:
            d = dims[k]
            block = joint[at : at + d, at : at + d]
            out[k] = 0.5 * (block + block.T)
            at += d
        if n_children == 0:
            continue
        key_at: dict[int, int] = {}
        at = 0
        for k in keys:
            key_at[k] = at
            at += dims[k]
        stack.extend((clique[i], key_at, joint) for i in range(n_children))
    return out
