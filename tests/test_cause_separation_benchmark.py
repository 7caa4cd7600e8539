"""``benchmarks/cause_separation.py``: redrawn observations are as their stated covariance
says, whatever the extractor did; only one kind is kept when asked."""

from __future__ import annotations

import math

import numpy as np

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.models.line import line_residual, line_residual_cov
from mapfuse_core.sim.scenario import load_scenario
from mapfuse_core.sim.simulate import simulate
from mapfuse_core.sim.worldgen import WorldParams, generate_scenario
from tests.scripts import load_benchmark


def _log():
    bench = load_benchmark("cause_separation")
    world = {**bench.parse_world_args(bench.DEFAULT_WORLD), "loop_length_m": 200.0}
    sc = generate_scenario(WorldParams(seed=3, **world), base=load_scenario("loop600"))
    return bench, simulate(sc, seed=3, workers=1).log


def test_redrawn_lines_whiten_to_unit_variance_with_the_covariance_they_carry() -> None:
    bench, log = _log()
    new = bench.redrawn(log, 3, (FeatureKind.LINE,))
    z = []
    for j in range(log.n_features):
        truth = bench.truth_in_sensor(log, j)
        if truth is None or log.feat_kind[j] != int(FeatureKind.LINE):
            np.testing.assert_array_equal(new.feat_params[j], log.feat_params[j])
            continue
        e = line_residual(truth, new.feat_params[j])[0]
        z.append(
            e / np.sqrt(np.diag(line_residual_cov(truth, new.feat_params[j], new.feat_cov[j])))
        )
    w = np.array(z)
    n = w.shape[0]
    assert n > 500
    # Mean within 3.5 standard errors of 0; variance within 3.5 √(2/n) of 1.  With the
    # covariance left unturned under the redrawn angle the lateral variance is about 0.5.
    assert np.all(np.abs(w.mean(axis=0)) < 3.5 / math.sqrt(n))
    assert np.all(np.abs(w.var(axis=0) - 1.0) < 3.5 * math.sqrt(2.0 / n))


def test_only_keeps_the_observations_of_one_kind() -> None:
    bench, log = _log()
    lines = bench.only(log, FeatureKind.LINE)
    assert np.all(lines.feat_kind == int(FeatureKind.LINE))
    assert lines.n_features == int(np.sum(log.feat_kind == int(FeatureKind.LINE)))
    assert lines.n_steps == log.n_steps


def test_the_fused_ekf_row_holds_its_nees_in_the_known_frame_from_its_anchor_on() -> None:
    bench, log = _log()
    rows = bench.run_seed(log, 3, ["ekf"])
    fused = next(r for r in rows if r["fusion"])
    unfused = next(r for r in rows if not r["fusion"])
    assert unfused["nees_known"] is None
    known = np.array(fused["nees_known"])
    # One value per step from the anchor to the end of the drive.
    assert 0 < known.size < len(fused["nees"])
    assert np.all(np.isfinite(known))
    assert np.all(known >= 0.0)
    summary = {(s["variant"], s["fusion"]): s for s in bench.summarise(rows)}
    s = summary[("ekf", True)]
    assert s["nees_known_after_anchor"] == round(float(known.mean()), 3)
    after = np.array(fused["nees"][-known.size :])
    assert s["nees_global_after_anchor"] == round(float(np.nanmean(after)), 3)
    # A consistent run's mean NEES (3 dof) in either frame is of order 3, not 0 or 1e3:
    # the frame change is right (the known map of loop600's worlds is in W).
    assert 0.3 < known.mean() < 30.0


def test_the_anchor_at_fusion_is_found_again_on_the_log_cut_there() -> None:
    bench, log = _log()
    fused = next(r for r in bench.run_seed(log, 3, ["ekf"]) if r["fusion"])
    # The cut run makes the same decisions up to the fusion step: its anchor is the
    # anchor as it stood then, consistent on this small world (3 dof: not 0, not 1e3).
    assert fused["anchor_nees_at_fusion"] is not None
    assert 0.0 < fused["anchor_nees_at_fusion"] < 30.0
    assert fused["anchor_nees_at_fusion"] != fused["anchor_nees"]


def test_the_exact_known_map_is_the_true_one_it_was_drawn_around() -> None:
    bench, log = _log()
    exact = bench.exact_known_map(log)
    km, ex = log.known_map, exact.known_map
    np.testing.assert_array_equal(ex.ids, km.ids)
    np.testing.assert_array_equal(ex.kinds, km.kinds)
    # The drawn map is off by its survey noise (0.1 m, 0.05 rad); the exact one is not.
    assert np.abs(km.params - ex.params).max() > 0.01
    for j, i in enumerate(km.ids.tolist()):
        w = int(np.flatnonzero(log.world.ids == i)[0])
        np.testing.assert_allclose(ex.params[j], log.world.params[w], atol=1e-12)
    np.testing.assert_allclose(np.sqrt(ex.covs[:, [0, 1, 2], [0, 1, 2]]), bench.EXACT_MAP_SIGMA)
    np.testing.assert_array_equal(exact.feat_params, log.feat_params)


def test_paired_stretches_gives_each_stretch_the_worlds_paired_difference() -> None:
    cs = load_benchmark("cause_separation")
    rows = [
        {"seed": 0, "variant": "ekf", "fusion": False, "nees": [1.0, 1.0, 5.0, 7.0]},
        {"seed": 0, "variant": "batch", "fusion": False, "nees": [2.0, 2.0, 3.0, 3.0]},
        {"seed": 1, "variant": "ekf", "fusion": False, "nees": [3.0, 3.0, 4.0, 4.0]},
        {"seed": 1, "variant": "batch", "fusion": False, "nees": [2.0, 2.0, 3.0, 3.0]},
        # A world the EKF did not run is left out of the pairing.
        {"seed": 2, "variant": "batch", "fusion": False, "nees": [9.0, 9.0, 9.0, 9.0]},
    ]
    out = cs.paired_stretches(rows, [0, 2])
    assert [(o["variant"], o["steps"], o["worlds"]) for o in out] == [
        ("batch", [0, 2], 2),
        ("batch", [2, 4], 2),
    ]
    # Steps 0-1: the EKF's means 1 and 3 against 2 and 2: differences -1 and +1.
    assert out[0]["ekf"] == 2.0
    assert out[0]["variant_nees"] == 2.0
    assert out[0]["difference"][0] == 0.0
    # Student-t, 1 dof: half-width 12.706 * sd(-1, 1) / sqrt(2) = 12.706.
    assert math.isclose(out[0]["difference"][2], 12.706, abs_tol=1e-3)
    # Steps 2-3: 6 and 4 against 3 and 3.
    assert out[1]["difference"][0] == 2.0


def test_the_batch_variants_take_the_decisions_of_the_ekf_on_the_log_as_extracted(
    monkeypatch,
) -> None:
    bench, log = _log()
    seen: list[tuple[str, int]] = []
    real_run = bench.run

    def spy(vlog, est, **kw):  # type: ignore[no-untyped-def]
        seen.append((est, id(vlog)))
        return real_run(vlog, est, **kw)

    monkeypatch.setattr(bench, "run", spy)
    rows = bench.run_seed(log, 3, ["batch_redrawn", "batch_exact_map"])
    assert [(r["variant"], r["fusion"]) for r in rows] == [
        ("batch_redrawn", True),
        ("batch_redrawn", False),
        ("batch_exact_map", True),
    ]
    # The EKF runs once per fusion setting, on the log as extracted (not on the
    # redrawn or exact-map copy), and every batch row uses those decisions.
    ekf_logs = [i for est, i in seen if est == "ekf"]
    assert ekf_logs[:2] == [id(log), id(log)]
    assert all(np.isfinite(r["nees_mean"]) and r["nees_mean"] > 0.0 for r in rows)
