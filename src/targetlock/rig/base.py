"""The small interfaces the control loop talks to; a simulated and a hardware rig implement them.

Units: setpoints and positions cross this boundary in encoder **ticks** (the drive boundary);
observations are **pixels** from the image centre (x right, y down); times are seconds on the
loop's clock (time zero when the loop starts, see :meth:`Rig.start_clock`).
"""
from __future__ import annotations

import abc
import threading
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ..model.camera import CameraParams

__all__ = ["Observation", "DriveFault", "Drives", "ObservationSource", "HandoffSource", "FrameLog", "Rig"]


@dataclass(frozen=True)
class Observation:
    """What the tracker reports about one frame."""
    capture_time: float
    """When the frame was captured (s, loop clock): the best estimate, i.e. on a rig the grab time
    minus the video latency; it arrives about ``latency`` later."""
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
    """When the observation became available to the loop (s, loop clock), for latency statistics."""
    scale: float = float("nan")
    """Apparent size of the target relative to its size when it was selected (unitless, ∝ 1/depth);
    NaN when the tracker does not measure it."""


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

    def is_disabled(self) -> bool | None:
        """True when the drives confirm their power stage is off, False when they report it on,
        None when they cannot tell (the default)."""
        return None

    def note_observation(self, valid: bool, now: float) -> None:
        """The loop reports whether the target was seen at ``now`` (s, loop clock); a safety
        supervisor uses it to hold the drives while the target is lost. Default: ignored."""

    def report(self) -> dict:
        """Figures for the run summary (counts, times in ms); empty when the drives keep none."""
        return {}


class FrameLog:
    """Counts of camera frames and of frames that gave a valid observation, from ``since`` on.

    Memory does not grow with the run: only counts and the capture times of the first and last
    counted frame are kept."""

    def __init__(self, since: float = 0.0) -> None:
        self.since = float(since)
        self.reset()

    def reset(self) -> None:
        """Forget what was counted (e.g. frames stamped before the loop's time zero)."""
        self.frames = 0
        self.valid = 0
        self.first = float("nan")
        self.last = float("nan")

    def record(self, t: float, valid: bool) -> None:
        """One frame captured at ``t`` (s, loop clock); ``valid``: it gave a valid observation."""
        if t >= self.since:
            if self.frames == 0:
                self.first = t
            self.frames += 1
            self.valid += bool(valid)
            self.last = t

    @property
    def lost_fraction(self) -> float:
        """Fraction of the counted frames without a valid observation (NaN before any frame)."""
        return 1.0 - self.valid / self.frames if self.frames else float("nan")


class ObservationSource(abc.ABC):
    """Delivers tracker observations when they arrive at the controller."""

    signals_arrivals: bool = False
    """True when :meth:`wait_arrival` wakes up on an arrival (live sources with their own thread)."""
    frame_log: FrameLog
    """Camera frames this source captured and how many gave a valid observation (set by each source)."""

    @abc.abstractmethod
    def poll(self, now: float) -> list[Observation]:
        """Observations that have arrived by ``now`` (s) and were not returned before, oldest first."""

    def wait_arrival(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s (wall time) for an observation that :meth:`poll` has not returned
        yet; True when there is one. Sources that cannot signal arrivals (``signals_arrivals`` False)
        return False at once and the loop waits for its tick."""
        return False

    def close(self) -> None:
        """Stop threads and release devices (idempotent). Default: nothing to release."""


class HandoffSource(ObservationSource):
    """A newest-only hand-off from a producer thread: :meth:`deliver` replaces any observation the
    loop has not taken yet, so the loop never works through a backlog; :meth:`wait_arrival` wakes
    the loop as soon as one is delivered."""

    signals_arrivals = True

    def __init__(self) -> None:
        self._slot: Observation | None = None
        self._ready = threading.Condition(threading.Lock())
        self.frame_log = FrameLog()

    def deliver(self, obs: Observation) -> None:
        """Hand ``obs`` to the loop (producer thread)."""
        with self._ready:
            self._slot = obs
            self._ready.notify_all()

    def poll(self, now: float) -> list[Observation]:
        with self._ready:
            obs, self._slot = self._slot, None
        return [] if obs is None else [obs]

    def wait_arrival(self, timeout: float) -> bool:
        with self._ready:
            if self._slot is None and timeout > 0:
                self._ready.wait(timeout)
            return self._slot is not None


class Rig(abc.ABC):
    """A rig: drives plus an observation source, advanced in time by the loop."""

    drives: Drives
    observations: ObservationSource
    camera: CameraParams
    """The tip camera the observations come from (image size, principal point, video latency)."""

    @abc.abstractmethod
    def advance(self, until: float) -> None:
        """Let the rig run until time ``until`` (s). The twin integrates its physics; hardware waits."""

    @property
    def frame_log(self) -> FrameLog:
        """Camera frames captured and how many gave a valid observation."""
        return self.observations.frame_log

    def start_clock(self) -> None:
        """Loop time zero is now (called by the loop right after homing). Default: nothing to align."""

    def truth_offset(self, t: float | None = None) -> np.ndarray:
        """Where the target really is in the image at ``t`` (px from the centre), where the rig can
        tell (the twin, motion capture); NaN otherwise or when out of view."""
        return np.array([np.nan, np.nan])

    def tip_angles(self) -> np.ndarray:
        """Measured bending angles of the tip (rad), where the rig can tell; NaN otherwise."""
        return np.array([np.nan, np.nan])

    def close(self) -> None:
        """Release devices; drives end disabled."""

    def __enter__(self) -> "Rig":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
