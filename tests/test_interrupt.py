"""Ctrl-C on the command line is never lost (``mapfuse/interrupt.py``)."""

from __future__ import annotations

import gc
import os
import signal
import sys

import pytest

from mapfuse import interrupt
from mapfuse.progress import progress_bar


class _PressesCtrlCWhenFreed:
    """An object whose finaliser receives the SIGINT, as a progress bar or a worker
    pool freed by the garbage collector at the wrong moment would."""

    def __del__(self) -> None:
        os.kill(os.getpid(), signal.SIGINT)
        # The handler runs at the next bytecode, still inside this finaliser.
        for _ in range(1000):
            pass


@pytest.fixture(autouse=True)
def _python_handles_sigint():
    """Python's own SIGINT handler, whatever this process inherited: a test run started
    in the background of a non-interactive shell inherits SIGINT ignored."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


def _swallowed(monkeypatch: pytest.MonkeyPatch) -> list[BaseException | None]:
    """Record what Python reports as ignored, instead of printing it."""
    seen: list[BaseException | None] = []
    monkeypatch.setattr(sys, "unraisablehook", lambda u: seen.append(u.exc_value))
    return seen


def test_a_ctrl_c_swallowed_by_a_finaliser_is_raised_again_by_check(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    seen = _swallowed(monkeypatch)
    with interrupt.catching_sigint():
        obj = _PressesCtrlCWhenFreed()
        del obj
        gc.collect()
        # Python reported the KeyboardInterrupt as ignored and went on...
        assert any(isinstance(e, KeyboardInterrupt) for e in seen)
        # ...but the press is recorded: the next check, or the next progress step, stops.
        with pytest.raises(KeyboardInterrupt):
            interrupt.check()
        with pytest.raises(KeyboardInterrupt):
            progress_bar("x", enabled=False)(1, 10)
    # Leaving restores Python's handler and forgets the press.
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    interrupt.check()


def test_check_is_a_no_op_outside_and_another_handler_is_left_alone() -> None:
    interrupt.check()
    mine = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with interrupt.catching_sigint():
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGINT)  # ignored, as its owner asked
            interrupt.check()
    finally:
        signal.signal(signal.SIGINT, mine)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
