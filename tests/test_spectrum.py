"""``mapfuse spectrum``: lag and seed parsing, the runs and their table, figure and CLI."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from mapfuse.campaign.spec import parse_seeds
from mapfuse.spectrum import (
    SpectrumResult,
    SpectrumRow,
    parse_lags,
    plot_spectrum,
    spectrum,
    spectrum_markdown,
)
from mapfuse_core.measlog import save_log
from tests.synthetic import synthetic_log


def test_parse_lags_sorts_and_accepts_inf() -> None:
    assert parse_lags("30, 0,5,inf,1,5") == (0.0, 1.0, 5.0, 30.0, math.inf)


@pytest.mark.parametrize(
    ("text", "msg"),
    [
        ("0,x", "'x' is not a number"),
        ("-1", "must be >= 0"),
        ("nan", "must be >= 0"),
        (",", "at least one"),
    ],
)
def test_parse_lags_rejects_bad_lags(text: str, msg: str) -> None:
    with pytest.raises(ValueError, match=msg):
        parse_lags(text)


def test_parse_seeds_takes_ranges_and_lists() -> None:
    assert parse_seeds("0-3") == (0, 1, 2, 3)
    assert parse_seeds("4,1,7") == (4, 1, 7)
    assert parse_seeds("2") == (2,)


@pytest.mark.parametrize(
    ("text", "msg"),
    [
        ("3-1", "runs backwards"),
        ("a", "seeds must look like"),
        ("-2", "seeds must look like"),
        ("", "seeds must look like"),
        ("4,1,1,7", "seeds repeat"),
    ],
)
def test_parse_seeds_rejects_bad_seeds(text: str, msg: str) -> None:
    with pytest.raises(ValueError, match=msg):
        parse_seeds(text)


@pytest.fixture(scope="module")
def log_path(tmp_path_factory: pytest.TempPathFactory) -> str:
    path = tmp_path_factory.mktemp("spectrum") / "log.npz"
    save_log(synthetic_log(steps=120, seed=7), path)
    return str(path)


def test_spectrum_runs_ekf_fixedlag_and_batch(log_path: str) -> None:
    """One row per estimator and lag; lag ∞ scores as batch does (same graph, the
    batch optimum to iSAM2's tolerance: 2 % of the RMSE, 5 % of the ANEES)."""
    res = spectrum(log_path, [math.inf, 0.0, 1.0], [0], association="truth")
    assert [(r.estimator, r.lag_s) for r in res.rows] == [
        ("ekf", 0.0),
        ("fixedlag", 0.0),
        ("fixedlag", 1.0),
        ("fixedlag", math.inf),
        ("batch", math.inf),
    ]
    assert [r.role for r in res.rows] == ["filter", "window", "window", "window", "smoother"]
    by = {(r.estimator, r.lag_s): r for r in res.rows}
    inf_row, batch = by[("fixedlag", math.inf)], by[("batch", math.inf)]
    assert inf_row.mean_rmse_m == pytest.approx(batch.mean_rmse_m, rel=0.02)
    assert inf_row.anees == pytest.approx(batch.anees, rel=0.05)
    # A smoother uses more of the log than the filter: lower RMSE than lag 0.
    assert batch.mean_rmse_m < by[("fixedlag", 0.0)].mean_rmse_m
    d = res.as_dict()
    assert d["rows"][-1]["lag_s"] == "inf"
    json.dumps(d)
    table = spectrum_markdown(res)
    assert "| fixedlag | 1 s |" in table
    assert "| batch | ∞ |" in table


def test_spectrum_rejects_unknown_association(log_path: str) -> None:
    with pytest.raises(ValueError, match="association must be 'ekf' or 'truth'"):
        spectrum(log_path, [0.0], [0], association="own")


TINY = str(Path(__file__).resolve().parent / "data" / "tiny_loop.toml")


def _values(res: SpectrumResult) -> list[tuple[object, ...]]:
    """Every result of a spectrum but its timings."""
    return [(r.estimator, r.lag_s, r.rmse_m, r.nees, r.nees_bounds) for r in res.rows]


@pytest.mark.slow
def test_spectrum_on_two_workers_equals_the_serial_one() -> None:
    """Seeds on the campaign engine's LocalCluster give the serial table exactly, in
    the order of the seeds whatever order they finish in."""
    kw = {"association": "truth", "steps": 60}
    lines: list[str] = []
    serial = spectrum(TINY, [0.0, math.inf], [5, 3], serial=True, **kw)  # type: ignore[arg-type]
    two = spectrum(TINY, [0.0, math.inf], [5, 3], workers=2, progress=lines.append, **kw)  # type: ignore[arg-type]
    assert serial.seeds == two.seeds == (5, 3)
    # Workers run single-threaded BLAS; this process may not: equal to rounding.
    for a, b in zip(_values(two), _values(serial), strict=True):
        assert a[:2] == b[:2]
        for x, y in zip(a[2:], b[2:], strict=True):
            assert np.asarray(x) == pytest.approx(np.asarray(y), rel=1e-12, abs=1e-15)
    assert [len(r.rmse_m) for r in two.rows] == [2] * 4
    assert serial.rows[0].rmse_m[0] != serial.rows[0].rmse_m[1]  # two seeds, two logs
    assert sorted(line.split()[1] for line in lines) == ["3", "5"]  # a line per seed
    one = spectrum(TINY, [0.0, math.inf], [3], **kw)  # type: ignore[arg-type]
    assert _values(one) == [
        (e, lag, (r[1],), (n[1],), (b[1],)) for e, lag, r, n, b in _values(serial)
    ]


def test_spectrum_refuses_no_seeds_and_no_lags(log_path: str) -> None:
    with pytest.raises(ValueError, match="at least one seed"):
        spectrum(log_path, [0.0], [])
    with pytest.raises(ValueError, match="at least one lag"):
        spectrum(log_path, [], [0])


@pytest.mark.parametrize(
    ("kw", "msg"),
    [
        ({"workers": 0}, "workers must be >= 1"),
        ({"serial": True, "workers": 2}, "serial excludes"),
        ({"serial": True, "scheduler": "tcp://127.0.0.1:1"}, "serial excludes"),
        ({"workers": 2, "scheduler": "tcp://127.0.0.1:1"}, "workers or scheduler, not both"),
    ],
)
def test_spectrum_refuses_bad_execution_settings(
    log_path: str, kw: dict[str, object], msg: str
) -> None:
    with pytest.raises(ValueError, match=msg):
        spectrum(log_path, [0.0], [0], **kw)  # type: ignore[arg-type]


def test_plot_spectrum_draws_on_the_given_axes() -> None:
    from matplotlib.figure import Figure

    roles = {"ekf": "filter", "fixedlag": "window", "batch": "smoother"}

    def row(est: str, lag: float, rmse: float, nees: float) -> SpectrumRow:
        return SpectrumRow(est, roles[est], lag, (rmse,), (nees,), ((2.0, 4.0),), (1.0,))  # type: ignore[arg-type]

    res = SpectrumResult(
        "toy",
        (0,),
        True,
        "ekf",
        "keep",
        (
            row("ekf", 0.0, 0.3, 3.5),
            row("fixedlag", 0.0, 0.25, 3.2),
            row("fixedlag", 5.0, 0.2, 3.0),
            row("fixedlag", math.inf, 0.1, 2.9),
            row("batch", math.inf, 0.1, 2.9),
        ),
    )
    ax = Figure().subplots()
    plot_spectrum(ax, res, "rmse")
    assert [t.get_text() for t in ax.get_xticklabels()] == ["0 s", "5 s", "∞"]
    assert ax.get_ylabel() == "position RMSE (m)"
    ax2 = Figure().subplots()
    plot_spectrum(ax2, res, "anees")
    assert ax2.get_ylabel() == "ANEES (3 dof)"
    with pytest.raises(ValueError, match="metric must be"):
        plot_spectrum(ax, res, "nees")


def test_cli_spectrum_writes_table_figure_and_json(
    log_path: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from mapfuse.cli import main

    out = tmp_path / "spec"
    code = main(
        ["spectrum", log_path, "--lags", "0,inf", "--association", "truth", "--out", str(out)]
    )
    assert code == 0
    printed = json.loads(capsys.readouterr().out)
    assert [r["estimator"] for r in printed["rows"]] == ["ekf", "fixedlag", "fixedlag", "batch"]
    assert (out / "spectrum.png").stat().st_size > 0
    assert "| ekf | 0 s |" in (out / "report.md").read_text()
    assert json.loads((out / "spectrum.json").read_text()) == printed


def test_cli_spectrum_reports_bad_lags(
    log_path: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from mapfuse.cli import main

    assert main(["spectrum", log_path, "--lags", "0,soon", "--out", str(tmp_path)]) == 2
    assert "'soon' is not a number" in capsys.readouterr().err
    # The one seed parser: a repeated seed is an error too.
    argv = ["spectrum", "loop600", "--lags", "0", "--seeds", "1,1", "--out", str(tmp_path)]
    assert main(argv) == 2
    assert "seeds repeat in '1,1'" in capsys.readouterr().err
