"""EKF reference: agreement with an absolute-frame EKF, joining, fusion, bad inputs."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from ekf_reference import EKFConfig, maps, run_ekf
from ekf_reference.association import Query, choose, predict_all_targets
from ekf_reference.loops import LoopClosureParams
from ekf_reference.maps import predict
from ekf_reference.pipeline import _Run
from ekf_reference.state import Element, ElementKind, GaussianMap, Role
from mapfuse_core.evaluation import nees_series, pose_errors, truth_in_global
from mapfuse_core.geometry.features import FeatureKind, canonical_line, transform_feature
from mapfuse_core.geometry.se2 import compose_jacobians, wrap_angle
from mapfuse_core.matching import AssociationConfig
from mapfuse_core.measlog import MeasurementLog, MeasurementLogError
from mapfuse_core.models import observe
from tests.synthetic import ring_world, synthetic_log, with_known


def absolute_ekf(log: MeasurementLog) -> tuple[np.ndarray, np.ndarray]:
    """A plain EKF in ``Wglobal`` (pose + circles) with true-id association."""
    x = np.zeros(3)
    P = np.zeros((3, 3))
    index: dict[int, int] = {}
    poses, covs = [], []
    for k in range(log.n_steps):
        if k > 0:
            new, J1, J2 = compose_jacobians(x[:3], log.odometry[k])
            F = np.eye(x.size)
            F[:3, :3] = J1
            x[:3] = new
            P = F @ P @ F.T
            P[:3, :3] += J2 @ log.odometry_cov[k] @ J2.T
        sl = log.feature_slice(k)
        # Re-observations first, as one batched update (as the EKF reference does) ...
        rows, Hs, Rs = [], [], []
        for j in range(sl.start, sl.stop):
            tid = int(log.feat_true_id[j])
            if tid not in index:
                continue
            i = index[tid]
            r, Jx, Jf = observe(FeatureKind.CIRCLE, log.feat_params[j], x[:3], x[i : i + 3])
            H = np.zeros((3, x.size))
            H[:, :3] = Jx
            H[:, i : i + 3] = Jf
            rows.append(r)
            Hs.append(H)
            Rs.append(log.feat_cov[j])  # ∂r/∂z = −I for circles
        if rows:
            r, H = np.concatenate(rows), np.vstack(Hs)
            R = np.zeros((r.size, r.size))
            for b, Rb in enumerate(Rs):
                R[3 * b : 3 * b + 3, 3 * b : 3 * b + 3] = Rb
            S = H @ P @ H.T + R
            K = P @ H.T @ np.linalg.inv(S)
            x = x - K @ r
            x[2] = float(wrap_angle(x[2]))
            P = P - K @ S @ K.T
            P = 0.5 * (P + P.T)
        # ... then new landmarks.
        for j in range(sl.start, sl.stop):
            z, Rz, tid = log.feat_params[j], log.feat_cov[j], int(log.feat_true_id[j])
            if tid in index:
                continue
            f, Jp, Jz = transform_feature(FeatureKind.CIRCLE, x[:3], z)
            n = x.size
            G = np.zeros((3, n))
            G[:, :3] = Jp
            x = np.concatenate([x, f])
            newP = np.zeros((n + 3, n + 3))
            newP[:n, :n] = P
            newP[n:, :n] = G @ P
            newP[:n, n:] = (G @ P).T
            newP[n:, n:] = G @ P @ G.T + Jz @ Rz @ Jz.T
            P = newP
            index[tid] = n
        poses.append(x[:3].copy())
        covs.append(P[:3, :3].copy())
    return np.array(poses), np.array(covs)


def circles_only_log(steps: int, seed: int = 1) -> MeasurementLog:
    world = ring_world(n_circles=24, n_lines=0)
    return synthetic_log(
        steps=steps,
        seed=seed,
        world=world,
        sigma_odo=(0.002, 0.001, 0.0005),
        sigma_circle=0.005,
    )


def test_robotcentric_local_map_agrees_with_absolute_ekf() -> None:
    log = circles_only_log(steps=60)
    # One local map for the whole run: no joining, pure robotcentric EKF.
    res = run_ekf(log, EKFConfig(local_map_steps=10_000), fusion=False)
    ref_poses, ref_covs = absolute_ekf(log)
    d = res.poses - ref_poses
    d[:, 2] = wrap_angle(d[:, 2])
    # The two filters linearise the same models at different points (robot frame vs
    # world frame), so they differ by second-order terms: measured ≤ 0.8 % of the
    # reference σ here.  2 % of σ and 1 % on variances leave room for that and still
    # catch a wrong Jacobian or model, which shows up at tens of per cent.
    sig = np.sqrt(np.diagonal(ref_covs, axis1=1, axis2=2))[1:]
    assert np.all(np.abs(d[1:]) <= 0.02 * sig)
    np.testing.assert_allclose(
        np.diagonal(res.covs, axis1=1, axis2=2)[1:],
        np.diagonal(ref_covs, axis1=1, axis2=2)[1:],
        rtol=0.01,
    )


def test_carried_features_make_local_maps_agree_with_absolute_ekf() -> None:
    """With ``carry_seen_steps=1`` a run split into local maps of 10 steps gives the
    absolute-frame EKF's pose and covariance at every step, not only at the joins, up
    to the first re-sighting of a feature the local map did not carry (the loop
    closing near the end of the lap, linked only at the next join)."""
    n, size = 60, 10
    log = circles_only_log(steps=n)
    ref_poses, ref_covs = absolute_ekf(log)
    until = _covered_until(log, size)
    assert until >= 45, until
    sig = np.sqrt(np.diagonal(ref_covs, axis1=1, axis2=2))[1:until]
    var = np.diagonal(ref_covs, axis1=1, axis2=2)[1:until]
    cfg = EKFConfig(local_map_steps=size, carry_seen_steps=1)
    res = run_ekf(log, cfg, fusion=False)
    assert res.map.params.shape[0] == len({int(t) for t in log.feat_true_id})
    d = res.poses[1:until] - ref_poses[1:until]
    d[:, 2] = wrap_angle(d[:, 2])
    # Same tolerances as the single local map above: CI local maps lose nothing in a
    # near-linear problem, so only the linearisation points differ.
    assert np.all(np.abs(d) <= 0.02 * sig)
    np.testing.assert_allclose(np.diagonal(res.covs, axis1=1, axis2=2)[1:until], var, rtol=0.01)
    # The paper's local maps start empty: between joins the vehicle ignores the
    # landmarks it keeps seeing, so its variance is far above the EKF's (the check
    # above would catch a carry that did nothing).
    paper = run_ekf(log, EKFConfig(local_map_steps=size), fusion=False)
    ratio = np.diagonal(paper.covs, axis1=1, axis2=2)[1:until] / var
    assert ratio.max() > 1.5


def _covered_until(log: MeasurementLog, size: int) -> int:
    """First step that re-sees a feature its local map (of ``size`` steps, carrying
    the last step's features) does not hold; ``n_steps`` if there is none."""
    ids = [set(log.feat_true_id[log.feature_slice(k)].tolist()) for k in range(log.n_steps)]
    seen: set[int] = set()
    for k in range(log.n_steps):
        start = k - k % size
        held = (ids[start - 1] if start > 0 else set()).union(*ids[start:k])
        if not all(i in held or i not in seen for i in ids[k]):
            return k
        seen |= ids[k]
    return log.n_steps


def test_carried_lines_make_local_maps_agree_with_one_local_map() -> None:
    """The same with walls (SPmap lines, bound along themselves) among the trees,
    against one local map for the whole run (the robotcentric EKF checked above)."""
    size = 10
    log = synthetic_log(
        steps=120, seed=4, sigma_odo=(0.002, 0.001, 0.0005), sigma_line=(0.005, 0.001)
    )
    assert (log.feat_kind == int(FeatureKind.LINE)).sum() >= 100
    until = _covered_until(log, size)
    assert until >= 100, until
    ref = run_ekf(log, EKFConfig(local_map_steps=10_000), fusion=False)
    var = np.diagonal(ref.covs, axis1=1, axis2=2)[1:until]
    res = run_ekf(log, EKFConfig(local_map_steps=size, carry_seen_steps=1), fusion=False)
    d = res.poses[1:until] - ref.poses[1:until]
    d[:, 2] = wrap_angle(d[:, 2])
    # Measured 0.7 % of σ and 0.9 % on variances.  A carried line's reference point
    # slides along it from one local map to the next, so the linearisation points
    # differ a little more than with circles only: 2 % on both; a wrong Jacobian
    # shows up at tens of per cent.
    assert np.all(np.abs(d) <= 0.02 * np.sqrt(var))
    np.testing.assert_allclose(np.diagonal(res.covs, axis1=1, axis2=2)[1:until], var, rtol=0.02)
    paper = run_ekf(log, EKFConfig(local_map_steps=size), fusion=False)
    assert (np.diagonal(paper.covs, axis1=1, axis2=2)[1:until] / var).max() > 1.5


def test_prediction_moves_features_by_the_inverse_increment() -> None:
    m = GaussianMap()
    m.add(Element(ElementKind.POSE, Role.BASE, True, -1), np.zeros(3), np.zeros((3, 3)))
    m.add(
        Element(ElementKind.CIRCLE, Role.FEATURE, True, 0),
        np.array([5.0, 0.0, 0.4]),
        np.eye(3) * 1e-4,
    )
    u = np.array([1.0, 0.0, math.pi / 2])
    predict(m, u, np.diag([1e-4, 1e-4, 1e-6]))
    # Circle at (5, 0) seen from a vehicle that moved 1 m and turned left 90°.
    np.testing.assert_allclose(m.mean[1], [0.0, -4.0, 0.4], atol=1e-12)
    np.testing.assert_allclose(m.mean[0], [0.0, 1.0, -math.pi / 2], atol=1e-12)


@pytest.mark.parametrize("carry", [False, True], ids=["paper", "carry"])
def test_joining_keeps_covariance_symmetric_positive_definite(carry: bool) -> None:
    log = synthetic_log(steps=240, seed=2)
    config = EKFConfig(local_map_steps=20, carry_seen_steps=int(carry))
    run = _Run(log, config, fusion=True)
    checked = 0
    for k in range(log.n_steps):
        if k > 0:
            predict(run.local, log.odometry[k], log.odometry_cov[k])
        run.observe(k)
        if (k + 1) % config.local_map_steps == 0:
            run.join(k)
            P = run.global_map.cov
            assert np.abs(P - P.T).max() < 1e-12
            w = np.linalg.eigvalsh(P)
            # Lines are bound (one exactly-zero direction each): PSD, not PD, there.
            assert w.min() > -1e-9 * max(1.0, w.max())
            feats = [i for i, e in enumerate(run.global_map.elements) if e.kind.name == "CIRCLE"]
            for i in feats:
                assert np.linalg.eigvalsh(run.global_map.block(i)).min() > 0
            checked += 1
    assert checked == 12


@pytest.mark.parametrize("carry", [False, True], ids=["paper", "carry"])
@pytest.mark.parametrize("fusion", [False, True])
def test_consistent_and_accurate_on_synthetic_ring(fusion: bool, carry: bool) -> None:
    log = synthetic_log(steps=400, seed=0)
    res = run_ekf(log, EKFConfig(carry_seen_steps=int(carry)), fusion=fusion)
    err = pose_errors(res.poses, truth_in_global(log.true_poses))
    nees = nees_series(err.dx, res.covs)[1:]
    # A consistent 3-dof filter: ≥ 90 % of steps under χ²(3, 0.95) = 7.815 (the paper's
    # consistency criterion); a filter that ignored half its odometry noise would fail it.
    assert np.mean(nees <= 7.815) >= 0.9
    assert err.position.max() < 0.35
    if fusion:
        assert res.anchor is not None
        truth = log.true_poses[0]
        assert math.hypot(*(res.anchor.x_Wknown_Wglobal[:2] - truth[:2])) < 0.15
        assert all(t == k for t, k in res.anchor.pairings)


def test_each_local_feature_ends_in_one_landmark() -> None:
    # ``obs_local_track`` is what the local maps decided, ``obs_landmark`` what the joins
    # made of it: observations of one local feature share its landmark, and joins
    # merge local features (fewer landmarks than local features).
    log = synthetic_log(steps=200, seed=0)
    res = run_ekf(log, EKFConfig(), fusion=False)
    local, landmark = res.details.obs_local_track, res.decisions.obs_landmark
    assert local.shape == landmark.shape == (log.n_features,)
    assert np.array_equal(local < 0, landmark < 0)
    pairs = {(int(t), int(m)) for t, m in zip(local, landmark, strict=True) if t >= 0}
    tracks = {t for t, _ in pairs}
    assert len(pairs) == len(tracks)
    assert len({m for _, m in pairs}) < len(tracks)


def test_no_fusion_has_no_anchor() -> None:
    res = run_ekf(synthetic_log(steps=120, seed=3), EKFConfig(), fusion=False)
    assert res.anchor is None
    assert res.matching is None  # no map matching attempted
    assert np.all(np.isnan(res.details.poses_in_known))


@pytest.mark.parametrize("keep", [[], [0]], ids=["empty", "one-feature"])
def test_too_small_known_map_is_a_documented_no_match(keep: list[int]) -> None:
    log = with_known(synthetic_log(steps=120, seed=4), keep)
    res = run_ekf(log, EKFConfig(), fusion=True)
    assert res.anchor is None  # "no match": SLAM without fusion, reported as such
    assert np.all(np.isfinite(res.poses))


def test_nan_in_log_is_refused_before_running() -> None:
    log = synthetic_log(steps=40, seed=5)
    odo = log.odometry.copy()
    odo[7, 1] = np.nan
    with pytest.raises(MeasurementLogError, match=r"odometry.*non-finite.*\(7, 1\)"):
        dataclasses.replace(log, odometry=odo)


def test_bad_config_is_refused() -> None:
    with pytest.raises(ValueError, match="local_map_steps"):
        EKFConfig(local_map_steps=0)
    with pytest.raises(ValueError, match="method must be one of nn, jcbb"):
        EKFConfig(data_association=AssociationConfig(method="magic"))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="data_association must be an AssociationConfig"):
        EKFConfig(data_association="nn")  # type: ignore[arg-type]
    for bad in (-1, True, 1.5):
        with pytest.raises(ValueError, match="carry_seen_steps"):
            EKFConfig(carry_seen_steps=bad)  # type: ignore[arg-type]
    assert EKFConfig(carry_seen_steps=np.int64(2)).carry_seen_steps == 2  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="loop_closure"):
        EKFConfig(carry_seen_steps=1, loop_closure=LoopClosureParams())


def test_jcbb_gives_same_associations_on_clean_data() -> None:
    log = synthetic_log(steps=120, seed=6)
    nn = run_ekf(log, EKFConfig(data_association=AssociationConfig(method="nn")), fusion=False)
    jc = run_ekf(log, EKFConfig(data_association=AssociationConfig(method="jcbb")), fusion=False)
    np.testing.assert_allclose(nn.poses, jc.poses, atol=1e-9)


def _segment(
    x0: float, x1: float, y: float, s_lat: float, s_th: float
) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    """A wall segment along ``y = const`` in the sensor frame: SPmap params, cov, extent."""
    line = canonical_line(np.array([0.5 * (x0 + x1), y, 0.0]))
    c, s = math.cos(line[2]), math.sin(line[2])
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    half = 0.5 * (x1 - x0)
    cov = R @ np.diag([(x1 - x0) ** 2 / 12.0, s_lat**2, s_th**2]) @ R.T
    return line, cov, (-half, half)


def test_two_segments_of_one_wall_in_one_scan_make_one_landmark() -> None:
    # A wall behind a tree: one scan sees it as two collinear segments.  Both are
    # observations of one line; a second landmark would split later observations
    # between the two by best fit.
    base = synthetic_log(steps=2, seed=3)
    segs = [_segment(2.0, 6.0, 5.0, 0.01, 0.002), _segment(8.0, 12.0, 5.0, 0.01, 0.002)]
    log = dataclasses.replace(
        base,
        feat_step=np.zeros(2, dtype=np.int64),
        feat_kind=np.full(2, int(FeatureKind.LINE), dtype=np.int8),
        feat_params=np.array([p for p, _, _ in segs]),
        feat_cov=np.array([c for _, c, _ in segs]),
        feat_true_id=np.full(2, 7, dtype=np.int64),
        feat_n_points=np.full(2, 20, dtype=np.int64),
        feat_extent=np.array([e for _, _, e in segs]),
    )
    run = _Run(log, EKFConfig(), fusion=False)
    run.observe(0)
    lines = [e for e in run.local.elements if e.kind == ElementKind.LINE]
    assert len(lines) == 1
    assert lines[0].n_obs == 2
    assert lines[0].extent[1] - lines[0].extent[0] == pytest.approx(10.0, abs=1e-6)
    assert run.obs_track[0] == run.obs_track[1]


@pytest.mark.parametrize("method", ["nn", "jcbb"])
def test_line_landmarks_take_several_observations_circles_one(method: str) -> None:
    m = GaussianMap()
    m.add(Element(ElementKind.POSE, Role.BASE, True, -1), np.zeros(3), np.zeros((3, 3)))
    line, cov, ext = _segment(0.0, 14.0, 5.0, 0.01, 0.002)
    m.add(Element(ElementKind.LINE, Role.FEATURE, True, 0, extent=ext), line, cov)
    m.add(
        Element(ElementKind.CIRCLE, Role.FEATURE, True, 1),
        np.array([10.0, -3.0, 0.3]),
        np.eye(3) * 1e-4,
    )
    queries = []
    for x0, x1 in ((1.0, 5.0), (9.0, 13.0)):
        p, c, e = _segment(x0, x1, 5.0, 0.01, 0.002)
        # The segments' extents relative to their own midpoints, as extraction gives.
        queries.append(Query(ElementKind.LINE, p, c, e))
    for dx in (0.0, 0.01):
        queries.append(
            Query(
                ElementKind.CIRCLE,
                np.array([10.0 + dx, -3.0, 0.3]),
                np.eye(3) * 1e-4,
                (math.nan, math.nan),
            )
        )
    targets = predict_all_targets(m, lambda e: True)

    def targets_of(**kw: object) -> list[int | None]:
        cfg = EKFConfig(data_association=AssociationConfig(method=method, **kw))  # type: ignore[arg-type]
        chosen = choose(m, queries, targets, cfg.data_association)
        return [c.target if c is not None else None for c in chosen]

    chosen = targets_of()
    assert chosen[:2] == [1, 1]
    assert sorted(chosen[2:], key=str) == [2, None]
    # One observation per line: the wall takes one segment only.
    assert sorted(targets_of(one_observation_per_line=True)[:2], key=str) == [1, None]
    if method == "jcbb":
        # A node budget of 1 ends the search before any pairing.
        assert targets_of(jcbb_max_nodes=1) == [None] * 4


def test_rarely_seen_local_features_can_be_kept_out_of_the_global_map() -> None:
    log = synthetic_log(steps=160, seed=5)
    base = run_ekf(log, EKFConfig(), fusion=False)
    res = run_ekf(log, EKFConfig(min_obs_to_join=3), fusion=False)
    # Measured: 6 observations (of local features seen once or twice) are dropped here;
    # every other observation keeps a landmark, and the dropped ones take no map entry.
    dropped = res.decisions.obs_landmark < 0
    assert np.sum(base.decisions.obs_landmark < 0) == 0
    assert 0 < dropped.sum() < 20
    assert len(res.map.kinds) <= len(base.map.kinds)
    # The filter still works: the poses stay close to the run that kept everything.
    assert np.max(np.abs(res.poses[:, :2] - base.poses[:, :2])) < 0.05
    same = run_ekf(log, EKFConfig(min_obs_to_join=1), fusion=False)
    np.testing.assert_array_equal(same.poses, base.poses)
    with pytest.raises(ValueError, match="min_obs_to_join"):
        EKFConfig(min_obs_to_join=0)


def test_shared_covariance_pseudo_inverse_survives_an_eigensolver_failure(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """numpy's symmetric eigensolver failed to converge on a finite PSD matrix in a
    loop600 run (seed 11, step 1519); the SVD fallback must give the same result."""
    rng = np.random.default_rng(0)
    B = rng.normal(size=(9, 6))
    P = B @ B.T  # rank 6 of 9: singular, as bound lines make the shared covariance
    expected = maps.psd_pinv(P)
    real_pinv = np.linalg.pinv

    def failing(a: np.ndarray, rcond: float = 1e-15, hermitian: bool = False) -> np.ndarray:
        if hermitian:
            raise np.linalg.LinAlgError("Eigenvalues did not converge")
        return real_pinv(a, rcond=rcond, hermitian=False)

    monkeypatch.setattr(np.linalg, "pinv", failing)
    got = maps.psd_pinv(P)
    np.testing.assert_allclose(got, expected, atol=1e-12)
    np.testing.assert_allclose(P @ got @ P, P, atol=1e-10)
