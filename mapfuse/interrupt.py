"""A Ctrl-C that is never lost: :func:`catching_sigint` and :func:`check`.

Python turns SIGINT into ``KeyboardInterrupt`` at the next bytecode the main thread
runs.  When that bytecode belongs to a finaliser (a ``__del__`` or a weakref callback,
run whenever the garbage collector frees an object, e.g. a progress bar or a worker
pool), the exception is reported as "ignored" and the command runs on as if the key
had not been pressed.  So the command line's handler also records the press, and
:func:`check`, which the progress callbacks call at every step, raises it again: one
press stops a command that still has steps to run (one that has finished its work
finishes normally).
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

__all__ = ["catching_sigint", "check"]

_pressed = False


def _handler(signum: int, frame: FrameType | None) -> None:
    global _pressed
    _pressed = True
    raise KeyboardInterrupt


def check() -> None:
    """Raise ``KeyboardInterrupt`` if Ctrl-C was pressed inside :func:`catching_sigint`
    (a no-op elsewhere, e.g. in a notebook)."""
    if _pressed:
        raise KeyboardInterrupt


@contextmanager
def catching_sigint() -> Iterator[None]:
    """Record every SIGINT while inside (main thread, Python's default handler only:
    anything else has installed its own and is left alone)."""
    global _pressed
    if (
        threading.current_thread() is not threading.main_thread()
        or signal.getsignal(signal.SIGINT) is not signal.default_int_handler
    ):
        yield
        return
    previous = signal.signal(signal.SIGINT, _handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        _pressed = False
