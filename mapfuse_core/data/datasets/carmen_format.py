"""Reading CARMEN log files (plain or gzipped) into checked records (``docs/carmen.md``).

One message a line, fields separated by white space; blank lines and lines starting
with ``#`` are skipped.  Read messages:

* ``FLASER n r_1 … r_n x y θ odom_x odom_y odom_θ ipc_timestamp hostname logger_timestamp``
  (front laser: ``x y θ`` the laser pose, ``odom_*`` the robot pose, both in the log's
  odometry frame; beams after CARMEN's convention for the old laser messages, see
  :func:`guess_beam_geometry`);
* ``ROBOTLASER1 laser_type start_angle fov angular_resolution max_range accuracy
  remission_mode n r_1 … r_n m e_1 … e_m laser_x laser_y laser_θ robot_x robot_y
  robot_θ tv rv forward_safety side_safety turn_axis ipc_timestamp hostname
  logger_timestamp`` (its own beam geometry and laser pose);
* ``ODOM x y θ tv rv accel ipc_timestamp hostname logger_timestamp``;
* ``PARAM name value [hostname timestamp]``.

Every other message type is skipped and counted.  A malformed line raises
:class:`~mapfuse_core.data.datasets.common.DatasetError` naming the file, the line number
and the problem.
"""

from __future__ import annotations

import gzip
import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mapfuse_core.data.datasets.common import DatasetError
from mapfuse_core.geometry.se2 import FloatArray

__all__ = ["CarmenRecords", "LaserMessage", "OdomMessage", "guess_beam_geometry", "read_carmen"]


@dataclass(frozen=True)
class LaserMessage:
    """One laser scan (``FLASER`` or ``ROBOTLASER1``) as read."""

    kind: str
    """Message type."""
    line: int
    """Line number (1-based) in the file."""
    ranges: FloatArray
    """(n,) ranges as written (m); no-return codes are not yet replaced."""
    start_angle: float
    """Bearing of the first beam in the laser frame (rad)."""
    angular_resolution: float
    """Angle between consecutive beams (rad)."""
    max_range: float
    """Maximum range written in the message (m), NaN when the message has none."""
    laser_pose: FloatArray
    """(3,) laser pose ``(x, y, θ)`` written in the message."""
    robot_pose: FloatArray
    """(3,) robot (odometry) pose written in the message."""
    timestamp: float
    """``ipc_timestamp`` (s)."""


@dataclass(frozen=True)
class OdomMessage:
    """One ``ODOM`` message."""

    line: int
    """Line number (1-based)."""
    pose: FloatArray
    """(3,) odometry pose ``(x, y, θ)``."""
    tv: float
    """Translational velocity (m/s)."""
    rv: float
    """Rotational velocity (rad/s)."""
    timestamp: float
    """``ipc_timestamp`` (s)."""


@dataclass(frozen=True)
class CarmenRecords:
    """The messages of one CARMEN log that the loader uses."""

    path: Path
    """The file read."""
    lasers: tuple[LaserMessage, ...]
    """Laser scans in file order."""
    odometry: tuple[OdomMessage, ...]
    """``ODOM`` messages in file order."""
    params: dict[str, str] = field(default_factory=dict)
    """``PARAM`` name → value (the last one written wins)."""
    skipped: dict[str, int] = field(default_factory=dict)
    """Message type → count of the lines skipped as of an unread type."""


def guess_beam_geometry(n: int) -> tuple[float, float]:
    """``(start_angle, angular_resolution)`` of an ``FLASER`` scan of ``n`` beams.

    ``FLASER`` carries no beam geometry; CARMEN's own reader guesses it from the beam
    count (``carmen_laser_guess_fov`` / ``carmen_laser_guess_angle_increment``): 180 or
    181 beams are 1° apart, 360 or 361 beams 0.5°, 401 beams 0.25° (a 100° scan);
    any other count spreads ``n`` beams evenly over 180°.  The scan starts at
    ``−90°`` (``−50°`` for 401 beams), the laser's right.
    """
    deg = math.pi / 180.0
    if n in (180, 181):
        return -90.0 * deg, 1.0 * deg
    if n in (360, 361):
        return -90.0 * deg, 0.5 * deg
    if n == 401:
        return -50.0 * deg, 0.25 * deg
    return -90.0 * deg, math.pi / (n - 1)


class _Line:
    """The tokens of one line and what is needed to report a problem in it."""

    def __init__(self, path: Path, lineno: int, tokens: list[str]) -> None:
        self.path, self.lineno, self.tokens = path, lineno, tokens

    def error(self, problem: str) -> DatasetError:
        return DatasetError(f"{self.path}:{self.lineno}: {self.tokens[0]}: {problem}")

    def count(self, want: int) -> None:
        if len(self.tokens) != want:
            raise self.error(f"has {len(self.tokens)} fields, expected {want}")

    def num(self, i: int, what: str) -> float:
        try:
            v = float(self.tokens[i])
        except ValueError:
            raise self.error(f"{what} (field {i}) is not a number: {self.tokens[i]!r}") from None
        if math.isnan(v):
            raise self.error(f"{what} (field {i}) is NaN")
        if math.isinf(v):
            raise self.error(f"{what} (field {i}) is infinite")
        return v

    def integer(self, i: int, what: str) -> int:
        try:
            v = int(self.tokens[i])
        except ValueError:
            raise self.error(f"{what} (field {i}) is not an integer: {self.tokens[i]!r}") from None
        if v < 0:
            raise self.error(f"{what} (field {i}) is negative: {v}")
        return v

    def nums(self, start: int, n: int, what: str) -> FloatArray:
        return np.array([self.num(start + i, what) for i in range(n)])

    def pose(self, start: int, what: str) -> FloatArray:
        return self.nums(start, 3, what)


def _n_beams(ln: _Line, i: int) -> int:
    if len(ln.tokens) <= i:
        raise ln.error(f"has {len(ln.tokens)} fields, too few for the beam count (field {i})")
    n = ln.integer(i, "beam count")
    if n < 2:
        raise ln.error(f"beam count {n} is below 2")
    return n


def _flaser(ln: _Line) -> LaserMessage:
    n = _n_beams(ln, 1)
    if len(ln.tokens) != n + 11:
        raise ln.error(
            f"has {len(ln.tokens)} fields, expected {n + 11} for n = {n} beams "
            "(n beams mismatch or missing fields)"
        )
    start, res = guess_beam_geometry(n)
    return LaserMessage(
        kind="FLASER",
        line=ln.lineno,
        ranges=ln.nums(2, n, "range"),
        start_angle=start,
        angular_resolution=res,
        max_range=math.nan,
        laser_pose=ln.pose(2 + n, "laser pose"),
        robot_pose=ln.pose(5 + n, "odometry pose"),
        timestamp=ln.num(8 + n, "ipc_timestamp"),
    )


def _robotlaser1(ln: _Line) -> LaserMessage:
    n = _n_beams(ln, 8)
    i_rem = 9 + n
    if len(ln.tokens) <= i_rem:
        raise ln.error(
            f"has {len(ln.tokens)} fields, too few for n = {n} beams and the remission count"
        )
    m = ln.integer(i_rem, "remission count")
    want = i_rem + 1 + m + 14
    if len(ln.tokens) != want:
        raise ln.error(
            f"has {len(ln.tokens)} fields, expected {want} for n = {n} beams and "
            f"{m} remissions (n beams mismatch or missing fields)"
        )
    fov = ln.num(3, "field of view")
    res = ln.num(4, "angular resolution")
    max_range = ln.num(5, "maximum range")
    if not 0.0 < fov <= 2.0 * math.pi + 1e-6:
        raise ln.error(f"field of view {fov} is not in (0, 2π]")
    if res <= 0.0:
        raise ln.error(f"angular resolution {res} is not > 0")
    if max_range <= 0.0:
        raise ln.error(f"maximum range {max_range} is not > 0")
    if abs((n - 1) * res - fov) > res + 1e-6:
        raise ln.error(
            f"{n} beams at {math.degrees(res):.4g}° span {math.degrees((n - 1) * res):.4g}°, "
            f"not the field of view {math.degrees(fov):.4g}°"
        )
    p = i_rem + 1 + m
    return LaserMessage(
        kind="ROBOTLASER1",
        line=ln.lineno,
        ranges=ln.nums(9, n, "range"),
        start_angle=ln.num(2, "start angle"),
        angular_resolution=res,
        max_range=max_range,
        laser_pose=ln.pose(p, "laser pose"),
        robot_pose=ln.pose(p + 3, "robot pose"),
        timestamp=ln.num(p + 11, "ipc_timestamp"),
    )


def _odom(ln: _Line) -> OdomMessage:
    ln.count(10)
    return OdomMessage(
        line=ln.lineno,
        pose=ln.pose(1, "pose"),
        tv=ln.num(4, "tv"),
        rv=ln.num(5, "rv"),
        timestamp=ln.num(7, "ipc_timestamp"),
    )


def _open_text(path: Path) -> list[str]:
    if not path.is_file():
        raise DatasetError(f"{path}: no such file")
    raw = path.read_bytes()
    if raw[:2] == b"\x1f\x8b":
        try:
            raw = gzip.decompress(raw)
        except (OSError, EOFError) as exc:
            raise DatasetError(f"{path}: damaged gzip file ({exc})") from exc
    try:
        return raw.decode("ascii").splitlines()
    except UnicodeDecodeError as exc:
        raise DatasetError(f"{path}: not a CARMEN text log ({exc})") from None


def read_carmen(path: str | Path) -> CarmenRecords:
    """The laser, odometry and parameter messages of a CARMEN log (plain or gzipped)."""
    path = Path(path)
    lasers: list[LaserMessage] = []
    odom: list[OdomMessage] = []
    params: dict[str, str] = {}
    skipped: Counter[str] = Counter()
    for lineno, text in enumerate(_open_text(path), start=1):
        tokens = text.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        ln = _Line(path, lineno, tokens)
        kind = tokens[0]
        if kind == "FLASER":
            lasers.append(_flaser(ln))
        elif kind == "ROBOTLASER1":
            lasers.append(_robotlaser1(ln))
        elif kind == "ODOM":
            odom.append(_odom(ln))
        elif kind == "PARAM":
            if len(tokens) < 3:
                raise ln.error(f"has {len(tokens)} fields, expected a name and a value")
            params[tokens[1]] = tokens[2]
        else:
            skipped[kind] += 1
    if not lasers:
        raise DatasetError(f"{path}: no laser message (FLASER or ROBOTLASER1)")
    return CarmenRecords(path, tuple(lasers), tuple(odom), params, dict(sorted(skipped.items())))
