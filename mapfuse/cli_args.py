"""The command line's shared options: one helper per option, used by every command that
takes it, so that an option has one name, one syntax, one check and one help text.

* :func:`add_source`: the positional ``SCENARIO`` (scenario, TOML, log ``.npz``,
  dataset, ``carmen:PATH``);
* :func:`add_estimator`: ``--estimator NAME`` (deprecated alias ``--backend``);
* :func:`add_estimators`: ``--estimators A,B`` (deprecated alias ``--backends``);
* :func:`add_fusion`: ``--fusion on/off`` or ``on/off/both`` (deprecated ``--no-fusion``
  and a bare ``--fusion``);
* :func:`add_output`: ``--out`` and ``--force``;
* :func:`add_quiet`: ``--quiet``;
* :func:`add_cluster`: ``--workers``, ``--scheduler``, ``--serial``;
* :func:`add_plugins`: ``--plugin MODULE:ATTR`` (repeatable);
* :func:`add_seed`, :func:`add_seeds`: ``--seed N``, ``--seeds 0-4,7``;
* :func:`add_steps`: ``--steps N``;
* :func:`add_data`: ``--data DIR`` (default ``$MAPFUSE_DATA``).

Values that are impossible whatever the input (``--steps 0``, ``--workers 0``, a
negative seed) are refused by the parser itself (exit status 2).  Every help text
shows the option's real default, or says in words what happens without it.  The
module imports nothing heavy, so that a command's clock starts before numpy does.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from typing import Any, NoReturn

from mapfuse.datadir import DATA_ENV

__all__ = [
    "Formatter",
    "Parser",
    "add_cluster",
    "add_data",
    "add_estimator",
    "add_estimators",
    "add_fusion",
    "add_output",
    "add_plugins",
    "add_quiet",
    "add_seed",
    "add_seeds",
    "add_source",
    "add_steps",
    "estimator_list",
    "fusions",
    "positive_int",
    "seed_int",
]


class Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line on stderr, as every other
    error of the command line (exit status 2)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"mapfuse: error: {self.prog}: {message} (see {self.prog} --help)\n")


class Formatter(argparse.ArgumentDefaultsHelpFormatter):
    """Appends ``(default: X)`` to an option's help where it has a value to show; a
    flag, or an option whose absence the help text describes, shows none."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if (
            action.default is None
            or action.default == ""
            or action.default is argparse.SUPPRESS
            or isinstance(action.default, bool)
            or action.nargs == 0
            or "%(default)" in (action.help or "")
        ):
            return action.help
        return super()._get_help_string(action)


def _warn_deprecated(old: str, new: str) -> None:
    print(f"mapfuse: warning: {old} is deprecated; use {new}", file=sys.stderr)


class _DeprecatedAlias(argparse.Action):
    """An old spelling: stores like the new option and prints a one-line warning."""

    def __init__(self, option_strings: Sequence[str], dest: str, **kwargs: Any) -> None:
        self.replacement: str = kwargs.pop("replacement")
        kwargs.setdefault("default", argparse.SUPPRESS)
        super().__init__(option_strings, dest, **kwargs)

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        _warn_deprecated(option_string or self.option_strings[0], self.replacement)
        setattr(namespace, self.dest, self.const if self.nargs == 0 else values)


class _Fusion(argparse.Action):
    """``--fusion on|off[|both]``; a bare ``--fusion`` (the old flag) means ``on``."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        if values is None:
            _warn_deprecated("--fusion without a value", "--fusion on")
            values = "on"
        setattr(namespace, self.dest, values)


# --------------------------------------------------------------------------- value types


def positive_int(text: str) -> int:
    """An integer ``>= 1`` (``--steps``, ``--workers``, ``--runs``)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def seed_int(text: str) -> int:
    """A seed: an integer in ``0 … MAX_SEED``."""
    from mapfuse_core.sim.limits import MAX_SEED

    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"must be in 0 … 2**63 - 1, got {value}")
    return value


def _seed_list(text: str) -> tuple[int, ...]:
    from mapfuse.campaign.spec import parse_seeds

    try:
        return parse_seeds(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def estimator_list(text: str) -> tuple[str, ...]:
    """``"ekf,batch"`` → ``("ekf", "batch")``: at least one name, each once."""
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    if not names or len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(f"needs distinct comma-separated names, got {text!r}")
    return names


def fusions(choice: str) -> tuple[bool, ...]:
    """The fusion settings of a ``--fusion`` choice (``on``, ``off``, ``both``)."""
    from mapfuse.campaign.spec import parse_fusion

    return parse_fusion(choice)


# --------------------------------------------------------------------------- helpers


def _estimator_names() -> str:
    from mapfuse.registry import available

    return ", ".join(available())


def add_source(p: argparse.ArgumentParser, kinds: str = "any", **kwargs: Any) -> None:
    """The positional input ``SCENARIO``: what it may be (``kinds``: ``"any"``,
    ``"simulated"`` (scenarios and corrected CARMEN logs: campaigns) or ``"truth"``
    (scenarios, saved logs, CARMEN logs: what has true poses))."""
    from mapfuse.runner import DATASETS
    from mapfuse_core.sim.scenario import list_builtin_scenarios

    scenarios = f"a built-in scenario ({', '.join(list_builtin_scenarios())}), a scenario .toml"
    carmen = "a CARMEN laser log carmen:PATH.log[.gz] (carmen,odometry=raw|corrected:PATH)"
    if kinds == "simulated":
        text = f"{scenarios}, or a corrected CARMEN log carmen:PATH (each seed draws its odometry)"
    elif kinds == "truth":
        text = f"{scenarios}, a saved log .npz with true poses, or {carmen}"
    else:
        text = (
            f"{scenarios}, a saved log .npz, a real dataset ({', '.join(DATASETS)}; needs "
            f"--data or ${DATA_ENV}), or {carmen}"
        )
    p.add_argument("scenario", metavar="SCENARIO", help=text, **kwargs)


def add_estimator(p: argparse.ArgumentParser, default: str = "ekf") -> None:
    """``--estimator NAME``: the one estimator a command runs (alias ``--backend``)."""
    p.add_argument(
        "--estimator",
        default=default,
        metavar="NAME",
        help=f"registered estimator: {_estimator_names()}, or a --plugin's",
    )
    p.add_argument(
        "--backend",
        dest="estimator",
        action=_DeprecatedAlias,
        replacement="--estimator",
        metavar="NAME",
        help="deprecated alias of --estimator",
    )


def add_estimators(p: argparse.ArgumentParser, default: str, what: str = "") -> None:
    """``--estimators A,B``: the estimators a command runs (alias ``--backends``)."""
    p.add_argument(
        "--estimators",
        default=default,
        type=estimator_list,
        metavar="A,B",
        help=what
        or f"comma-separated registered estimators: {_estimator_names()}, or a --plugin's",
    )
    p.add_argument(
        "--backends",
        dest="estimators",
        type=estimator_list,
        action=_DeprecatedAlias,
        replacement="--estimators",
        metavar="A,B",
        help="deprecated alias of --estimators",
    )


def add_fusion(p: argparse.ArgumentParser, *, several: bool) -> None:
    """``--fusion on|off|both`` on a command that runs several settings (default
    ``both``), ``--fusion on|off`` on one that runs one (default ``on``); ``--no-fusion``
    and a bare ``--fusion`` are deprecated spellings of ``off`` and ``on``."""
    choices = ["on", "off", "both"] if several else ["on", "off"]
    p.add_argument(
        "--fusion",
        choices=choices,
        default="both" if several else "on",
        nargs="?",
        const=None,
        action=_Fusion,
        help="fuse the known map (on), SLAM without it (off)"
        + (", or each estimator both ways (both)" if several else "")
        + "; a log without a known map runs off",
    )
    p.add_argument(
        "--no-fusion",
        dest="fusion",
        action=_DeprecatedAlias,
        replacement="--fusion off",
        nargs=0,
        const="off",
        help="deprecated alias of --fusion off",
    )


def add_output(p: argparse.ArgumentParser, kind: str = "folder", what: str = "") -> None:
    """``--out`` (a folder, or a file with ``kind="file"``) and ``--force``."""
    p.add_argument(
        "--out",
        required=True,
        metavar="DIR" if kind == "folder" else "FILE",
        help=what or f"output {kind}",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace another run's files in --out (without it such a folder is refused "
        "before any work)"
        if kind == "folder"
        else "replace the file --out if it exists (without it an existing file is refused "
        "before any work)",
    )


def add_quiet(p: argparse.ArgumentParser) -> None:
    """``--quiet``."""
    p.add_argument(
        "--quiet",
        action="store_true",
        help="no progress bars and no summary line on stderr (warnings and errors still print)",
    )


def add_cluster(p: argparse.ArgumentParser, workers_default: str) -> None:
    """``--workers N`` | ``--scheduler ADDRESS`` | ``--serial``: where runs go."""
    g = p.add_mutually_exclusive_group()
    g.add_argument(
        "--workers",
        type=positive_int,
        default=None,
        metavar="N",
        help=f"local dask worker processes (default: {workers_default})",
    )
    g.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="address of a running dask scheduler, e.g. tcp://host:8786 (default: a local cluster)",
    )
    g.add_argument(
        "--serial", action="store_true", help="run everything in this process, without dask"
    )


def add_plugins(p: argparse.ArgumentParser) -> None:
    """``--plugin MODULE:ATTR`` (repeatable)."""
    p.add_argument(
        "--plugin",
        action="append",
        default=None,
        metavar="MODULE:ATTR",
        help="register the estimator MODULE:ATTR (an instance, its class or a factory) "
        "before running, under its own name; repeatable (default: none; installed "
        "plug-ins are entry points and need none)",
    )


def add_seed(p: argparse.ArgumentParser, help: str | None = None) -> None:
    """``--seed N``."""
    p.add_argument(
        "--seed",
        type=seed_int,
        default=None,
        metavar="N",
        help=help
        or "seed of the simulation (default: the scenario's own), or of a corrected "
        "CARMEN log's simulated odometry (default 0); not for a saved log or a dataset",
    )


def add_seeds(p: Any, default: str | None = "0", **kwargs: Any) -> None:
    """``--seeds 0-4,7``: distinct seeds, ranges and lists (``p``: a parser or one of
    its groups)."""
    p.add_argument(
        "--seeds",
        type=_seed_list,
        default=default,
        metavar="SEEDS",
        help="seeds, e.g. 0-39 or 0,3,7 (each once)",
        **kwargs,
    )


def add_steps(p: argparse.ArgumentParser, minimum: int = 1) -> None:
    """``--steps N``: the log's first N steps (a simulation stops there)."""

    def steps(text: str) -> int:
        value = positive_int(text)
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
        return value

    p.add_argument(
        "--steps",
        type=steps,
        default=None,
        metavar="N",
        help="only the log's first N steps: a simulation stops there; more than the log "
        "holds is an error (default: the whole log)",
    )


def add_data(p: argparse.ArgumentParser) -> None:
    """``--data DIR`` for the real datasets, ``$MAPFUSE_DATA`` by default."""
    now = os.environ.get(DATA_ENV)
    p.add_argument(
        "--data",
        default=None,
        metavar="DIR",
        help="data directory of the real datasets (carpark, victoria-park) (default: "
        f"${DATA_ENV}, {'now ' + now if now else 'unset'})",
    )
