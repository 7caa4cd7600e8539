"""CARMEN logs: the reader, odometry, the indoor extraction profile, the floor plan."""

from __future__ import annotations

import dataclasses
import gzip
import math
import re
from pathlib import Path

import numpy as np
import pytest

from mapfuse_core.data.datasets.carmen import (
    CarmenOptions,
    IncrementNoise,
    carmen_scans,
    detect_odometry_kind,
    load_carmen,
    redraw_odometry,
)
from mapfuse_core.data.datasets.carmen_format import guess_beam_geometry, read_carmen
from mapfuse_core.data.datasets.carmen_kind import UndecidedOdometryError
from mapfuse_core.data.datasets.common import DatasetError
from mapfuse_core.data.datasets.floorplan import (
    build_floor_plan,
    label_with_plan,
    line_nees,
    same_wall,
)
from mapfuse_core.measlog import load_log, save_log
from mapfuse_core.perception.extraction import (
    EXTRACTION_PROFILES,
    ExtractionParams,
    extract_features,
)
from mapfuse_core.sensor import LaserParams
from mapfuse_core.sim.laser import simulate_scan
from mapfuse_core.sim.world import WallSegment, World

DATA = Path(__file__).parent / "data" / "carmen"
SNIPPET = DATA / "snippet.log"

# --------------------------------------------------------------------------- reader


@pytest.mark.parametrize("name", ["snippet.log", "snippet.log.gz"])
def test_reader_reads_every_message_type_plain_and_gzipped(name: str) -> None:
    rec = read_carmen(DATA / name)
    assert [m.kind for m in rec.lasers] == ["FLASER", "ROBOTLASER1"]
    assert len(rec.odometry) == 2
    assert rec.params == {"robot_frontlaser_offset": "0.1", "robot_front_laser_max": "50"}
    assert rec.skipped == {"NEFF": 1, "TRUEPOS": 1}
    fl, rl = rec.lasers
    np.testing.assert_array_equal(fl.ranges, [1.0, 2.0, 50.0, 0.0])
    np.testing.assert_array_equal(fl.laser_pose, [0.1, 0.0, 0.0])
    assert fl.line == 7
    assert rl.start_angle == pytest.approx(-math.pi / 2, abs=1e-7)
    assert rl.angular_resolution == pytest.approx(math.pi / 2, abs=1e-7)
    assert rl.max_range == 30.0
    np.testing.assert_array_equal(rl.laser_pose, [0.6, 0.0, 0.1])
    np.testing.assert_array_equal(rl.robot_pose, [0.5, 0.0, 0.1])


def test_loader_marks_no_returns_and_counts_skipped_messages_in_metadata() -> None:
    log = load_carmen(SNIPPET)
    assert log.metadata["skipped_messages"] == "NEFF: 1, TRUEPOS: 1"
    assert log.metadata["laser_messages"] == "FLASER: 1, ROBOTLASER1: 1"
    assert log.metadata["odometry"] == "raw"
    assert log.true_poses is None
    # Laser 0 at robot (0, 0, 0) ⊕ offset (0.1, 0, 0); laser 1 written at (0.6, 0, 0.1).
    np.testing.assert_allclose(log.odometry[1], [0.5, 0.0, 0.1], atol=1e-12)
    np.testing.assert_allclose(log.odometry_cov[1], IncrementNoise().cov(log.odometry[1]))
    np.testing.assert_array_equal(log.timestamps, [0.0, 1.0])


def test_flaser_ranges_at_max_or_zero_are_no_return() -> None:
    (s0, l0), (s1, l1) = carmen_scans(read_carmen(SNIPPET), CarmenOptions())
    np.testing.assert_array_equal(s0.ranges, [1.0, 2.0, np.inf, np.inf])  # 50 = PARAM max, 0
    np.testing.assert_array_equal(s1.ranges, [1.0, np.inf, 2.5])  # 31 > message max 30
    assert l0.max_range_m == 50.0
    assert l1.max_range_m == 30.0
    np.testing.assert_allclose(s1.bearings, [-math.pi / 2, 0.0, math.pi / 2], atol=1e-7)


def test_raw_scans_are_kept_only_when_every_message_has_the_same_beams(tmp_path: Path) -> None:
    # The snippet mixes a 4-beam FLASER with a 3-beam ROBOTLASER1.
    mixed = load_carmen(SNIPPET)
    assert mixed.scan_ranges is None
    assert mixed.metadata["raw_scans"] == "not kept: laser message 1 has other beams than the first"
    flaser = "\n".join(
        [
            "PARAM robot_front_laser_max 50 nohost 0",
            "FLASER 4 1.0 25.0 50.0 0.0 0.1 0.0 0.0 0.0 0.0 0.0 1.5 host 1.5",
            "FLASER 4 3.0 2.0 1.0 4.0 0.2 0.0 0.0 0.2 0.0 0.0 2.5 host 2.5",
        ]
    )
    path = tmp_path / "two.log"
    path.write_text(flaser + "\n")
    log = load_carmen(path, options=CarmenOptions(odometry="raw"))
    assert log.metadata["raw_scans"] == "2 x 4 beams"
    assert log.scan_bearings is not None
    assert log.scan_ranges is not None
    assert log.scan_ranges.dtype == np.float32
    np.testing.assert_allclose(
        log.scan_bearings, [-math.pi / 2 + i * math.pi / 3 for i in range(4)]
    )
    # 25 m is beyond the 20 m used for features but a return; 50 (the max) and 0 are none.
    np.testing.assert_array_equal(log.scan_ranges[0], [1.0, 25.0, np.inf, np.inf])
    np.testing.assert_array_equal(log.scan_ranges[1], [3.0, 2.0, 1.0, 4.0])
    kept = CarmenOptions(odometry="raw", keep_scans=False)
    assert load_carmen(path, options=kept).scan_ranges is None


def test_beam_geometry_follows_carmen_convention() -> None:
    assert guess_beam_geometry(180) == pytest.approx((-math.pi / 2, math.radians(1.0)))
    assert guess_beam_geometry(361) == pytest.approx((-math.pi / 2, math.radians(0.5)))
    assert guess_beam_geometry(5) == pytest.approx((-math.pi / 2, math.pi / 4))


_FLASER_OK = "FLASER 2 1.0 2.0 0 0 0 0 0 0 1.0 host 1.0"
_RL1_OK = (
    "ROBOTLASER1 0 -1.5707963 3.1415927 1.5707963 30.0 0.01 0 3 1.0 2.0 2.5 0 "
    "0 0 0 0 0 0 0 0 0 0 0 2.5 host 2.5"
)


@pytest.mark.parametrize(
    ("line", "problem"),
    [
        ("FLASER 2 1.0 2.0 0 0 0 0 0 0", "has 10 fields, expected 11 to 13"),
        ("FLASER 2 1.0 2.0 0 0 0 0 0 0 1.0 2.0 3.0", "n beams mismatch"),
        ("FLASER 3 1.0 2.0 0 0 0 0 0 0 1.0 host 1.0", "n beams mismatch"),
        ("FLASER x 1.0 2.0 0 0 0 0 0 0 1.0 host 1.0", "beam count (field 1) is not an integer"),
        ("FLASER 2 1.0 abc 0 0 0 0 0 0 1.0 host 1.0", "range (field 3) is not a number"),
        ("FLASER 2 1.0 nan 0 0 0 0 0 0 1.0 host 1.0", "range (field 3) is NaN"),
        ("FLASER 2 1.0 2.0 0 inf 0 0 0 0 1.0 host 1.0", "laser pose (field 5) is infinite"),
        ("FLASER 1 1.0 0 0 0 0 0 0 1.0 host 1.0", "beam count 1 is below 2"),
        ("FLASER", "too few for the beam count"),
        (_RL1_OK.replace(" 3 1.0 2.0 2.5 ", " 4 1.0 2.0 2.5 "), "n beams mismatch"),
        (_RL1_OK.replace("3.1415927", "1.0"), "not the field of view"),
        (_RL1_OK.replace(" 1.5707963 30.0", " 0 30.0"), "angular resolution 0.0 is not > 0"),
        (_RL1_OK.replace(" 0 0 0 0 0 0 0 0 0 0 0 2.5", " 2 0 0 0 0 0 0 0 0 0 0 0 2.5"), "expected"),
        ("ODOM 0 0 0 0 0 0", "has 7 fields, expected 8 to 10"),
        ("ODOM 0 0 q 0 0 0 1.0 host 1.0", "pose (field 3) is not a number"),
        ("PARAM lonely", "expected a name and a value"),
    ],
)
def test_malformed_line_gives_one_line_error_naming_file_and_line(
    tmp_path: Path, line: str, problem: str
) -> None:
    path = tmp_path / "bad.log"
    path.write_text(f"# header\n{_FLASER_OK}\n{line}\n")
    with pytest.raises(DatasetError) as err:
        read_carmen(path)
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith(f"{path}:3: ")
    assert problem in msg


def test_malformed_gzipped_log_names_the_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.log.gz"
    path.write_bytes(gzip.compress(f"{_FLASER_OK}\nODOM 1 2\n".encode(), mtime=0))
    with pytest.raises(DatasetError, match=re.escape(f"{path}:2: ODOM: has 3 fields")):
        read_carmen(path)


def test_log_without_laser_or_file_is_an_error(tmp_path: Path) -> None:
    path = tmp_path / "empty.log"
    path.write_text("ODOM 0 0 0 0 0 0 1.0 host 1.0\n")
    with pytest.raises(DatasetError, match="no laser message"):
        read_carmen(path)
    with pytest.raises(DatasetError, match="no such file"):
        read_carmen(tmp_path / "absent.log")


# --------------------------------------------------------------------------- odometry


def _corrected_log(tmp_path: Path, n: int = 30) -> Path:
    """A corrected-style log: a robot driving a circle, every pose field repeated."""
    lines = ["PARAM robot_frontlaser_offset 0.0 nohost 0"]
    for k in range(n):
        a = 0.1 * k
        x, y, th = 3.0 * math.sin(a), 3.0 - 3.0 * math.cos(a), a
        ranges = " ".join(["2.0"] * 181)
        p = f"{x:.6f} {y:.6f} {th:.6f}"
        lines.append(f"ODOM {p} 0 0 0 {k}.0 host {k}.0")
        lines.append(f"FLASER 181 {ranges} {p} {p} {k}.5 host {k}.5")
    path = tmp_path / "corrected.log"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_detection_tells_corrected_from_raw(tmp_path: Path) -> None:
    # Moving poses, every ODOM velocity 0: corrected.
    assert detect_odometry_kind(read_carmen(_corrected_log(tmp_path))) == "corrected"
    # The snippet's ODOM reports a velocity: raw odometry.
    assert detect_odometry_kind(read_carmen(SNIPPET)) == "raw"
    # One laser message and nothing else: no evidence either way.
    bare = tmp_path / "bare.log"
    bare.write_text("FLASER 2 1 1 0.5 0 0 0 0 0 1.0 host 1.0\n")
    with pytest.raises(UndecidedOdometryError, match="no evidence in it"):
        detect_odometry_kind(read_carmen(bare))


def test_reading_reports_progress_once_per_scan_to_the_last(tmp_path: Path) -> None:
    calls: list[tuple[int, int]] = []
    log = load_carmen(_corrected_log(tmp_path, n=30), progress=lambda k, n: calls.append((k, n)))
    assert log.n_steps == 30
    assert calls == [(k, 30) for k in range(1, 31)]


def test_simulated_odometry_is_seeded_and_its_noise_matches_its_covariance(
    tmp_path: Path,
) -> None:
    path = _corrected_log(tmp_path, n=400)
    a = load_carmen(path, options=CarmenOptions(seed=7))
    b = load_carmen(path, options=CarmenOptions(seed=7))
    c = load_carmen(path, options=CarmenOptions(seed=8))
    assert a.metadata["odometry"] == "simulated from reference"
    np.testing.assert_array_equal(a.odometry, b.odometry)
    assert not np.array_equal(a.odometry, c.odometry)
    assert a.true_poses is not None
    ref = load_carmen(path, options=CarmenOptions(odometry="raw")).odometry
    z = (a.odometry[1:] - ref[1:]) / np.sqrt(np.diagonal(a.odometry_cov[1:], axis1=1, axis2=2))
    # 399 × 3 standard normals: the variance of each component is 1 ± 0.21 (3σ).
    np.testing.assert_allclose(z.var(axis=0), 1.0, atol=0.21)


def test_redrawn_odometry_is_the_log_loaded_with_that_seed_bit_for_bit(tmp_path: Path) -> None:
    path = _corrected_log(tmp_path, n=40)
    noise = IncrementNoise(trans_frac=0.08)
    first = load_carmen(path, options=CarmenOptions(seed=7, odometry_noise=noise))
    again = load_carmen(path, options=CarmenOptions(seed=8, odometry_noise=noise))
    redrawn = redraw_odometry(first, 8, noise)
    assert redrawn.seed == 8
    assert save_log(redrawn, tmp_path / "a.npz").read_bytes() == (
        save_log(again, tmp_path / "b.npz").read_bytes()
    )
    # Labels and metadata put on the log stay.
    labels = np.arange(first.n_features, dtype=np.int64) % 5
    labelled = dataclasses.replace(
        first, feat_true_id=labels, metadata={**first.metadata, "known_map": "a plan"}
    )
    kept = redraw_odometry(labelled, 8, noise)
    np.testing.assert_array_equal(kept.feat_true_id, labels)
    assert kept.metadata == {**again.metadata, "known_map": "a plan"}
    np.testing.assert_array_equal(kept.odometry, again.odometry)


def test_redrawing_needs_simulated_odometry_and_an_int_seed(tmp_path: Path) -> None:
    path = _corrected_log(tmp_path, n=30)
    raw = load_carmen(path, options=CarmenOptions(odometry="raw"))
    with pytest.raises(ValueError, match="odometry 'raw'"):
        redraw_odometry(raw, 1)
    with pytest.raises(ValueError, match="seed must be an int"):
        redraw_odometry(load_carmen(path), True)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="seed must be >= 0, got -2"):
        redraw_odometry(load_carmen(path), -2)


def test_metadata_survives_save_and_load(tmp_path: Path) -> None:
    log = load_carmen(_corrected_log(tmp_path))
    back = load_log(save_log(log, tmp_path / "log.npz"))
    assert back.metadata == log.metadata


def test_bad_options_are_refused() -> None:
    with pytest.raises(ValueError, match="odometry must be"):
        CarmenOptions(odometry="wheel")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="trans_floor_m must be > 0"):
        IncrementNoise(trans_floor_m=0.0)
    with pytest.raises(ValueError, match="keep_scans must be a bool"):
        CarmenOptions(keep_scans=1)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- profile


def test_profiles_are_selected_by_name() -> None:
    assert EXTRACTION_PROFILES == ("default", "indoor_sick")
    assert ExtractionParams.profile("indoor_sick") == ExtractionParams.indoor_sick()
    assert ExtractionParams.profile("default") == ExtractionParams()
    with pytest.raises(ValueError, match="unknown extraction profile 'outdoor'"):
        ExtractionParams.profile("outdoor")


_MIN_INDOOR_LINES = 6
"""Lines the indoor profile must find in the synthetic office scan: of its 9 walls in
view, the two seen at grazing incidence and the 0.6 m door frame may fail."""


def _office() -> World:
    """A 6 m × 4 m room with a door gap, a cupboard and a partition (walls 0.6–6 m)."""
    segs = [
        ((-1.0, -2.0), (5.0, -2.0)),
        ((5.0, -2.0), (5.0, 0.4)),
        ((5.0, 1.4), (5.0, 2.0)),  # door frame beyond the door gap
        ((5.0, 2.0), (-1.0, 2.0)),
        ((2.0, 1.0), (3.0, 1.0)),  # cupboard front
        ((3.0, 1.0), (3.0, 2.0)),
        ((2.0, 1.0), (2.0, 2.0)),
        ((1.5, -2.0), (1.5, -1.2)),  # partition stub
        ((3.5, -1.2), (4.3, -1.2)),  # desk front
    ]
    return World(tuple(WallSegment(i, a, b) for i, (a, b) in enumerate(segs)), ())


@pytest.mark.parametrize("n_beams", [181, 361])
def test_indoor_profile_finds_the_walls_of_a_synthetic_office(n_beams: int) -> None:
    laser = LaserParams(
        fov_rad=math.pi,
        max_range_m=80.0,
        n_beams=n_beams,
        sigma_range_m=0.01,
        sigma_bearing_rad=math.radians(0.05),
    )
    rng = np.random.default_rng(3)
    counts = []
    for _ in range(10):
        scan = simulate_scan(_office(), np.array([0.0, 0.0, 0.0]), laser, rng)
        counts.append(len(extract_features(scan, laser, ExtractionParams.indoor_sick()).features))
        default = len(extract_features(scan, laser, ExtractionParams()).features)
        assert default < counts[-1]
    assert min(counts) >= _MIN_INDOOR_LINES


# --------------------------------------------------------------------------- real data


def _carmen_file(data_dir: Path, name: str) -> Path:
    path = data_dir / "carmen" / f"{name}-corrected.log.gz"
    if not path.is_file():
        pytest.skip(f"CARMEN log not found ({path})")
    return path


_MIN_LINES_PER_SCAN = {"intel": 3.5, "csail": 3.0}
"""Lower bounds on lines per scan, about 10 % under the measured values in
``docs/results/carmen.md`` (a margin for platform round-off in split decisions)."""

_NEES_RANGE = (0.6, 1.25)
"""Accepted mean line NEES per dof against the plan without its survey σ: the
profile's model-error terms are set on Intel (mean near 1); CSAIL's smoother walls come
out lower (``docs/results/carmen.md``)."""


@pytest.mark.realdata
@pytest.mark.slow
@pytest.mark.parametrize("name", ["intel", "csail"])
def test_real_log_lines_per_scan_and_line_nees_against_the_plan(data_dir: Path, name: str) -> None:
    from mapfuse_core.data.datasets.floorplan import FloorPlanParams

    log = load_carmen(_carmen_file(data_dir, name))
    assert log.metadata["odometry"] == "simulated from reference"
    assert log.true_poses is not None
    assert log.n_features / log.n_steps >= _MIN_LINES_PER_SCAN[name]
    bare = build_floor_plan(log, FloorPlanParams(survey_sigma_m=1e-6, survey_sigma_rad=1e-8))
    nees = line_nees(log, bare) / 2.0
    assert _NEES_RANGE[0] <= nees.mean() <= _NEES_RANGE[1]


_SEEDS = range(4)
"""Seeds of the simulated odometry the CCDA and fusion checks run over."""


@pytest.mark.realdata
@pytest.mark.slow
@pytest.mark.parametrize("name", ["intel", "csail"])
def test_real_log_ccda_places_the_plan_with_correct_pairings_and_lowers_the_error(
    data_dir: Path, name: str
) -> None:
    from ekf_reference import EKFConfig, run_ekf
    from mapfuse_core.data.datasets.carmen import carmen_association
    from mapfuse_core.evaluation import anchor_truth, pose_metrics, truth_in_global
    from mapfuse_core.geometry.se2 import relative

    raw = load_carmen(_carmen_file(data_dir, name))
    assert raw.true_poses is not None
    plan = build_floor_plan(raw)
    labelled = label_with_plan(raw, plan)
    truth = truth_in_global(raw.true_poses)
    assoc = carmen_association()
    accepted, anchor_m, anchor_rad, rmse_plan, rmse_none = 0, [], [], [], []
    for seed in _SEEDS:
        # The file read once; each seed's odometry as loading it with that seed gives
        # (test_redrawn_odometry_is_the_log_loaded_with_that_seed_bit_for_bit).
        log = redraw_odometry(labelled, seed)
        r_plan = run_ekf(log, EKFConfig(data_association=assoc))
        r_none = run_ekf(log, EKFConfig(data_association=assoc), fusion=False)
        rmse_plan.append(pose_metrics(r_plan.poses, r_plan.covs, truth)[0].rmse)
        rmse_none.append(pose_metrics(r_none.poses, r_none.covs, truth)[0].rmse)
        if r_plan.anchor is None:
            continue
        accepted += 1
        judged = [same_wall(plan, a, b) for a, b in r_plan.anchor.pairings if a >= 0]
        assert len(judged) >= 10
        assert all(judged), f"seed {seed}: {r_plan.anchor.pairings}"
        err = relative(anchor_truth(raw.true_poses), r_plan.anchor.x_Wknown_Wglobal)[0]
        anchor_m.append(math.hypot(err[0], err[1]))
        anchor_rad.append(abs(err[2]))
    # Seeds 0-3 (docs/results/carmen.md): CCDA accepts on 4 (Intel) and 3 (CSAIL, seed 1
    # refuses every attempt) with every judged pairing correct; anchor errors
    # 0.17-0.37 m but CSAIL seed 0 (1.28 m, 2.5°, a match made late, at step 319, on a
    # map 3 m adrift); the median RMSE with the plan is 0.31 against 2.12 m (Intel) and
    # 1.32 against 1.75 m (CSAIL).  The medians' bounds leave about half as much again.
    assert accepted >= 3
    assert float(np.median(anchor_m)) < 0.5
    assert float(np.median(anchor_rad)) < math.radians(2.0)
    assert max(anchor_m) < 2.0
    assert float(np.median(rmse_plan)) < float(np.median(rmse_none))
