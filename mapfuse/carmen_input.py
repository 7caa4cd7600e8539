"""CARMEN logs as run inputs: ``carmen:PATH.log[.gz]`` and its known map (``docs/real-data.md``).

The same steps for every CARMEN log, with no per-file setting: the log is read with
:func:`~mapfuse_core.data.datasets.load_carmen`'s defaults (the ``indoor_sick``
extraction profile, odometry kind decided from the log's evidence unless the source
states it).  A log with a reference trajectory (a corrected log) gets its floor plan
built from its own scans at the reference poses
(:func:`~mapfuse_core.data.datasets.build_floor_plan`): the reference's own plan, the
stand-in for a building plan, which CCDA must place without being given the start
pose.  Its observations are labelled with the plan's walls in either case, so that
pairings and ``--association truth`` are judged against it.

Source syntax: ``carmen:PATH`` or, with options, ``carmen,KEY=VALUE[,KEY=VALUE]:PATH``.
Options sit between ``carmen`` and the first ``:``, so that any path (with commas,
colons, question marks) is read as it is written.  The one option is ``odometry=raw`` or
``odometry=corrected`` (the command line's ``--odometry``).
"""

from __future__ import annotations

import copy
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from mapfuse_core.measlog import MeasurementLog

if TYPE_CHECKING:
    from mapfuse_core.changes import ChangeParams
    from mapfuse_core.data.datasets import FloorPlan
    from mapfuse_core.data.datasets.carmen_kind import UndecidedOdometryError

__all__ = [
    "CARMEN_PREFIX",
    "KNOWN_MAPS",
    "ODOMETRY_KINDS",
    "CarmenOptionError",
    "CarmenSource",
    "carmen_change_params",
    "carmen_log_kind",
    "carmen_path",
    "is_carmen",
    "load_carmen_input",
    "parse_carmen_source",
    "with_odometry",
]

#: Prefix of a CARMEN log input: ``carmen:PATH``.
CARMEN_PREFIX = "carmen:"

#: ``--known-map`` choices: the floor plan built from the reference, or none.
KNOWN_MAPS = ("floorplan", "none")

#: ``--odometry`` choices (and of the source's ``odometry=`` option).
ODOMETRY_KINDS = ("raw", "corrected")

_SYNTAX = "carmen:PATH or carmen,odometry=raw|corrected:PATH"


@dataclass(frozen=True)
class CarmenSource:
    """A parsed ``carmen:`` input."""

    path: Path
    """The log file (it exists)."""
    odometry: Literal["auto", "raw", "corrected"] = "auto"
    """The log's kind as stated in the source, or ``"auto"``: decided from its evidence."""

    def text(self) -> str:
        """The source string that gives this input."""
        opts = "" if self.odometry == "auto" else f",odometry={self.odometry}"
        return f"carmen{opts}:{self.path}"


def is_carmen(source: str) -> bool:
    """Whether ``source`` names a CARMEN log (``carmen:PATH`` or ``carmen,…:PATH``)."""
    return source.startswith((CARMEN_PREFIX, "carmen,"))


def _options(source: str, head: str) -> dict[str, str]:
    out: dict[str, str] = {}
    for item in head.split(",")[1:]:
        key, eq, value = (t.strip() for t in item.partition("="))
        if not (key and eq and value):
            raise ValueError(
                f"{source!r}: expected key=value options between 'carmen' and ':', "
                f"got {item!r} ({_SYNTAX})"
            )
        if key != "odometry":
            raise ValueError(f"{source!r}: unknown option {key!r} (known: odometry)")
        if key in out:
            raise ValueError(f"{source!r}: option {key!r} given twice")
        if value not in ODOMETRY_KINDS:
            raise ValueError(
                f"{source!r}: odometry must be {' or '.join(ODOMETRY_KINDS)}, got {value!r}"
            )
        out[key] = value
    return out


def parse_carmen_source(source: str) -> CarmenSource:
    """The file and options of a ``carmen:`` input; an error naming the problem when the
    syntax is wrong, an option is unknown or bad, or the file is missing."""
    head, colon, raw = source.partition(":")
    if not is_carmen(source) or not colon:
        raise ValueError(f"{source!r} is not a CARMEN input ({_SYNTAX})")
    opts = _options(source, head)
    if not raw:
        raise ValueError(f"{source!r}: give the log file after 'carmen:' (carmen:PATH.log[.gz])")
    path = Path(raw)
    if not path.exists():
        raise ValueError(f"CARMEN log {path} does not exist")
    if not path.is_file():
        raise ValueError(f"CARMEN log {path} is not a file")
    stated = opts.get("odometry")
    return CarmenSource(
        path, "auto" if stated is None else "raw" if stated == "raw" else "corrected"
    )


def carmen_path(source: str) -> Path:
    """The file of a ``carmen:`` input (:func:`parse_carmen_source`'s checks)."""
    return parse_carmen_source(source).path


def with_odometry(source: str, odometry: str | None) -> str:
    """``source`` with the ``--odometry`` choice in it (``None``: unchanged); an error
    when ``source`` is not a CARMEN log or states the other kind."""
    if odometry is None:
        return source
    if not is_carmen(source):
        raise ValueError(f"--odometry applies to CARMEN logs (carmen:PATH) only, not {source!r}")
    if odometry not in ODOMETRY_KINDS:
        raise ValueError(f"--odometry must be {' or '.join(ODOMETRY_KINDS)}, got {odometry!r}")
    src = parse_carmen_source(source)
    if src.odometry not in ("auto", odometry):
        raise ValueError(f"--odometry {odometry} contradicts odometry={src.odometry} in {source!r}")
    return replace(src, odometry="raw" if odometry == "raw" else "corrected").text()


class CarmenOptionError(ValueError):
    """A CARMEN log that needs an option stated (its odometry kind) or refuses one
    given (a floor plan of a log without a reference trajectory)."""


def _undecided(exc: UndecidedOdometryError) -> CarmenOptionError:
    return CarmenOptionError(
        f"CARMEN log {exc.question()}; state it with --odometry raw|corrected "
        "(in a campaign: carmen,odometry=raw|corrected:PATH)"
    )


def carmen_log_kind(source: str) -> str:
    """``"raw"`` or ``"corrected"``: the kind ``source`` is loaded as (stated, or
    decided from the log's evidence); an error naming ``--odometry`` when undecided."""
    from mapfuse_core.data.datasets import read_carmen
    from mapfuse_core.data.datasets.carmen import detect_odometry_kind
    from mapfuse_core.data.datasets.carmen_kind import UndecidedOdometryError

    src = parse_carmen_source(source)
    if src.odometry != "auto":
        return src.odometry
    try:
        return detect_odometry_kind(read_carmen(src.path))
    except UndecidedOdometryError as exc:
        raise _undecided(exc) from None


_KEPT_READS = 2
"""CARMEN logs whose reading one process keeps (:func:`_read`): a campaign's worker
runs seed after seed of one log."""

_reads: OrderedDict[tuple[object, ...], tuple[MeasurementLog, FloorPlan | None]] = OrderedDict()
_reads_lock = threading.Lock()


def _read(
    path: Path,
    odometry: Literal["auto", "raw", "corrected"],
    progress: Callable[[int, int], None] | None,
) -> tuple[MeasurementLog, FloorPlan | None]:
    """The log at ``path`` read with seed 0 (odometry kind ``odometry``) and its floor
    plan (``None`` without a reference trajectory), a deep copy of the kept one when this
    process read the same file before (same path, device, inode, size, modification and
    status-change times).

    Reading and extracting are most of a CARMEN run's set-up
    (``docs/results/performance.md``); the seed changes only the simulated odometry,
    which :func:`~mapfuse_core.data.datasets.redraw_odometry` draws again bit for bit.
    The copy keeps a caller's changes to its arrays out of the next run.
    ``progress(n, n)`` once on a kept read.
    """
    from mapfuse_core.data.datasets import CarmenOptions, build_floor_plan, load_carmen

    st = path.stat()
    key = (
        str(path.resolve()),
        st.st_dev,
        st.st_ino,
        st.st_size,
        st.st_mtime_ns,
        st.st_ctime_ns,
        odometry,
    )
    with _reads_lock:
        kept = _reads.get(key)
        if kept is not None:
            _reads.move_to_end(key)
    if kept is not None:
        if progress is not None:
            progress(kept[0].n_steps, kept[0].n_steps)
        return copy.deepcopy(kept)
    log = load_carmen(path, options=CarmenOptions(seed=0, odometry=odometry), progress=progress)
    read = (log, None if log.true_poses is None else build_floor_plan(log))
    with _reads_lock:
        _reads[key] = copy.deepcopy(read)
        while len(_reads) > _KEPT_READS:
            _reads.popitem(last=False)
    return read


def load_carmen_input(
    source: str,
    *,
    seed: int | None = None,
    known_map: str | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> MeasurementLog:
    """The measurement log of a ``carmen:`` input (:func:`parse_carmen_source`).

    ``seed``: seed of the odometry simulated from the reference (corrected logs;
    default 0).  ``known_map``: ``"floorplan"`` (the plan built from the log's
    reference trajectory; an error for a log without one), ``"none"``, or ``None``
    (the floor plan when the log has a reference trajectory, else none).  A log whose
    kind its evidence does not decide, and the source does not state, is an error
    naming ``--odometry``.  ``progress(k, n)``: after each scan's extraction, or once
    with ``k = n`` when this process has read the file before: a process reads and
    extracts a file once for every seed (:func:`_read`).
    """
    from mapfuse_core.data.datasets import CarmenOptions, label_with_plan, redraw_odometry
    from mapfuse_core.data.datasets.carmen_kind import UndecidedOdometryError

    if known_map is not None and known_map not in KNOWN_MAPS:
        raise ValueError(f"--known-map must be one of {', '.join(KNOWN_MAPS)}, got {known_map!r}")
    src = parse_carmen_source(source)
    path = src.path
    CarmenOptions(seed=0 if seed is None else seed, odometry=src.odometry)  # checks both
    try:
        log, plan = _read(Path(path), src.odometry, progress)
    except UndecidedOdometryError as exc:
        raise _undecided(exc) from None
    if plan is None:
        if known_map == "floorplan":
            raise CarmenOptionError(
                f"CARMEN log {path} has no reference trajectory (raw odometry, "
                f"{log.metadata['log_kind']}): no floor plan can be built from it; use "
                "--known-map none, or --odometry corrected if its poses are corrected ones"
            )
        return replace(log, metadata={**log.metadata, "known_map": "none"})
    log = redraw_odometry(log, 0 if seed is None else seed)
    fused = known_map != "none"
    out = label_with_plan(log, plan, as_known_map=fused)
    walls = len(plan.walls)
    described = {
        "known_map": f"floor plan from the reference trajectory ({walls} walls)"
        if fused
        else "none",
        "reference_labels": f"walls of the floor plan from the reference trajectory ({walls})",
    }
    return replace(out, metadata={**out.metadata, **described})


def carmen_change_params(log: MeasurementLog, params: ChangeParams) -> ChangeParams:
    """``params`` with the view predicted by a CARMEN log's own scanner and the indoor
    extractor (``load_carmen``'s defaults), when the log keeps its raw scans; otherwise
    ``params`` unchanged (the beam-count view rule)."""
    from mapfuse_core.data.datasets import CarmenOptions
    from mapfuse_core.data.datasets.carmen import carmen_view_laser

    b = log.scan_bearings
    if b is None or b.shape[0] < 2:
        return params
    return params.with_sensor(carmen_view_laser(b), CarmenOptions().extraction)
