"""The plausibility gate: observations no tracker can produce never reach a controller.

A tracker only sees inside the image, and a frame cannot have been captured in the future, long
before its video latency, or before the frame the loop already used. One such observation used to
freeze the PI integrators for the rest of a run (an offset of 1e300 px) or turn them NaN (a
non-finite capture time). :class:`ObservationGate` rejects them before any controller, counts them
per reason and logs them (the first few, then every thousandth); the run summary reports the
counts. A lost target (``valid`` False, NaN offset) is a legitimate observation and passes.
"""
from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass

from ..config import param
from ..rig.base import Observation

__all__ = ["GateConfig", "ObservationGate", "REASONS"]

log = logging.getLogger(__name__)

REASONS = ("time_not_finite", "time_in_future", "too_old", "time_backwards", "offset_not_finite",
           "outside_image", "confidence_not_finite")


@dataclass(frozen=True)
class GateConfig:
    """What the loop accepts as a plausible observation."""
    margin_px: float = param(20.0, unit="px", lo=0.0, hi=10000.0,
                             doc="reject targets further outside the image than this")
    max_extra_age: float = param(1.0, unit="s", lo=0.0, hi=60.0,
                                 doc="reject observations older than the video latency plus this")
    max_future: float = param(0.05, unit="s", lo=0.0, hi=1.0,
                              doc="reject capture times later than the loop's now plus this (clock jitter)")


class ObservationGate:
    """Checks each observation against the image (``width`` x ``height`` px, principal point
    ``cx``, ``cy``), the loop's clock and the video ``latency`` (s)."""

    LOG_FIRST = 5

    def __init__(self, config: GateConfig, *, width: float, height: float, cx: float, cy: float,
                 latency: float) -> None:
        m = config.margin_px
        self.config = config
        self.x_range = (-cx - m, width - cx + m)       # offsets are from the principal point (px)
        self.y_range = (-cy - m, height - cy + m)
        self.max_age = latency + config.max_extra_age
        self.rejected: Counter[str] = Counter()
        self.last_time = -math.inf

    @classmethod
    def for_camera(cls, config: GateConfig, camera) -> "ObservationGate":
        """A gate for a :class:`~targetlock.model.camera.CameraParams`."""
        return cls(config, width=camera.width, height=camera.height, cx=camera.cx, cy=camera.cy,
                   latency=camera.latency)

    @property
    def n_rejected(self) -> int:
        return sum(self.rejected.values())

    def reset(self) -> None:
        """A new run: forget the last capture time and the counts."""
        self.rejected.clear()
        self.last_time = -math.inf

    def reason(self, obs: Observation, now: float) -> str | None:
        """Why ``obs`` is implausible at ``now`` (s, loop clock), or None when it is plausible."""
        t = obs.capture_time
        if not math.isfinite(t):
            return "time_not_finite"
        if t > now + self.config.max_future:
            return "time_in_future"
        if now - t > self.max_age:
            return "too_old"
        if t < self.last_time:
            return "time_backwards"
        if not math.isfinite(obs.confidence):
            return "confidence_not_finite"
        if obs.valid:
            x, y = float(obs.offset[0]), float(obs.offset[1])
            if not (math.isfinite(x) and math.isfinite(y)):
                return "offset_not_finite"
            if not (self.x_range[0] <= x <= self.x_range[1] and self.y_range[0] <= y <= self.y_range[1]):
                return "outside_image"
        return None

    def admit(self, observations: list[Observation], now: float) -> list[Observation]:
        """The plausible ones of ``observations`` (oldest first), in order; the others are counted
        and logged."""
        out = []
        for obs in observations:
            why = self.reason(obs, now)
            if why is None:
                self.last_time = obs.capture_time
                out.append(obs)
                continue
            self.rejected[why] += 1
            n = self.n_rejected
            if n <= self.LOG_FIRST or n % 1000 == 0:
                log.warning("observation rejected (%s) at t = %.3f s: capture time %r s, offset %s px, valid %s"
                            " (%d rejected so far)", why.replace("_", " "), now, obs.capture_time,
                            list(map(float, obs.offset)), obs.valid, n)
        return out
