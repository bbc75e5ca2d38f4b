"""Safety supervisor around any :class:`~targetlock.rig.base.Drives`: the only way the loop reaches the motors.

:class:`SafeDrives` enforces, whatever the controller asks:

* no motion before homing (:class:`~.errors.MotionRefused`);
* set-points clamped to the drives' limits, then rate limited to ``max_rate`` (rad/s, converted
  to ticks/s with the drives' ``rad_per_tick``) relative to the last set-point sent;
* non-finite set-points (NaN, inf) are never sent: that axis holds its last set-point;
* target lost for longer than ``target_lost_hold`` (reported through
  :meth:`SafeDrives.note_observation`): no new set-points, the drives hold, until the target is back;
* a drive fault, bus loss or heartbeat loss (an exception from the drives, or their ``fault()``
  found by the monitor thread) trips the supervisor: it disables the drives, records the reason
  (:meth:`SafeDrives.fault`), refuses every command with :class:`SafetyTrip`, and stays tripped
  until an explicit :meth:`SafeDrives.enable` succeeds;
* :meth:`SafeDrives.emergency_stop` from any thread trips and disables at once;
* :meth:`SafeDrives.close` (also on leaving the ``with`` block, on exceptions, Ctrl-C, and at
  interpreter exit) disables the drives.
"""
from __future__ import annotations

import atexit
import logging
import threading
import time
import weakref
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..config import param
from ..rig.base import DriveFault, Drives
from .errors import MotionRefused

__all__ = ["SafetyConfig", "SafeDrives", "SafetyTrip", "SafetyStats"]

log = logging.getLogger(__name__)


class SafetyTrip(DriveFault):
    """The supervisor is tripped (fault, stop or disable); commands are refused until enable()."""


@dataclass(frozen=True)
class SafetyConfig:
    max_rate: float = param(1.6, unit="rad/s", lo=1e-4, hi=100.0,
                            doc="largest set-point change per second and axis (1.6 rad/s = 100000 tick/s)")
    max_step_interval: float = param(0.1, unit="s", lo=0.001, hi=10.0,
                                     doc="a pause between set-points longer than this allows no bigger step")
    target_lost_hold: float = param(0.5, unit="s", lo=0.0, hi=60.0,
                                    doc="hold the last set-point once the target has been lost this long")
    monitor_period: float = param(0.02, unit="s", lo=0.0, hi=1.0,
                                  doc="poll the drives for faults this often in the background; 0 = only on calls")


@dataclass
class SafetyStats:
    sent: int = 0
    clamped: int = 0
    rate_limited: int = 0
    nonfinite: int = 0
    held: int = 0
    refused: int = 0
    trips: list[str] = field(default_factory=list)


class SafeDrives(Drives):
    """Wraps ``inner`` (any :class:`Drives`); thread-safe; use as a context manager.

    ``clock``: monotonic seconds for the rate limit; ``close_inner``: also call ``inner.close()``
    (if it has one) in :meth:`close`.
    """

    def __init__(self, inner: Drives, config: SafetyConfig = SafetyConfig(), *,
                 clock: Callable[[], float] = time.monotonic, close_inner: bool = True) -> None:
        self.inner = inner
        self.config = config
        self.clock = clock
        self.close_inner = close_inner
        self.n_axes = inner.n_axes
        self.stats = SafetyStats()
        self._lock = threading.RLock()          # command path (may wait on the bus)
        self._state = threading.Lock()          # trip state; never held while talking to the drives
        self._send_gate = threading.Lock()      # held only around the drives' send_setpoints call
        self._in_flight = False                 # a set-point is being sent (guarded by _state)
        self._tripped: str | None = None
        self._last: np.ndarray | None = None
        self._last_time: float | None = None
        self._lost_since: float | None = None
        self._holding = False
        self._closed = False
        self._monitor_stop = threading.Event()
        self._monitor: threading.Thread | None = None
        if config.monitor_period > 0:
            self._monitor = threading.Thread(target=self._watch, name="safety-monitor", daemon=True)
            self._monitor.start()
        ref = weakref.ref(self)

        def _at_exit() -> None:
            obj = ref()
            if obj is not None:
                obj.close()
        self._atexit = _at_exit
        atexit.register(_at_exit)

    # ---------------------------------------------------------------- trip handling

    def _trip(self, reason: str) -> None:
        """Latch ``reason`` (the first one is kept) and disable the drives at once.

        The drives are disabled immediately, without waiting for a set-point that another thread
        may be sending; if one was in flight, they are disabled once more after it, so the last
        command the drives get is always the disable.
        """
        with self._state:
            first = self._tripped is None
            if first:
                self._tripped = reason
                self.stats.trips.append(reason)
            in_flight = self._in_flight
        if first:
            log.error("safety stop: %s", reason)
        self._disable_inner()
        if in_flight:
            got = self._send_gate.acquire(timeout=5.0)   # wait for that set-point to be out ...
            try:
                self._disable_inner()                    # ... and disable once more after it
            finally:
                if got:
                    self._send_gate.release()

    def _disable_inner(self) -> None:
        try:
            self.inner.disable()
        except Exception as exc:  # noqa: BLE001 - a stop must never raise; the reason is recorded
            log.error("disabling the drives failed: %s", exc)

    def _refuse_if_tripped(self) -> None:
        with self._state:
            reason = self._tripped
        if reason is not None:
            self.stats.refused += 1
            raise SafetyTrip(f"drives stopped: {reason} (call enable() to resume)")

    def _check_inner_fault(self) -> None:
        fault = self.inner.fault()
        if fault is not None:
            self._trip(f"drive fault: {fault}")
            self._refuse_if_tripped()

    def _watch(self) -> None:
        while not self._monitor_stop.wait(self.config.monitor_period):
            with self._state:
                tripped = self._tripped is not None
            if tripped or self._closed:
                continue
            try:
                fault = self.inner.fault()
            except Exception as exc:  # noqa: BLE001 - a monitor that cannot ask must stop the drives
                fault = f"fault() failed: {exc}"
            if fault is not None:
                self._trip(f"drive fault: {fault}")

    @property
    def tripped(self) -> bool:
        with self._state:
            return self._tripped is not None

    @property
    def holding(self) -> bool:
        """True while set-points are held because the target has been lost too long."""
        return self._holding

    def emergency_stop(self, reason: str = "emergency stop") -> None:
        """Trip and disable the drives now; safe to call from any thread (or a signal handler's thread)."""
        self._trip(reason)

    # ---------------------------------------------------------------- Drives interface

    @property
    def homed(self) -> bool:
        return self.inner.homed

    @property
    def limits(self) -> tuple[np.ndarray, np.ndarray]:
        return self.inner.limits

    @property
    def rad_per_tick(self) -> float:
        return self.inner.rad_per_tick

    def fault(self) -> str | None:
        with self._state:
            if self._tripped is not None:
                return self._tripped
        return self.inner.fault()

    def _call(self, what: str, fn: Callable[[], object]) -> object:
        try:
            return fn()
        except SafetyTrip:
            raise
        except MotionRefused as exc:
            with self._state:
                reason = self._tripped
            if reason is not None:      # refused because a stop came in meanwhile
                raise SafetyTrip(f"drives stopped: {reason} (call enable() to resume)") from exc
            raise
        except DriveFault as exc:
            self._trip(f"{what} failed: {exc}")
            raise SafetyTrip(f"drives stopped: {what} failed: {exc}") from exc

    def home(self) -> None:
        with self._lock:
            self._refuse_if_tripped()
            self._check_inner_fault()
            self._call("homing", self.inner.home)
            self._reset_reference()

    def _reset_reference(self) -> None:
        try:
            self._last = np.asarray(self.inner.positions(), dtype=float)
        except DriveFault as exc:
            self._trip(f"reading positions failed: {exc}")
            raise SafetyTrip(f"drives stopped: reading positions failed: {exc}") from exc
        self._last_time = None

    def send_setpoints(self, ticks: np.ndarray) -> None:
        """Command set-points (ticks) through the safety rules; may hold instead of sending."""
        with self._lock:
            self._refuse_if_tripped()
            self._check_inner_fault()
            if not self.inner.homed:
                self.stats.refused += 1
                raise MotionRefused("refusing motion: drives are not homed (call home() first)")
            sp = np.array(ticks, dtype=float).reshape(-1)
            if sp.shape != (self.n_axes,):
                raise ValueError(f"expected {self.n_axes} set-points, got {np.shape(ticks)}")
            if self._last is None:
                self._reset_reference()
            ref = self._last
            bad = ~np.isfinite(sp)
            if bad.any():
                self.stats.nonfinite += 1
                log.warning("non-finite set-point %s: holding those axes", sp.tolist())
                sp[bad] = ref[bad]
            if self._holding:
                self.stats.held += 1
                return
            lo, hi = self.inner.limits
            clipped = np.clip(sp, lo, hi)
            if np.any(clipped != sp):
                self.stats.clamped += 1
            now = self.clock()
            dt = self.config.max_step_interval if self._last_time is None else \
                min(max(now - self._last_time, 0.0), self.config.max_step_interval)
            max_step = self.config.max_rate / self.inner.rad_per_tick * dt
            step = np.clip(clipped - ref, -max_step, max_step)
            if np.any(step != clipped - ref):
                self.stats.rate_limited += 1
            out = np.rint(ref + step)
            out = np.clip(out, lo, hi).astype(np.int64)

            def send() -> None:
                with self._send_gate:
                    with self._state:                  # a stop may have come while we computed
                        refused = self._tripped is not None
                        self._in_flight = not refused
                    if refused:
                        self._refuse_if_tripped()
                    try:
                        self.inner.send_setpoints(out)
                    finally:
                        with self._state:
                            self._in_flight = False
            self._call("sending set-points", send)
            self._last = out.astype(float)
            self._last_time = now
            self.stats.sent += 1

    def positions(self) -> np.ndarray:
        return self._call("reading positions", self.inner.positions)

    def report(self) -> dict:
        """The supervisor's counts (sent, clamped, rate limited, held, refused, trips) and the drives' own figures."""
        s = self.stats
        return {"supervisor": {"sent": s.sent, "clamped": s.clamped, "rate_limited": s.rate_limited,
                               "nonfinite": s.nonfinite, "held": s.held, "refused": s.refused, "trips": list(s.trips)},
                "drives": self.inner.report()}

    def note_observation(self, valid: bool, now: float) -> None:
        """Tell the supervisor whether the target was seen at time ``now`` (s, the caller's clock)."""
        if valid:
            if self._holding:
                log.info("target back: resuming set-points")
            self._lost_since = None
            self._holding = False
            return
        if self._lost_since is None:
            self._lost_since = now
        if not self._holding and now - self._lost_since > self.config.target_lost_hold:
            log.warning("target lost for %.2f s: holding the drives", now - self._lost_since)
            self._holding = True

    def disable(self) -> None:
        """Disable the drives and trip: an explicit enable() is needed to move again."""
        self._trip("disabled on request")

    def is_disabled(self) -> bool | None:
        """What the drives themselves confirm about their power stage (None: they cannot tell)."""
        return self.inner.is_disabled()

    def enable(self) -> None:
        """Explicit resume: re-enable the drives (fault reset there) and clear the trip if healthy."""
        with self._lock:
            if self._closed:
                raise SafetyTrip("drives are closed")
            try:
                self.inner.enable()
            except DriveFault as exc:
                with self._state:
                    self._tripped = self._tripped or f"enable failed: {exc}"
                raise SafetyTrip(f"enable failed: {exc}") from exc
            fault = self.inner.fault()
            if fault is not None:
                raise SafetyTrip(f"drives still report a fault after enable: {fault}")
            with self._state:
                if self._tripped is not None:
                    log.info("safety trip cleared by enable() (was: %s)", self._tripped)
                self._tripped = None
            self._holding = False
            self._lost_since = None
            if self.inner.homed:
                self._reset_reference()
            else:
                self._last, self._last_time = None, None

    def close(self) -> None:
        """Disable the drives (and close them if ``close_inner``); idempotent."""
        if self._closed:
            return
        self._closed = True
        self._monitor_stop.set()
        try:
            with self._state:
                if self._tripped is None:
                    self._tripped = "closed"
            try:
                self.inner.disable()
            except Exception as exc:  # noqa: BLE001
                log.error("disabling the drives on close failed: %s", exc)
            if self.close_inner and hasattr(self.inner, "close"):
                try:
                    self.inner.close()
                except Exception as exc:  # noqa: BLE001
                    log.error("closing the drives failed: %s", exc)
        finally:
            if self._monitor is not None and self._monitor is not threading.current_thread():
                self._monitor.join(timeout=1.0)
            atexit.unregister(self._atexit)

    def __enter__(self) -> "SafeDrives":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            log.error("leaving the drives' context on %s: disabling", exc_type.__name__)
        self.close()
