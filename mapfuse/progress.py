"""Progress bars with rate and ETA, in a terminal and in Jupyter alike (``tqdm.auto``).

Estimators report progress as ``progress(k, n)`` (``k`` of ``n`` steps done) and
:func:`mapfuse.comparison.compare` as ``progress(label, k, n)``; :func:`progress_bar` and
:class:`LabelledProgress` turn those calls into one tqdm bar per run, e.g. in a
notebook ``run(log, "ekf", progress=progress_bar("ekf"))``.  Bars write to stderr, so
a command's stdout holds its JSON result alone.
"""

from __future__ import annotations

import sys
from typing import Any

from tqdm.auto import tqdm

from mapfuse.interrupt import check as check_interrupt

__all__ = ["LabelledProgress", "ProgressBar", "close_all", "progress_bar"]

_open: set[ProgressBar] = set()


class ProgressBar:
    """A ``progress(k, n)`` callback drawing one tqdm bar (created at the first call)."""

    def __init__(self, label: str, enabled: bool = True, delay_s: float = 0.0) -> None:
        self.label = label
        """Text in front of the bar."""
        self.enabled = enabled
        """Whether anything is drawn (``False``: ``--quiet``)."""
        self.delay_s = delay_s
        """Seconds before the bar first shows: work done sooner draws nothing."""
        self._bar: Any = None

    def __call__(self, k: int, n: int) -> None:
        # A Ctrl-C the command line recorded but Python lost (:mod:`mapfuse.interrupt`).
        check_interrupt()
        if not self.enabled:
            return
        if self._bar is None:
            self._bar = tqdm(
                total=n,
                desc=self.label,
                unit="step",
                file=sys.stderr,
                dynamic_ncols=True,
                delay=self.delay_s,
            )
            _open.add(self)
        self._bar.update(k - self._bar.n)
        if k >= n:
            self.close()

    def close(self) -> None:
        """Finish the bar (also when a run stops early)."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        _open.discard(self)


def close_all() -> None:
    """Finish every open bar (e.g. on Ctrl-C, before a message on the next line)."""
    for bar in list(_open):
        bar.close()


def progress_bar(label: str, enabled: bool = True) -> ProgressBar:
    """A ``progress(k, n)`` callback showing a bar labelled ``label``."""
    return ProgressBar(label, enabled)


class LabelledProgress:
    """A ``progress(label, k, n)`` callback: one :class:`ProgressBar` per label."""

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = enabled
        """Whether anything is drawn."""
        self._bars: dict[str, ProgressBar] = {}

    def __call__(self, label: str, k: int, n: int) -> None:
        bar = self._bars.setdefault(label, ProgressBar(label, self.enabled))
        bar(k, n)

    def close(self) -> None:
        """Finish every bar."""
        for bar in self._bars.values():
            bar.close()
