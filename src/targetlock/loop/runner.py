"""The fixed-rate control loop: one tick = advance rig, read observations and motors, step controller,
send setpoints (ticks) to the drives.

Ticks run on absolute deadlines k·period. The loop homes the drives first (no motion before homing),
engages the controller at the measured motor position, and on any exception — including Ctrl-C —
stops commanding and leaves the drives disabled before re-raising.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..config import ConfigError, param
from ..controllers.base import Controller
from ..rig.base import Observation, Rig
from .clock import Clock, SimClock

__all__ = ["LoopConfig", "ControlLoop", "Tick"]


@dataclass(frozen=True)
class LoopConfig:
    rate: float = param(50.0, unit="Hz", lo=1.0, hi=2000.0, doc="control loop rate (report: 50 Hz)")
    seconds: float = param(40.0, unit="s", lo=0.02, hi=86400.0, doc="duration of the run")
    metrics_after: float = param(2.0, unit="s", lo=0.0, hi=3600.0, doc="error metrics ignore the first seconds")

    def check(self, prefix: str = "") -> None:
        if self.metrics_after >= self.seconds:
            raise ConfigError(f"{prefix}metrics_after = {self.metrics_after:g} s leaves nothing to score in a run of "
                              f"{prefix}seconds = {self.seconds:g} s; allowed: [0, {self.seconds:g}) s (or a longer run)")


@dataclass
class Tick:
    """What happened in one tick (handed to the ``on_tick`` callback; reused, copy what you keep)."""
    index: int = 0
    time: float = 0.0
    lateness: float = 0.0
    observation: Observation | None = None
    motor: np.ndarray | None = None          # rad
    setpoint: np.ndarray | None = None       # rad
    ticks: np.ndarray | None = None          # what was sent
    sent: float = 0.0                        # clock time right after the setpoints were sent (s)


class ControlLoop:
    def __init__(self, rig: Rig, controller: Controller, *, rate: float, clock: Clock | None = None,
                 silence: float = 0.25) -> None:
        self.rig = rig
        self.silence = silence
        self.controller = controller
        self.period = 1.0 / rate
        self.clock = clock or SimClock()

    def run(self, seconds: float, on_tick: Callable[[Tick], None] | None = None) -> int:
        """Run for ``seconds`` (s); returns the number of ticks executed."""
        rig, ctrl, drives = self.rig, self.controller, self.rig.drives
        rpt = drives.rad_per_tick
        if not drives.homed:
            drives.home()
        self.clock.start()
        start_clock = getattr(rig, "start_clock", None)  # hardware rigs align their clock with the loop's
        if start_clock is not None:
            start_clock()
        note = getattr(drives, "note_observation", None)  # the safety supervisor's target-lost hold
        last_seen = 0.0
        ctrl.reset(drives.positions() * rpt, 0.0)
        n = int(round(seconds / self.period))
        tick = Tick()
        done = 0
        try:
            for k in range(1, n + 1):
                t = k * self.period
                tick.lateness = self.clock.sleep_until(t)
                rig.advance(t)
                arrived = rig.observations.poll(t)
                obs = arrived[-1] if arrived else None
                if note is not None:
                    if obs is not None:
                        last_seen = t
                        note(obs.valid, t)
                    elif t - last_seen > self.silence:
                        note(False, t)  # no frames at all counts as lost
                motor = drives.positions() * rpt
                setpoint = ctrl.step(obs, motor, t)
                ticks = np.rint(setpoint / rpt).astype(np.int64)
                drives.send_setpoints(ticks)
                tick.sent = self.clock.now()
                done = k
                if on_tick is not None:
                    tick.index, tick.time, tick.observation = k, t, obs
                    tick.motor, tick.setpoint, tick.ticks = motor, setpoint, ticks
                    on_tick(tick)
        except BaseException:
            drives.disable()
            raise
        return done
