"""SIGTERM and SIGHUP handled like SIGINT: an exception unwinds the run, so cleanup code runs.

`kill PID` (SIGTERM, as sent by `timeout`, a batch system or a closing session) would otherwise
end the process at once, leaving a half-written staging folder and printing nothing. Inside
`terminate_by_exception()` it raises `Terminated` in the main thread instead; `stairfit.cli`
prints one line and exits with 128 + the signal number (143 for SIGTERM), as a shell reports a
process killed by that signal.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

HANDLED = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))
"""The signals turned into `Terminated` (SIGINT already raises KeyboardInterrupt)."""


class Terminated(BaseException):
    """The process was asked to stop by a signal; `signum` says which.

    A BaseException (like KeyboardInterrupt), so that `except Exception` does not swallow it.
    """

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum

    @property
    def name(self) -> str:
        """The signal's name, e.g. "SIGTERM"."""
        return signal.Signals(self.signum).name


def _raise(signum: int, frame: FrameType | None) -> None:
    raise Terminated(signum)


@contextmanager
def terminate_by_exception() -> Iterator[None]:
    """Within the block, SIGTERM and SIGHUP raise `Terminated` (main thread only; else no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, _raise) for s in HANDLED}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
