"""Measurement log: round trip, bit-identical files, clear errors for bad input."""

from __future__ import annotations

import dataclasses
import zipfile
from pathlib import Path

import numpy as np
import pytest

from mapfuse_core.measlog import (
    FORMAT_VERSION,
    KnownMapArrays,
    MeasurementLog,
    MeasurementLogError,
    load_log,
    save_log,
)


def small_log(n: int = 5, seed: int = 3) -> MeasurementLog:
    rng = np.random.default_rng(seed)
    steps = np.array([0, 0, 2, 3, 3, 3], dtype=np.int64)
    m = steps.size
    cov = np.diag([0.01, 0.02, 0.003])
    return MeasurementLog(
        scenario="unit",
        seed=seed,
        timestamps=np.arange(n) * 0.125,
        odometry=np.vstack([np.zeros(3), rng.normal(size=(n - 1, 3)) * 0.1]),
        odometry_cov=np.stack([np.zeros((3, 3))] + [cov] * (n - 1)),
        feat_step=steps,
        feat_kind=np.array([0, 1, 1, 0, 1, 0], dtype=np.int8),
        feat_params=np.abs(rng.normal(size=(m, 3))) + 0.1,
        feat_cov=np.stack([cov] * m),
        feat_true_id=np.array([1, 2, -1, 4, 5, 1], dtype=np.int64),
        feat_n_points=np.full(m, 12, dtype=np.int64),
        feat_extent=np.array([[-1.0, 1.0], [np.nan, np.nan]] * 3),
        known_map=KnownMapArrays(
            ids=np.array([1, 2], dtype=np.int64),
            kinds=np.array([0, 1], dtype=np.int8),
            params=np.array([[0.0, 1.0, 0.2], [3.0, 4.0, 0.5]]),
            covs=np.stack([cov, cov]),
        ),
        true_poses=rng.normal(size=(n, 3)),
        rejected={"too_few_points": 4, "radius_out_of_range": 1},
    )


def test_round_trip_preserves_every_array(tmp_path: Path) -> None:
    log = small_log()
    back = load_log(save_log(log, tmp_path / "log.npz"))
    for f in dataclasses.fields(MeasurementLog):
        if f.name.startswith("_"):
            continue
        a, b = getattr(log, f.name), getattr(back, f.name)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b, err_msg=f.name)
            assert a.dtype == b.dtype, f.name
        elif isinstance(a, KnownMapArrays):
            for g in ("ids", "kinds", "params", "covs"):
                np.testing.assert_array_equal(getattr(a, g), getattr(b, g))
        else:
            assert a == b, f.name


def test_same_content_gives_identical_bytes(tmp_path: Path) -> None:
    a = save_log(small_log(), tmp_path / "a.npz").read_bytes()
    b = save_log(small_log(), tmp_path / "b.npz").read_bytes()
    assert a == b


def test_no_pickled_objects_and_named_true_poses(tmp_path: Path) -> None:
    path = save_log(small_log(), tmp_path / "log.npz")
    with np.load(path, allow_pickle=False) as npz:
        assert npz["true_poses"].shape == (5, 3)
        assert all(npz[k].dtype != object for k in npz.files)


def test_feature_slice() -> None:
    log = small_log()
    assert log.feature_slice(0) == slice(0, 2)
    assert log.feature_slice(1) == slice(2, 2)
    assert log.feature_slice(3) == slice(3, 6)
    with pytest.raises(IndexError, match="outside"):
        log.feature_slice(5)


def test_head_keeps_the_first_steps_and_their_features() -> None:
    log = small_log()
    h = log.head(3)
    assert h.n_steps == 3
    # Steps 0 and 2 hold features 0–2; step 3's three features are cut.
    assert h.n_features == 3
    np.testing.assert_array_equal(h.feat_step, [0, 0, 2])
    np.testing.assert_array_equal(h.feat_true_id, log.feat_true_id[:3])
    assert h.true_poses is not None
    assert log.true_poses is not None
    np.testing.assert_array_equal(h.true_poses, log.true_poses[:3])
    assert h.feature_slice(2) == slice(2, 3)
    assert log.head(99).n_steps == log.n_steps
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="n_steps"):
            log.head(bad)  # type: ignore[arg-type]


def test_gate_covariances_round_trip_fall_back_and_are_cut_by_head(tmp_path: Path) -> None:
    log = small_log()
    assert log.feat_gate_cov is None
    assert log.gate_covs is log.feat_cov
    gated = dataclasses.replace(log, feat_gate_cov=0.5 * log.feat_cov)
    back = load_log(save_log(gated, tmp_path / "log.npz"))
    assert back.feat_gate_cov is not None
    np.testing.assert_array_equal(back.feat_gate_cov, gated.feat_gate_cov)
    np.testing.assert_array_equal(back.gate_covs, 0.5 * log.feat_cov)
    assert load_log(save_log(log, tmp_path / "plain.npz")).feat_gate_cov is None
    head = gated.head(3)
    assert head.feat_gate_cov is not None
    np.testing.assert_array_equal(head.feat_gate_cov, gated.feat_gate_cov[:3])


def test_bad_gate_covariances_are_named() -> None:
    log = small_log()
    with pytest.raises(MeasurementLogError, match="'feat_cov' must be a numpy array"):
        dataclasses.replace(log, feat_cov=None)
    with pytest.raises(MeasurementLogError, match="'feat_gate_cov' has shape"):
        dataclasses.replace(log, feat_gate_cov=log.feat_cov[:2])
    bad = log.feat_cov.copy()
    bad[4] = np.diag([0.01, -0.02, 0.003])
    with pytest.raises(MeasurementLogError, match=r"'feat_gate_cov'\[4\] has a negative variance"):
        dataclasses.replace(log, feat_gate_cov=bad)
    nan = log.feat_cov.copy()
    nan[1, 0, 0] = np.nan
    with pytest.raises(MeasurementLogError, match="'feat_gate_cov' has a non-finite value"):
        dataclasses.replace(log, feat_gate_cov=nan)


def test_nan_is_rejected_with_its_location() -> None:
    log = small_log()
    params = log.feat_params.copy()
    params[2, 1] = np.nan
    with pytest.raises(MeasurementLogError, match=r"feat_params.*non-finite.*\(2, 1\)"):
        dataclasses.replace(log, feat_params=params)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("feat_kind", np.array([0, 1, 7, 0, 1, 0], dtype=np.int8), "not a feature kind"),
        ("feat_step", np.array([0, 0, 2, 3, 3, 9], dtype=np.int64), "outside"),
        ("feat_step", np.array([0, 2, 0, 3, 3, 3], dtype=np.int64), "non-decreasing"),
        ("odometry", np.zeros((4, 3)), "odometry.*shape"),
        ("timestamps", np.array([0.0, 1.0, 0.5, 2.0, 3.0]), "decrease"),
    ],
)
def test_inconsistent_arrays_are_named(field: str, value: np.ndarray, message: str) -> None:
    with pytest.raises(MeasurementLogError, match=message):
        dataclasses.replace(small_log(), **{field: value})


def test_asymmetric_or_negative_covariance() -> None:
    log = small_log()
    cov = log.feat_cov.copy()
    cov[1, 0, 1] = 0.5
    with pytest.raises(MeasurementLogError, match=r"feat_cov'\[1\] is not symmetric"):
        dataclasses.replace(log, feat_cov=cov)
    cov = log.feat_cov.copy()
    cov[4, 2, 2] = -1.0
    with pytest.raises(MeasurementLogError, match="negative variance"):
        dataclasses.replace(log, feat_cov=cov)


def test_other_version_is_refused(tmp_path: Path) -> None:
    path = save_log(small_log(), tmp_path / "log.npz")
    with np.load(path) as npz:
        arrays = {k: npz[k] for k in npz.files}
    arrays["format_version"] = np.array(FORMAT_VERSION + 1)
    np.savez(tmp_path / "future.npz", **arrays)  # type: ignore[arg-type]
    with pytest.raises(MeasurementLogError, match=f"version {FORMAT_VERSION + 1}"):
        load_log(tmp_path / "future.npz")


def test_damaged_and_foreign_files(tmp_path: Path) -> None:
    path = save_log(small_log(), tmp_path / "log.npz")
    data = path.read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(MeasurementLogError, match=r"cut\.npz.*not a readable"):
        load_log(tmp_path / "cut.npz")
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(MeasurementLogError, match="not a mapfuse measurement log"):
        load_log(tmp_path / "other.npz")
    with pytest.raises(MeasurementLogError, match="no such"):
        load_log(tmp_path / "missing.npz")


def test_missing_array_is_named(tmp_path: Path) -> None:
    path = save_log(small_log(), tmp_path / "log.npz")
    with zipfile.ZipFile(path) as zin, zipfile.ZipFile(tmp_path / "m.npz", "w") as zout:
        for item in zin.infolist():
            if item.filename != "odometry_cov.npy":
                zout.writestr(item, zin.read(item.filename))
    with pytest.raises(MeasurementLogError, match="missing array 'odometry_cov'"):
        load_log(tmp_path / "m.npz")


def test_gps_reference_round_trip_and_pairing(tmp_path: Path) -> None:
    log = dataclasses.replace(
        small_log(), gps_times=np.array([0.1, 0.3]), gps_xy=np.array([[1.0, 2.0], [3.0, 4.0]])
    )
    back = load_log(save_log(log, tmp_path / "gps.npz"))
    assert back.gps_xy is not None
    np.testing.assert_array_equal(back.gps_xy, log.gps_xy)
    with pytest.raises(MeasurementLogError, match="together"):
        dataclasses.replace(small_log(), gps_times=np.array([0.1]))


def _with_scans(log: MeasurementLog, beams: int = 4) -> MeasurementLog:
    ranges = np.linspace(1.0, 9.0, log.n_steps * beams).reshape(log.n_steps, beams)
    ranges[1, 2] = np.inf
    return dataclasses.replace(
        log,
        scan_bearings=np.linspace(-1.0, 1.0, beams),
        scan_ranges=ranges.astype(np.float32),
    )


def test_raw_scans_round_trip_as_float32_and_are_cut_by_head(tmp_path: Path) -> None:
    log = _with_scans(small_log())
    back = load_log(save_log(log, tmp_path / "log.npz"))
    assert back.scan_ranges is not None
    assert back.scan_bearings is not None
    assert back.scan_ranges.dtype == np.float32
    np.testing.assert_array_equal(back.scan_ranges, log.scan_ranges)
    np.testing.assert_array_equal(back.scan_bearings, log.scan_bearings)
    assert np.isinf(back.scan_ranges[1, 2])
    head = log.head(3)
    assert head.scan_ranges is not None
    assert head.scan_ranges.shape == (3, 4)
    # A log without scans keeps none.
    assert load_log(save_log(small_log(), tmp_path / "bare.npz")).scan_ranges is None


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"scan_bearings": None}, "given together"),
        ({"scan_ranges": np.ones((5, 3), dtype=np.float32)}, r"shape \(5, 3\)"),
        ({"scan_ranges": np.ones((4, 4), dtype=np.float32)}, r"shape \(4, 4\)"),
        ({"scan_ranges": np.ones((5, 4))}, "float32"),
        ({"scan_bearings": np.array([0.0, 0.5, 0.5, 1.0])}, "increase strictly"),
        ({"scan_bearings": np.array([0.0, 1.0, 2.0, 4.0])}, "within ±π"),
        ({"scan_bearings": np.array([0.0, np.nan, 2.0, 3.0])}, "non-finite"),
    ],
)
def test_bad_raw_scans_are_named(change: dict[str, object], message: str) -> None:
    log = _with_scans(small_log())
    with pytest.raises(MeasurementLogError, match=message):
        dataclasses.replace(log, **change)


@pytest.mark.parametrize("value", [np.nan, -1.0])
def test_a_range_that_is_no_range_is_named_with_its_beam(value: float) -> None:
    log = _with_scans(small_log())
    assert log.scan_ranges is not None
    bad = log.scan_ranges.copy()
    bad[3, 1] = value
    with pytest.raises(MeasurementLogError, match=r"'scan_ranges'\[3, 1\]"):
        dataclasses.replace(log, scan_ranges=bad)


def test_simulated_logs_keep_their_raw_scans() -> None:
    from mapfuse_core.sim.scenario import load_scenario
    from mapfuse_core.sim.simulate import simulate

    scenario = dataclasses.replace(load_scenario("loop600"), steps=6)
    sim = simulate(scenario, seed=0, workers=1)
    assert sim.log.scan_ranges is not None
    assert sim.log.scan_bearings is not None
    assert sim.log.scan_ranges.shape == (6, scenario.laser.n_beams)
    for k, scan in enumerate(sim.scans):
        np.testing.assert_allclose(sim.log.scan_ranges[k], scan.ranges, rtol=1e-6)
