"""The factor-graph mirror: agreement with the EKF, iSAM2 vs batch, ties, NEES, validation."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import gtsam
import numpy as np
import pytest

from ekf_reference import EKFConfig, run_ekf
from mapfuse_core.data.measlog import MeasurementLog
from mapfuse_core.evaluation import nees_series, pose_errors, truth_in_global
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import compose, inverse, wrap_angle
from mapfuse_core.matching import AssociationConfig, chi2_gate
from mapfuse_core.matching.ccda import CCDAParams
from mapfuse_graph import factors as fx
from mapfuse_graph.graph import (
    GraphBuilder,
    GraphOptions,
    landmark_key,
    odometry_noise_cov,
    pose_key,
)
from mapfuse_graph.solvers import (
    GraphResult,
    ISAM2Options,
    _ISAM2Estimate,
    _joint_pose_cov,
    _newest_last,
    _newest_pose_marginal,
    _ValuesEstimate,
    body_to_abs_cov,
    levenberg_marquardt,
    run_graph,
    tree_marginals,
)
from tests.synthetic import synthetic_log

SIGMA_ODO = np.array([0.01, 0.005, 0.002])


@pytest.fixture(autouse=True)
def _guard_on() -> object:
    before = fx.jacobian_checks_enabled()
    fx.set_jacobian_checks(True)
    yield
    fx.set_jacobian_checks(before)


def _scaled_log(steps: int, seed: int, scale: float) -> MeasurementLog:
    return synthetic_log(
        steps=steps,
        seed=seed,
        sigma_odo=tuple(scale * SIGMA_ODO),
        sigma_circle=0.03 * scale,
        sigma_line=(0.02 * scale, 0.005 * scale),
    )


def _rel_diff(a: np.ndarray, b: np.ndarray, covs: np.ndarray) -> np.ndarray:
    """|a − b| / σ per step and coordinate (angle wrapped), step 0 excluded."""
    d = a - b
    d[:, 2] = wrap_angle(d[:, 2])
    sig = np.sqrt(np.einsum("kii->ki", covs))
    return np.asarray(np.abs(d[1:]) / sig[1:])


# --------------------------------------------------------------------------- agreement


@pytest.mark.parametrize(("scale", "tol"), [(0.3, 0.25), (0.03, 0.05)])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_isam2_filtered_agrees_with_ekf(seed: int, scale: float, tol: float) -> None:
    """Short run, one local map (no joins), same association: filtered graph ≈ EKF.

    The remaining difference is the EKF's single linearisation against the graph's
    relinearisation: it shrinks in proportion to the noise (measured max 0.19 σ at
    scale 0.3, 0.03 σ at scale 0.03), so it is not a model difference.
    """
    log = _scaled_log(60, seed, scale)
    ekf = run_ekf(log, EKFConfig(fusion=False, local_map_steps=10_000))
    res = run_graph(
        log, "isam2", fusion=False, association="ekf", decisions=ekf.decisions, marginals=False
    )
    assert res.filtered_poses is not None
    assert res.filtered_covs is not None
    assert _rel_diff(res.filtered_poses, ekf.poses, ekf.covs).max() <= tol
    ratio = np.einsum("kii->ki", res.filtered_covs[1:]) / np.einsum("kii->ki", ekf.covs[1:])
    assert ratio.min() >= 0.97
    assert ratio.max() <= 1.03


def test_batch_on_steps_0_to_k_is_the_filtered_estimate() -> None:
    """Batch over steps 0..k gives iSAM2's filtered X_k (measured ≤ 0.01 σ)."""
    log = synthetic_log(steps=60, seed=0)
    inc = run_graph(log, "isam2", fusion=False, association="truth", marginals=False)
    assert inc.filtered_poses is not None
    assert inc.filtered_covs is not None
    for k in (5, 30, 59):
        batch = run_graph(log, "batch", fusion=False, association="truth", steps=k + 1)
        d = batch.poses[k] - inc.filtered_poses[k]
        d[2] = float(wrap_angle(d[2]))
        sig = np.sqrt(np.diag(inc.filtered_covs[k]))
        assert np.all(np.abs(d) <= 0.03 * sig)
        np.testing.assert_allclose(np.diag(batch.covs[k]), np.diag(inc.filtered_covs[k]), rtol=0.02)


@pytest.mark.parametrize("association", ["truth", "own"])
def test_isam2_final_equals_batch(association: str) -> None:
    log = synthetic_log(steps=200, seed=1)
    inc = run_graph(log, "isam2", fusion=True, association=association)
    bat = run_graph(log, "batch", fusion=True, association=association)
    np.testing.assert_array_equal(inc.obs_landmark, bat.obs_landmark)
    assert _rel_diff(inc.poses, bat.poses, bat.covs).max() <= 0.05
    np.testing.assert_allclose(
        np.einsum("kii->ki", inc.covs[1:]), np.einsum("kii->ki", bat.covs[1:]), rtol=0.02
    )
    assert inc.anchor is not None
    assert bat.anchor is not None
    d = inc.anchor.x_Wknown_Wglobal - bat.anchor.x_Wknown_Wglobal
    assert np.all(np.abs(d) <= 0.05 * np.sqrt(np.diag(bat.anchor.cov)))
    assert inc.final_error == pytest.approx(bat.final_error, rel=1e-4)


def test_filtered_estimate_is_isam2s_own_solve_and_marginal() -> None:
    """The newest pose read off the root's last rows (fusion on: anchor, known features and
    ties enter mid-run) equals iSAM2's full linear solve and its own marginal."""
    log = synthetic_log(steps=60, seed=2)
    n = log.n_steps
    b = GraphBuilder(log, GraphOptions(association="truth"))
    isam = gtsam.ISAM2()
    lin_point = isam.getLinearizationPoint()
    est = _ISAM2Estimate(isam, np.zeros((n, 3, 3)))
    for k in range(n):
        sg = b.step(k, est)
        keys = sg.factors.keys()
        isam.update(sg.factors, sg.values, [], _newest_last([int(q) for q in keys], pose_key(k)))
        x, P, shortcut = _newest_pose_marginal(isam, lin_point, pose_key(k))
        assert shortcut
        best = fx.pose_of(isam.calculateBestEstimate().atPose2(pose_key(k)))
        np.testing.assert_allclose(x, best, rtol=0, atol=1e-9)
        np.testing.assert_allclose(P, isam.marginalCovariance(pose_key(k)), rtol=1e-8, atol=1e-15)
        est.last_pose = (k, x)
    assert b.anchor_added
    res = run_graph(log, "isam2", association="truth", marginals=False)
    assert res.extra["filtered_marginal_shortcuts"] == n


def test_tree_marginals_equal_gtsam_marginals() -> None:
    """One pass down the Bayes tree gives GTSAM's marginal of every variable (poses, 2-dim
    lines, 3-dim circles, anchor, known features)."""
    log = synthetic_log(steps=50, seed=4)
    b = GraphBuilder(log, GraphOptions(association="truth"))
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    est = _ValuesEstimate(values)
    for k in range(log.n_steps):
        sg = b.step(k, est)
        graph.push_back(sg.factors)
        values.insert(sg.values)
    lin = graph.linearize(values)
    zero = values.zeroVectors()
    keys = list(map(int, values.keys()))
    dims = {q: int(zero.at(q).shape[0]) for q in keys}
    assert {2, 3} <= set(dims.values())
    got = tree_marginals(lin, dims)
    ref = gtsam.Marginals(lin, values)
    assert set(got) == set(keys)
    for q in keys:
        P = ref.marginalCovariance(q)
        np.testing.assert_allclose(got[q], P, rtol=0, atol=1e-9 * np.abs(P).max())


def test_circle_centre_factor_is_the_circle_factors_centre_rows() -> None:
    rng = np.random.default_rng(5)
    xk, ck = pose_key(0), landmark_key(0, FeatureKind.CIRCLE)
    for theta in (0.3, math.pi - 1e-9, -math.pi + 1e-9, -2.0):
        x = np.array([*rng.uniform(-20, 20, 2), theta])
        z = np.array([*rng.uniform(-10, 10, 2), 0.4])
        c = rng.uniform(-20, 20, 2)
        v = gtsam.Values()
        v.insert(xk, gtsam.Pose2(*x))
        v.insert(ck, c)
        lin = fx.circle_centre_factor(xk, ck, z, gtsam.noiseModel.Unit.Create(2)).linearize(v)
        A, b = lin.jacobian()
        xv = fx.pose_of(v.atPose2(xk))
        r, Jx, Jc = fx.circle_observation_error(z, xv, np.array([*c, 0.7]))
        np.testing.assert_allclose(-b, r[:2], rtol=0, atol=1e-12)
        np.testing.assert_allclose(A[:, :3], fx.to_body(Jx, float(xv[2]))[:2], rtol=0, atol=1e-12)
        np.testing.assert_allclose(A[:, 3:], Jc[:2, :2], rtol=0, atol=1e-12)


@pytest.mark.parametrize("backend", ["batch", "isam2"])
def test_split_circles_is_the_same_model(backend: str) -> None:
    """Centre and radius variables ≡ one (x, y, r) variable when the observations' radius
    noise is independent of the centre's (the synthetic logs' diagonal covariances)."""
    log = synthetic_log(steps=120, seed=3)
    joint = run_graph(log, backend, fusion=False, association="truth")
    split = run_graph(
        log, backend, fusion=False, association="truth", options=GraphOptions(split_circles=True)
    )
    circles = split.landmarks.kinds == int(FeatureKind.CIRCLE)
    assert np.any(circles)
    assert split.n_variables == joint.n_variables + int(circles.sum())
    # Measured 6e-8 σ (batch) and 2e-6 σ (isam2, whose linearisation points lag a little
    # differently when the radius has its own relinearisation threshold).
    tol = 1e-6 if backend == "batch" else 1e-4
    assert _rel_diff(split.poses, joint.poses, joint.covs).max() <= tol
    assert split.final_error == pytest.approx(joint.final_error, rel=1e-6)
    sig = np.sqrt(np.einsum("kii->ki", joint.landmarks.covs))
    d = np.abs(split.landmarks.variables - joint.landmarks.variables)
    assert np.nanmax(d[circles] / sig[circles]) <= tol
    np.testing.assert_allclose(
        split.landmarks.covs[circles], joint.landmarks.covs[circles], rtol=1e-6, atol=1e-15
    )
    assert np.all(split.landmarks.covs[circles][:, :2, 2] == 0.0)


def test_split_circles_refuses_what_would_change_the_model(small_log: MeasurementLog) -> None:
    split = GraphOptions(split_circles=True)
    with pytest.raises(ValueError, match="fixed association"):
        run_graph(small_log, "isam2", fusion=False, association="own", options=split)
    with pytest.raises(ValueError, match="robust"):
        run_graph(
            small_log, "isam2", fusion=False, association="truth", robust="huber", options=split
        )
    with pytest.raises(ValueError, match="known map with circles"):
        run_graph(small_log, "isam2", fusion=True, association="truth", options=split)
    cov = small_log.feat_cov.copy()
    j = int(np.nonzero(small_log.feat_kind == int(FeatureKind.CIRCLE))[0][0])
    cov[j, 0, 2] = cov[j, 2, 0] = 0.1 * math.sqrt(cov[j, 0, 0] * cov[j, 2, 2])
    with pytest.raises(ValueError, match=f"observation {j} correlates"):
        run_graph(
            _tampered(small_log, feat_cov=cov),
            "isam2",
            fusion=False,
            association="truth",
            options=split,
        )


def _known_frame_solution(log: MeasurementLog) -> np.ndarray:
    """The same problem written in ``Wknown`` without an anchor or ties.

    Poses ``Y_k = x^Wknown_R_k`` with no prior on ``Y_0``; landmarks in ``Wknown``, and
    each landmark that is a known feature carries that feature's prior directly.
    Then ``x^Wknown_Wglobal = Y_0`` and ``x^Wglobal_R_k = ⊖Y_0 ⊕ Y_k``.
    """
    g = gtsam.NonlinearFactorGraph()
    v = gtsam.Values()
    assert log.true_poses is not None
    tp = log.true_poses
    for k in range(log.n_steps):
        v.insert(pose_key(k), gtsam.Pose2(*tp[k]))
        if k:
            u = log.odometry[k]
            noise = fx.make_noise(odometry_noise_cov(u, log.odometry_cov[k]))
            g.add(gtsam.BetweenFactorPose2(pose_key(k - 1), pose_key(k), gtsam.Pose2(*u), noise))
    dense: dict[int, int] = {}
    known_row = {int(i): r for r, i in enumerate(log.known_map.ids)}
    for j in range(log.n_features):
        tid, k = int(log.feat_true_id[j]), int(log.feat_step[j])
        kind = FeatureKind(int(log.feat_kind[j]))
        if tid not in dense:
            dense[tid] = len(dense)
            key = landmark_key(dense[tid], kind)
            v.insert(key, fx.landmark_from_observation(kind, tp[k], log.feat_params[j]))
            if tid in known_row:
                r = known_row[tid]
                mean, P = log.known_map.params[r], log.known_map.covs[r]
                if kind == FeatureKind.LINE:
                    g.add(fx.known_line_prior_factor(key, mean, P))
                else:
                    g.add(gtsam.PriorFactorVector(key, mean, fx.make_noise(P)))
        key = landmark_key(dense[tid], kind)
        g.add(fx.observation_factor(kind, pose_key(k), key, log.feat_params[j], log.feat_cov[j]))
    sol, report = levenberg_marquardt(g, v)
    assert report.converged
    return np.array([fx.pose_of(sol.atPose2(pose_key(k))) for k in range(log.n_steps)])


@pytest.mark.parametrize(
    ("known_sigma", "tie_sigma", "tol"),
    [
        ((0.1, 0.1, 0.05), (1e-3, 1e-4), 1e-3),  # the known map's σ (measured 4e-5 σ)
        ((1e-4, 1e-4, 1e-5), (1e-6, 1e-7), 1e-5),  # known features fixed (measured 3e-7 σ)
    ],
)
def test_anchor_ties_equal_known_features_as_priors(
    known_sigma: tuple[float, float, float], tie_sigma: tuple[float, float], tol: float
) -> None:
    """Tie factors through the anchor ≡ priors on the landmarks in Wknown."""
    log = synthetic_log(steps=80, seed=0, known_sigma=known_sigma)
    Y = _known_frame_solution(log)
    res = run_graph(
        log, "batch", fusion=True, association="truth", options=GraphOptions(tie_sigma=tie_sigma)
    )
    assert res.anchor is not None
    da = res.anchor.x_Wknown_Wglobal - Y[0]
    da[2] = float(wrap_angle(da[2]))
    assert np.all(np.abs(da) <= tol * np.sqrt(np.diag(res.anchor.cov)))
    X = np.array([compose(inverse(Y[0]), y) for y in Y])
    assert _rel_diff(res.poses, X, res.covs).max() <= tol


def test_smoothed_nees_is_consistent() -> None:
    """Exactly Gaussian logs: smoothed NEES averages near 3 (30 seeds measured 2.80)."""
    means, within = [], []
    for seed in range(10):
        log = synthetic_log(steps=60, seed=seed)
        res = run_graph(log, "isam2", fusion=True, association="truth")
        assert log.true_poses is not None
        nees = nees_series(pose_errors(res.poses, truth_in_global(log.true_poses)).dx, res.covs)
        means.append(np.nanmean(nees))
        within.append(np.nanmean(nees <= 7.815))
    assert 2.0 <= float(np.mean(means)) <= 4.0
    assert float(np.mean(within)) >= 0.9


def test_body_to_abs_cov_matches_sampled_retractions() -> None:
    rng = np.random.default_rng(1)
    base = gtsam.Pose2(3.0, -2.0, 2.5)
    P_body = np.array([[4e-4, 1e-4, 2e-5], [1e-4, 9e-4, -3e-5], [2e-5, -3e-5, 1e-5]])
    samples = np.array(
        [fx.pose_of(base.retract(d)) for d in rng.multivariate_normal(np.zeros(3), P_body, 20000)]
    )
    emp = np.cov(samples.T)
    np.testing.assert_allclose(body_to_abs_cov(P_body, base.theta()), emp, rtol=0.05, atol=2e-6)


# --------------------------------------------------------------------------- association


def _purity(lm: np.ndarray, true_ids: np.ndarray) -> float:
    ok = n = 0
    for i in np.unique(lm[lm >= 0]):
        _, counts = np.unique(true_ids[lm == i], return_counts=True)
        ok += int(counts.max())
        n += int(counts.sum())
    return ok / n


def test_own_association_recovers_the_world() -> None:
    log = synthetic_log(steps=200, seed=0)
    res = run_graph(log, "isam2", fusion=True, association="own")
    assert _purity(res.obs_landmark, log.feat_true_id) == 1.0
    assert len(res.landmarks.kinds) == len(np.unique(log.feat_true_id))
    assert res.anchor is not None
    assert res.anchor.source == "ccda"
    assert all(t == k for t, k in res.anchor.pairings)
    assert log.true_poses is not None
    d = res.anchor.x_Wknown_Wglobal - log.true_poses[0]
    d[2] = float(wrap_angle(d[2]))
    assert float(d @ np.linalg.solve(res.anchor.cov, d)) <= 16.27  # χ²(3, 0.999)


def test_ekf_and_graph_read_one_association_config(monkeypatch: pytest.MonkeyPatch) -> None:
    """The EKF's CCDA call and the graph's own CCDA call both receive the parameters of
    the one AssociationConfig they are given, and the graph gates with its χ² probability."""
    import ekf_reference.pipeline
    import mapfuse_graph.own_association
    from mapfuse_core.matching import ccda

    cfg = AssociationConfig(gate_prob=0.995, ccda=CCDAParams(min_pairings=5))
    seen: dict[str, list[CCDAParams]] = {"ekf": [], "graph": []}

    def spy(who: str) -> Callable[..., ccda.CCDAResult]:
        def call(a: object, b: object, params: CCDAParams) -> ccda.CCDAResult:
            seen[who].append(params)
            return ccda.ccda_match(a, b, params)  # type: ignore[arg-type]

        return call

    monkeypatch.setattr(ekf_reference.pipeline, "ccda_match", spy("ekf"))
    monkeypatch.setattr(mapfuse_graph.own_association, "ccda_match", spy("graph"))
    log = synthetic_log(steps=120, seed=0)
    run_ekf(log, EKFConfig(fusion=True, data_association=cfg))
    opts = GraphOptions(association="own", data_association=cfg)
    run_graph(log, "isam2", fusion=True, association="own", options=opts)
    assert seen["ekf"]
    assert seen["graph"]
    assert all(p is cfg.ccda for p in seen["ekf"] + seen["graph"])
    b = GraphBuilder(log, opts)
    assert b._gate == {2: chi2_gate(0.995, 2), 3: chi2_gate(0.995, 3)}


def test_mapfuse_defaults_give_the_graph_the_ekfs_association_config(
    small_log: MeasurementLog,
) -> None:
    from mapfuse import registry
    from mapfuse.profiles import default_options

    ekf = default_options(registry.get("ekf"), small_log).data_association
    graph = default_options(registry.get("batch"), small_log).graph.data_association
    assert graph == ekf
    assert graph.ccda.min_pairings == 8


def _line_landmarks_taking_two_segments(res: GraphResult, log: MeasurementLog) -> int:
    """Scans in which one line landmark takes two or more observations."""
    n = 0
    for k in range(log.n_steps):
        sl = log.feature_slice(k)
        lm = res.obs_landmark[sl][(log.feat_kind[sl] == int(FeatureKind.LINE))]
        lm = lm[lm >= 0]
        n += int(lm.size - np.unique(lm).size)
    return n


def test_own_association_gives_a_wall_every_segment_of_a_scan() -> None:
    """loop600's trees split walls into several segments of one scan: by default they all
    go to the wall's landmark, each to the landmark of its own world wall; with one
    observation per line, never two to one landmark."""
    import dataclasses as dc

    from mapfuse_core.sim.scenario import load_scenario
    from mapfuse_core.sim.simulate import simulate

    log = simulate(dc.replace(load_scenario("loop600"), steps=120), seed=0).log
    res = run_graph(log, "isam2", fusion=False, association="own", marginals=False)
    assert _line_landmarks_taking_two_segments(res, log) > 10
    assert _purity(res.obs_landmark, log.feat_true_id) == 1.0
    strict = GraphOptions(data_association=AssociationConfig(one_observation_per_line=True))
    res1 = run_graph(log, "isam2", fusion=False, association="own", options=strict, marginals=False)
    assert _line_landmarks_taking_two_segments(res1, log) == 0
    assert len(res1.landmarks.kinds) > len(res.landmarks.kinds)


def test_graph_options_refuse_a_bad_association_config() -> None:
    with pytest.raises(ValueError, match="data_association must be an AssociationConfig"):
        GraphOptions(data_association={"gate_prob": 0.99})  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="nearest neighbour only"):
        GraphOptions(association="own", data_association=AssociationConfig(method="jcbb"))
    assert GraphOptions(data_association=AssociationConfig(method="jcbb")).association == "ekf"


def test_ekf_association_with_fusion_uses_the_ekf_anchor() -> None:
    log = synthetic_log(steps=120, seed=0)
    ekf = run_ekf(log, EKFConfig(fusion=True))
    assert ekf.anchor is not None
    res = run_graph(log, "isam2", fusion=True, association="ekf", decisions=ekf.decisions)
    assert res.anchor is not None
    assert res.anchor.source == "ekf"
    assert res.anchor.accepted_at_step == ekf.anchor.accepted_at_step
    merged = {int(k) for k in ekf.obs_known_id if k >= 0}
    assert {k for _, k in res.anchor.pairings} == merged
    assert log.true_poses is not None
    err = pose_errors(res.poses, truth_in_global(log.true_poses)).position
    assert err.max() < 0.2


def test_fusion_off_has_no_anchor_and_no_known_variables() -> None:
    log = synthetic_log(steps=40, seed=0)
    res = run_graph(log, "batch", fusion=False, association="truth")
    assert res.anchor is None
    n_lm = len(res.landmarks.kinds)
    assert res.n_variables == log.n_steps + n_lm
    assert np.all(res.landmarks.known_ids == -1)


def test_robust_kernel_on_clean_data_changes_little() -> None:
    log = synthetic_log(steps=60, seed=2)
    plain = run_graph(log, "batch", fusion=True, association="truth")
    huber = run_graph(log, "batch", fusion=True, association="truth", robust="huber")
    assert _rel_diff(huber.poses, plain.poses, plain.covs).max() <= 0.5


def test_graph_result_decisions_round_trip_the_associations() -> None:
    log = synthetic_log(steps=40, seed=0)
    res = run_graph(log, "isam2", fusion=True, association="truth")
    assert isinstance(res, GraphResult)
    d = res.decisions
    assert d.anchor is not None
    assert res.anchor is not None
    np.testing.assert_array_equal(d.anchor.x_Wknown_Wglobal, res.anchor.x_Wknown_Wglobal)
    np.testing.assert_array_equal(d.obs_landmark, res.obs_landmark)
    known = res.landmarks.known_ids
    for i in np.nonzero(res.obs_landmark >= 0)[0][:50]:
        assert d.obs_known_id[i] == known[res.obs_landmark[i]]
    again = run_graph(log, "isam2", fusion=True, associations=d.arrays)
    np.testing.assert_allclose(again.poses, res.poses, atol=1e-9)


# --------------------------------------------------------------------------- validation


def _tampered(log: MeasurementLog, **arrays: np.ndarray) -> MeasurementLog:
    """A copy of ``log`` with arrays replaced, bypassing the log's own validation.

    The graph must not trust its input to have been validated elsewhere.
    """
    out = dataclasses.replace(log)
    for name, a in arrays.items():
        object.__setattr__(out, name, a)
    return out


def test_joint_pose_covariance_is_the_marginals_in_the_absolute_frame() -> None:
    log = synthetic_log(steps=200, seed=1)
    res = run_graph(log, "batch", fusion=True, association="truth", joint_stride=20)
    J = res.joint_pose_cov
    assert J is not None
    assert J.steps.tolist() == list(range(20, 200, 20))
    n = J.steps.size
    blocks = J.cov.reshape(n, 3, n, 3)[np.arange(n), :, np.arange(n), :]
    # Its diagonal blocks are the per-pose marginals (also turned into the absolute frame).
    np.testing.assert_allclose(blocks, res.covs[J.steps], rtol=1e-8, atol=1e-14)
    # A coarser stride picks the same sub-blocks: GTSAM's block order is the keys' order.
    coarse = run_graph(log, "batch", fusion=True, association="truth", joint_stride=40)
    assert coarse.joint_pose_cov is not None
    pick = np.flatnonzero(np.isin(J.steps, coarse.joint_pose_cov.steps))
    rows = (3 * pick[:, None] + np.arange(3)).ravel()
    np.testing.assert_allclose(
        J.cov[np.ix_(rows, rows)], coarse.joint_pose_cov.cov, rtol=1e-8, atol=1e-14
    )
    # The poses share the anchor and the map: errors 160 steps apart are still correlated.
    sd = np.sqrt(np.diag(J.cov))
    corr = J.cov[0:3, 3 * n - 3 :] / np.outer(sd[0:3], sd[3 * n - 3 :])
    print(f"\ncorrelation of steps 20 and 180: max {np.abs(corr).max():.2f}")
    assert np.abs(corr).max() > 0.3
    assert run_graph(log, "batch", fusion=True, association="truth").joint_pose_cov is None


def test_joint_pose_covariance_turns_every_block_by_both_headings() -> None:
    """Off-diagonal blocks are G_s P_st G_tᵀ, each side with its own pose's heading."""
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.1, 0.05, 0.02]))
    graph.add(gtsam.PriorFactorPose2(pose_key(0), gtsam.Pose2(0, 0, 0), noise))
    heading = [0.0, 0.7, 2.0, -2.9]
    for k, th in enumerate(heading):
        values.insert(pose_key(k), gtsam.Pose2(float(k), 0.5 * k, th))
        if k:
            rel = gtsam.Pose2(k - 1.0, 0.5 * (k - 1), heading[k - 1]).between(
                gtsam.Pose2(float(k), 0.5 * k, th)
            )
            graph.add(gtsam.BetweenFactorPose2(pose_key(k - 1), pose_key(k), rel, noise))
    m = gtsam.Marginals(graph, values)
    poses = np.array([[float(k), 0.5 * k, th] for k, th in enumerate(heading)])
    got = _joint_pose_cov(m, poses, 1)
    assert got.steps.tolist() == [1, 2, 3]
    keys = gtsam.KeyVector([pose_key(k) for k in (1, 2, 3)])
    P = m.jointMarginalCovariance(keys).fullMatrix()
    G = np.zeros((9, 9))
    for i, k in enumerate((1, 2, 3)):
        c, s = math.cos(heading[k]), math.sin(heading[k])
        G[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    np.testing.assert_allclose(got.cov, G @ P @ G.T, rtol=1e-12, atol=1e-15)


@pytest.fixture(scope="module")
def small_log() -> MeasurementLog:
    return synthetic_log(steps=20, seed=0)


def test_rejects_unknown_feature_kind(small_log: MeasurementLog) -> None:
    kinds = small_log.feat_kind.copy()
    kinds[3] = 7
    with pytest.raises(ValueError, match="observation 3 has unknown feature kind 7"):
        run_graph(_tampered(small_log, feat_kind=kinds), "isam2", association="truth")


def test_rejects_nan(small_log: MeasurementLog) -> None:
    p = small_log.feat_params.copy()
    p[5, 1] = np.nan
    with pytest.raises(ValueError, match="feat_params"):
        run_graph(_tampered(small_log, feat_params=p), "isam2", association="truth")


def test_rejects_singular_observation_noise(small_log: MeasurementLog) -> None:
    c = small_log.feat_cov.copy()
    c[2] = 0.0
    with pytest.raises(ValueError, match="observation 2"):
        run_graph(_tampered(small_log, feat_cov=c), "isam2", association="truth")


def test_rejects_singular_odometry_noise(small_log: MeasurementLog) -> None:
    c = small_log.odometry_cov.copy()
    c[4] = 0.0
    with pytest.raises(ValueError, match="odometry covariance of step 4"):
        run_graph(_tampered(small_log, odometry_cov=c), "batch", association="truth")


def test_rejects_bad_association_arrays(small_log: MeasurementLog) -> None:
    m = small_log.n_features
    lm = np.arange(m, dtype=np.int64)
    with pytest.raises(ValueError, match="shape"):
        run_graph(small_log, "isam2", associations=(lm[:-1], np.full(m, -1)))
    with pytest.raises(ValueError, match="missing from the map"):
        run_graph(small_log, "isam2", associations=(lm, np.full(m, 999_999)))
    kinds_differ = np.zeros(m, dtype=np.int64)  # one landmark for lines and circles
    with pytest.raises(ValueError, match="observed both as a"):
        run_graph(small_log, "isam2", associations=(kinds_differ, np.full(m, -1)))
    orphan = lm.copy()
    orphan[0] = -1
    kn = np.full(m, -1)
    kn[0] = int(small_log.known_map.ids[0])
    with pytest.raises(ValueError, match="has no landmark"):
        run_graph(small_log, "isam2", associations=(orphan, kn))
    with pytest.raises(ValueError, match="integers"):
        run_graph(small_log, "isam2", associations=(lm + 0.5, np.full(m, -1)))


def test_rejects_bad_arguments(small_log: MeasurementLog) -> None:
    with pytest.raises(ValueError, match="needs decisions"):
        run_graph(small_log, "isam2", association="ekf")
    with pytest.raises(ValueError, match="backend"):
        run_graph(small_log, "lm", association="truth")
    with pytest.raises(ValueError, match="association"):
        run_graph(small_log, "isam2", association="nn")
    with pytest.raises(ValueError, match="robust"):
        run_graph(small_log, "isam2", association="truth", robust="tukey")
    with pytest.raises(ValueError, match="steps"):
        run_graph(small_log, "isam2", association="truth", steps=0)
    with pytest.raises(ValueError, match="relinearize_threshold"):
        ISAM2Options(relinearize_threshold={"x": (0.1, 0.1)})
    for kw in (
        {"joint_stride": 0},
        {"joint_stride": 2.5},
        {"joint_stride": 20},
        {"joint_stride": 5, "marginals": False},
    ):
        with pytest.raises(ValueError, match="joint_stride"):
            run_graph(small_log, "batch", association="truth", **kw)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="joint_stride"):
        run_graph(small_log, "isam2", association="truth", joint_stride=5)


def test_builder_refuses_out_of_order_steps(small_log: MeasurementLog) -> None:
    b = GraphBuilder(small_log, GraphOptions(association="truth"))
    with pytest.raises(ValueError, match="in order"):
        b.step(1, None)  # type: ignore[arg-type]


def test_isam2_survives_rejected_input(small_log: MeasurementLog) -> None:
    """A rejected run leaves nothing behind: the next run on good input is unaffected."""
    kinds = small_log.feat_kind.copy()
    kinds[0] = 9
    with pytest.raises(ValueError, match="unknown feature kind"):
        run_graph(_tampered(small_log, feat_kind=kinds), "isam2", association="truth")
    res = run_graph(small_log, "isam2", association="truth")
    assert np.all(np.isfinite(res.poses))
    assert math.isfinite(res.final_error)
