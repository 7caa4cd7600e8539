"""``mapfuse spectrum``: the filtering–smoothing spectrum (:mod:`mapfuse.spectrum`) from
the command line, writing ``OUT/spectrum.json``, ``OUT/report.md`` and
``OUT/spectrum.png``."""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

__all__ = ["add_spectrum_parser"]


def _lags(text: str) -> tuple[float, ...]:
    from mapfuse.spectrum import parse_lags

    try:
        return parse_lags(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--lags: ")) from None


def _check_truth(args: argparse.Namespace, kind: str, source: str) -> None:
    """The spectrum scores against true poses: a saved log must hold them, a CARMEN log
    be a corrected one."""
    from mapfuse.carmen_input import carmen_log_kind
    from mapfuse.cli_common import UsageError, checking, reading
    from mapfuse_core.measlog import load_log

    if kind == "npz":
        with reading():
            log = load_log(source)
        if log.true_poses is None:
            raise UsageError(f"{source}: the spectrum needs true poses, and this log has none")
        if len(args.seeds) > 1:
            raise UsageError(
                f"--seeds: a saved log ({source}) is one run, not {len(args.seeds)} seeds"
            )
    elif kind == "carmen":
        with checking():
            if carmen_log_kind(source) != "corrected":
                raise ValueError(
                    f"{source}: the spectrum needs true poses, and this CARMEN log's poses "
                    "are raw odometry"
                )


def _cmd_spectrum(args: argparse.Namespace) -> int:
    from mapfuse.cli_common import (
        UsageError,
        check_out_dir,
        check_source,
        checking,
        emit,
        labelled_bars,
        progress_bar,
        summary,
    )
    from mapfuse.outdir import prepare_output_dir
    from mapfuse.spectrum import (
        SpectrumEstimators,
        check_roles,
        spectrum,
        spectrum_figure,
        spectrum_markdown,
    )

    if len(args.estimators) != 3:
        raise UsageError(
            "--estimators names the filter, the fixed-lag smoother and the full smoother, "
            f"three names, got {','.join(args.estimators)}"
        )
    roles = SpectrumEstimators(*args.estimators)
    src = check_source(args, kinds=("scenario", "npz", "carmen"))
    _check_truth(args, src.kind, src.text)
    with checking():
        check_roles(roles)
    check_out_dir(args)
    serial = True if args.serial else None
    several = len(args.seeds) > 1 and not args.serial
    runs = labelled_bars(args)
    seeds_bar = progress_bar(args, "spectrum seeds") if several else None

    def say(msg: str) -> None:
        if not args.quiet:
            from tqdm.auto import tqdm

            tqdm.write(msg, file=sys.stderr)

    result = spectrum(
        src.text,
        args.lags,
        args.seeds,
        fusion=args.fusion == "on",
        association=args.association,
        landmarks=args.landmarks,
        steps=args.steps,
        progress=say,
        workers=args.workers,
        scheduler=args.scheduler,
        serial=serial,
        estimators=roles,
        plugins=tuple(args.plugin or ()),
        run_progress=runs,
        seed_progress=seeds_bar,
    )
    runs.close()
    if seeds_bar is not None:
        seeds_bar.close()
    with checking():
        out = prepare_output_dir(args.out, force=args.force)
    fig_path = out / "spectrum.png"
    spectrum_figure(result).savefig(fig_path, dpi=120)
    (out / "spectrum.json").write_text(json.dumps(result.as_dict(), indent=2) + "\n")
    (out / "report.md").write_text(spectrum_markdown(result, fig_path.name))
    emit(result.as_dict())
    best = min(result.rows, key=lambda r: r.mean_rmse_m)
    lag = "∞" if math.isinf(best.lag_s) else f"{best.lag_s:g} s"
    summary(
        args,
        f"spectrum of {result.scenario} over {len(result.seeds)} seeds, {len(result.rows)} "
        f"rows in {result.wall_time_s:.1f} s; lowest RMSE {best.mean_rmse_m:.3f} m "
        f"({best.estimator} at lag {lag}) → {out / 'report.md'}",
    )
    return 0


def add_spectrum_parser(sub: Any) -> None:
    """Register ``mapfuse spectrum`` on the CLI's subparsers."""
    from mapfuse.cli_args import (
        Formatter,
        add_cluster,
        add_estimators,
        add_fusion,
        add_output,
        add_plugins,
        add_quiet,
        add_seeds,
        add_source,
        add_steps,
    )

    p = sub.add_parser(
        "spectrum",
        help="RMSE and ANEES against lag: EKF, fixed-lag smoother, batch",
        description="Run the filter (lag 0), the fixed-lag smoother at each --lags and the "
        "full smoother (lag inf) on each seed (several seeds on a dask LocalCluster, one "
        "per core, or --scheduler; one seed, or --serial, in this process); write "
        "OUT/spectrum.json, OUT/report.md and OUT/spectrum.png, and print the table as "
        "JSON.",
        formatter_class=Formatter,
    )
    add_source(p, kinds="truth")
    p.add_argument(
        "--lags",
        type=_lags,
        default="0,1,5,30,inf",
        metavar="LAGS",
        help="fixed-lag lags in seconds, comma-separated (inf allowed)",
    )
    add_seeds(p)
    add_estimators(
        p,
        "ekf,fixedlag,batch",
        what="the filter, the fixed-lag smoother and the full smoother, comma-separated "
        "(the smoothers take association and the fixed-lag one fixedlag options)",
    )
    add_fusion(p, several=False)
    p.add_argument(
        "--association",
        default="ekf",
        choices=("ekf", "truth"),
        help="graph association: the filter's decisions or the true ids",
    )
    p.add_argument(
        "--landmarks",
        default="keep",
        choices=("keep", "window"),
        help="fixed-lag landmarks: kept in the window or marginalised after the lag",
    )
    add_steps(p, minimum=2)
    add_plugins(p)
    add_cluster(p, "the cores, at most one per seed")
    add_output(p)
    add_quiet(p)
    p.set_defaults(func=_cmd_spectrum)
