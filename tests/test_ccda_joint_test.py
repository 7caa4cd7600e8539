"""The joint test of a CCDA match's pairings before the EKF fuses them
(``AssociationConfig.match_joint_test``): its statistic, and what the EKF does with it."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

import ekf_reference.pipeline as pipeline
from ekf_reference import EKFConfig, run_ekf
from ekf_reference.association import apply_iterated, element_pairings
from ekf_reference.pipeline import JOINTLY_INCONSISTENT
from ekf_reference.state import Element, ElementKind, GaussianMap, Role
from mapfuse_core.geometry.features import FeatureKind, transform_feature
from mapfuse_core.matching import chi2_gate
from mapfuse_core.matching.ccda import CCDAResult, pairing_chi2
from mapfuse_core.measlog import KnownMapArrays
from tests.synthetic import synthetic_log

TRUTH = np.array([3.0, -2.0, 0.4])
FLAT = np.diag([100.0**2, 100.0**2, np.pi**2])
KNOWN = np.array(
    [
        [10.0, 2.0, 0.3],
        [-6.0, 8.0, 0.4],
        [25.0, -12.0, 0.25],
        [-15.0, -20.0, 0.5],
        [18.0, 15.0, 0.35],
        [-2.0, -9.0, 0.45],
    ]
)
KNOWN_COV = np.diag([1e-4, 1e-4, 1e-4])
SIGMA_COMMON = 1.0
"""σ (m) of the drift the features share (the vehicle's, carried into every feature)."""
SIGMA_OWN = np.array([0.03, 0.03, 0.01])
"""σ of each feature's own error (x, y, radius)."""


def _drifted_map(
    rng: np.random.Generator, shift_one: float = 0.0
) -> tuple[GaussianMap, list[tuple[int, int]]]:
    """Six circles seen after a drift they share: each is known to ±1 m, their relative
    positions to ±4 cm.  ``shift_one`` (m) moves the first one's partner: a wrong
    pairing whose offset is within the shared drift."""
    n = len(KNOWN)
    common = np.zeros((3 * n, 3 * n))
    for a in range(n):
        for b in range(n):
            common[3 * a : 3 * a + 2, 3 * b : 3 * b + 2] = SIGMA_COMMON**2 * np.eye(2)
    P = common + np.diag(np.tile(SIGMA_OWN**2, n))
    true_feats = np.array([transform_feature(FeatureKind.CIRCLE, TRUTH, f)[0] for f in KNOWN])
    seen = true_feats + rng.multivariate_normal(np.zeros(3 * n), P).reshape(n, 3)
    known = KNOWN + rng.normal(size=KNOWN.shape) * np.sqrt(np.diag(KNOWN_COV))
    known[0, 0] += shift_one
    m = GaussianMap()
    guess = TRUTH + np.array([0.5, -0.4, 0.02])
    m.add(Element(ElementKind.POSE, Role.ANCHOR, False, -1), guess, FLAT)
    feats = []
    for i in range(n):
        cross = np.zeros((3, 3 * len(m)))
        cross[:, 3:] = P[3 * i : 3 * i + 3, : 3 * i]
        feats.append(
            m.add(
                Element(ElementKind.CIRCLE, Role.FEATURE, False, i),
                seen[i],
                P[3 * i : 3 * i + 3, 3 * i : 3 * i + 3],
                cross,
            )
        )
    pairs = []
    for i in range(n):
        k = m.add(Element(ElementKind.CIRCLE, Role.KNOWN, False, 100 + i), known[i], KNOWN_COV)
        pairs.append((feats[i], k))
    return m, pairs


def _update(m: GaussianMap, pairs: list[tuple[int, int]]) -> tuple[float, int]:
    upd = apply_iterated(m, lambda state: element_pairings(state, pairs))
    assert upd.converged
    return upd.nis, upd.dims - 3


def test_joint_nis_of_correct_pairings_is_chi2_less_the_anchors_three_dofs() -> None:
    # 400 maps: the mean of χ²(15) over 400 draws has a standard error of
    # sqrt(2·15/400) = 0.27; 4 standard errors is 1.1.
    rng = np.random.default_rng(7)
    nis = []
    for _ in range(400):
        m, pairs = _drifted_map(rng)
        c2, dof = _update(m, pairs)
        nis.append(c2)
    assert dof == 15
    assert abs(float(np.mean(nis)) - 15.0) < 1.1
    # The 99.9 % gate refuses a correct match about once in a thousand.
    assert np.mean(np.array(nis) > chi2_gate(0.999, 15)) < 0.01


def test_a_wrong_pairing_within_the_shared_drift_passes_every_marginal_gate_not_the_joint_one() -> (
    None
):
    rng = np.random.default_rng(3)
    m, pairs = _drifted_map(rng, shift_one=0.6)
    c2, dof = _update(m, pairs)
    assert c2 > chi2_gate(0.999, dof)
    # What CCDA tests: each pairing alone, with the features' marginal covariances.
    m0, _ = _drifted_map(np.random.default_rng(3), shift_one=0.6)
    feats = [i for i, _ in pairs]
    knowns = [k for _, k in pairs]
    map_a = KnownMapArrays(
        ids=np.arange(len(feats)),
        kinds=np.full(len(feats), int(FeatureKind.CIRCLE), dtype=np.int8),
        params=m0.mean[feats],
        covs=np.stack([m0.block(i) for i in feats]),
    )
    map_b = KnownMapArrays(
        ids=np.arange(len(knowns)),
        kinds=np.full(len(knowns), int(FeatureKind.CIRCLE), dtype=np.int8),
        params=m0.mean[knowns],
        covs=np.stack([m0.block(k) for k in knowns]),
    )
    per_pair, dofs = pairing_chi2(map_a, map_b, m.mean[0], [(i, i) for i in range(len(feats))])
    assert np.all(per_pair <= chi2_gate(0.999, 3))
    assert dofs.tolist() == [3] * len(feats)


class _Swapping:
    """``ccda_match`` that, on the first accepted match, pairs the map circle of the last
    circle pairing with a known circle no pairing uses; when ``persistent``, also every
    later match that pairs that map feature.  Records the map feature ids of every call."""

    def __init__(self, persistent: bool) -> None:
        self.original = pipeline.ccda_match
        self.persistent = persistent
        self.calls: list[list[int]] = []
        self.feature: int | None = None
        """Id (in the map given to CCDA) of the map feature given the wrong partner."""
        self.other: int | None = None
        """Row of that wrong partner in the known map."""
        self.known_id: int | None = None
        """Its id."""
        self.row_differs = False
        """Whether the swapped pairing's index in the match differs from its row in the
        map (so a mix-up of the two excludes another feature)."""

    def __call__(self, map_a: KnownMapArrays, map_b: KnownMapArrays, params: object) -> CCDAResult:
        self.calls.append([int(i) for i in map_a.ids])
        res = self.original(map_a, map_b, params)  # type: ignore[arg-type]
        if not res.accepted:
            return res
        circles = [j for j in range(len(map_b)) if map_b.kinds[j] == int(FeatureKind.CIRCLE)]
        if self.feature is None:
            used = {jb for _, jb in res.pairings}
            p, (ia, _) = [(p, x) for p, x in enumerate(res.pairings) if x[1] in circles][-1]
            self.feature = int(map_a.ids[ia])
            self.other = next(j for j in circles if j not in used)
            self.known_id = int(map_b.ids[self.other])
            self.row_differs = p != ia
        elif not self.persistent:
            return res
        hit = [ia for ia, _ in res.pairings if int(map_a.ids[ia]) == self.feature]
        if not hit or any(jb == self.other for _, jb in res.pairings):
            return res
        bad = tuple((a, self.other if a == hit[0] else b) for a, b in res.pairings)
        return dataclasses.replace(res, pairings=bad)


@pytest.mark.parametrize(("joint_test", "exclusions"), [(True, 0), (True, 4), (False, 4)])
def test_ekf_refuses_a_jointly_inconsistent_match_counts_it_and_anchors_without_it(
    monkeypatch: pytest.MonkeyPatch, joint_test: bool, exclusions: int
) -> None:
    log = synthetic_log(steps=300, seed=4)
    # With the re-run the wrong partner is offered again whenever that map feature is
    # in the match: only its exclusion gives a correct anchor at the refusal's step.
    swap = _Swapping(persistent=exclusions > 0 and joint_test)
    monkeypatch.setattr(pipeline, "ccda_match", swap)
    # The joint test alone: the anchor watch would undo the wrong match fused without
    # it later in the run (tests/test_anchor_watch.py).
    cfg = EKFConfig(anchor_watch=None)
    assoc = dataclasses.replace(
        cfg.data_association, match_joint_test=joint_test, match_exclusions=exclusions
    )
    cfg = dataclasses.replace(cfg, data_association=assoc)
    with warnings.catch_warnings():
        # The corrupted match, fused, does not converge and says so.
        warnings.simplefilter("ignore", RuntimeWarning)
        res = run_ekf(log, cfg, fusion=True)
    assert res.matching is not None
    reasons = res.matching.reasons
    assert sum(reasons.values()) == res.matching.attempts == len(swap.calls)
    assert res.anchor is not None
    wrong = [(t, kid) for t, kid in res.anchor.pairings if t != kid]
    if not joint_test:
        assert JOINTLY_INCONSISTENT not in reasons
        assert res.details.ccda_refused == ()
        assert res.details.ccda_excluded == ()
        assert len(wrong) == 1
        return
    assert reasons[JOINTLY_INCONSISTENT] == 1
    ((step, c2, dof),) = res.details.ccda_refused
    assert c2 > chi2_gate(cfg.data_association.gate_prob, dof)
    assert wrong == []
    if exclusions == 0:
        # Refused as it stands; a correct match comes at a later attempt.
        assert res.details.ccda_excluded == ()
        assert res.anchor.accepted_at_step > step
        return
    # The swapped pairing fails its own test; CCDA runs again at once on the same map
    # less exactly that feature, and its match is accepted at the same step.
    assert swap.row_differs
    assert res.details.ccda_excluded == ((step, swap.known_id),)
    assert res.anchor.accepted_at_step == step
    first, rerun = swap.calls[-2:]
    assert swap.feature in first
    assert rerun == [i for i in first if i != swap.feature]
