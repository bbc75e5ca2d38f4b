"""Motor drives of the steering module: position mode with a path generator (report §3.3, Table 3.2).

The drive is modelled as a first-order system with rate limitation: the handle angle theta (rad)
approaches the setpoint with time constant ``time_constant`` while its speed never exceeds
``max_velocity``. Setpoints arrive in encoder ticks and are converted with ``rad_per_tick``; they
are clamped to the setpoint range before the drive sees them. Ticks exist only at this boundary.

The report gives both "settling time 0.2 s" (Table 3.2) and "10 Hz cut-off" (§3.4.2): the time
constant is a parameter; the default 1/(2·pi·10 Hz) = 15.9 ms follows the cut-off in the text.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from numba import njit

from ..config import ConfigError, param

__all__ = ["DriveParams", "drive_step"]


@dataclass(frozen=True)
class DriveParams:
    """One steering drive (both axes use the same kind of drive)."""
    rad_per_tick: float = param(0.000016, unit="rad/tick", lo=1e-9, hi=1.0, lo_open=True,
                                doc="encoder gain (Table 3.2)")
    max_velocity_ticks: float = param(100000.0, unit="tick/s", lo=1.0, hi=1e9,
                                      doc="path-generator velocity limit (Table 3.2)")
    time_constant: float = param(1.0 / (2.0 * math.pi * 10.0), unit="s", lo=0.0, hi=5.0,
                                 doc="first-order time constant (10 Hz cut-off)")
    min_angle: float = param(-2.0, unit="rad", lo=-6.3, hi=0.0, doc="lowest handle angle the drive may be sent to")
    max_angle: float = param(2.0, unit="rad", lo=0.0, hi=6.3, doc="highest handle angle the drive may be sent to")

    @property
    def max_velocity(self) -> float:
        """Velocity limit in rad/s."""
        return self.max_velocity_ticks * self.rad_per_tick

    @property
    def min_ticks(self) -> int:
        return int(math.ceil(self.min_angle / self.rad_per_tick))

    @property
    def max_ticks(self) -> int:
        return int(math.floor(self.max_angle / self.rad_per_tick))

    def check(self, prefix: str = "") -> None:
        if self.min_angle >= self.max_angle:
            raise ConfigError(f"{prefix}min_angle = {self.min_angle} must be below {prefix}max_angle = {self.max_angle}")


@njit(cache=True, inline="always")
def drive_step(theta: float, setpoint: float, dt: float, time_constant: float, max_velocity: float) -> float:
    """Handle angle (rad) after ``dt`` s: exact first-order response, then the rate limit."""
    if time_constant > 0.0:
        target = setpoint + (theta - setpoint) * math.exp(-dt / time_constant)
    else:
        target = setpoint
    step_max = max_velocity * dt
    delta = target - theta
    if delta > step_max:
        delta = step_max
    elif delta < -step_max:
        delta = -step_max
    return theta + delta
