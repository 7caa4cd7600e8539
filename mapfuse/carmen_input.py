"""CARMEN logs as run inputs: ``carmen:PATH.log[.gz]`` and its known map (``docs/carmen.md``).

The same steps for every CARMEN log, with no per-file setting: the log is read with
:func:`~mapfuse_core.data.datasets.load_carmen`'s defaults (the ``indoor_sick``
extraction profile, odometry kind detected from the file).  A log with a reference
trajectory (a corrected log) gets its floor plan built from its own scans at the
reference poses (:func:`~mapfuse_core.data.datasets.build_floor_plan`): the
reference's own plan, the stand-in for a building plan, which CCDA must place without
being given the start pose.  Its observations are labelled with the plan's walls in
either case, so that pairings and ``--association truth`` are judged against it.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from mapfuse_core.measlog import MeasurementLog

if TYPE_CHECKING:
    from mapfuse_core.changes import ChangeParams

__all__ = [
    "CARMEN_PREFIX",
    "KNOWN_MAPS",
    "carmen_change_params",
    "carmen_path",
    "is_carmen",
    "load_carmen_input",
]

#: Prefix of a CARMEN log input: ``carmen:PATH``.
CARMEN_PREFIX = "carmen:"

#: ``--known-map`` choices: the floor plan built from the reference, or none.
KNOWN_MAPS = ("floorplan", "none")


def is_carmen(source: str) -> bool:
    """Whether ``source`` names a CARMEN log (``carmen:PATH``)."""
    return source.startswith(CARMEN_PREFIX)


def carmen_path(source: str) -> Path:
    """The file of a ``carmen:PATH`` input; an error when none is named or it is absent."""
    raw = source[len(CARMEN_PREFIX) :]
    if not raw:
        raise ValueError(f"{source!r}: give the log file after 'carmen:' (carmen:PATH.log[.gz])")
    path = Path(raw)
    if not path.exists():
        raise ValueError(f"CARMEN log {path} does not exist")
    if not path.is_file():
        raise ValueError(f"CARMEN log {path} is not a file")
    return path


def load_carmen_input(
    source: str, *, seed: int | None = None, known_map: str | None = None
) -> MeasurementLog:
    """The measurement log of ``carmen:PATH``.

    ``seed``: seed of the odometry simulated from the reference (corrected logs;
    default 0).  ``known_map``: ``"floorplan"`` (the plan built from the log's
    reference trajectory; an error for a log without one), ``"none"``, or ``None``
    (the floor plan when the log has a reference trajectory, else none).
    """
    from mapfuse_core.data.datasets import (
        CarmenOptions,
        build_floor_plan,
        label_with_plan,
        load_carmen,
    )

    if known_map is not None and known_map not in KNOWN_MAPS:
        raise ValueError(f"--known-map must be one of {', '.join(KNOWN_MAPS)}, got {known_map!r}")
    path = carmen_path(source)
    log = load_carmen(path, options=CarmenOptions(seed=0 if seed is None else seed))
    if log.true_poses is None:
        if known_map == "floorplan":
            raise ValueError(
                f"CARMEN log {path} has no reference trajectory (raw odometry): no floor "
                "plan can be built from it; use --known-map none"
            )
        return replace(log, metadata={**log.metadata, "known_map": "none"})
    plan = build_floor_plan(log)
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
