"""One run through the library against the same run through the ``mapfuse`` command.

Prints one JSON object.  Target: the library's CPU time within 10 % of the command's.

Each run is a fresh process started without the thread variables
(``OPENBLAS_NUM_THREADS``, ``OMP_NUM_THREADS``, ``MKL_NUM_THREADS``, ...), as a notebook
or a researcher's script starts; the rest of the environment is passed on.  Both do
the same work: simulate the scenario, run the backend with fusion and write the run's
files (metrics, trajectories, figure).  The command is ``mapfuse run SCENARIO --estimator
B --seed S --out DIR --quiet``; the library's process calls :func:`mapfuse.runner.prepare_log`,
:func:`mapfuse.runner.run` and :func:`mapfuse.outputs.write_outputs`, and reports the CPU
and wall time of each of the three.

``cpu_s`` is the processor time of the whole process and of the children it waited
for (the simulation's extraction workers), read with ``getrusage(RUSAGE_CHILDREN)``;
``wall_s`` its elapsed time.  Each figure is the least of ``--repeat`` runs.  CPU time
shows threads that contend for the cores even on an idle machine; on a busy one the
wall time shows them more.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

#: The variables that set the thread count of BLAS and OpenMP runtimes; removed from the
#: runs' environment.  ``OPENBLAS_CORETYPE`` and the like are passed on unchanged.
THREAD_VARIABLES = (
    "OPENBLAS_NUM_THREADS",
    "OMP_NUM_THREADS",
    "MKL_NUM_THREADS",
    "GOTO_NUM_THREADS",
    "BLIS_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
)

# The library's run: phases timed in the process itself, printed as JSON on stdout.
_LIBRARY = """
import json, os, sys, time

def cpu():
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system

source, seed, backend, out = sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4]
phases = {}
c, w = cpu(), time.perf_counter()
from mapfuse.outputs import write_outputs
from mapfuse.runner import prepare_log, run
log = prepare_log(source, seed=seed)
phases["prepare_log"] = (cpu() - c, time.perf_counter() - w)
c, w = cpu(), time.perf_counter()
r = run(log, backend)
phases["run"] = (cpu() - c, time.perf_counter() - w)
c, w = cpu(), time.perf_counter()
write_outputs(r, out)
phases["write_outputs"] = (cpu() - c, time.perf_counter() - w)
print(json.dumps({k: {"cpu_s": v[0], "wall_s": v[1]} for k, v in phases.items()}))
"""

_CLI = "import sys; from mapfuse.cli import main; sys.exit(main(sys.argv[1:]))"


def cli_command() -> list[str]:
    """The ``mapfuse`` command installed beside this interpreter (its console script,
    as a user runs it), or the same entry point through ``-c`` when there is none."""
    script = Path(sys.executable).with_name("mapfuse")
    return [str(script)] if script.is_file() else [sys.executable, "-c", _CLI]


def clean_environment() -> dict[str, str]:
    """This process's environment without :data:`THREAD_VARIABLES`."""
    return {k: v for k, v in os.environ.items() if k not in THREAD_VARIABLES}


def timed(cmd: list[str], env: dict[str, str]) -> tuple[float, float, str]:
    """CPU time (the child and its waited-for descendants), wall time and stdout of
    ``cmd``; an error naming the command when it fails."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[:3])} ... failed ({proc.returncode}):\n{proc.stderr}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return cpu, wall, proc.stdout


def library_run(source: str, seed: int, backend: str, out: Path) -> dict[str, Any]:
    """The library's run in a fresh process: totals and its phases."""
    cmd = [sys.executable, "-c", _LIBRARY, source, str(seed), backend, str(out)]
    cpu, wall, stdout = timed(cmd, clean_environment())
    return {"cpu_s": cpu, "wall_s": wall, "phases": json.loads(stdout)}


def cli_run(source: str, seed: int, backend: str, out: Path) -> dict[str, Any]:
    """The command's run in a fresh process: totals."""
    args = ["run", source, "--estimator", backend, "--seed", str(seed), "--out", str(out)]
    cmd = [*cli_command(), *args, "--force", "--quiet"]
    cpu, wall, _ = timed(cmd, clean_environment())
    return {"cpu_s": cpu, "wall_s": wall}


def least(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The least CPU and wall time of ``runs`` (each on its own), and the phases of
    the run with the least CPU time."""
    best = min(runs, key=lambda r: r["cpu_s"])
    out: dict[str, Any] = {
        "cpu_s": round(best["cpu_s"], 2),
        "wall_s": round(min(r["wall_s"] for r in runs), 2),
    }
    if "phases" in best:
        out["phases"] = {
            k: {m: round(v, 2) for m, v in times.items()} for k, times in best["phases"].items()
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenario", default="loop600")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--backends", default="ekf,batch")
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    results: dict[str, dict[str, Any]] = {}
    load = [os.getloadavg()[0]]
    with tempfile.TemporaryDirectory() as tmp:
        for backend in args.backends.split(","):
            lib, cli = [], []
            # Alternated, so that a change in the machine's load falls on both.
            for i in range(args.repeat):
                out = Path(tmp) / f"{backend}-{i}"
                lib.append(library_run(args.scenario, args.seed, backend, out / "library"))
                cli.append(cli_run(args.scenario, args.seed, backend, out / "cli"))
                load.append(os.getloadavg()[0])
            row = {"library": least(lib), "cli": least(cli)}
            row["cpu_ratio"] = round(row["library"]["cpu_s"] / row["cli"]["cpu_s"], 3)
            results[backend] = row
    print(
        json.dumps(
            {
                "benchmark": "library_vs_cli",
                "scenario": args.scenario,
                "seed": args.seed,
                "fusion": True,
                "repeat": args.repeat,
                "backends": results,
                "target_cpu_ratio": 1.10,
                "cli_command": cli_command()[0],
                "thread_variables_removed": list(THREAD_VARIABLES),
                "cpu_count": os.cpu_count(),
                "load_average_1min": [round(x, 2) for x in load],
                "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
