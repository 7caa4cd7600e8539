"""Monte Carlo campaigns: many seeds (and worlds) through every estimator, on dask.

* :mod:`~mapfuse.campaign.spec` — what a campaign runs (:class:`CampaignSpec`);
* :mod:`~mapfuse.campaign.task` — one run (one seed) on a worker (:func:`run_seed`);
* :mod:`~mapfuse.campaign.store` — the campaign directory: per-run table, arrays, resume;
* :mod:`~mapfuse.campaign.engine` — the dask.distributed engine (:func:`run_campaign`);
* :mod:`~mapfuse.campaign.stats` — ANEES with χ² bounds, RMSE per step, intervals;
* :mod:`~mapfuse.campaign.plots` and :mod:`~mapfuse.campaign.report` — figures and
  ``report.md``.

``docs/campaigns.md`` describes the directory layout and running on a real cluster.
"""

from mapfuse.campaign.engine import CampaignSummary, run_campaign
from mapfuse.campaign.spec import CampaignSpec, parse_seeds
from mapfuse.campaign.store import CampaignStore

__all__ = ["CampaignSpec", "CampaignStore", "CampaignSummary", "parse_seeds", "run_campaign"]
