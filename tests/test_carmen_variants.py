"""Corrected or raw: the CARMEN loader's decision on every message variant, the override
(``odometry=raw|corrected``, ``--odometry``, ``carmen,odometry=…:PATH``) and the seven
real logs.

The snippets are written here, one per variant.  Small scans (4 beams) keep the
revisit evidence silent, so that each snippet tests the one piece of evidence it is
about; the revisit evidence is tested on a simulated room driven round twice.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest

from mapfuse.carmen_input import (
    carmen_log_kind,
    load_carmen_input,
    parse_carmen_source,
    with_odometry,
)
from mapfuse.cli import main
from mapfuse_core.data.datasets.carmen import CarmenOptions, detect_odometry_kind, load_carmen
from mapfuse_core.data.datasets.carmen_format import read_carmen
from mapfuse_core.data.datasets.carmen_kind import (
    REVISIT_MIN_PAIRS,
    UndecidedOdometryError,
    judge_odometry,
)
from mapfuse_core.geometry.se2 import FloatArray, compose, relative
from mapfuse_core.sim.laser import LaserParams, simulate_scan
from mapfuse_core.sim.world import WallSegment, World

SEVEN = ("acapulco", "belgioioso", "csail", "fhw", "freiburg-101", "intel", "seattle")
"""The public corrected logs in the shared data folder."""

_RANGES4 = (1.5, 2.0, 2.5, 3.0)

# --------------------------------------------------------------------------- snippets


def _path(n: int = 12) -> FloatArray:
    """(n, 3) robot poses: 0.3 m steps along a gentle arc."""
    k = np.arange(n, dtype=float)
    out: FloatArray = np.c_[0.3 * k, 0.02 * k * k, 0.04 * k]
    return out


def _p(pose: FloatArray, fmt: str = "{:.6f}") -> str:
    return " ".join(fmt.format(float(v)) for v in pose)


def _flaser(
    laser: FloatArray,
    robot: FloatArray,
    t: float,
    *,
    kind: str = "FLASER",
    time_fields: int = 3,
    fmt: str = "{:.6f}",
) -> str:
    """An ``FLASER``/``RLASER`` line; ``time_fields`` 1: ``ipc_timestamp`` only (old
    loggers), 2: with the host name, 3: with the logger timestamp."""
    tail = [f"{t:.3f}", "host", f"{t:.3f}"][:time_fields]
    ranges = " ".join(str(r) for r in _RANGES4)
    return f"{kind} 4 {ranges} {_p(laser, fmt)} {_p(robot, fmt)} {' '.join(tail)}"


def _robotlaser1(laser: FloatArray, robot: FloatArray, t: float, tv: float, rv: float) -> str:
    """A ``ROBOTLASER1`` line (4 beams over 180°, no remissions)."""
    geometry = f"0 {-math.pi / 2:.7f} {math.pi:.7f} {math.pi / 3:.7f} 30.0 0.01 0"
    ranges = " ".join(str(r) for r in _RANGES4)
    return (
        f"ROBOTLASER1 {geometry} 4 {ranges} 0 {_p(laser)} {_p(robot)} "
        f"{tv} {rv} 0.3 0.2 0.5 {t:.3f} host {t:.3f}"
    )


def _odom(pose: FloatArray, t: float, tv: float = 0.0, rv: float = 0.0) -> str:
    return f"ODOM {_p(pose)} {tv} {rv} 0 {t:.3f} host {t:.3f}"


def _write(tmp_path: Path, name: str, lines: Sequence[str]) -> Path:
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def _corrected_flaser(tmp_path: Path, *, time_fields: int = 3, kind: str = "FLASER") -> Path:
    """A benchmark-style corrected log: each scan's pose in both fields, an ``ODOM``
    line repeating it without velocities."""
    lines = []
    for k, pose in enumerate(_path()):
        lines.append(_odom(pose, k))
        lines.append(_flaser(pose, pose, k + 0.5, kind=kind, time_fields=time_fields))
    return _write(tmp_path, "a.log", lines)


def _offset_param(value: float) -> str:
    return f"PARAM robot_frontlaser_offset {value} nohost 0"


def _evidence(path: Path) -> dict[str, str | None]:
    return {e.name: e.says for e in judge_odometry(read_carmen(path)).evidence}


# --------------------------------------------------------------------------- variants


@pytest.mark.parametrize("time_fields", [1, 2, 3])
def test_corrected_flaser_in_old_and_new_time_fields(tmp_path: Path, time_fields: int) -> None:
    path = _corrected_flaser(tmp_path, time_fields=time_fields)
    assert detect_odometry_kind(read_carmen(path)) == "corrected"
    assert _evidence(path) == {
        "pose fields": None,
        "laser offset": None,
        "velocities": "corrected",
        "revisits": None,
    }


def test_corrected_rear_laser_log_is_read_from_its_rlaser_messages(tmp_path: Path) -> None:
    path = _corrected_flaser(tmp_path, kind="RLASER")
    rec = read_carmen(path)
    assert {m.kind for m in rec.lasers} == {"RLASER"}
    log = load_carmen(path)
    assert log.metadata["log_kind"] == "corrected: detected"
    assert log.metadata["laser_messages"] == "RLASER: 12"
    assert log.true_poses is not None
    np.testing.assert_allclose(log.true_poses, _path(), atol=1e-6)


def test_raw_rear_laser_looking_backwards_applies_its_stated_offset(tmp_path: Path) -> None:
    # A rear laser 0.2 m behind the robot centre, turned by a half turn: its relation
    # to the odometry has a heading of ±π, which the rigid-relation test must not
    # take for drift.
    lines = ["PARAM robot_rearlaser_offset 0.2 nohost 0"]
    for k, robot in enumerate(_path()):
        # A heading just either side of the half turn, as rounding leaves it.
        mount = np.array([-0.2, 0.0, math.pi - 5e-7 if k % 2 else -math.pi + 5e-7])
        lines.append(_odom(robot, k, tv=0.3))
        lines.append(_flaser(compose(robot, mount), robot, k + 0.5, kind="RLASER"))
    path = _write(tmp_path, "rear.log", lines)
    assert _evidence(path) == {
        "pose fields": None,
        "laser offset": None,
        "velocities": "raw",
        "revisits": None,
    }
    # The same poses in both fields: the stated rear offset is not applied.
    lines = ["PARAM robot_rearlaser_offset 0.2 nohost 0"]
    lines += [_flaser(p, p, k, kind="RLASER") for k, p in enumerate(_path())]
    assert _evidence(_write(tmp_path, "rear-fixed.log", lines))["laser offset"] == "corrected"


def test_rlaser_beside_a_front_laser_is_skipped_and_counted(tmp_path: Path) -> None:
    pose = np.zeros(3)
    lines = [_flaser(pose, pose, 1.0), _flaser(pose, pose, 1.1, kind="RLASER")]
    rec = read_carmen(_write(tmp_path, "both.log", lines))
    assert [m.kind for m in rec.lasers] == ["FLASER"]
    assert rec.skipped == {"RLASER": 1}


def test_stated_offset_not_applied_between_the_pose_fields_says_corrected(
    tmp_path: Path,
) -> None:
    # The case: corrected poses in both fields, a PARAM laser offset, and
    # nothing else (no ODOM): the offset a CARMEN robot module applies is missing.
    lines = [_offset_param(-0.04)]
    lines += [_flaser(p, p, k) for k, p in enumerate(_path())]
    path = _write(tmp_path, "offset.log", lines)
    assert detect_odometry_kind(read_carmen(path)) == "corrected"
    assert _evidence(path)["laser offset"] == "corrected"
    log = load_carmen(path)
    assert log.true_poses is not None
    assert "not applied between the pose fields" in log.metadata["log_kind_evidence"]


@pytest.mark.parametrize(
    ("mounting", "angular"),
    [((0.1, 0.0, 0.0), 0.0), ((-0.1, 0.0, 0.0), 0.0), ((0.1, 0.0, -0.05), 0.05)],
    ids=["robot-plus-offset", "offset-the-other-way", "angular-offset-the-other-way"],
)
def test_raw_flaser_with_the_offset_applied_and_odom_velocities_is_raw(
    tmp_path: Path, mounting: tuple[float, float, float], angular: float
) -> None:
    lines = [_offset_param(0.1), f"PARAM robot_frontlaser_angular_offset {angular} nohost 0"]
    for k, robot in enumerate(_path()):
        lines.append(_odom(robot, k, tv=0.3, rv=0.04))
        lines.append(_flaser(compose(robot, np.array(mounting)), robot, k + 0.5))
    path = _write(tmp_path, "raw.log", lines)
    assert detect_odometry_kind(read_carmen(path)) == "raw"
    assert _evidence(path) == {
        "pose fields": None,
        "laser offset": None,
        "velocities": "raw",
        "revisits": None,
    }
    log = load_carmen(path)
    assert log.true_poses is None
    assert log.metadata["log_kind"] == "raw: detected"
    # The increments are the written laser poses' (the robot's ⊕ the mounting).
    lp = np.array([compose(r, np.array(mounting)) for r in _path()])
    np.testing.assert_allclose(log.odometry[1], relative(lp[0], lp[1])[0], atol=1e-5)


def test_raw_flaser_without_odom_velocities_or_offset_is_undecided(tmp_path: Path) -> None:
    # Raw odometry in both fields, a zero offset and no ODOM line: nothing tells.
    lines = [_offset_param(0.0)] + [_flaser(p, p, k) for k, p in enumerate(_path())]
    path = _write(tmp_path, "bare.log", lines)
    with pytest.raises(UndecidedOdometryError) as info:
        load_carmen(path)
    text = str(info.value)
    assert "cannot tell whether the poses are corrected or raw odometry" in text
    assert "no evidence in it tells a corrected log from raw odometry" in text
    assert "state it: odometry raw or corrected" in text
    assert "velocities: no message carries velocities" in text


def test_robotlaser1_velocities_say_raw_and_zero_velocities_while_moving_say_corrected(
    tmp_path: Path,
) -> None:
    mount = np.array([0.2, 0.0, 0.0])
    raw = [_robotlaser1(compose(p, mount), p, k, 0.3, 0.05) for k, p in enumerate(_path())]
    raw_path = _write(tmp_path, "rl1-raw.log", raw)
    assert detect_odometry_kind(read_carmen(raw_path)) == "raw"
    fixed = [_robotlaser1(p, p, k, 0.0, 0.0) for k, p in enumerate(_path())]
    fixed_path = _write(tmp_path, "rl1-fixed.log", fixed)
    assert detect_odometry_kind(read_carmen(fixed_path)) == "corrected"


def test_a_robot_that_does_not_move_gives_no_velocity_evidence(tmp_path: Path) -> None:
    pose = np.array([1.0, 2.0, 0.5])
    lines = [_odom(pose, k) for k in range(5)] + [_flaser(pose, pose, 5.5)]
    path = _write(tmp_path, "still.log", lines)
    assert _evidence(path)["velocities"] is None
    with pytest.raises(UndecidedOdometryError):
        detect_odometry_kind(read_carmen(path))


def test_odometry_that_drifts_from_the_laser_pose_is_raw(tmp_path: Path) -> None:
    # Laser poses corrected, odometry fields raw: the odometry drifts from the laser
    # pose by a growing heading and position error.
    truth = _path(20)
    k = np.arange(20.0)[:, None]
    odometry = truth + k * [0.01, -0.005, math.radians(0.5)]
    lines = [_flaser(t, o, i) for i, (t, o) in enumerate(zip(truth, odometry, strict=True))]
    path = _write(tmp_path, "drift.log", lines)
    verdict = judge_odometry(read_carmen(path))
    assert verdict.kind == "raw"
    assert verdict.mounting is None
    assert "odometry drifts from the laser pose in 20 of 20 laser messages" in verdict.summary()
    log = load_carmen(path)
    assert log.true_poses is None
    # Raw increments come from the odometry fields (no offset stated: zero).
    np.testing.assert_allclose(log.odometry[5], relative(odometry[4], odometry[5])[0], atol=1e-5)


def test_pose_fields_equal_to_their_printed_digits_are_one_trajectory(tmp_path: Path) -> None:
    # A raw log printing poses with 2 decimals: laser = robot ⊕ 0.1 m, each rounded.
    lines = [_offset_param(0.1)]
    for k, robot in enumerate(_path()):
        laser = compose(robot, np.array([0.1, 0.0, 0.0]))
        lines.append(_odom(robot, k, tv=0.3))
        lines.append(_flaser(laser, robot, k + 0.5, fmt="{:.2f}"))
    verdict = judge_odometry(read_carmen(_write(tmp_path, "coarse.log", lines)))
    assert verdict.evidence[0].says is None
    assert verdict.mounting is not None
    assert verdict.kind == "raw"


def test_disagreeing_evidence_is_undecided_and_says_so(tmp_path: Path) -> None:
    # Velocities say raw; the stated offset, not applied, says corrected.
    lines = [_offset_param(-0.04)]
    for k, pose in enumerate(_path()):
        lines.append(_odom(pose, k, tv=0.3))
        lines.append(_flaser(pose, pose, k + 0.5))
    path = _write(tmp_path, "mixed.log", lines)
    with pytest.raises(UndecidedOdometryError, match="its evidence disagrees"):
        load_carmen(path)


def test_the_file_name_is_no_evidence(tmp_path: Path) -> None:
    # Corrected content under a raw-sounding name, raw content under a corrected one.
    corrected = tmp_path / "raw-odometry.clf"
    corrected.write_text(_corrected_flaser(tmp_path).read_text())
    lines = [_odom(p, k, tv=0.3) for k, p in enumerate(_path())]
    lines += [_flaser(p, p, k + 0.5) for k, p in enumerate(_path())]
    raw = _write(tmp_path, "intel-corrected.log", lines)
    assert load_carmen(corrected).metadata["log_kind"] == "corrected: detected"
    assert load_carmen(raw).metadata["log_kind"] == "raw: detected"


# --------------------------------------------------------------------------- override


def test_the_stated_kind_overrides_the_evidence_both_ways(tmp_path: Path) -> None:
    corrected = _corrected_flaser(tmp_path)
    as_raw = load_carmen(corrected, options=CarmenOptions(odometry="raw"))
    assert as_raw.true_poses is None
    assert as_raw.seed == -1
    assert as_raw.metadata["log_kind"] == "raw: stated (the evidence says corrected)"
    lines = [_offset_param(0.1)]
    for k, robot in enumerate(_path()):
        lines.append(_odom(robot, k, tv=0.3, rv=0.04))
        lines.append(_flaser(compose(robot, np.array([0.1, 0.0, 0.0])), robot, k + 0.5))
    raw = _write(tmp_path, "raw.log", lines)
    as_corrected = load_carmen(raw, options=CarmenOptions(odometry="corrected", seed=4))
    assert as_corrected.true_poses is not None
    assert as_corrected.seed == 4
    assert as_corrected.metadata["log_kind"] == "corrected: stated (the evidence says raw)"


def test_an_undecided_log_loads_as_either_kind_when_stated(tmp_path: Path) -> None:
    path = _write(tmp_path, "bare.log", [_flaser(p, p, k) for k, p in enumerate(_path())])
    raw = load_carmen(path, options=CarmenOptions(odometry="raw"))
    corrected = load_carmen(path, options=CarmenOptions(odometry="corrected"))
    assert raw.true_poses is None
    assert corrected.true_poses is not None
    assert raw.metadata["log_kind"] == "raw: stated (the evidence says undecided)"


def test_source_options_parse_and_refuse_what_is_wrong(tmp_path: Path) -> None:
    path = _corrected_flaser(tmp_path)
    assert parse_carmen_source(f"carmen:{path}").odometry == "auto"
    assert parse_carmen_source(f"carmen,odometry=raw:{path}").odometry == "raw"
    # Everything after the first ':' is the path, commas and colons included.
    odd = tmp_path / "a,b:c.log"
    odd.write_text(path.read_text())
    assert parse_carmen_source(f"carmen,odometry=corrected:{odd}").path == odd
    assert with_odometry(f"carmen:{path}", "raw") == f"carmen,odometry=raw:{path}"
    assert with_odometry(f"carmen:{path}", None) == f"carmen:{path}"
    for source, message in [
        (f"carmen,odom=raw:{path}", "unknown option 'odom' (known: odometry)"),
        (f"carmen,odometry=wheel:{path}", "odometry must be raw or corrected, got 'wheel'"),
        (f"carmen,odometry:{path}", "expected key=value options between 'carmen' and ':'"),
        (f"carmen,odometry=raw,odometry=raw:{path}", "option 'odometry' given twice"),
    ]:
        with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
            parse_carmen_source(source)
    with pytest.raises(ValueError, match="--odometry raw contradicts odometry=corrected"):
        with_odometry(f"carmen,odometry=corrected:{path}", "raw")


def test_undecided_input_names_the_option_and_the_stated_one_loads(tmp_path: Path) -> None:
    path = _write(tmp_path, "bare.log", [_flaser(p, p, k) for k, p in enumerate(_path())])
    with pytest.raises(ValueError, match=r"state it with --odometry raw\|corrected") as info:
        load_carmen_input(f"carmen:{path}")
    assert "carmen,odometry=raw|corrected:PATH" in str(info.value)
    with pytest.raises(ValueError, match="--odometry raw"):
        carmen_log_kind(f"carmen:{path}")
    assert carmen_log_kind(f"carmen,odometry=raw:{path}") == "raw"
    log = load_carmen_input(f"carmen,odometry=raw:{path}")
    assert log.true_poses is None
    assert log.metadata["known_map"] == "none"


def _run(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(args)
    out = capsys.readouterr()
    return code, out.out, out.err


def test_cli_odometry_option_and_its_errors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _write(tmp_path, "bare.log", [_flaser(p, p, k) for k, p in enumerate(_path())])
    out = ["--out", str(tmp_path / "o"), "--force", "--quiet"]
    code, _, err = _run(["run", f"carmen:{path}", *out], capsys)
    assert code == 2
    assert "state it with --odometry raw|corrected" in err
    assert len(err.strip().splitlines()) == 1
    code, stdout, _ = _run(["run", f"carmen:{path}", "--odometry", "raw", *out], capsys)
    assert code == 0
    m = json.loads(stdout)["metrics"]
    assert m["log"]["log_kind"] == "raw: stated (the evidence says undecided)"
    assert m["position_error_m"] is None
    code, stdout, _ = _run(
        ["run", f"carmen:{path}", "--odometry", "corrected", "--known-map", "none", *out], capsys
    )
    assert code == 0
    assert json.loads(stdout)["metrics"]["position_error_m"] is not None
    for args, message in [
        (["loop600", "--odometry", "raw"], "--odometry applies to CARMEN logs"),
        (
            [f"carmen,odometry=corrected:{path}", "--odometry", "raw"],
            "--odometry raw contradicts odometry=corrected",
        ),
        ([f"carmen,colour=red:{path}"], "unknown option 'colour'"),
    ]:
        code, _, err = _run(["run", *args, *out], capsys)
        assert code == 2
        assert message in err
        assert len(err.strip().splitlines()) == 1


# --------------------------------------------------------------------------- revisits


def _room() -> World:
    """A 12 m × 8 m room with a partition and two cupboards."""
    segs = [
        ((-3.0, -4.0), (9.0, -4.0)),
        ((9.0, -4.0), (9.0, 4.0)),
        ((9.0, 4.0), (-3.0, 4.0)),
        ((-3.0, 4.0), (-3.0, -4.0)),
        ((3.0, -4.0), (3.0, -2.0)),
        ((5.0, 2.5), (6.5, 2.5)),
        ((-3.0, 0.5), (-2.2, 0.5)),
    ]
    return World(tuple(WallSegment(i, a, b) for i, (a, b) in enumerate(segs)), ())


def _loop_poses(laps: int = 2, step: float = 0.5) -> FloatArray:
    """Laser poses driving a 8 m × 4 m rectangle ``laps`` times, ``step`` apart."""
    corners = [(-1.0, -2.0), (7.0, -2.0), (7.0, 2.0), (-1.0, 2.0)]
    out = []
    for _ in range(laps):
        for a, b in zip(corners, corners[1:] + corners[:1], strict=True):
            n = round(math.dist(a, b) / step)
            heading = math.atan2(b[1] - a[1], b[0] - a[0])
            for j in range(n):
                t = j / n
                out.append((a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), heading))
    return np.array(out)


def _room_log(tmp_path: Path, name: str, written: FloatArray, true: FloatArray) -> Path:
    """FLASER only (no ODOM, no PARAM): scans simulated at the ``true`` poses, the
    ``written`` poses in both pose fields."""
    laser = LaserParams(
        fov_rad=math.pi,
        max_range_m=80.0,
        n_beams=181,
        sigma_range_m=0.01,
        sigma_bearing_rad=math.radians(0.05),
    )
    rng = np.random.default_rng(11)
    world = _room()
    lines = []
    for k, (w, x) in enumerate(zip(written, true, strict=True)):
        scan = simulate_scan(world, x, laser, rng)
        r = " ".join(f"{v:.2f}" for v in np.where(np.isfinite(scan.ranges), scan.ranges, 81.83))
        lines.append(f"FLASER 181 {r} {_p(w)} {_p(w)} {k}.0 host {k}.0")
    return _write(tmp_path, name, lines)


def _drifted(poses: FloatArray, seed: int) -> FloatArray:
    """Dead reckoning along ``poses`` with 3 % of every step and 1°/m of heading error."""
    rng = np.random.default_rng(seed)
    out = [poses[0]]
    for k in range(1, poses.shape[0]):
        inc = relative(poses[k - 1], poses[k])[0]
        d = math.hypot(inc[0], inc[1])
        noise = rng.standard_normal(3) * [0.03 * d, 0.03 * d, math.radians(1.0) * d]
        out.append(compose(out[-1], inc + noise))
    return np.array(out)


def test_revisits_tell_a_closed_loop_from_drifting_odometry(tmp_path: Path) -> None:
    true = _loop_poses()
    corrected = read_carmen(_room_log(tmp_path, "loop.log", true, true))
    verdict = judge_odometry(corrected)
    assert verdict.kind == "corrected"
    assert [e.says for e in verdict.evidence] == [None, None, None, "corrected"]
    drifted = read_carmen(_room_log(tmp_path, "drift.log", _drifted(true, 3), true))
    verdict = judge_odometry(drifted)
    assert verdict.kind == "raw"
    assert [e.says for e in verdict.evidence] == [None, None, None, "raw"]
    assert "do not coincide" in verdict.evidence[3].detail


def test_one_lap_has_no_revisit_to_judge(tmp_path: Path) -> None:
    true = _loop_poses(laps=1)[:30]
    rec = read_carmen(_room_log(tmp_path, "short.log", true, true))
    ev = judge_odometry(rec).evidence[3]
    assert ev.says is None
    assert "too few to judge" in ev.detail
    assert int(ev.detail.split()[0]) < REVISIT_MIN_PAIRS


# --------------------------------------------------------------------------- montecarlo


def test_montecarlo_runs_a_corrected_carmen_log_and_refuses_a_raw_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    true = _loop_poses()
    path = _room_log(tmp_path, "loop.log", true, true)
    out = tmp_path / "mc"
    code, stdout, err = _run(
        [
            "montecarlo",
            f"carmen:{path}",
            "--runs",
            "2",
            "--steps",
            "12",
            "--fusion",
            "off",
            "--serial",
            "--quiet",
            "--no-report",
            "--out",
            str(out),
        ],
        capsys,
    )
    assert code == 0, err
    assert json.loads(stdout)["ran"] == 2
    rows = [json.loads(x) for x in (out / "runs.jsonl").read_text().splitlines()]
    assert [r["status"] for r in rows] == ["ok", "ok"]
    assert rows[0]["steps"] == 12
    assert rows[0]["rmse_m"] != rows[1]["rmse_m"]  # each seed draws its own odometry
    drifted = _room_log(tmp_path, "drift.log", _drifted(true, 3), true)
    for args, message in [
        ([f"carmen:{drifted}"], "a campaign needs a reference trajectory"),
        ([f"carmen:{path}", "--world-per-run", "walls=6"], "--world-per-run generates"),
    ]:
        code, _, err = _run(
            ["montecarlo", *args, "--runs", "1", "--out", str(tmp_path / "x")], capsys
        )
        assert code == 2
        assert message in err


# --------------------------------------------------------------------------- real logs


def _real(data_dir: Path, name: str) -> Path:
    path = data_dir / "carmen" / f"{name}-corrected.log.gz"
    if not path.is_file():
        pytest.skip(f"{path} not found; set MAPFUSE_DATA to the shared data folder")
    return path


@pytest.mark.parametrize("name", SEVEN)
def test_real_logs_are_detected_corrected_and_load_raw_when_stated(
    data_dir: Path, name: str
) -> None:
    rec = read_carmen(_real(data_dir, name))
    verdict = judge_odometry(rec)
    assert verdict.kind == "corrected", verdict.summary()
    says = {e.name: e.says for e in verdict.evidence}
    # Their ODOM lines move without velocities; their scans coincide where they
    # revisit a place; the two with a -0.04 m offset PARAM do not apply it; no
    # evidence says raw.
    assert says["velocities"] == "corrected"
    assert says["revisits"] == "corrected"
    assert says["laser offset"] == ("corrected" if name in ("belgioioso", "freiburg-101") else None)
    assert "raw" not in says.values()
    assert carmen_log_kind(f"carmen,odometry=raw:{_real(data_dir, name)}") == "raw"


@pytest.mark.parametrize("name", SEVEN)
def test_real_scans_with_drifting_odometry_are_detected_raw(
    data_dir: Path, tmp_path: Path, name: str
) -> None:
    # The log's own scans with dead-reckoned poses in both fields and nothing else
    # (no ODOM, no PARAM): only the revisits can tell, and they must say raw.
    rec = read_carmen(_real(data_dir, name))
    poses = np.array([m.laser_pose for m in rec.lasers])
    drifted = _drifted(poses, 0)
    lines = []
    for k, (m, w) in enumerate(zip(rec.lasers, drifted, strict=True)):
        r = " ".join(f"{v:.2f}" for v in m.ranges)
        lines.append(f"FLASER {m.ranges.shape[0]} {r} {_p(w)} {_p(w)} {k}.0 host {k}.0")
    verdict = judge_odometry(read_carmen(_write(tmp_path, "raw.log", lines)))
    assert verdict.kind == "raw", verdict.summary()
