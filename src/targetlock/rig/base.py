"""The small interfaces the control loop talks to; a simulated and a hardware rig implement them.

Units: setpoints and positions cross this boundary in encoder **ticks** (the drive boundary);
observations are **pixels** from the image centre (x right, y down); times are seconds on the
rig's clock.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Observation", "DriveFault", "Drives", "ObservationSource", "Rig"]


@dataclass(frozen=True)
class Observation:
    """What the tracker reports about one frame."""
    capture_time: float
    """When the frame was captured (s, rig clock); it arrives ``latency`` later."""
    offset: np.ndarray
    """Target position relative to the image centre (px, x right, y down); NaN when lost."""
    valid: bool
    """False when the target is lost or the estimate is not trustworthy."""
    confidence: float = 1.0
    """Tracker confidence in [0, 1]."""
    frame_index: int = -1
    truth: np.ndarray | None = field(default=None, compare=False)
    """Ground-truth offset (px) where the rig knows it (twin); never used by controllers."""
    arrival_time: float = float("nan")
    """When the observation became available to the loop (s, rig clock), for latency statistics."""


class DriveFault(RuntimeError):
    """A drive reported a fault, lost its heartbeat or the bus went away."""


class Drives(abc.ABC):
    """Both steering drives of a rig (axis 0: image x, axis 1: image y)."""

    n_axes: int = 2

    @property
    @abc.abstractmethod
    def homed(self) -> bool:
        """True once homing has completed; no motion is allowed before."""

    @abc.abstractmethod
    def home(self) -> None:
        """Run (or, on the twin, declare) homing; positions are zero at the handle's neutral."""

    @abc.abstractmethod
    def send_setpoints(self, ticks: np.ndarray) -> None:
        """Command new position setpoints (ticks, int64 array of n_axes)."""

    @abc.abstractmethod
    def positions(self) -> np.ndarray:
        """Measured positions (ticks, int64 array of n_axes)."""

    @property
    @abc.abstractmethod
    def limits(self) -> tuple[np.ndarray, np.ndarray]:
        """(lowest, highest) setpoint allowed per axis, in ticks."""

    @property
    @abc.abstractmethod
    def rad_per_tick(self) -> float:
        """Encoder gain (rad/tick), to express positions in SI for the controllers."""

    def fault(self) -> str | None:
        """A description of the current fault, or None when the drives are healthy."""
        return None

    def disable(self) -> None:
        """Stop commanding and disable the power stage (safe state)."""

    def enable(self) -> None:
        """Explicit re-enable after a fault has been cleared."""

    def report(self) -> dict:
        """Figures for the run summary (counts, times in ms); empty when the drives keep none."""
        return {}


class ObservationSource(abc.ABC):
    """Delivers tracker observations when they arrive at the controller."""

    @abc.abstractmethod
    def poll(self, now: float) -> list[Observation]:
        """Observations that have arrived by ``now`` (s) and were not returned before, oldest first."""


class Rig(abc.ABC):
    """A rig: drives plus an observation source, advanced in time by the loop."""

    drives: Drives
    observations: ObservationSource

    @abc.abstractmethod
    def advance(self, until: float) -> None:
        """Let the rig run until time ``until`` (s). The twin integrates its physics; hardware waits."""

    def close(self) -> None:
        """Release devices; drives end disabled."""

    def __enter__(self) -> "Rig":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
