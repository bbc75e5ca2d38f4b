"""Termination signals handled like Ctrl-C: SIGTERM and SIGHUP (and SIGINT) become a :class:`StopSignal`.

A service manager, ``kill`` or a closed terminal ends a run with SIGTERM or SIGHUP; by default
Python dies at once, without disabling the drives, flushing the data or writing a summary. Inside
:func:`stop_on_signals` such a signal raises :class:`StopSignal` (a :class:`KeyboardInterrupt`, so
every Ctrl-C path — the loop's safe stop, ``finally`` blocks, the CLI's handler — treats it the
same), with two guarantees that Python's own Ctrl-C lacks:

* it is never raised inside a :func:`deferred` block (one loop tick: the drive handshake, a CSV
  row): it waits until the block ends, so no set-point or row is cut in half;
* only the first signal raises; later ones (an impatient second Ctrl-C, a supervisor repeating
  SIGTERM) are logged and ignored while the run stops safely.

Use::

    with stop_on_signals():
        run_target_lock(cfg, run)     # StopSignal ends it like Ctrl-C; exit code 128 + signal number
"""
from __future__ import annotations

import logging
import signal
import threading
from contextlib import contextmanager
from typing import Iterator

__all__ = ["StopSignal", "stop_on_signals", "deferred", "STOP_SIGNALS"]

log = logging.getLogger(__name__)

STOP_SIGNALS: tuple[signal.Signals, ...] = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))


class StopSignal(KeyboardInterrupt):
    """A run was stopped by a signal (SIGINT, SIGTERM, SIGHUP); handled like Ctrl-C."""

    def __init__(self, signum: int) -> None:
        self.signum = int(signum)
        self.signal_name = signal.Signals(signum).name
        super().__init__(f"stopped by {self.signal_name}")

    @property
    def exit_code(self) -> int:
        """The shell's convention for a process ended by this signal: 128 + signal number."""
        return 128 + self.signum


class _State:
    active = 0            # depth of nested stop_on_signals() blocks
    deferring = 0         # depth of deferred() blocks
    pending: int | None = None   # a signal received inside deferred(), raised when it ends
    raised: int | None = None    # the signal that was raised (later ones are ignored)


_state = _State()


def _handler(signum: int, frame) -> None:  # noqa: ARG001 - signal handler signature
    if _state.raised is not None or _state.pending is not None:
        log.warning("%s received while stopping: ignored, the run is already being stopped safely",
                    signal.Signals(signum).name)
        return
    if _state.deferring:
        _state.pending = signum
        return
    _state.raised = signum
    raise StopSignal(signum)


class _Deferred:
    """Context manager object (reused: no allocation per tick)."""

    def __enter__(self) -> None:
        _state.deferring += 1

    def __exit__(self, exc_type, exc, tb) -> None:
        _state.deferring -= 1
        if _state.deferring == 0 and _state.pending is not None and _state.raised is None:
            signum, _state.pending = _state.pending, None
            _state.raised = signum
            if exc_type is None:
                raise StopSignal(signum)
            # The block is already leaving with an exception: that one reaches the safe-stop path.


_DEFERRED = _Deferred()


def deferred() -> _Deferred:
    """A block a stop signal must not cut into (raised when the block ends). Cheap; nestable; a no-op
    outside :func:`stop_on_signals`."""
    return _DEFERRED


@contextmanager
def stop_on_signals(signals: tuple[int, ...] = STOP_SIGNALS) -> Iterator[None]:
    """Turn ``signals`` into :class:`StopSignal` inside the block; the previous handlers come back
    after it. Only in the main thread (Python runs signal handlers there); elsewhere, and inside an
    enclosing ``stop_on_signals``, it changes nothing."""
    if threading.current_thread() is not threading.main_thread() or _state.active:
        yield
        return
    previous = {s: signal.getsignal(s) for s in signals}
    _state.pending = _state.raised = None
    for s in signals:
        signal.signal(s, _handler)
    _state.active += 1
    try:
        yield
    finally:
        _state.active -= 1
        for s, h in previous.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)  # None: set outside Python
        _state.pending = _state.raised = None
