"""A Monte Carlo campaign from Python: :func:`montecarlo` (``mf.montecarlo``).

The library side of ``mapfuse montecarlo``: the same spec, engine, directory and
report, with a result to explore in a notebook (:class:`MonteCarlo`).
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mapfuse.campaign.engine import CampaignSummary, run_campaign
from mapfuse.campaign.spec import CampaignSpec, parse_seeds
from mapfuse.campaign.summary import GroupSummary, summarise

__all__ = ["MonteCarlo", "montecarlo"]


@dataclass(frozen=True, eq=False)
class MonteCarlo:
    """A finished campaign: where it is, what this call ran, and its summaries."""

    out: Path
    """The campaign directory (``runs.jsonl``, ``arrays/``, ``report.md``)."""
    summary: CampaignSummary
    """What this call ran, skipped and how long it took."""
    groups: tuple[GroupSummary, ...]
    """One summary per estimator and fusion setting: ANEES per step with its bounds,
    RMSE per step, intervals over the runs (:mod:`mapfuse.campaign.summary`)."""

    def group(self, estimator: str, fusion: bool) -> GroupSummary:
        """The summary of ``estimator`` with or without fusion."""
        for g in self.groups:
            if g.estimator == estimator and g.fusion is bool(fusion):
                return g
        have = ", ".join(f"{g.estimator}/{g.fusion}" for g in self.groups)
        raise KeyError(f"no {estimator} group with fusion={fusion} (have {have})")


def montecarlo(
    scenario: str = "loop600",
    seeds: Iterable[int] | str = range(20),
    estimators: Sequence[str] = ("ekf",),
    *,
    fusions: Sequence[bool] = (True, False),
    world: Mapping[str, Any] | None = None,
    steps: int | None = None,
    out: str | Path | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    serial: bool = False,
    plugins: Sequence[str] = (),
    report: bool = True,
    quiet: bool = True,
) -> MonteCarlo:
    """Run ``estimators`` × ``fusions`` on the log of each of ``seeds`` of ``scenario``.

    ``seeds``: integers or the command line's text (``"0-39"``, ``"0,3,7"``).
    ``world``: generator arguments (:func:`mapfuse_core.sim.worldgen.generate_scenario`
    keywords but ``seed``) to draw a new world for every run.  ``out``: the campaign
    directory (default: a new temporary one); rerunning into it resumes.  The runs go
    to a local dask cluster of ``workers`` processes (default: the cores), to the
    cluster at ``scheduler``, or one after the other in this process (``serial``); the
    same seeds give the same rows whatever the choice.  ``plugins``: ``module:attribute``
    estimators each worker registers.  ``report`` writes ``report.md`` and its figures.
    """
    seed_list = parse_seeds(seeds) if isinstance(seeds, str) else tuple(int(s) for s in seeds)
    spec = CampaignSpec(
        scenario=scenario,
        seeds=seed_list,
        estimators=tuple(estimators),
        fusions=tuple(fusions),
        steps=steps,
        world=None if world is None else dict(world),
        plugins=tuple(plugins),
    )
    folder = Path(tempfile.mkdtemp(prefix="mapfuse-montecarlo-")) if out is None else Path(out)
    summary = run_campaign(
        spec, folder, workers=workers, scheduler=scheduler, serial=serial, quiet=quiet
    )
    if report:
        from mapfuse.campaign.report import write_report

        write_report(folder)
    return MonteCarlo(out=summary.out, summary=summary, groups=tuple(summarise(str(folder))))
