"""Clocks for the control loop: simulated (as fast as the CPU allows) or the wall clock.

Both count seconds from the loop's start. The loop sleeps until *absolute* deadlines
(start + k·period), so a late tick never shifts the ones after it.
"""
from __future__ import annotations

import abc
import time

__all__ = ["Clock", "SimClock", "WallClock"]


class Clock(abc.ABC):
    realtime: bool = False
    """True when time passes on its own (the wall clock): the loop may then act between deadlines."""

    @abc.abstractmethod
    def now(self) -> float:
        """Seconds since start()."""

    @abc.abstractmethod
    def start(self) -> None:
        """Set time zero."""

    @abc.abstractmethod
    def sleep_until(self, deadline: float) -> float:
        """Wait until ``deadline`` (s since start); returns the lateness (s, >= 0)."""


class SimClock(Clock):
    """Deterministic time that jumps to each deadline at once."""

    def __init__(self) -> None:
        self._t = 0.0

    def start(self) -> None:
        self._t = 0.0

    def now(self) -> float:
        return self._t

    def sleep_until(self, deadline: float) -> float:
        self._t = max(self._t, deadline)
        return 0.0


class WallClock(Clock):
    """Monotonic wall time; sleeps coarsely, then spins the last ``spin`` seconds for low jitter."""

    realtime = True

    def __init__(self, spin: float = 0.0005) -> None:
        self._t0 = time.perf_counter()
        self.spin = spin

    def start(self) -> None:
        self._t0 = time.perf_counter()

    def now(self) -> float:
        return time.perf_counter() - self._t0

    def sleep_until(self, deadline: float) -> float:
        while True:
            remaining = deadline - self.now()
            if remaining <= 0:
                return -remaining
            if remaining > self.spin:
                time.sleep(remaining - self.spin)
