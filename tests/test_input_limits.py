"""Documented limits and load-time checks: seeds, steps and beams bounded before any
allocation; logs with wrong dtypes, shapes or non-PSD covariances refused, naming the
file, the array and the index (docs/conventions.md)."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import pytest

from mapfuse.cli import main
from mapfuse_core.measlog import MeasurementLogError, load_log, save_log
from mapfuse_core.sensor import MAX_BEAMS, LaserParams
from mapfuse_core.sim.limits import MAX_SEED, MAX_STEPS, check_seed
from mapfuse_core.sim.scenario import scenario_from_toml
from mapfuse_core.sim.simulate import simulate
from mapfuse_core.sim.vehicle import VehicleParams, simulate_motion
from tests.test_measlog import small_log
from tests.test_scenario import SMALL

# ----------------------------------------------------------------------- simulation limits


def test_laser_refuses_more_beams_than_the_maximum() -> None:
    assert LaserParams(n_beams=MAX_BEAMS).n_beams == MAX_BEAMS
    with pytest.raises(ValueError, match="n_beams must be <= 10,000"):
        LaserParams(n_beams=100_000_000)


def test_motion_refuses_more_steps_than_the_maximum_before_allocating() -> None:
    rng = np.random.default_rng(0)
    path = np.array([[0.0, 0.0], [9.0, 0.0]])
    t0 = time.perf_counter()
    # 1e13 poses would be 1.4 PB of arrays: the check must come first.
    with pytest.raises(ValueError, match="above the maximum of 1,000,000 steps"):
        simulate_motion(np.zeros(3), path, 10**13, VehicleParams(), rng)
    assert time.perf_counter() - t0 < 1.0
    assert MAX_STEPS == 1_000_000


@pytest.mark.parametrize("seed", [-1, MAX_SEED + 1, 2**64])
def test_simulate_refuses_a_seed_outside_int64(seed: int) -> None:
    scenario = scenario_from_toml(SMALL, "small.toml")
    with pytest.raises(ValueError, match=r"seed must be in 0 … 2\*\*63 - 1"):
        simulate(scenario, seed=seed, workers=1)


def test_largest_seed_simulates_and_round_trips(tmp_path: Path) -> None:
    log = simulate(scenario_from_toml(SMALL, "small.toml"), seed=MAX_SEED, workers=1).log
    assert load_log(save_log(log, tmp_path / "log.npz")).seed == MAX_SEED


def test_check_seed_accepts_numpy_integers_and_refuses_other_types() -> None:
    assert check_seed(np.int64(7)) == 7
    with pytest.raises(ValueError, match="must be an integer"):
        check_seed(1.5)
    with pytest.raises(ValueError, match="must be an integer"):
        check_seed(True)


def test_cli_simulate_refuses_a_seed_of_2_64_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(["simulate", "loop600", "--seed", str(2**64), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2
    assert err.strip().count("\n") == 0
    assert "argument --seed: must be in 0 … 2**63 - 1, got 18446744073709551616" in err
    assert not (tmp_path / "o").exists()


# ----------------------------------------------------------------------- measurement logs


def _rewrite(src: Path, dst: Path, **arrays: np.ndarray) -> Path:
    """A copy of the log ``src`` with some arrays replaced."""
    with np.load(src, allow_pickle=False) as npz:
        content = {k: npz[k] for k in npz.files}
    content.update(arrays)
    np.savez(dst, **content)
    return dst


@pytest.fixture
def log_file(tmp_path: Path) -> Path:
    return save_log(small_log(), tmp_path / "log.npz")


def _huge(a: np.ndarray, index: tuple[int, ...], value: float) -> np.ndarray:
    a[index] = value
    return a


@pytest.mark.parametrize(
    ("name", "value", "message"),
    [
        ("odometry", np.full((5, 3), "x"), "'odometry' must be numeric, got <U1"),
        ("feat_params", np.ones((6, 3), dtype=complex), "'feat_params' must be numeric"),
        ("odometry_cov", np.ones((5, 3, 3), dtype=bool), "'odometry_cov' must be numeric"),
        ("seed", np.zeros((2, 2), dtype=np.int64), "'seed' must be a scalar, got shape (2, 2)"),
        ("seed", np.array(2**64 - 1, dtype=np.uint64), "'seed' has a value outside int64"),
        ("seed", np.array(-5), "'seed' must be in -1 … 2**63 - 1, got -5"),
        ("feat_step", np.zeros(6), "'feat_step' must be integer, got float64"),
        ("feat_true_id", np.full(6, 2**63, dtype=np.uint64), "'feat_true_id' has a value outside"),
        ("scenario", np.array(["a", "b"]), "'scenario' must be a text scalar"),
        ("format_version", np.ones((1, 1), dtype=np.int64), "'format_version' must be a scalar"),
        ("rejected_counts", np.array([[1, 2]]), "'rejected_counts' must be 1-D"),
        ("timestamps", np.zeros((5, 2)), "'timestamps' has shape (5, 2), expected N"),
        (
            "odometry",
            _huge(np.zeros((5, 3)), (2, 0), 1e300),
            "'odometry' has a value beyond ±1e+09 (1e+300) at index (2, 0)",
        ),
        (
            "feat_cov",
            _huge(np.stack([np.eye(3)] * 6), (1, 1, 1), 1e20),
            "'feat_cov' has a value beyond ±1e+18 (1e+20) at index (1, 1, 1)",
        ),
    ],
)
def test_log_with_a_wrong_dtype_or_shape_is_refused_naming_file_and_array(
    log_file: Path, tmp_path: Path, name: str, value: np.ndarray, message: str
) -> None:
    bad = _rewrite(log_file, tmp_path / "bad.npz", **{name: value})
    with pytest.raises(MeasurementLogError) as info:
        load_log(bad)
    text = str(info.value)
    assert text.startswith(f"{bad}: ")
    assert message in text
    assert "\n" not in text


#: An indefinite symmetric 3×3 (eigenvalues about 1.1e-2, 1.0e-2 and -4.0e-4).
NOT_PSD = np.array([[0.01, 0.0, 0.0], [0.0, 0.01, 0.0032], [0.0, 0.0032, 0.0006]])


@pytest.mark.parametrize("index", [1, 4])  # a circle and a line of small_log
def test_one_non_psd_feature_covariance_among_many_is_refused_with_its_index(
    log_file: Path, tmp_path: Path, index: int
) -> None:
    covs = small_log().feat_cov.copy()
    covs[index] = NOT_PSD
    bad = _rewrite(log_file, tmp_path / "bad.npz", feat_cov=covs)
    low = np.linalg.eigvalsh(NOT_PSD)[0]
    assert low < -3e-4
    with pytest.raises(MeasurementLogError) as info:
        load_log(bad)
    assert str(info.value) == (
        f"{bad}: 'feat_cov'[{index}] is not positive semi-definite (min eigenvalue {low:.3g})"
    )


def test_non_psd_known_map_covariance_is_refused_with_its_index(
    log_file: Path, tmp_path: Path
) -> None:
    covs = small_log().known_map.covs.copy()
    covs[1] = NOT_PSD
    bad = _rewrite(log_file, tmp_path / "bad.npz", known_covs=covs)
    with pytest.raises(MeasurementLogError, match=r"'known_covs'\[1\] is not positive semi-def"):
        load_log(bad)


def test_psd_check_is_relative_to_each_variance_not_to_the_largest() -> None:
    # A line's along-line pseudo-variance of 1e8 beside 1e-4 and 1e-6: the (y, θ) block
    # is indefinite (determinant 1e-10 - 4e-10), its eigenvalue -3e-6 only 3e-14 of the
    # largest entry, which a tolerance on the matrix's scale would pass.
    cov = np.array([[1e8, 0.0, 0.0], [0.0, 1e-4, 2e-5], [0.0, 2e-5, 1e-6]])
    log = small_log()
    covs = log.feat_cov.copy()
    covs[3] = cov
    with pytest.raises(MeasurementLogError, match=r"'feat_cov'\[3\] is not positive semi"):
        dataclasses.replace(log, feat_cov=covs)


def test_singular_psd_covariances_from_rounding_are_accepted() -> None:
    # J Σ Jᵀ with a 3×2 J is singular: its smallest eigenvalue is rounding, of either sign.
    rng = np.random.default_rng(5)
    log = small_log()
    covs = []
    for _ in range(log.n_features):
        J = rng.normal(size=(3, 2)) * np.array([[1e3], [1.0], [1e-3]])
        covs.append(J @ np.diag([0.3, 2e-4]) @ J.T)
    checked = dataclasses.replace(log, feat_cov=np.array(covs))
    assert checked.n_features == log.n_features


@pytest.mark.parametrize(
    ("cov", "what"),
    [(np.zeros((3, 3)), "zero"), (np.diag([0.01, 0.01, 0.0]), "no heading variance")],
)
def test_odometry_covariance_that_is_not_positive_definite_is_refused_with_its_index(
    log_file: Path, tmp_path: Path, cov: np.ndarray, what: str
) -> None:
    covs = small_log().odometry_cov.copy()
    covs[3] = cov
    bad = _rewrite(log_file, tmp_path / "bad.npz", odometry_cov=covs)
    with pytest.raises(MeasurementLogError) as info:
        load_log(bad)
    assert str(info.value).startswith(
        f"{bad}: 'odometry_cov'[3] is not positive definite (min eigenvalue 0)"
    ), what


def test_odometry_row_zero_may_be_zero() -> None:
    log = small_log()
    assert np.all(log.odometry_cov[0] == 0.0)
