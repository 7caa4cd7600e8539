"""Run a campaign: :func:`run_campaign` on dask.distributed, or serially in this process.

By default a ``LocalCluster`` of ``workers`` processes (default: the cores) with one
thread each and single-threaded BLAS: a run is pure Python and small dense algebra,
so processes, not threads, use the cores.  ``scheduler`` connects to an existing
cluster instead (``dask scheduler`` / ``dask worker``, ``docs/campaigns.md``).
``serial=True`` runs every seed in this process, without dask (the reference the
engine's overhead is measured against).  Results are stored as each run completes,
in completion order; finished runs are skipped.
"""

from __future__ import annotations

import functools
import os
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from mapfuse.campaign.spec import CampaignSpec
from mapfuse.campaign.store import CampaignStore
from mapfuse.campaign.task import RunOutcome, run_seed

__all__ = ["BLAS_ENV", "LOCAL_CLUSTER_CONFIG", "CampaignSummary", "map_on_cluster", "run_campaign"]

T = TypeVar("T")
R = TypeVar("R")

#: Environment of every local worker: one BLAS thread each.
BLAS_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}

#: dask settings of a local cluster: glibc's own trim and mmap thresholds in the
#: workers.  dask.distributed sets ``MALLOC_TRIM_THRESHOLD_`` (64 KiB) in every worker
#: it spawns, which also fixes glibc's mmap threshold: each array over 128 KiB (a
#: covariance of 128 landmark dofs) is then mapped and unmapped anew, and a CARMEN EKF
#: run takes twice its CPU in page faults (``docs/results/performance.md``).  A
#: variable of the user's own environment still reaches the workers.
LOCAL_CLUSTER_CONFIG = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}


@dataclass(frozen=True)
class CampaignSummary:
    """What one :func:`run_campaign` call did."""

    out: Path
    """The campaign directory."""
    ran: tuple[int, ...]
    """Seeds run by this call, in completion order."""
    skipped: tuple[int, ...]
    """Seeds already finished in the directory."""
    failed_rows: int
    """Rows of this call's runs recorded with an error."""
    wall_time_s: float
    """Wall time of the call (s), cluster start-up included."""
    workers: int
    """Workers that ran the seeds (1 when serial)."""


def _progress(total: int, initial: int, quiet: bool) -> Any:
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=initial, unit="run", disable=quiet, desc="montecarlo")


def _serial(spec: CampaignSpec, todo: list[int]) -> Iterator[RunOutcome]:
    for seed in todo:
        yield run_seed(spec, seed)


def map_on_cluster(
    fn: Callable[[T], R],
    items: Sequence[T],
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    name: str = "mapfuse-run",
) -> Iterator[tuple[R, int]]:
    """``fn(item)`` for every item on dask.distributed, yielded as ``(result, workers)``
    in completion order: a ``LocalCluster`` of ``workers`` single-threaded processes
    (default: the cores; one BLAS thread each) or the cluster at ``scheduler``.  ``fn``
    and the items must pickle (a module-level function and plain data).  Whoever
    aggregates the results orders them itself: completion order depends on the
    workers, the results do not."""
    import dask
    from dask.distributed import Client, LocalCluster, as_completed

    cluster = None
    if scheduler is None:
        n = workers if workers is not None else (os.cpu_count() or 1)
        with dask.config.set(LOCAL_CLUSTER_CONFIG):
            cluster = LocalCluster(
                n_workers=n,
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
                env=BLAS_ENV,
            )
        client = Client(cluster)
    else:
        client = Client(scheduler)
    try:
        n_workers = len(client.scheduler_info(n_workers=-1)["workers"])
        tag = uuid.uuid4().hex[:8]
        futures = [
            client.submit(fn, item, key=f"{name}-{i}-{tag}", pure=False)
            for i, item in enumerate(items)
        ]
        for fut in as_completed(futures):
            result = fut.result()
            fut.release()
            yield result, n_workers
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _distributed(
    spec: CampaignSpec, todo: list[int], workers: int | None, scheduler: str | None
) -> Iterator[tuple[RunOutcome, int]]:
    return map_on_cluster(
        functools.partial(run_seed, spec), todo, workers=workers, scheduler=scheduler
    )


def run_campaign(
    spec: CampaignSpec,
    out: str | Path,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    serial: bool = False,
    quiet: bool = False,
    retry_failed: bool = False,
) -> CampaignSummary:
    """Run the seeds of ``spec`` not yet finished in ``out`` and store each as it ends.

    ``workers``: local worker processes (default: the cores); ``scheduler``: the address
    of an existing dask scheduler (``tcp://host:8786``) instead; ``serial``: no dask.
    ``retry_failed``: run again the seeds with a row recorded as an error.
    """
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if serial and scheduler is not None:
        raise ValueError("serial and scheduler exclude each other")
    t0 = time.perf_counter()
    for k, v in BLAS_ENV.items():
        os.environ.setdefault(k, v)
    store = CampaignStore.open(out, spec)
    per_run = len(spec.estimators) * len(spec.fusions)
    rows = store.rows()
    seeds_with_rows = {r["seed"] for r in rows}
    finished = store.finished(per_run)
    if retry_failed:
        finished -= {r["seed"] for r in rows if r["status"] != "ok"}
    stale = (seeds_with_rows - finished) & set(spec.seeds)
    if stale:
        store.drop(stale)
    todo = [s for s in spec.seeds if s not in finished]
    skipped = tuple(s for s in spec.seeds if s in finished)
    ran: list[int] = []
    failed = 0
    n_workers = 1
    bar = _progress(len(spec.seeds), len(skipped), quiet)
    try:
        if todo:
            stream: Iterator[tuple[RunOutcome, int]] = (
                ((o, 1) for o in _serial(spec, todo))
                if serial
                else _distributed(spec, todo, workers, scheduler)
            )
            for outcome, used in stream:
                n_workers = used
                store.write(outcome)
                ran.append(outcome.seed)
                bad = sum(r["status"] != "ok" for r in outcome.rows)
                failed += bad
                bar.update(1)
                if bad:
                    bar.set_postfix(failed_rows=failed)
    finally:
        bar.close()
    return CampaignSummary(
        out=store.root,
        ran=tuple(ran),
        skipped=skipped,
        failed_rows=failed,
        wall_time_s=time.perf_counter() - t0,
        workers=n_workers,
    )
