"""Per-dataset defaults of every estimator: one table of :class:`Profile` by dataset name.

A log whose scenario name has a profile runs each estimator with the profile's
overrides of the estimator's defaults (``options_type()``); any other log runs with
the defaults.  A key ending in ``:`` names a family of logs by prefix (``carmen:``, every
CARMEN log, whatever its file).  Why each Victoria Park setting is what it is:
``docs/results/victoria-park.md``; the CARMEN one: ``docs/real-data.md``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from mapfuse.carmen_input import CARMEN_PREFIX
from mapfuse.estimator import Estimator
from mapfuse_core.data.datasets import VICTORIA_PARK_NAME
from mapfuse_core.measlog import MeasurementLog

__all__ = ["PROFILES", "Profile", "default_options", "profile_of"]

#: Field overrides of an estimator's options, made on demand (so that a profile of a
#: graph backend imports gtsam only when that backend runs).
Overrides = Callable[[], Mapping[str, Any]]


@dataclass(frozen=True)
class Profile:
    """How the estimators run on one dataset."""

    dataset: str
    """Scenario name of the dataset's logs (``MeasurementLog.scenario``), or the prefix,
    ending in ``:``, of a family's names."""
    summary: str
    """One line on what the profile changes and why."""
    overrides: Mapping[str, Overrides]
    """Estimator name → overrides of its default options' fields."""


def _victoria_park_ekf() -> Mapping[str, Any]:
    from ekf_reference.loops import LoopClosureParams

    return {
        "local_map_steps": 200,
        "min_obs_to_join": 2,
        "loop_closure": LoopClosureParams(),
        "join_circle_sigma_m": 0.1,
    }


def _carmen_association() -> Mapping[str, Any]:
    from mapfuse_core.data.datasets import carmen_association

    return {"data_association": carmen_association()}


def _carmen_graph() -> Mapping[str, Any]:
    from mapfuse_core.data.datasets import carmen_association
    from mapfuse_graph.options import GraphOptions

    # Cauchy: a wrong re-observation of the EKF's decisions ties a landmark to a wall a
    # door width away; the kernel lowers the smoothers' ANEES on all seven logs
    # (docs/results/carmen.md#robust-kernel-on-the-ekfs-decisions).
    return {"graph": GraphOptions(data_association=carmen_association(), robust="cauchy")}


def _victoria_park_graph() -> Mapping[str, Any]:
    return {"split_circles_where_exact": True}


#: Every dataset with its own defaults, by scenario name.
PROFILES: Mapping[str, Profile] = {
    VICTORIA_PARK_NAME: Profile(
        dataset=VICTORIA_PARK_NAME,
        summary="long local maps, seen-twice features, loop closure at the joins (EKF); "
        "split circle landmarks (graph)",
        overrides={
            "ekf": _victoria_park_ekf,
            "batch": _victoria_park_graph,
            "isam2": _victoria_park_graph,
            "fixedlag": _victoria_park_graph,
        },
    ),
    CARMEN_PREFIX: Profile(
        dataset=CARMEN_PREFIX,
        summary="CCDA needs 12 pairings to accept a floor-plan match (office walls come in "
        "parallel families a door or corridor width apart); collinear line pieces are "
        "one wall only up to a doorway (1 m) apart; the graph backends weigh their "
        "observations with a Cauchy kernel (the EKF's wrong re-observations)",
        overrides={
            "ekf": _carmen_association,
            "batch": _carmen_graph,
            "isam2": _carmen_graph,
            "fixedlag": _carmen_graph,
        },
    ),
}


def profile_of(log: MeasurementLog) -> Profile | None:
    """The profile of ``log``'s dataset (its exact name first, then a family prefix),
    or ``None``."""
    exact = PROFILES.get(log.scenario)
    if exact is not None:
        return exact
    for key, profile in PROFILES.items():
        if key.endswith(":") and log.scenario.startswith(key):
            return profile
    return None


def default_options(estimator: Estimator, log: MeasurementLog) -> Any:
    """``estimator``'s options for ``log``: its defaults with the dataset's overrides."""
    options = estimator.options_type()
    profile = profile_of(log)
    if profile is None or estimator.name not in profile.overrides:
        return options
    return dataclasses.replace(options, **profile.overrides[estimator.name]())
