"""Estimators for the campaign tests, registered on the workers by ``--plugin``."""

from __future__ import annotations

import dataclasses
import os
import time
from typing import Any

from mapfuse_core.estimate import EstimatorResult
from mapfuse_core.measlog import MeasurementLog
from tests.toy_estimator import DeadReckoning, DeadReckoningOptions


class _ToyVariant(DeadReckoning):
    """The toy dead-reckoning estimator under its own name, with :meth:`before` called on
    every log before the run."""

    options_type = DeadReckoningOptions

    def before(self, log: MeasurementLog) -> None:
        """What the variant does to a run (fail it, hold it up)."""

    def run(
        self,
        log: MeasurementLog,
        options: DeadReckoningOptions,
        *,
        fusion: bool,
        upstream: EstimatorResult | None = None,
        progress: Any = None,
    ) -> EstimatorResult:
        self.before(log)
        res = super().run(log, options, fusion=fusion, progress=progress)
        return dataclasses.replace(res, estimator=self.name)


class FailsOnOddSeeds(_ToyVariant):
    """The toy dead-reckoning estimator, raising on logs of odd seeds."""

    name = "fails_on_odd"

    def before(self, log: MeasurementLog) -> None:
        if log.seed % 2:
            raise RuntimeError(f"deliberate failure on seed {log.seed}")


class HangsWhenAsked(_ToyVariant):
    """The toy dead-reckoning estimator, blocking for ten minutes on logs of seeds from
    ``MAPFUSE_TEST_HANG_FROM_SEED`` on when that variable is set: a campaign that stops
    at a known run, for the kill-and-resume test, whatever the machine's speed."""

    name = "hangs"

    def before(self, log: MeasurementLog) -> None:
        start = os.environ.get("MAPFUSE_TEST_HANG_FROM_SEED")
        if start is not None and log.seed >= int(start):
            time.sleep(600.0)


class DividesByZero(_ToyVariant):
    """The toy dead-reckoning estimator with a bug: it divides by zero on every log (the
    command line's internal-error test)."""

    name = "divides_by_zero"

    def before(self, log: MeasurementLog) -> None:
        raise ZeroDivisionError("deliberate division by zero")
