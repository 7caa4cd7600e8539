"""Every association gate reads a log's gate covariances (``feat_gate_cov``), every
update its ``feat_cov``: the EKF's and the factor graph's own association alike."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from ekf_reference import run_ekf
from mapfuse_core.measlog import MeasurementLog
from mapfuse_graph.solvers import run_graph
from tests.synthetic import synthetic_log

pytestmark = pytest.mark.usefixtures("jacobian_checks")


@pytest.fixture(scope="module")
def log() -> MeasurementLog:
    return synthetic_log(steps=120, seed=1)


def _ekf_landmarks(log: MeasurementLog) -> np.ndarray:
    res = run_ekf(log, fusion=False)
    assert res.decisions is not None
    return np.asarray(res.decisions.obs_landmark)


def test_ekf_gates_read_the_gate_covariances(log: MeasurementLog) -> None:
    plain = _ekf_landmarks(log)
    # The same covariances given as the gate's: the same decisions, to the pairing.
    same = dataclasses.replace(log, feat_gate_cov=log.feat_cov.copy())
    np.testing.assert_array_equal(_ekf_landmarks(same), plain)
    # Gates a thousandth as wide refuse pairings the plain run makes: more landmarks.
    narrow = _ekf_landmarks(dataclasses.replace(log, feat_gate_cov=1e-3 * log.feat_cov))
    assert np.unique(narrow[narrow >= 0]).size > np.unique(plain[plain >= 0]).size


def test_graph_gates_read_the_gate_covariances(
    log: MeasurementLog, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The graph's own association tests each observation against the landmarks with
    # the observation's gate covariance: every covariance its gate reads is one of them.
    import mapfuse_graph.own_association as own

    seen: list[np.ndarray] = []
    real = own.residual_noise_cov

    def spy(kind, z, zcov):  # type: ignore[no-untyped-def]
        seen.append(np.array(zcov))
        return real(kind, z, zcov)

    monkeypatch.setattr(own, "residual_noise_cov", spy)
    gate = 0.25 * log.feat_cov
    run_graph(dataclasses.replace(log, feat_gate_cov=gate), "isam2", association="own")
    assert len(seen) > 100
    flat = gate.reshape(len(gate), -1)
    for zcov in seen:
        assert np.any(np.all(flat == zcov.reshape(-1), axis=1))


def test_updates_weigh_with_the_update_covariances(log: MeasurementLog) -> None:
    # Gates twice as wide pair as before on this world; the estimates stay the plain
    # run's to the digit, so the updates never read the gate covariances.
    plain = run_ekf(log, fusion=True)
    wide = run_ekf(dataclasses.replace(log, feat_gate_cov=4.0 * log.feat_cov), fusion=True)
    assert plain.decisions is not None
    assert wide.decisions is not None
    np.testing.assert_array_equal(wide.decisions.obs_landmark, plain.decisions.obs_landmark)
    assert plain.filtered is not None
    assert wide.filtered is not None
    np.testing.assert_array_equal(wide.filtered.poses, plain.filtered.poses)
    np.testing.assert_array_equal(wide.filtered.covs, plain.filtered.covs)
    # The graph's factors on a given association likewise.
    g_plain = run_graph(log, "batch", association="truth")
    g_wide = run_graph(
        dataclasses.replace(log, feat_gate_cov=0.25 * log.feat_cov), "batch", association="truth"
    )
    assert g_plain.smoothed is not None
    assert g_wide.smoothed is not None
    np.testing.assert_array_equal(g_wide.smoothed.poses, g_plain.smoothed.poses)


def test_known_gates_running_sum_weighs_as_the_update(
    log: MeasurementLog, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The known-map gate sums the d² of a known feature's consecutive pairings, whose
    # shared errors the update's covariance counts once: it takes weighed_d2, not the
    # gate's distance.
    import ekf_reference.known_gating as kg

    weighed: list[tuple[float, float]] = []
    pushed: list[float] = []
    real, real_push = kg.weighed_d2, kg.KnownGate._push

    def spy(state, c):  # type: ignore[no-untyped-def]
        weighed.append((real(state, c), c.d2 if c.R_gate is not None else math.nan))
        return weighed[-1][0]

    def push(self, kid, value):  # type: ignore[no-untyped-def]
        if not math.isnan(value):
            pushed.append(value)
        real_push(self, kid, value)

    monkeypatch.setattr(kg, "weighed_d2", spy)
    monkeypatch.setattr(kg.KnownGate, "_push", push)
    run_ekf(dataclasses.replace(log, feat_gate_cov=0.5 * log.feat_cov), fusion=True)
    # Every accepted pairing's entry in the sum is its weighed d².
    assert pushed == [w for w, _ in weighed]
    gated = [(w, d) for w, d in weighed if not math.isnan(d)]
    assert len(gated) > 50
    # Gates on half the covariance: every weighed distance is below the gate's.
    assert all(w < d for w, d in gated)


def test_the_graph_refuses_a_degenerate_gate_covariance(log: MeasurementLog) -> None:
    gate = log.feat_cov.copy()
    line = int(np.flatnonzero(log.feat_kind == 0)[0])
    gate[line] = 0.0
    with pytest.raises(ValueError, match=f"observation {line}: its gate covariance projected"):
        run_graph(dataclasses.replace(log, feat_gate_cov=gate), "isam2", association="own")
