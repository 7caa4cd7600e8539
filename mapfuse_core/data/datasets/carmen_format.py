"""Reading CARMEN log files (plain or gzipped) into checked records (``docs/real-data.md``).

One message a line, fields separated by white space; blank lines and lines starting
with ``#`` are skipped.  Read messages:

* ``FLASER n r_1 … r_n x y θ odom_x odom_y odom_θ`` + time fields (front laser, the
  old message: ``x y θ`` the laser pose, ``odom_*`` the robot pose; beams after
  CARMEN's convention for the old laser messages, see :func:`guess_beam_geometry`);
  ``RLASER``, the rear laser, has the same fields;
* ``ROBOTLASER1 laser_type start_angle fov angular_resolution max_range accuracy
  remission_mode n r_1 … r_n m e_1 … e_m laser_x laser_y laser_θ robot_x robot_y
  robot_θ tv rv forward_safety side_safety turn_axis`` + time fields (front laser, the
  new message, with its own beam geometry); ``ROBOTLASER2``, the rear laser, has the
  same fields;
* ``ODOM x y θ tv rv accel`` + time fields;
* ``PARAM name value [hostname timestamp]``.

The time fields are ``ipc_timestamp ipc_hostname logger_timestamp``; the logger
timestamp, or the host name and the logger timestamp, may be missing (older loggers and
converters).  A host name is never a number, which keeps a line with a beam too many or
too few from being read with shifted fields.

The front laser's messages are the scans when the log has any; a log with only rear
laser messages is read from those.  The laser messages not used, and every other
message type, are skipped and counted.  A malformed line raises
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

__all__ = [
    "FRONT_LASERS",
    "REAR_LASERS",
    "CarmenRecords",
    "LaserMessage",
    "OdomMessage",
    "guess_beam_geometry",
    "printed_resolution",
    "read_carmen",
]


@dataclass(frozen=True)
class LaserMessage:
    """One laser scan (``FLASER``, ``RLASER``, ``ROBOTLASER1`` or ``ROBOTLASER2``) as read."""

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
    pose_resolution: float
    """Place value of the last printed digit of the coarsest of the six pose numbers
    (``0.0410729`` → 1e-7, ``12.5`` → 0.1; an exact ``0`` counts as exact): how far the
    printed poses may be from the values they stand for."""
    tv: float = math.nan
    """Translational velocity written in the message (m/s), NaN when it has none."""
    rv: float = math.nan
    """Rotational velocity written in the message (rad/s), NaN when it has none."""

    @property
    def rear(self) -> bool:
        """Whether the message is of the rear laser."""
        return self.kind in REAR_LASERS


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
    """Laser scans in file order: the front laser's, or the rear laser's in a log
    without front laser messages."""
    odometry: tuple[OdomMessage, ...]
    """``ODOM`` messages in file order."""
    params: dict[str, str] = field(default_factory=dict)
    """``PARAM`` name → value (the last one written wins)."""
    skipped: dict[str, int] = field(default_factory=dict)
    """Message type → count of the lines skipped: of a type not read, or of the laser
    not used."""


#: Laser messages of the front laser, old and new format.
FRONT_LASERS = ("FLASER", "ROBOTLASER1")
#: Laser messages of the rear laser, old and new format.
REAR_LASERS = ("RLASER", "ROBOTLASER2")


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


def printed_resolution(token: str) -> float:
    """Place value of the last digit of a printed number (``"0.0410729"`` → 1e-7,
    ``"1.01893e+09"`` → 1e4, ``"12"`` → 1); 0 for a plain ``0``, which is exact."""
    mantissa, _, exponent = token.lower().partition("e")
    digits = mantissa.partition(".")[2]
    if not digits and mantissa.lstrip("+-").strip("0") == "":
        return 0.0
    try:
        exp = int(exponent) if exponent else 0
    except ValueError:
        return 0.0
    return 10.0 ** (exp - len(digits))


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


class _Line:
    """The tokens of one line and what is needed to report a problem in it."""

    def __init__(self, path: Path, lineno: int, tokens: list[str]) -> None:
        self.path, self.lineno, self.tokens = path, lineno, tokens

    def error(self, problem: str) -> DatasetError:
        return DatasetError(f"{self.path}:{self.lineno}: {self.tokens[0]}: {problem}")

    def time_fields(self, start: int, what: str) -> None:
        """Check that ``start`` begins the time fields, ``ipc_timestamp [hostname
        [logger_timestamp]]``, and that they end the line."""
        n = len(self.tokens)
        extra = n - start
        if not 1 <= extra <= 3 or (extra >= 2 and _is_number(self.tokens[start + 1])):
            raise self.error(
                f"has {n} fields, expected {start + 1} to {start + 3} for {what} "
                "followed by ipc_timestamp [hostname [logger_timestamp]] "
                "(n beams mismatch or missing fields)"
            )

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

    def resolution(self, start: int, n: int) -> float:
        return max(printed_resolution(t) for t in self.tokens[start : start + n])


def _n_beams(ln: _Line, i: int) -> int:
    if len(ln.tokens) <= i:
        raise ln.error(f"has {len(ln.tokens)} fields, too few for the beam count (field {i})")
    n = ln.integer(i, "beam count")
    if n < 2:
        raise ln.error(f"beam count {n} is below 2")
    return n


def _flaser(ln: _Line) -> LaserMessage:
    """``FLASER`` or ``RLASER``."""
    n = _n_beams(ln, 1)
    ln.time_fields(8 + n, f"n = {n} beams and two poses")
    start, res = guess_beam_geometry(n)
    return LaserMessage(
        kind=ln.tokens[0],
        line=ln.lineno,
        ranges=ln.nums(2, n, "range"),
        start_angle=start,
        angular_resolution=res,
        max_range=math.nan,
        laser_pose=ln.pose(2 + n, "laser pose"),
        robot_pose=ln.pose(5 + n, "odometry pose"),
        timestamp=ln.num(8 + n, "ipc_timestamp"),
        pose_resolution=ln.resolution(2 + n, 6),
    )


def _robotlaser(ln: _Line) -> LaserMessage:
    """``ROBOTLASER1`` or ``ROBOTLASER2``."""
    n = _n_beams(ln, 8)
    i_rem = 9 + n
    if len(ln.tokens) <= i_rem:
        raise ln.error(
            f"has {len(ln.tokens)} fields, too few for n = {n} beams and the remission count"
        )
    m = ln.integer(i_rem, "remission count")
    p = i_rem + 1 + m
    ln.time_fields(p + 11, f"n = {n} beams, {m} remissions, two poses and five robot fields")
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
    return LaserMessage(
        kind=ln.tokens[0],
        line=ln.lineno,
        ranges=ln.nums(9, n, "range"),
        start_angle=ln.num(2, "start angle"),
        angular_resolution=res,
        max_range=max_range,
        laser_pose=ln.pose(p, "laser pose"),
        robot_pose=ln.pose(p + 3, "robot pose"),
        timestamp=ln.num(p + 11, "ipc_timestamp"),
        pose_resolution=ln.resolution(p, 6),
        tv=ln.num(p + 6, "tv"),
        rv=ln.num(p + 7, "rv"),
    )


def _odom(ln: _Line) -> OdomMessage:
    ln.time_fields(7, "a pose and three velocity fields")
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


_LASER_READERS = {
    "FLASER": _flaser,
    "RLASER": _flaser,
    "ROBOTLASER1": _robotlaser,
    "ROBOTLASER2": _robotlaser,
}


def read_carmen(path: str | Path) -> CarmenRecords:
    """The laser, odometry and parameter messages of a CARMEN log (plain or gzipped)."""
    path = Path(path)
    front: list[LaserMessage] = []
    rear: list[LaserMessage] = []
    odom: list[OdomMessage] = []
    params: dict[str, str] = {}
    skipped: Counter[str] = Counter()
    for lineno, text in enumerate(_open_text(path), start=1):
        tokens = text.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        ln = _Line(path, lineno, tokens)
        kind = tokens[0]
        if kind in _LASER_READERS:
            msg = _LASER_READERS[kind](ln)
            (rear if msg.rear else front).append(msg)
        elif kind == "ODOM":
            odom.append(_odom(ln))
        elif kind == "PARAM":
            if len(tokens) < 3:
                raise ln.error(f"has {len(tokens)} fields, expected a name and a value")
            params[tokens[1]] = tokens[2]
        else:
            skipped[kind] += 1
    lasers = front or rear
    if not lasers:
        raise DatasetError(f"{path}: no laser message ({', '.join(FRONT_LASERS + REAR_LASERS)})")
    if front:
        skipped.update(m.kind for m in rear)
    return CarmenRecords(path, tuple(lasers), tuple(odom), params, dict(sorted(skipped.items())))
