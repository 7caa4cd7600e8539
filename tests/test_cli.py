"""The ``mapfuse`` command line: options checked before any work, help and defaults,
JSON alone on stdout, output folders, Ctrl-C, progress bars."""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import mapfuse.runner
import mapfuse_core.sim.simulate
from mapfuse.cli import EXIT_INTERRUPTED, _parser, main
from mapfuse_core.measlog import save_log
from tests.synthetic import synthetic_log

ROOT = Path(__file__).resolve().parents[1]

#: The error of a graph-only option given for the EKF alone.
GRAPH_ONLY = "no option of ekf takes it (the graph backends do)"


@pytest.fixture(scope="module")
def log_npz(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return save_log(synthetic_log(60, 0), tmp_path_factory.mktemp("log") / "log.npz")


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any attempt to load or simulate a log fails the test: errors must come first."""

    def fail(*args: object, **kwargs: object) -> None:
        raise AssertionError("work started before the options were checked")

    monkeypatch.setattr(mapfuse.runner, "load", fail)
    monkeypatch.setattr(mapfuse.runner, "simulate", fail)
    monkeypatch.setattr(mapfuse_core.sim.simulate, "simulate", fail)
    monkeypatch.delenv("MAPFUSE_DATA", raising=False)


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    return env


def _mapfuse(*args: str, **kw: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "mapfuse.cli", *args],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=600,
        check=False,
        **kw,  # type: ignore[arg-type]
    )


def _subparsers(p: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    out = [p]
    for a in p._actions:
        if isinstance(a, argparse._SubParsersAction):
            for sp in a.choices.values():
                out += _subparsers(sp)
    return out


def test_every_option_has_help_and_shows_its_default() -> None:
    for p in _subparsers(_parser()):
        assert isinstance(p.formatter_class, type)
        assert issubclass(p.formatter_class, argparse.ArgumentDefaultsHelpFormatter), p.prog
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                continue
            assert a.help, f"{p.prog} {a.option_strings or a.dest} has no help"
    helps = {sp.prog: " ".join(sp.format_help().split()) for sp in _subparsers(_parser())}
    assert "(default: ekf)" in helps["mapfuse run"]
    assert "(default: ekf,batch,isam2)" in helps["mapfuse compare"]
    assert "(default: ekf)" in helps["mapfuse baseline record"]
    for ds in ("carpark", "victoria-park", "loop600", ".npz"):
        assert ds in helps["mapfuse compare"].replace("victoria- park", "victoria-park")


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--version"]) == 0
    out = capsys.readouterr().out.strip()
    assert out.startswith("mapfuse ")
    assert len(out.split()) >= 2


@pytest.mark.parametrize(
    ("argv", "code", "message"),
    [
        (["run", "{npz}", "--estimator", "batch", "--robust", "tukey"], 2, "--robust: unknown"),
        (["run", "{npz}", "--estimator", "batch", "--robust", "huber:-1"], 2, "must be > 0"),
        (["run", "{npz}", "--robust", "huber"], 2, GRAPH_ONLY),
        (["run", "{npz}", "--association", "truth"], 2, GRAPH_ONLY),
        (["run", "{npz}", "--estimator", "ekf", "--robust", "huber"], 2, GRAPH_ONLY),
        (["run", "{npz}", "--estimator", "ekf", "--association", "own"], 2, GRAPH_ONLY),
        (["run", "{npz}", "--seed", "3"], 2, "--seed does not apply to a saved log"),
        (["run", "loop600", "--data", "{tmp}"], 2, "--data applies to carpark and victoria-park"),
        (["run", "carpark"], 2, "needs a data directory (--data DIR or $MAPFUSE_DATA)"),
        (["run", "carpark", "--data", "{tmp}/none"], 2, "is not a directory"),
        (["run", "victoria-park", "--data", "{tmp}", "--seed", "1"], 2, "--seed does not apply"),
        (["run", "{npz}", "--steps", "61"], 2, "--steps 61 is more than"),
        (["run", "loop600", "--steps", "99999"], 2, "more than scenario 'loop600' drives (2400"),
        (["run", "{npz}", "--export-graph"], 2, "--export-graph: the ekf estimator holds no"),
        (["run", "{npz}", "--estimator", "nope"], 2, "unknown estimator 'nope'"),
        (["run", "{npz}", "--plugin", "no_such_module:X"], 2, "--plugin: plugin"),
        (["run", "{npz}", "--plugin", "math:pi"], 2, "is not a mapfuse estimator"),
        (["run", "{tmp}/missing.npz"], 3, "does not exist"),
        (["run", "no-such-scenario"], 3, "no-such-scenario"),
        (["run", "carmen:{tmp}/missing.log"], 3, "CARMEN log"),
        (["compare", "{npz}", "--estimators", "ekf", "--robust", "huber"], 2, GRAPH_ONLY),
        (["compare", "{npz}", "--estimators", "batch", "--robust", "x"], 2, "unknown robust"),
        (["compare", "{npz}", "--estimators", "ekf", "--association", "own"], 2, GRAPH_ONLY),
        (["compare", "{npz}", "--estimators", "ekf,nope"], 2, "unknown estimator 'nope'"),
        (["compare", "{npz}", "--seed", "1"], 2, "--seed does not apply"),
        (["compare", "loop600", "--beside", "carpark"], 2, "--beside carpark: only simulated"),
        (["compare", "loop600", "--beside", "{npz}"], 2, "only simulated scenarios"),
        (["compare", "loop600", "--beside", "no-such-scenario"], 3, "no-such-scenario"),
        (["simulate", "loop600", "--steps", "5000"], 2, "more than scenario 'loop600' drives"),
        (["simulate", "loop600", "--steps", "50", "--plot-step", "50"], 2, "beyond the log's"),
    ],
)
def test_bad_options_fail_before_any_work(
    argv: list[str],
    code: int,
    message: str,
    log_npz: Path,
    tmp_path: Path,
    no_work: None,
    capsys: pytest.CaptureFixture[str],
) -> None:
    args = [a.format(npz=log_npz, tmp=tmp_path) for a in argv]
    if "--out" not in args:
        args += ["--out", str(tmp_path / "out")]
    assert main([*args, "--quiet"]) == code
    err = capsys.readouterr()
    assert err.out == ""
    lines = err.err.strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("mapfuse: error: ")
    assert message in lines[0]
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["run", "{npz}", "--steps", "0"], "argument --steps: must be >= 1, got 0"),
        (["run", "{npz}", "--steps", "many"], "argument --steps: expected an integer"),
        (["run", "loop600", "--seed", "-1"], "argument --seed: must be in 0 … 2**63 - 1, got -1"),
        (["run", "{npz}", "--fusion", "both"], "argument --fusion: invalid choice: 'both'"),
        (["compare", "{npz}", "--estimators", "ekf,ekf"], "needs distinct comma-separated"),
        (["simulate", "loop600", "--plot-step", "-1"], "argument --plot-step: must be >= 0"),
        (["montecarlo", "loop600", "--runs", "0"], "argument --runs: must be >= 1"),
        (["montecarlo", "loop600", "--runs", "2", "--workers", "0"], "--workers: must be >= 1"),
        (["montecarlo", "loop600", "--runs", "2", "--serial", "--workers", "2"], "not allowed"),
        (["spectrum", "loop600", "--lags", "0,-1"], "a lag must be >= 0 seconds"),
        (["spectrum", "loop600", "--steps", "1"], "argument --steps: must be >= 2"),
        (["baseline", "check", "--baseline", "b.json", "--tolerance", "0"], "must be a finite"),
    ],
)
def test_impossible_values_are_refused_by_the_parser(
    argv: list[str], message: str, log_npz: Path, tmp_path: Path, no_work: None,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    args = [a.format(npz=log_npz, tmp=tmp_path) for a in argv]
    if "--out" not in args and argv[0] != "baseline":
        args += ["--out", str(tmp_path / "out")]
    assert main(args) == 2
    err = capsys.readouterr()
    assert err.out == ""
    assert message in err.err.strip().splitlines()[-1]
    assert "Traceback" not in err.err


def test_deprecated_spellings_still_work_with_one_warning_each(
    capsys: pytest.CaptureFixture[str],
) -> None:
    p = _parser()
    args = p.parse_args(["run", "x.npz", "--backend", "batch", "--no-fusion", "--out", "o"])
    assert (args.estimator, args.fusion) == ("batch", "off")
    args = p.parse_args(["compare", "x.npz", "--backends", "ekf,isam2", "--fusion", "--out", "o"])
    assert (args.estimators, args.fusion) == (("ekf", "isam2"), "on")
    err = capsys.readouterr().err.splitlines()
    assert err == [
        "mapfuse: warning: --backend is deprecated; use --estimator",
        "mapfuse: warning: --no-fusion is deprecated; use --fusion off",
        "mapfuse: warning: --backends is deprecated; use --estimators",
        "mapfuse: warning: --fusion without a value is deprecated; use --fusion on",
    ]
    # The new spellings warn of nothing.
    args = p.parse_args(
        ["compare", "x.npz", "--estimators", "ekf", "--fusion", "off", "--out", "o"]
    )
    assert (args.estimators, args.fusion) == (("ekf",), "off")
    assert capsys.readouterr().err == ""


def test_unwritable_out_fails_before_any_work(
    log_npz: Path, tmp_path: Path, no_work: None, capsys: pytest.CaptureFixture[str]
) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    for cmd in (["run", str(log_npz)], ["compare", str(log_npz)]):
        assert main([*cmd, "--out", str(blocker / "sub"), "--quiet"]) == 2
        assert "is not writable" in capsys.readouterr().err
        assert main([*cmd, "--out", str(blocker), "--quiet"]) == 2
        assert "is a file" in capsys.readouterr().err
    rec = ["baseline", "record", str(log_npz), "--out", str(blocker / "b.json"), "--quiet"]
    assert main(rec) == 2
    assert "not writable" in capsys.readouterr().err


def test_force_refuses_then_clears_another_runs_files(
    log_npz: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    base = ["run", str(log_npz), "--estimator", "ekf", "--fusion", "off", "--out", str(out)]
    base.append("--quiet")
    assert main(base) == 0
    capsys.readouterr()
    stale = out / "associations.npz"
    assert stale.is_file()  # the EKF decides its own associations
    (out / "trajectory_filtered.tum").write_text("# from another backend\n")
    (out / "notes.txt").write_text("mine")
    before = (out / "metrics.json").stat().st_mtime_ns
    time.sleep(0.01)
    assert main(base) == 2
    err = capsys.readouterr().err
    assert "holds another run's files" in err
    assert "--force" in err
    assert (out / "metrics.json").stat().st_mtime_ns == before  # untouched
    # A graph run writes no associations.npz: with --force the EKF's must not stay.
    graph = [*base[:3], "batch", *base[4:], "--force", "--association", "truth"]
    assert main(graph) == 0
    capsys.readouterr()
    assert not stale.exists()
    assert not (out / "trajectory_filtered.tum").exists()  # batch has no filtered estimate
    assert (out / "notes.txt").read_text() == "mine"  # not a mapfuse file: kept
    assert json.loads((out / "metrics.json").read_text())["backend"] == "batch"


def test_compare_options_choose_backends_fusion_association_robust(
    log_npz: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "cmp"
    argv = ["compare", str(log_npz), "--estimators", "ekf,batch", "--fusion", "off"]
    argv += ["--association", "truth", "--robust", "huber", "--out", str(out), "--quiet"]
    assert main(argv) == 0
    printed = json.loads(capsys.readouterr().out)
    metrics = json.loads((out / "comparison.json").read_text())
    assert [(m["backend"], m["fusion"]) for m in metrics] == [("ekf", False), ("batch", False)]
    assert metrics[1]["association"] == "truth"
    assert printed["outputs"]["comparison"] == str(out / "comparison.json")
    assert sorted(p.name for p in (out / "runs").iterdir()) == ["batch_no_fusion", "ekf_no_fusion"]


def test_robust_none_states_no_kernel_over_a_profiles() -> None:
    from mapfuse.cli import _check_graph_flags

    args = argparse.Namespace(association=None, robust="none")
    assert _check_graph_flags(args, ["ekf", "batch"]) == {"batch": {"graph": {"robust": None}}}
    args = argparse.Namespace(association=None, robust="cauchy:2")
    assert _check_graph_flags(args, ["isam2"]) == {"isam2": {"graph": {"robust": "cauchy:2"}}}


def test_compare_stdout_is_json_alone(log_npz: Path, tmp_path: Path) -> None:
    out = tmp_path / "cmp"
    # With progress bars on: they go to stderr.
    proc = _mapfuse("compare", str(log_npz), "--estimators", "ekf,isam2", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    parsed = json.loads(proc.stdout)
    assert parsed["outputs"]["report"] == str(out / "report.md")
    # The one-line summary ends stderr, after the progress bars.
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("compared 4 runs (ekf, isam2; fusion both) on synthetic")
    assert last.endswith(f"→ {out / 'report.md'}")
    # The check a user runs: mapfuse compare ... | python -c 'json.load(sys.stdin)'.
    check = subprocess.run(
        [sys.executable, "-c", "import json,sys; json.load(sys.stdin)"],
        input=proc.stdout,
        text=True,
        check=False,
    )
    assert check.returncode == 0


def test_progress_bars_show_rate_and_eta_and_quiet_silences_them(
    log_npz: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["run", str(log_npz), "--estimator", "ekf", "--out", str(tmp_path / "a")]
    assert main(argv) == 0
    cap = capsys.readouterr()
    json.loads(cap.out)
    assert "ekf with fusion: 100%" in cap.err
    assert "60/60" in cap.err
    assert "step/s" in cap.err  # the rate
    assert "<" in cap.err  # elapsed<remaining, tqdm's ETA
    assert main([*argv[:-1], str(tmp_path / "b"), "--quiet"]) == 0
    assert capsys.readouterr().err == ""


def test_ctrl_c_is_one_line_and_exit_130(
    log_npz: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(mapfuse.runner, "load", interrupted)
    assert main(["run", str(log_npz), "--out", str(tmp_path / "o")]) == EXIT_INTERRUPTED
    assert capsys.readouterr().err == "mapfuse: interrupted\n"


def _sigint_default() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.slow
def test_sigint_during_a_simulation(tmp_path: Path) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "mapfuse.cli", "simulate", "loop600", "--out", str(tmp_path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=_env(),
        # As from a terminal: a test run started in the background of a non-interactive
        # shell would hand its SIGINT-ignored disposition on.
        preexec_fn=_sigint_default,
    )
    assert proc.stderr is not None
    # Wait until the simulation runs (its progress bar appears), then press Ctrl-C.
    seen = b""
    while b"simulate" not in seen:
        chunk = proc.stderr.read1(256)  # type: ignore[attr-defined]
        assert chunk, "the simulation ended without a progress bar"
        seen += chunk
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == EXIT_INTERRUPTED
    assert out == b""
    assert (seen + err).decode().rstrip().splitlines()[-1].endswith("mapfuse: interrupted")
    assert b"Traceback" not in seen + err


def test_run_export_graph_writes_g2o_and_names_what_it_leaves_out(
    log_npz: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["run", str(log_npz), "--estimator", "batch", "--export-graph", "--quiet"]
    assert main([*argv, "--out", str(tmp_path)]) == 0
    cap = capsys.readouterr()
    outputs = json.loads(cap.out)["outputs"]
    assert outputs["graph_g2o"] == str(tmp_path / "graph.g2o")
    assert "left out (in graph.json)" in cap.err
    assert "circle observation" in cap.err
    side = json.loads((tmp_path / "graph.json").read_text())
    assert side["left_out"]["factors"]
