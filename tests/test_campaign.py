"""Monte Carlo campaigns (mapfuse.campaign): statistics against scipy, the campaign
directory, determinism across worker counts, resume, failures, a real scheduler.

Campaigns run on ``tests/data/tiny_loop.toml`` (a 120 m generated loop) cut to a few
dozen steps, with the toy dead-reckoning estimator where the estimator does not matter.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import binomtest, chi2
from scipy.stats import t as student_t

from mapfuse import registry
from mapfuse.campaign import CampaignSpec, CampaignStore, parse_seeds, run_campaign
from mapfuse.campaign.report import write_report
from mapfuse.campaign.stats import (
    anees_bounds,
    anees_series,
    mean_interval,
    proportion_interval,
    rmse_per_step,
)
from mapfuse.campaign.summary import summarise
from mapfuse.campaign.task import make_log
from mapfuse_core.sim.scenario import load_scenario
from mapfuse_core.sim.simulate import simulate

ROOT = Path(__file__).resolve().parents[1]
TINY = str(ROOT / "tests" / "data" / "tiny_loop.toml")
PLUGINS = ("tests.toy_estimator:DeadReckoning", "tests.campaign_plugins:FailsOnOddSeeds")
# Columns that are wall-clock measurements, not results.
TIMING = ("runtime_s", "wall_s")


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT), "OPENBLAS_NUM_THREADS": "1"}


def _results(out: Path) -> tuple[list[dict], dict[int, dict[str, np.ndarray]]]:
    """Rows sorted by (seed, estimator, fusion) without timing columns, and arrays."""
    store = CampaignStore(out)
    rows = sorted(
        ({k: v for k, v in r.items() if k not in TIMING} for r in store.rows()),
        key=lambda r: (r["seed"], r["estimator"], r["fusion"]),
    )
    return rows, {s: store.arrays(s) for s in {r["seed"] for r in rows}}


def _same_arrays(a: dict[int, dict[str, np.ndarray]], b: dict[int, dict[str, np.ndarray]]) -> bool:
    return a.keys() == b.keys() and all(
        a[s].keys() == b[s].keys()
        and all(np.array_equal(a[s][k], b[s][k], equal_nan=True) for k in a[s])
        for s in a
    )


# --------------------------------------------------------------------------- statistics


@pytest.mark.parametrize("n", [1, 2, 10, 40, 500])
def test_anees_bounds_are_scipy_chi2_quantiles_over_n(n: int) -> None:
    lo, hi = anees_bounds(n)
    assert float(lo) == pytest.approx(chi2.ppf(0.025, 3 * n) / n, rel=1e-12)
    assert float(hi) == pytest.approx(chi2.ppf(0.975, 3 * n) / n, rel=1e-12)


def test_anees_bounds_per_step_use_the_runs_present_there() -> None:
    nees = np.array([[1.0, np.nan, 2.0], [3.0, np.nan, np.nan]])
    s = anees_series(nees)
    np.testing.assert_array_equal(s.runs, [2, 0, 1])
    np.testing.assert_allclose(s.anees[[0, 2]], [2.0, 2.0])
    assert np.isnan(s.anees[1])
    assert s.lower[0] == pytest.approx(chi2.ppf(0.025, 6) / 2)
    assert s.upper[2] == pytest.approx(chi2.ppf(0.975, 3))
    assert not s.inside[1]


def test_consistent_nees_is_inside_its_anees_bounds_on_95_percent_of_steps() -> None:
    # 20 runs × 4000 independent steps of χ²(3) NEES: the fraction inside is binomial
    # with p = 0.95, sd √(0.95·0.05/4000) = 0.0034; 0.015 is over 4 sd.
    rng = np.random.default_rng(7)
    s = anees_series(rng.chisquare(3, size=(20, 4000)))
    assert s.fraction_inside == pytest.approx(0.95, abs=0.015)
    # The mean of 80000 χ²(3) draws: sd √(6/80000) = 0.0087.
    assert s.overall == pytest.approx(3.0, abs=0.04)


def test_rmse_per_step_skips_missing_runs() -> None:
    e = np.array([[3.0, 1.0], [4.0, np.nan]])
    np.testing.assert_allclose(rmse_per_step(e), [np.sqrt(12.5), 1.0])


def test_mean_interval_is_the_student_t_interval() -> None:
    x = np.random.default_rng(3).normal(2.0, 0.5, 12)
    iv = mean_interval(list(x))
    lo, hi = student_t.interval(0.95, 11, loc=x.mean(), scale=x.std(ddof=1) / np.sqrt(12))
    assert (iv.value, iv.low, iv.high, iv.n) == pytest.approx((x.mean(), lo, hi, 12), rel=1e-12)


@pytest.mark.parametrize(("k", "n"), [(0, 10), (3, 10), (10, 10), (37, 40)])
def test_proportion_interval_is_scipy_clopper_pearson(k: int, n: int) -> None:
    iv = proportion_interval(k, n)
    ci = binomtest(k, n).proportion_ci(0.95, method="exact")
    assert (iv.low, iv.high) == pytest.approx((ci.low, ci.high), abs=1e-12)


def test_parse_seeds_reads_ranges_and_lists_and_rejects_the_rest() -> None:
    assert parse_seeds("0-3,7") == (0, 1, 2, 3, 7)
    for bad in ("3-1", "a", "1,1", "-2"):
        with pytest.raises(ValueError, match="seed"):
            parse_seeds(bad)


# --------------------------------------------------------------------------- store


def test_truncated_last_line_of_a_killed_write_is_dropped(tmp_path: Path) -> None:
    spec = CampaignSpec(TINY, (0,), ("toy",), (False,), steps=10, plugins=PLUGINS[:1])
    store = CampaignStore.open(tmp_path, spec)
    store.table_path.write_text('{"seed": 0, "status": "ok"}\n{"seed": 1, "sta')
    assert [r["seed"] for r in store.rows()] == [0]
    assert store.table_path.read_text() == '{"seed": 0, "status": "ok"}\n'


def test_a_directory_of_another_campaign_is_refused(tmp_path: Path) -> None:
    CampaignStore.open(tmp_path, CampaignSpec(TINY, (0,), ("toy",), (False,), steps=10))
    with pytest.raises(ValueError, match="other steps"):
        CampaignStore.open(tmp_path, CampaignSpec(TINY, (0,), ("toy",), (False,), steps=20))


def test_a_short_waypoint_log_is_the_head_of_the_full_one() -> None:
    spec = CampaignSpec(TINY, (2,), ("toy",), (False,), steps=40)
    short = make_log(spec, 2)
    full = simulate(load_scenario(TINY), seed=2, workers=1).log.head(40)
    for name in ("odometry", "true_poses", "feat_params", "feat_step"):
        np.testing.assert_array_equal(getattr(short, name), getattr(full, name))


# --------------------------------------------------------------------------- campaigns


def test_failing_run_is_recorded_and_the_others_go_on(tmp_path: Path) -> None:
    spec = CampaignSpec(
        TINY, (0, 1, 2), ("toy", "fails_on_odd"), (False,), steps=30, plugins=PLUGINS
    )
    summary = run_campaign(spec, tmp_path, serial=True, quiet=True)
    assert summary.failed_rows == 1
    # The plugins were registered for the runs only.
    assert not {"toy", "fails_on_odd"} & set(registry.available())
    rows = {(r["seed"], r["estimator"]): r for r in CampaignStore(tmp_path).rows()}
    assert len(rows) == 6
    bad = rows[(1, "fails_on_odd")]
    assert bad["status"] == "error"
    assert "deliberate failure on seed 1" in bad["error"]
    assert all(r["status"] == "ok" for k, r in rows.items() if k != (1, "fails_on_odd"))
    groups = {g.estimator: g for g in summarise(tmp_path)}
    assert groups["fails_on_odd"].seeds == (0, 2)
    assert groups["fails_on_odd"].failed == (1,)
    report = Path(write_report(tmp_path)["report"]).read_text()
    assert "seed 1: RuntimeError: deliberate failure on seed 1" in report


def test_same_seeds_give_identical_results_serially_and_on_one_and_two_workers(
    tmp_path: Path,
) -> None:
    # The EKF with and without fusion on generated worlds (a new world per run): every
    # per-run value but the timings, and every array, bit for bit.
    spec = CampaignSpec(
        TINY,
        (3, 4, 5),
        ("ekf",),
        (True, False),
        steps=60,
        world={"loop_length_m": 120.0, "walls": 4, "trees": 12, "laser_range_m": 30.0},
    )
    serial = run_campaign(spec, tmp_path / "serial", serial=True, quiet=True)
    one = run_campaign(spec, tmp_path / "one", workers=1, quiet=True)
    two = run_campaign(spec, tmp_path / "two", workers=2, quiet=True)
    assert (serial.workers, one.workers, two.workers) == (1, 1, 2)
    ref_rows, ref_arrays = _results(tmp_path / "serial")
    assert len(ref_rows) == 6
    assert all(r["status"] == "ok" for r in ref_rows), ref_rows
    assert {r["scenario"] for r in ref_rows} == {"world-loop-3", "world-loop-4", "world-loop-5"}
    for d in ("one", "two"):
        rows, arrays = _results(tmp_path / d)
        assert rows == ref_rows
        assert _same_arrays(arrays, ref_arrays)


def test_killed_campaign_resumes_and_skips_finished_runs(tmp_path: Path) -> None:
    out = tmp_path / "mc"
    cmd = [
        sys.executable, "-m", "mapfuse.cli", "montecarlo", TINY, "--seeds", "0-5",
        "--estimators", "hangs", "--plugin", "tests.campaign_plugins:HangsWhenAsked",
        "--fusion", "off", "--steps", "30",
        "--serial", "--quiet", "--no-report", "--out", str(out),
    ]  # fmt: skip
    # Seeds 0-2 finish, seed 3 blocks until the kill: the cut falls at a known run.
    hang = {**_env(), "MAPFUSE_TEST_HANG_FROM_SEED": "3"}
    proc = subprocess.Popen(cmd, env=hang, cwd=ROOT)
    table = out / "runs.jsonl"
    deadline = time.monotonic() + 120
    try:
        while time.monotonic() < deadline:
            if table.exists() and len(table.read_text().splitlines()) >= 3:
                break
            if proc.poll() is not None:
                pytest.fail(f"the campaign ended (exit {proc.returncode}) before the kill")
            time.sleep(0.2)
        else:
            pytest.fail("the campaign wrote no three runs within 120 s")
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    # A write cut short by the kill.
    with table.open("a") as f:
        f.write('{"seed": 5, "estimator": "ha')
    before = {r["seed"] for r in CampaignStore(out).rows()}
    assert before == {0, 1, 2}
    res = subprocess.run(cmd, env=_env(), cwd=ROOT, capture_output=True, text=True, check=True)
    summary = json.loads(res.stdout)
    assert summary["skipped"] == 3
    assert summary["ran"] == 3
    seeds = [r["seed"] for r in CampaignStore(out).rows()]
    assert sorted(seeds) == [0, 1, 2, 3, 4, 5]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.slow
def test_campaign_runs_on_a_separate_scheduler_and_two_workers(tmp_path: Path) -> None:
    dask = str(Path(sys.executable).with_name("dask"))
    if not Path(dask).exists():
        pytest.skip("the dask command is not installed beside this Python")
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    common = ["--no-dashboard"]
    procs = [
        subprocess.Popen(
            [dask, "scheduler", "--host", "127.0.0.1", "--port", str(port), *common],
            env=_env(), cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
    ]  # fmt: skip
    try:
        for _ in range(2):
            procs.append(
                subprocess.Popen(
                    [dask, "worker", address, "--nthreads", "1", "--host", "127.0.0.1", *common],
                    env=_env(), cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                )
            )  # fmt: skip
        from dask.distributed import Client

        with Client(address, timeout=60) as client:
            client.wait_for_workers(2, timeout=120)
        out = tmp_path / "mc"
        cmd = [
            sys.executable, "-m", "mapfuse.cli", "montecarlo", TINY, "--runs", "4",
            "--estimators", "toy", "--plugin", PLUGINS[0], "--fusion", "off",
            "--steps", "30", "--scheduler", address, "--quiet", "--out", str(out),
        ]  # fmt: skip
        res = subprocess.run(cmd, env=_env(), cwd=ROOT, capture_output=True, text=True, timeout=300)
        assert res.returncode == 0, res.stderr
        summary = json.loads(res.stdout)
        assert (summary["ran"], summary["workers"], summary["failed_rows"]) == (4, 2, 0)
        rows, _ = _results(out)
        assert [r["seed"] for r in rows] == [0, 1, 2, 3]
        assert (out / "report.md").exists()
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def test_a_campaign_row_measures_the_anchor_in_the_known_maps_own_frame() -> None:
    """The anchor's truth is ``⊖x^W_Wknown ⊕ x^W_R0``: with the known map in a frame of
    its own the NEES is against that, not against the vehicle's start in ``W``.  A
    campaign row's ``anchor_nees`` is the run's ``metrics.anchor.nees``."""
    from mapfuse.metrics import anchor_block
    from mapfuse_core.estimate import Anchor
    from mapfuse_core.evaluation import anchor_truth
    from mapfuse_core.geometry.se2 import compose, inverse

    true_poses = np.array([[3.0, -2.0, 0.4], [4.0, -2.0, 0.4]])
    frame = np.array([10.0, 5.0, 0.7])  # x^W_Wknown
    truth = compose(inverse(frame), true_poses[0])
    cov = np.diag([0.04, 0.09, 0.01])
    err = np.array([0.2, -0.3, 0.1])
    anchor = Anchor(x_Wknown_Wglobal=truth + err, cov=cov, accepted_at_step=1, pairings=())
    metrics = anchor_block(anchor, true_poses, frame)
    assert metrics is not None
    assert metrics.nees == pytest.approx(float(err @ np.linalg.solve(cov, err)), rel=1e-9)
    # Against the start in W (the known frame ignored) it would be thousands.
    wrong = anchor.x_Wknown_Wglobal - anchor_truth(true_poses)
    assert float(wrong @ np.linalg.solve(cov, wrong)) > 1e3
    assert anchor_block(None, true_poses, frame) is None
    without_truth = anchor_block(anchor, None, frame)
    assert without_truth is not None
    assert without_truth.nees is None


def test_local_workers_keep_glibc_s_own_malloc_thresholds(monkeypatch: pytest.MonkeyPatch) -> None:
    # dask.distributed sets MALLOC_TRIM_THRESHOLD_ in the workers it spawns, which fixes
    # glibc's mmap threshold too and doubles an EKF run's CPU in page faults
    # (docs/results/performance.md); the local cluster leaves both to glibc.
    from mapfuse.campaign.engine import map_on_cluster

    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    got = [value for value, _ in map_on_cluster(os.getenv, ["MALLOC_TRIM_THRESHOLD_"], workers=1)]
    assert got == [None]
    assert "MALLOC_TRIM_THRESHOLD_" not in os.environ
