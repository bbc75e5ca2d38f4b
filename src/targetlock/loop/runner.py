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
# s: on the wall clock a loop further behind its deadlines than this skips the slots that have passed. A
# short stall is caught up (the ticks after it run late, on the original grid); a starved host would
# otherwise fall behind without bound, and frames judged against the wall clock would all become too
# old for the gate (the lock then holds, target "lost", while the frames are fine).
MAX_BEHIND = 0.2


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
    skipped: int = 0                         # slots skipped just before this tick (a starved wall-clock loop)


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

    def begin(self) -> None:
        """Home the drives if needed (no motion before homing), start the clock at t = 0 and engage
        the controller at the measured motor position. Then call :meth:`tick` once per period."""
        rig, drives = self.rig, self.rig.drives
        if not drives.homed:
            drives.home()
        self.clock.start()
        rig.start_clock()                 # hardware rigs align their clock with the loop's
        self.gate.reset()
        self._early = self.step_on_arrival and self.clock.realtime and rig.observations.signals_arrivals
        self._last_seen = 0.0
        self._k = 0
        self._tick = Tick()
        self._limits = drives.limits
        positions = drives.positions()
        self._held = np.asarray(positions, dtype=float)
        self.controller.reset(positions * drives.rad_per_tick, 0.0)

    def tick(self) -> Tick:
        """Run the next tick: :meth:`observe`, then :meth:`act` with the controller's set-point.
        Returns the (reused) :class:`Tick`. On any exception the drives are disabled first."""
        with deferred():          # a stop signal waits for the end of the whole tick
            self.observe()
            return self.act()

    def observe(self) -> Tick:
        """First half of a tick: wait for its deadline (or earlier, see the module doc), advance the rig,
        gate the newest observation and read the motors. Fills ``index``, ``time``, ``lateness``,
        ``early``, ``observation`` and ``motor`` of the returned :class:`Tick`."""
        rig, drives, tick = self.rig, self.rig.drives, self._tick
        try:
            k = self._k + 1
            tick.skipped = 0
            if self.clock.realtime:
                now = self.clock.now()
                if now - k * self.period > MAX_BEHIND:
                    tick.skipped = int(now / self.period) - k
                    k += tick.skipped
            deadline = k * self.period
            if self._early:
                t, tick.lateness, tick.early = self._wait(deadline)
            else:
                t, tick.lateness = deadline, self.clock.sleep_until(deadline)
            with deferred():          # a stop signal waits for the end of the tick
                rig.advance(t)
                # The gate judges capture times against the clock's now: a late tick runs after t.
                arrived = self.gate.admit(rig.observations.poll(t), self.clock.now())
                obs = arrived[-1] if arrived else None
                if obs is not None:
                    self._last_seen = t
                    drives.note_observation(obs.valid, t)
                elif t - self._last_seen > self.silence:
                    drives.note_observation(False, t)  # no plausible frames at all counts as lost
                tick.motor = drives.positions() * drives.rad_per_tick
                tick.index, tick.time, tick.observation = k, t, obs
                self._k = k
            return tick
        except BaseException:
            drives.disable()
            raise

    def act(self) -> Tick:
        """Second half of a tick: the controller's set-point from this tick's observation and motors,
        clipped to the drives' limits before the integer cast, sent. Fills ``setpoint``, ``ticks``, ``sent``."""
        drives, tick = self.rig.drives, self._tick
        try:
            with deferred():
                assert tick.motor is not None, "act() before observe()"
                setpoint = self.controller.step(tick.observation, tick.motor, tick.time)
                raw = setpoint / drives.rad_per_tick
                if np.all(np.isfinite(raw)):
                    # clipped before the integer cast: a huge finite value must not wrap to the other limit
                    self._held = np.clip(raw, *self._limits)
                ticks = np.rint(self._held).astype(np.int64)
                drives.send_setpoints(ticks)
                tick.sent = self.clock.now()
                tick.setpoint, tick.ticks = setpoint, ticks
            return tick
        except BaseException:
            drives.disable()
            raise

    def run(self, seconds: float, on_tick: Callable[[Tick], None] | None = None) -> int:
        """Run for ``seconds`` (s); returns the number of ticks executed (fewer than ``seconds`` × rate only
        when a starved wall-clock loop skipped slots: :data:`MAX_BEHIND`)."""
        self.begin()
        n, executed = int(round(seconds / self.period)), 0
        try:
            while self._k < n:
                tick = self.tick()
                executed += 1
                if on_tick is not None:
                    on_tick(tick)
        except BaseException:
            self.rig.drives.disable()
            raise
        return executed
