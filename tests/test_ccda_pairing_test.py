"""The test of each pairing of a CCDA match against the others before the EKF fuses
them (``AssociationConfig.match_pairing_test``, :func:`ekf_reference.anchoring.worst_pairing`):
one pairing off by a few of its own σ among right ones passes the joint test and fails
its own."""

from __future__ import annotations

import dataclasses

import numpy as np

from ekf_reference.anchoring import (
    JOINTLY_INCONSISTENT,
    PAIRING_INCONSISTENT,
    fuse_match,
    vet_match,
    worst_pairing,
)
from ekf_reference.state import Element, ElementKind, GaussianMap, Role
from mapfuse_core.geometry.features import FeatureKind, transform_feature
from mapfuse_core.matching import AssociationConfig, chi2_gate
from mapfuse_core.matching.ccda import CCDAResult
from mapfuse_core.measlog import KnownMapArrays
from tests.test_ccda_joint_test import KNOWN as JOINT_KNOWN
from tests.test_ccda_joint_test import SIGMA_COMMON, SIGMA_OWN, TRUTH

KNOWN = np.vstack([JOINT_KNOWN, [[5.0, 20.0, 0.3], [-20.0, 5.0, 0.4]]])
"""The joint test's six circles and two more: eight pairings."""
KNOWN_COV = np.diag([0.02**2, 0.02**2, 0.01**2])
ASSOC = AssociationConfig()


def _case(rng: np.random.Generator, shift_one: float) -> tuple[GaussianMap, KnownMapArrays]:
    """The run's map of eight circles after a shared drift, and the known map with
    the first circle ``shift_one`` m from where it stands."""
    n = len(KNOWN)
    common = np.zeros((3 * n, 3 * n))
    for a in range(n):
        for b in range(n):
            common[3 * a : 3 * a + 2, 3 * b : 3 * b + 2] = SIGMA_COMMON**2 * np.eye(2)
    P = common + np.diag(np.tile(SIGMA_OWN**2, n))
    true_feats = np.array([transform_feature(FeatureKind.CIRCLE, TRUTH, f)[0] for f in KNOWN])
    seen = true_feats + rng.multivariate_normal(np.zeros(3 * n), P).reshape(n, 3)
    g = GaussianMap()
    for i in range(n):
        cross = np.zeros((3, 3 * len(g)))
        cross[:, :] = P[3 * i : 3 * i + 3, : 3 * i]
        g.add(
            Element(ElementKind.CIRCLE, Role.FEATURE, False, i),
            seen[i],
            P[3 * i : 3 * i + 3, 3 * i : 3 * i + 3],
            cross,
        )
    params = KNOWN + rng.normal(size=KNOWN.shape) * np.sqrt(np.diag(KNOWN_COV))
    params[0, 0] += shift_one
    known = KnownMapArrays(
        ids=np.arange(100, 100 + n, dtype=np.int64),
        kinds=np.full(n, int(FeatureKind.CIRCLE), dtype=np.int8),
        params=params,
        covs=np.repeat(KNOWN_COV[None], n, axis=0),
        extents=None,
    )
    return g, known


def _match(n: int) -> CCDAResult:
    return CCDAResult(
        accepted=True,
        reason="accepted",
        pairings=tuple((i, i) for i in range(n)),
        x_A_B=TRUTH + np.array([0.5, -0.4, 0.02]),
        cov=np.diag([1.0, 1.0, 0.01]),
        n_nodes=n,
        n_edges=0,
        clique_size=n,
        runner_up_size=0,
    )


def _tests(shift_one: float, draws: int, seed: int) -> tuple[int, int, int]:
    """Over ``draws`` maps: (joint test passed, a pairing failed, it was the shifted one)."""
    rng = np.random.default_rng(seed)
    joint_ok = failed = shifted = 0
    n = len(KNOWN)
    for _ in range(draws):
        g, known = _case(rng, shift_one)
        res = _match(n)
        feats = list(range(n))
        _, _, upd = fuse_match(g, feats, known, res, ASSOC)
        if upd.nis > chi2_gate(ASSOC.gate_prob, upd.dims - 3):
            continue
        joint_ok += 1
        bad = worst_pairing(g, feats, known, res, ASSOC, upd)
        if bad is not None:
            failed += 1
            shifted += bad[0] == 0
            assert bad[1] > chi2_gate(ASSOC.gate_prob, bad[2])
            assert bad[2] == 3
    return joint_ok, failed, shifted


def test_right_pairings_pass_their_own_tests_but_about_once_in_a_hundred_maps() -> None:
    # Eight pairings at 0.999 each: a right match is refused with probability about
    # 0.8 %; over 150 maps the expected count is 1.2, and 6 has probability < 0.1 %.
    joint_ok, failed, _ = _tests(0.0, 150, seed=11)
    assert joint_ok >= 145
    assert failed <= 6


def test_a_pairing_the_joint_test_lets_through_fails_its_own() -> None:
    # The shifted circle's own σ against the others is about 0.04 m (its 0.03 m, the
    # survey's 0.02 m): 0.2 m is five of them, a χ² of about 25 on 3 dof (gate 16.3)
    # that the joint test (21 dof, gate 46.8) lets through on about half the maps.
    joint_ok, failed, shifted = _tests(0.2, 100, seed=12)
    assert joint_ok >= 25
    assert failed >= 0.7 * joint_ok
    assert shifted == failed


def test_vet_match_names_the_shifted_pairing_whichever_test_refuses_the_match() -> None:
    rng = np.random.default_rng(13)
    n = len(KNOWN)
    feats = list(range(n))
    # 0.2 m: the joint test passes on about half the maps; take the first such map.
    for _ in range(50):
        g, known = _case(rng, 0.2)
        v = vet_match(g, feats, known, _match(n), ASSOC)
        if v.refusal == PAIRING_INCONSISTENT:
            break
    assert v.refusal == PAIRING_INCONSISTENT
    assert v.culprit == 0
    assert v.dof == 3
    assert v.chi2 > chi2_gate(ASSOC.gate_prob, 3)
    # 2 m, fifty of its σ: the joint test refuses; the culprit is still named, unless
    # the caller does not want it (the per-pairing fuses are then skipped).
    g, known = _case(rng, 2.0)
    v = vet_match(g, feats, known, _match(n), ASSOC)
    assert v.refusal == JOINTLY_INCONSISTENT
    assert v.culprit == 0
    v = vet_match(g, feats, known, _match(n), ASSOC, culprit_if_joint_fails=False)
    assert v.refusal == JOINTLY_INCONSISTENT
    assert v.culprit is None
    # With the tests off nothing is refused.
    off = dataclasses.replace(ASSOC, match_joint_test=False)
    assert vet_match(g, feats, known, _match(n), off).refusal is None
