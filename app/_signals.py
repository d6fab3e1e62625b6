"""SIGTERM and SIGHUP handled like SIGINT: an exception unwinds the run, so cleanup code runs.

`kill PID` (SIGTERM, as sent by `timeout`, a batch system or a closing session) would otherwise
end the process at once, leaving a half-written staging folder and printing nothing. Inside
`terminate_by_exception()` it raises `Terminated` in the main thread instead (and SIGINT
`KeyboardInterrupt`, as always); `stairfit.cli` prints one line and exits with 128 + the signal
number (143 for SIGTERM, 130 for SIGINT), as a shell reports a process killed by that signal.

Python runs a signal's handler wherever the main thread is, and some places cannot take an
exception: an import of a compiled module (jaxlib's initialisation aborted the process on one),
JAX's start of its backends (a timer it starts there was left running for a minute), and a
garbage-collection callback or `__del__` (the exception is printed and dropped). In the first
two the signal is sent again a moment later instead of raising (`_raise`, `UNSAFE`); in the
last the dropped exception is noticed and the signal sent again (`_redeliver`). Either way the
run stops at the next point that can raise, a fraction of a second later. A signal the process
was started to ignore (`nohup`, a background job's SIGINT) stays ignored.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType

HANDLED = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))
"""The signals turned into `Terminated` (SIGINT raises KeyboardInterrupt)."""
RETRY_S = 0.05
"""How long a signal that arrived at a point that cannot raise waits before it is sent again."""


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


def _send_again(signum: int) -> None:
    """Send `signum` to this process again in `RETRY_S`, from a helper thread (a signal sent
    from here would run its handler here, at once)."""
    again = threading.Timer(RETRY_S, os.kill, (os.getpid(), signum))
    again.daemon = True
    again.start()


UNSAFE = ("<frozen importlib", os.path.join("jax", "_src", "xla_bridge.py"))
"""Code (file names, or their start) that must not be interrupted by an exception: Python's
import machinery, JAX's start of its backends."""


def _unsafe(frame: FrameType | None) -> bool:
    """Whether `frame` or a caller of it runs code of `UNSAFE`."""
    while frame is not None:
        name = frame.f_code.co_filename
        if name.startswith(UNSAFE[0]) or any(name.endswith(u) for u in UNSAFE[1:]):
            return True
        frame = frame.f_back
    return False


def _raise(signum: int, frame: FrameType | None) -> None:
    """The handler: `Terminated` (SIGTERM, SIGHUP) or `KeyboardInterrupt` (SIGINT), or, inside
    `UNSAFE` code, the same signal again a moment later."""
    if _unsafe(frame):
        _send_again(signum)
        return
    if signum == signal.SIGINT:
        raise KeyboardInterrupt
    raise Terminated(signum)


def _redeliver(
    previous: Callable[[sys.UnraisableHookArgs], object],
) -> Callable[[sys.UnraisableHookArgs], None]:
    """An unraisable-exception hook that sends a dropped interruption again (module docstring)
    instead of printing it; anything else goes to `previous`."""

    def hook(info: sys.UnraisableHookArgs) -> None:
        exc = info.exc_value
        if isinstance(exc, Terminated):
            _send_again(exc.signum)
        elif isinstance(exc, KeyboardInterrupt):
            _send_again(signal.SIGINT)
        else:
            previous(info)

    return hook


@contextmanager
def terminate_by_exception() -> Iterator[None]:
    """Within the block, SIGTERM and SIGHUP raise `Terminated` and SIGINT `KeyboardInterrupt`,
    never inside an import or where the exception would be dropped (module docstring); main
    thread only, else a no-op."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    defaults = {signal.SIGINT: signal.default_int_handler} | dict.fromkeys(HANDLED, signal.SIG_DFL)
    ours = [s for s, default in defaults.items() if signal.getsignal(s) is default]
    previous = {s: signal.signal(s, _raise) for s in ours}
    hook, sys.unraisablehook = sys.unraisablehook, _redeliver(sys.unraisablehook)
    try:
        yield
    finally:
        sys.unraisablehook = hook
        for s, handler in previous.items():
            signal.signal(s, handler)
