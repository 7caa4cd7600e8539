"""The filtering–smoothing spectrum: position RMSE and ANEES against the smoother's lag.

``mapfuse spectrum SCENARIO --lags 0,1,5,30,inf --seeds 0-4`` runs, per seed, the EKF
(the filter: lag 0), the fixed-lag smoother (:mod:`mapfuse_graph.fixedlag`) at each lag,
and batch (the full smoother: lag ∞), the seeds in parallel on the campaign engine's
dask cluster (:func:`spectrum`).  The graph runs consume the EKF's association decisions
of the same seed (or ``--association truth``), so that the lag is the only difference
between the fixed-lag rows.  Each fixed-lag run is scored on its *final* poses (a pose
as it leaves the window), the estimate a user with that latency gets.

ANEES is the mean over seeds of each run's mean NEES (3 degrees of freedom); the two
sided 95 % bounds of a consistent estimator's ANEES are printed beside it, from the
per-run intervals of :func:`~mapfuse_core.evaluation.nees_mean_interval` averaged over
seeds (approximate: it treats the seeds as independent and each run's interval as
that of its mean).
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

#: ``progress(label, k, n)``: run ``label`` has done ``k`` of ``n`` steps.
LabelledProgress = Callable[[str, int, int], None]

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = [
    "SeedRun",
    "SeedSpectrum",
    "SpectrumEstimators",
    "SpectrumJob",
    "SpectrumResult",
    "SpectrumRow",
    "check_roles",
    "parse_lags",
    "plot_spectrum",
    "spectrum",
    "spectrum_figure",
    "spectrum_markdown",
    "spectrum_seed",
]


def parse_lags(text: str) -> tuple[float, ...]:
    """``"0,1,5,30,inf"`` → lags in seconds, ascending, each ``>= 0`` (``inf`` allowed)."""
    lags: list[float] = []
    for part in text.split(","):
        s = part.strip().lower()
        if not s:
            continue
        try:
            v = float(s)
        except ValueError:
            raise ValueError(f"--lags: {part.strip()!r} is not a number (or 'inf')") from None
        if math.isnan(v) or v < 0:
            raise ValueError(f"--lags: a lag must be >= 0 seconds or inf, got {part.strip()!r}")
        lags.append(v)
    if not lags:
        raise ValueError("--lags: give at least one lag, e.g. 0,1,5,30,inf")
    return tuple(sorted(set(lags)))


#: A row's place in the spectrum: the filter (lag 0), the fixed-lag smoother at a lag,
#: the full smoother (lag ∞).
Role = Literal["filter", "window", "smoother"]

_ROLE_ORDER: dict[str, int] = {"filter": 0, "window": 1, "smoother": 2}


@dataclass(frozen=True)
class SpectrumEstimators:
    """Which registered estimator plays each role of the spectrum."""

    filter: str = "ekf"
    """Lag 0: a filter, whose result the others consume (their decisions)."""
    window: str = "fixedlag"
    """A fixed-lag smoother, run at every lag; its options need a ``fixedlag`` field
    with ``lag_s`` and ``landmarks``."""
    smoother: str = "batch"
    """Lag ∞: a smoother over the whole log."""


@dataclass(frozen=True)
class SpectrumRow:
    """One estimator at one lag, over every seed."""

    estimator: str
    """Registered name of the estimator."""
    role: Role
    """Its place in the spectrum (:data:`Role`)."""
    lag_s: float
    """Lag in seconds: 0 for the filter, ``inf`` for the full smoother."""
    rmse_m: tuple[float, ...]
    """Per seed: position RMSE (m) of the evaluated poses."""
    nees: tuple[float, ...]
    """Per seed: mean NEES of the run."""
    nees_bounds: tuple[tuple[float, float], ...]
    """Per seed: two-sided 95 % interval of a consistent run's mean NEES."""
    time_s: tuple[float, ...]
    """Per seed: the estimator's total step time (s)."""

    @property
    def label(self) -> str:
        """``"ekf"``, ``"batch"`` or ``"fixedlag 5 s"`` (a windowed row names its lag)."""
        return self.estimator if self.role != "window" else f"{self.estimator} {_lag(self.lag_s)}"

    @property
    def mean_rmse_m(self) -> float:
        """Mean of :attr:`rmse_m` over seeds."""
        return float(sum(self.rmse_m) / len(self.rmse_m))

    @property
    def anees(self) -> float:
        """Mean of :attr:`nees` over seeds."""
        return float(sum(self.nees) / len(self.nees))

    @property
    def anees_bounds(self) -> tuple[float, float]:
        """Seed average of :attr:`nees_bounds` (approximate two-sided 95 % bounds)."""
        n = len(self.nees_bounds)
        return (
            sum(b[0] for b in self.nees_bounds) / n,
            sum(b[1] for b in self.nees_bounds) / n,
        )

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary (``inf`` lag as the string ``"inf"``)."""
        lo, hi = self.anees_bounds
        return {
            "estimator": self.estimator,
            "lag_s": self.lag_s if math.isfinite(self.lag_s) else "inf",
            "rmse_m": round(self.mean_rmse_m, 5),
            "anees": round(self.anees, 4),
            "anees_bounds_95": [round(lo, 4), round(hi, 4)],
            "per_seed": {
                "rmse_m": [round(v, 5) for v in self.rmse_m],
                "nees": [round(v, 4) for v in self.nees],
                "time_s": [round(v, 3) for v in self.time_s],
            },
        }


@dataclass(frozen=True)
class SpectrumResult:
    """The spectrum of one scenario."""

    scenario: str
    """Scenario (or log) it was run on."""
    seeds: tuple[int, ...]
    """Seeds, in run order."""
    fusion: bool
    """Whether the known map was fused."""
    association: str
    """Association of the graph runs."""
    landmarks: str
    """Fixed-lag landmark policy (:attr:`~mapfuse_graph.fixedlag.FixedLagOptions.landmarks`)."""
    rows: tuple[SpectrumRow, ...]
    """EKF, fixed-lag rows by ascending lag, batch."""
    wall_time_s: float = 0.0
    """Wall time of the whole spectrum."""
    steps: int | None = field(default=None)
    """Steps of each log used (``None``: all)."""

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary."""
        return {
            "scenario": self.scenario,
            "seeds": list(self.seeds),
            "fusion": self.fusion,
            "association": self.association,
            "landmarks": self.landmarks,
            "steps": self.steps,
            "rows": [r.as_dict() for r in self.rows],
            "wall_time_s": round(self.wall_time_s, 2),
        }


def _lag(v: float) -> str:
    return "∞" if math.isinf(v) else f"{v:g} s"


@dataclass(frozen=True)
class SpectrumJob:
    """What one seed of a spectrum runs (plain data: it travels to a worker)."""

    source: str
    """Scenario name, ``.toml`` or log ``.npz``."""
    seed: int | None
    """Simulation seed (``None`` for a saved log)."""
    lags: tuple[float, ...]
    """Fixed-lag lags in seconds, ascending."""
    fusion: bool
    """Whether to fuse the known map."""
    association: str
    """Association of the graph runs."""
    landmarks: str
    """Fixed-lag landmark policy."""
    steps: int | None
    """Steps of the log used (``None``: all)."""
    data_dir: str | None
    """Data directory for a real dataset."""
    estimators: SpectrumEstimators = field(default_factory=lambda: SpectrumEstimators())
    """The estimator of each role."""
    plugins: tuple[str, ...] = ()
    """``module:attribute`` estimators registered for the job (on a worker too)."""


@dataclass(frozen=True)
class SeedRun:
    """One estimator at one lag on one seed."""

    estimator: str
    """Registered name of the estimator."""
    role: Role
    """Its place in the spectrum (:data:`Role`)."""
    lag_s: float
    """Lag in seconds (0 for the filter, ``inf`` for the full smoother)."""
    rmse_m: float
    """Position RMSE of the evaluated poses (m)."""
    nees: float
    """Mean NEES of the run."""
    nees_bounds: tuple[float, float]
    """Two-sided 95 % interval of a consistent run's mean NEES."""
    time_s: float
    """The estimator's total step time (s)."""


@dataclass(frozen=True)
class SeedSpectrum:
    """Every run of one seed (what a worker sends back)."""

    seed: int | None
    """The job's seed."""
    scenario: str
    """The log's scenario name."""
    fusion: bool
    """Whether the known map was fused (``False`` where the log has none)."""
    runs: tuple[SeedRun, ...]
    """EKF, fixed-lag at each lag, batch, in run order."""


def _run_name(job: SpectrumJob) -> str:
    """``"seed 3"``, or the saved log's name."""
    return f"seed {job.seed}" if job.seed is not None else Path(job.source).name


def _prefixed(progress: LabelledProgress | None, prefix: str) -> LabelledProgress | None:
    """``progress`` with ``prefix`` in front of every label."""
    if progress is None or not prefix:
        return progress
    cb = progress

    def call(label: str, k: int, n: int) -> None:
        cb(f"{prefix}{label}", k, n)

    return call


def spectrum_seed(
    job: SpectrumJob,
    progress: Callable[[str], None] | None = None,
    run_progress: LabelledProgress | None = None,
) -> SeedSpectrum:
    """The filter, the fixed-lag smoother at each lag and the full smoother on the log of
    one seed, planned together (:mod:`mapfuse.plan`: the smoothers consume the filter's
    run).  ``progress(line)`` after each run; ``run_progress(label, k, n)`` as the
    simulation and each run advance."""
    from mapfuse.registry import registered_plugins

    with registered_plugins(job.plugins):
        return _spectrum_seed(job, progress, run_progress)


def _spectrum_seed(
    job: SpectrumJob,
    progress: Callable[[str], None] | None,
    run_progress: LabelledProgress | None,
) -> SeedSpectrum:
    from mapfuse.execution import fusion_for
    from mapfuse.metrics import run_metrics
    from mapfuse.plan import RunRequest, execute, plan_runs
    from mapfuse.runner import labelled, load
    from mapfuse_graph.fixedlag import FixedLagOptions

    log = load(
        job.source,
        seed=job.seed,
        steps=job.steps,
        data=job.data_dir,
        progress=labelled(run_progress, "simulate"),
    )
    if log.true_poses is None:
        raise ValueError(f"{job.source}: the spectrum needs true poses (a simulated log)")
    roles = job.estimators
    graph = {"association": job.association}
    # Labelled, so that each is found in the plan whether or not its estimator fuses.
    requests: list[tuple[Role, float, RunRequest]] = [
        ("filter", 0.0, RunRequest(roles.filter, job.fusion, label=roles.filter))
    ]
    for lag in job.lags:
        opts = {**graph, "fixedlag": FixedLagOptions(lag_s=lag, landmarks=job.landmarks)}
        label = f"{roles.window} {_lag(lag)}"
        requests.append(("window", lag, RunRequest(roles.window, job.fusion, opts, label)))
    requests.append(
        ("smoother", math.inf, RunRequest(roles.smoother, job.fusion, graph, roles.smoother))
    )
    plan = plan_runs([r for _, _, r in requests], len(log.known_map) > 0)
    done = execute(plan, log, progress=run_progress)
    made = {d.planned.label: d for d in done}
    runs: list[SeedRun] = []
    for role, lag, req in requests:
        assert req.label is not None
        d = made[req.label]
        assert d.result is not None  # errors raise
        m = run_metrics(d.result, log)
        assert m.position_error is not None  # the log has truth
        assert m.nees is not None
        iv = m.nees.mean_interval
        bounds = (math.nan, math.nan) if iv is None else (iv.acceptance_95[0], iv.acceptance_95[1])
        runs.append(
            SeedRun(
                estimator=req.estimator,
                role=role,
                lag_s=lag,
                rmse_m=m.position_error.rmse,
                nees=m.nees.mean,
                nees_bounds=bounds,
                time_s=float(sum(d.result.step_time_s)),
            )
        )
        if progress is not None:
            progress(
                f"{_run_name(job)} {req.estimator} {_lag(lag)}: rmse "
                f"{m.position_error.rmse:.4f} m, nees {m.nees.mean:.3f}"
            )
    return SeedSpectrum(
        seed=job.seed, scenario=log.scenario, fusion=fusion_for(log, job.fusion), runs=tuple(runs)
    )


def check_roles(roles: SpectrumEstimators) -> None:
    """Each role's estimator exists and takes the options the spectrum sets: the
    window's and the smoother's an ``association``, the window's a ``fixedlag``."""
    import dataclasses

    from mapfuse.registry import resolve

    def fields(name: str) -> set[str]:
        opts = resolve(name).options_type
        if not dataclasses.is_dataclass(opts):
            return set()
        return {f.name for f in dataclasses.fields(opts)}

    resolve(roles.filter)
    for role, name in (("window", roles.window), ("smoother", roles.smoother)):
        if "association" not in fields(name):
            raise ValueError(f"the spectrum's {role} {name!r} takes no association option")
    if "fixedlag" not in fields(roles.window):
        raise ValueError(f"the spectrum's window {roles.window!r} takes no fixedlag option")


def spectrum(
    source: str,
    lags: Sequence[float],
    seeds: Sequence[int],
    *,
    fusion: bool = True,
    association: str = "ekf",
    landmarks: str = "keep",
    steps: int | None = None,
    data_dir: str | None = None,
    progress: Callable[[str], None] | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    serial: bool | None = None,
    estimators: SpectrumEstimators | None = None,
    plugins: Sequence[str] = (),
    run_progress: LabelledProgress | None = None,
    seed_progress: Callable[[int, int], None] | None = None,
) -> SpectrumResult:
    """Run the EKF, the fixed-lag smoother at each of ``lags`` and batch on each seed's
    log of ``source`` (a scenario, ``.toml`` or a log ``.npz``).

    The seeds run on the campaign engine (:func:`mapfuse.campaign.engine.map_on_cluster`):
    a dask ``LocalCluster`` of ``workers`` processes (default: the cores, at most one per
    seed) or the cluster at ``scheduler``.  ``serial=True`` runs them one after the
    other in this process, with a ``progress`` line per run; by default a single seed
    runs so, several seeds on the cluster, with a line per finished seed.  Each seed's
    runs depend on the seed alone, and the table is built in the order of ``seeds``, so
    the result is the same serially and on any number of workers (but the times).

    ``estimators``: the estimator of each role (default :class:`SpectrumEstimators`);
    ``plugins``: ``module:attribute`` estimators registered for every seed, on the
    workers too.  ``run_progress(label, k, n)``: the simulation and every run of a
    serial spectrum as they advance (labels prefixed by the seed when there are
    several); ``seed_progress(k, n)``: ``k`` of the ``n`` seeds done."""
    from mapfuse.registry import registered_plugins
    from mapfuse_graph.fixedlag import FixedLagOptions

    roles = SpectrumEstimators() if estimators is None else estimators
    with registered_plugins(tuple(plugins)):
        check_roles(roles)
    if association not in ("ekf", "truth"):
        raise ValueError(f"association must be 'ekf' or 'truth', got {association!r}")
    if steps is not None and steps < 2:
        raise ValueError(f"steps must be >= 2, got {steps}")
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if serial and (workers is not None or scheduler is not None):
        raise ValueError("serial excludes workers and scheduler")
    if workers is not None and scheduler is not None:
        raise ValueError("workers are local processes: give workers or scheduler, not both")
    lags = sorted(set(float(v) for v in lags))
    if not lags:
        raise ValueError("the spectrum needs at least one lag")
    FixedLagOptions(lag_s=lags[0], landmarks=landmarks)  # validates before any run
    if not seeds:
        raise ValueError("the spectrum needs at least one seed")
    saved = source.endswith(".npz")
    if saved and len(seeds) > 1:
        raise ValueError(f"--seeds: a saved log ({source}) is one run, not {len(seeds)} seeds")
    t_start = time.perf_counter()
    jobs = [
        SpectrumJob(
            source=source,
            seed=None if saved else int(seed),
            lags=tuple(lags),
            fusion=fusion,
            association=association,
            landmarks=landmarks,
            steps=steps,
            data_dir=data_dir,
            estimators=roles,
            plugins=tuple(plugins),
        )
        for seed in seeds
    ]
    job_of = {job.seed: job for job in jobs}
    if serial is None:
        serial = len(jobs) == 1 and workers is None and scheduler is None
    done: dict[int | None, SeedSpectrum] = {}
    several = len(jobs) > 1
    if serial:
        for i, job in enumerate(jobs):
            prefix = f"{_run_name(job)}: " if several else ""
            done[job.seed] = spectrum_seed(job, progress, _prefixed(run_progress, prefix))
            if seed_progress is not None:
                seed_progress(i + 1, len(jobs))
    else:
        from mapfuse.campaign.engine import map_on_cluster

        n = min(workers or os.cpu_count() or 1, len(jobs)) if scheduler is None else None
        for out, _ in map_on_cluster(
            spectrum_seed, jobs, workers=n, scheduler=scheduler, name="mapfuse-spectrum"
        ):
            done[out.seed] = out
            if seed_progress is not None:
                seed_progress(len(done), len(jobs))
            if progress is not None:
                best = min(out.runs, key=lambda r: r.rmse_m)
                progress(
                    f"{_run_name(job_of[out.seed])} done: {len(out.runs)} runs, lowest rmse "
                    f"{best.rmse_m:.4f} m ({best.estimator} {_lag(best.lag_s)})"
                )
    per_seed = [done[job.seed] for job in jobs]
    first = per_seed[0]
    rows = [
        SpectrumRow(
            estimator=run0.estimator,
            role=run0.role,
            lag_s=run0.lag_s,
            rmse_m=tuple(s.runs[i].rmse_m for s in per_seed),
            nees=tuple(s.runs[i].nees for s in per_seed),
            nees_bounds=tuple(s.runs[i].nees_bounds for s in per_seed),
            time_s=tuple(s.runs[i].time_s for s in per_seed),
        )
        for i, run0 in enumerate(first.runs)
    ]
    rows.sort(key=lambda r: (_ROLE_ORDER[r.role], r.lag_s))
    return SpectrumResult(
        scenario=first.scenario,
        seeds=tuple(seeds),
        fusion=first.fusion,
        association=association,
        landmarks=landmarks,
        rows=tuple(rows),
        wall_time_s=time.perf_counter() - t_start,
        steps=steps,
    )


def _x_positions(rows: Sequence[SpectrumRow]) -> tuple[list[float], list[float], list[str]]:
    """x of each row on a symlog axis: lags as given, ∞ one decade past the largest."""
    finite = [r.lag_s for r in rows if math.isfinite(r.lag_s)]
    top = max([1.0, *finite])
    x_inf = 10.0 ** (math.ceil(math.log10(top)) + 1)
    xs = [r.lag_s if math.isfinite(r.lag_s) else x_inf for r in rows]
    ticks = sorted(set(xs))
    labels = [_lag(v) if v != x_inf else "∞" for v in ticks]
    return xs, ticks, labels


def plot_spectrum(ax: Axes, result: SpectrumResult, metric: str = "rmse") -> None:
    """Draw ``metric`` (``"rmse"``: position RMSE, m; ``"anees"``) against lag on ``ax``:
    the fixed-lag curve, the EKF at lag 0 and batch at ∞ as markers, per-seed values
    as faint points; for ANEES the approximate 95 % bounds as a band."""
    if metric not in ("rmse", "anees"):
        raise ValueError(f"metric must be 'rmse' or 'anees', got {metric!r}")
    rows = list(result.rows)
    xs, ticks, labels = _x_positions(rows)

    def value(r: SpectrumRow) -> float:
        return r.mean_rmse_m if metric == "rmse" else r.anees

    def seeds_of(r: SpectrumRow) -> tuple[float, ...]:
        return r.rmse_m if metric == "rmse" else r.nees

    fl = [(x, r) for x, r in zip(xs, rows, strict=True) if r.role == "window"]
    if fl:
        ax.plot(
            [x for x, _ in fl],
            [value(r) for _, r in fl],
            "o-",
            color="tab:red",
            label=fl[0][1].estimator,
        )
    style = {"filter": ("s", "tab:blue"), "smoother": ("D", "tab:orange")}
    for x, r in zip(xs, rows, strict=True):
        ax.plot([x] * len(seeds_of(r)), seeds_of(r), ".", color="0.6", zorder=1)
        if r.role in style:
            m, c = style[r.role]
            ax.plot([x], [value(r)], m, color=c, markersize=8, label=r.estimator, zorder=3)
    if metric == "anees":
        lo = [r.anees_bounds[0] for _, r in fl]
        hi = [r.anees_bounds[1] for _, r in fl]
        if fl and all(math.isfinite(v) for v in lo + hi):
            ax.fill_between(
                [x for x, _ in fl],
                lo,
                hi,
                color="0.85",
                label="95 % bounds",
                zorder=0,
            )
        ax.axhline(3.0, color="0.4", lw=0.8, ls="--")
    ax.set_xscale("symlog", linthresh=1.0)
    # The same span on every panel: a little room left of lag 0 and right of ∞.
    ax.set_xlim(-0.3, ticks[-1] * 1.5)
    ax.set_xticks(ticks)
    ax.set_xticklabels(labels)
    ax.set_xlabel("lag")
    ax.set_ylabel("position RMSE (m)" if metric == "rmse" else "ANEES (3 dof)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)


def spectrum_figure(result: SpectrumResult) -> Figure:
    """RMSE and ANEES against lag, side by side."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4), layout="constrained")
    a, b = fig.subplots(1, 2)
    plot_spectrum(a, result, "rmse")
    plot_spectrum(b, result, "anees")
    seeds = ",".join(map(str, result.seeds))
    fig.suptitle(
        f"{result.scenario}: filtering–smoothing spectrum (seeds {seeds}, "
        f"{'fusion' if result.fusion else 'no fusion'}, association {result.association})"
    )
    return fig


def spectrum_markdown(result: SpectrumResult, figure: str | None = None) -> str:
    """``report.md``: the table of the spectrum."""
    lines = [
        f"# Filtering–smoothing spectrum: {result.scenario}",
        "",
        f"Seeds {', '.join(map(str, result.seeds))}; "
        f"{'fusion' if result.fusion else 'no fusion'}; graph association "
        f"`{result.association}`; fixed-lag landmarks `{result.landmarks}`"
        + (f"; first {result.steps} steps" if result.steps else "")
        + ". Fixed-lag rows are scored on each pose as it leaves the window.",
        "",
        "| estimator | lag | position RMSE (m) | ANEES | 95 % bounds | time (s) |",
        "|---|---|---|---|---|---|",
    ]
    for r in result.rows:
        lo, hi = r.anees_bounds
        t = sum(r.time_s) / len(r.time_s)
        lines.append(
            f"| {r.estimator} | {_lag(r.lag_s)} | {r.mean_rmse_m:.4f} | {r.anees:.3f} | "
            f"{lo:.2f}–{hi:.2f} | {t:.1f} |"
        )
    if figure:
        lines += ["", f"![spectrum]({figure})"]
    return "\n".join(lines) + "\n"
