"""The fixed-rate control loop: one tick = advance rig, read observations and motors, step controller,
send setpoints (ticks) to the drives.

Ticks run on absolute deadlines k·period. On the wall clock with a live source (one that signals
arrivals), tick k may run *early*, as soon as an observation arrives after tick k-1, instead of at
its deadline: a frame then reaches the drives within the time of one controller step instead of
waiting up to a period, while there is still at most one tick per period slot (the controllers and
the safety supervisor's rate limit see no more set-points than before). On the simulated clock the
ticks are exactly k·period, as before.

Every observation passes the plausibility gate (:mod:`.gate`) before the controller sees it. The
loop homes the drives first (no motion before homing), engages the controller at the measured
motor position, and on any exception — including Ctrl-C and the stop signals of
:mod:`.signals` — stops commanding and leaves the drives disabled before re-raising. A stop signal
never cuts a tick in half.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..config import ConfigError, param
from ..controllers.base import Controller
from ..rig.base import Observation, Rig
from .clock import Clock, SimClock
from .gate import GateConfig, ObservationGate
from .signals import deferred

__all__ = ["LoopConfig", "ControlLoop", "Tick"]

_FINISH = 0.0005  # s: the last bit before a deadline is left to the clock's precise sleep_until


@dataclass(frozen=True)
class LoopConfig:
    rate: float = param(50.0, unit="Hz", lo=1.0, hi=2000.0, doc="control loop rate (report: 50 Hz)")
    seconds: float = param(40.0, unit="s", lo=0.02, hi=86400.0, doc="duration of the run")
    metrics_after: float = param(2.0, unit="s", lo=0.0, hi=3600.0, doc="error metrics ignore the first seconds")
    step_on_arrival: bool = param(True, doc="on the wall clock, run a tick as soon as a live source delivers an "
                                            "observation (at most one tick per period) instead of at its deadline")
    gate: GateConfig = field(default_factory=GateConfig)

    def check(self, prefix: str = "") -> None:
        if self.metrics_after >= self.seconds:
            raise ConfigError(f"{prefix}metrics_after = {self.metrics_after:g} s leaves nothing to score in a run of "
                              f"{prefix}seconds = {self.seconds:g} s; allowed: [0, {self.seconds:g}) s (or a longer run)")


@dataclass
class Tick:
    """What happened in one tick (handed to the ``on_tick`` callback; reused, copy what you keep)."""
    index: int = 0
    time: float = 0.0                        # s, loop clock (the deadline, or earlier on an arrival)
    lateness: float = 0.0                    # s after the deadline (0 for a tick run early)
    observation: Observation | None = None
    motor: np.ndarray | None = None          # rad
    setpoint: np.ndarray | None = None       # rad
    ticks: np.ndarray | None = None          # what was sent
    sent: float = 0.0                        # clock time right after the setpoints were sent (s)
    early: bool = False                      # run on an observation's arrival, before the deadline


class ControlLoop:
    """``gate``: the plausibility gate (default: :class:`GateConfig` defaults for the rig's camera);
    ``step_on_arrival``: see the module doc; ``silence`` (s): no frames at all for this long counts
    as a lost target for the drives' supervisor."""

    def __init__(self, rig: Rig, controller: Controller, *, rate: float, clock: Clock | None = None,
                 silence: float = 0.25, gate: ObservationGate | None = None, step_on_arrival: bool = True) -> None:
        self.rig = rig
        self.silence = silence
        self.controller = controller
        self.period = 1.0 / rate
        self.clock = clock or SimClock()
        self.gate = gate or ObservationGate.for_camera(GateConfig(), rig.camera)
        self.step_on_arrival = step_on_arrival

    def _wait(self, deadline: float) -> tuple[float, float, bool]:
        """Until the deadline or, on the wall clock with a live source, an earlier arrival:
        (tick time s, lateness s, early)."""
        clock, source = self.clock, self.rig.observations
        while True:
            remaining = deadline - clock.now()
            if remaining <= _FINISH:
                return deadline, clock.sleep_until(deadline), False
            if source.wait_arrival(remaining - _FINISH):
                now = clock.now()
                if now < deadline:
                    return now, 0.0, True
                return deadline, now - deadline, False   # woken too late (a loaded host): a late tick

    def run(self, seconds: float, on_tick: Callable[[Tick], None] | None = None) -> int:
        """Run for ``seconds`` (s); returns the number of ticks executed."""
        rig, ctrl, drives, gate = self.rig, self.controller, self.rig.drives, self.gate
        rpt = drives.rad_per_tick
        if not drives.homed:
            drives.home()
        self.clock.start()
        rig.start_clock()                 # hardware rigs align their clock with the loop's
        gate.reset()
        early_ticks = self.step_on_arrival and self.clock.realtime and rig.observations.signals_arrivals
        last_seen = 0.0
        ctrl.reset(drives.positions() * rpt, 0.0)
        n = int(round(seconds / self.period))
        tick = Tick()
        done = 0
        try:
            for k in range(1, n + 1):
                deadline = k * self.period
                if early_ticks:
                    t, tick.lateness, tick.early = self._wait(deadline)
                else:
                    t, tick.lateness = deadline, self.clock.sleep_until(deadline)
                with deferred():          # a stop signal waits for the end of the tick
                    rig.advance(t)
                    # The gate judges capture times against the clock's now: a late tick runs after t.
                    arrived = gate.admit(rig.observations.poll(t), self.clock.now())
                    obs = arrived[-1] if arrived else None
                    if obs is not None:
                        last_seen = t
                        drives.note_observation(obs.valid, t)
                    elif t - last_seen > self.silence:
                        drives.note_observation(False, t)  # no plausible frames at all counts as lost
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
