"""The safety supervisor: each rule against a small fake Drives, then around the real CANopen driver."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from targetlock.interfaces.errors import MotionRefused
from targetlock.interfaces.od402 import State
from targetlock.interfaces.safety import SafeDrives, SafetyConfig, SafetyTrip
from targetlock.rig.base import DriveFault, Drives

from iface_helpers import rig


class FakeDrives(Drives):
    """Records what reaches the 'motors'."""

    def __init__(self):
        self._homed = False
        self.sent: list[list[int]] = []
        self.pos = np.zeros(2, dtype=np.int64)
        self.fault_text: str | None = None
        self.fail_send: Exception | None = None
        self.persistent = False
        self.powered = True
        self.disables = 0
        self.enables = 0
        self.closed = False
        self.lock = threading.Lock()
        self.events: list[str] = []

    @property
    def homed(self):
        return self._homed

    def home(self):
        self._homed = True

    def send_setpoints(self, ticks):
        with self.lock:
            if self.fail_send is not None:
                raise self.fail_send
            self.events.append("send" if self.powered else "send-while-disabled")
            t = np.asarray(ticks)
            assert t.dtype == np.int64
            self.sent.append(t.tolist())
            self.pos = t.copy()

    def positions(self):
        return self.pos.copy()

    @property
    def limits(self):
        return np.array([-1000, -2000]), np.array([1000, 2000])

    @property
    def rad_per_tick(self):
        return 1e-3

    def fault(self):
        return self.fault_text

    def disable(self):
        with self.lock:
            self.powered = False
            self.disables += 1
            self.events.append("disable")

    def enable(self):
        if self.persistent:
            raise DriveFault("fault reset failed: STO active")
        self.fault_text = None
        self.powered = True
        self.enables += 1
        self.events.append("enable")

    def close(self):
        self.closed = True


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def make(max_rate=1.0, hold=0.5, monitor=0.0):
    fake, clock = FakeDrives(), Clock()
    safe = SafeDrives(fake, SafetyConfig(max_rate=max_rate, target_lost_hold=hold, monitor_period=monitor,
                                         max_step_interval=0.1), clock=clock)
    return fake, clock, safe


def test_no_motion_before_homing():
    fake, clock, safe = make()
    with safe:
        with pytest.raises(MotionRefused, match="not homed"):
            safe.send_setpoints(np.array([10, 10]))
        assert fake.sent == []
        safe.home()
        safe.send_setpoints(np.array([10, 10]))
        assert fake.sent == [[10, 10]]


def test_setpoints_are_clamped_to_the_limits():
    fake, clock, safe = make(max_rate=100.0)
    with safe:
        safe.home()
        safe.send_setpoints(np.array([5000, -5000]))
        assert fake.sent[-1] == [1000, -2000]
        assert safe.stats.clamped == 1


def test_rate_limit_in_ticks_per_second():
    fake, clock, safe = make(max_rate=1.0)          # 1 rad/s at 1e-3 rad/tick = 1000 tick/s
    with safe:
        safe.home()
        safe.send_setpoints(np.array([0, 0]))
        for _ in range(5):
            clock.t += 0.02
            safe.send_setpoints(np.array([500, -500]))
        assert fake.sent[1:] == [[20, -20], [40, -40], [60, -60], [80, -80], [100, -100]]
        clock.t += 5.0                               # a long pause does not allow a long jump
        safe.send_setpoints(np.array([500, -500]))
        assert fake.sent[-1] == [200, -200]
        assert safe.stats.rate_limited == 6
        clock.t += 0.02
        safe.send_setpoints(np.array([205, -195]))   # small steps pass unchanged
        assert fake.sent[-1] == [205, -195]


def test_non_finite_setpoints_are_never_sent():
    fake, clock, safe = make(max_rate=100.0)
    with safe:
        safe.home()
        safe.send_setpoints(np.array([100, 200]))
        clock.t += 0.02
        safe.send_setpoints(np.array([np.nan, 300.0]))
        assert fake.sent[-1] == [100, 300]
        clock.t += 0.02
        safe.send_setpoints(np.array([np.inf, -np.inf]))
        assert fake.sent[-1] == [100, 300]
        assert safe.stats.nonfinite == 2
        assert all(np.isfinite(s).all() for s in fake.sent)


def test_target_lost_for_too_long_holds_the_drives():
    fake, clock, safe = make(max_rate=100.0, hold=0.5)
    with safe:
        safe.home()
        safe.note_observation(True, 0.0)
        safe.send_setpoints(np.array([10, 10]))
        safe.note_observation(False, 0.1)
        safe.note_observation(False, 0.5)
        clock.t += 0.02
        safe.send_setpoints(np.array([20, 20]))      # lost 0.4 s < 0.5 s: still commanding
        assert fake.sent[-1] == [20, 20] and not safe.holding
        safe.note_observation(False, 0.7)            # lost 0.6 s
        assert safe.holding
        n = len(fake.sent)
        for _ in range(3):
            clock.t += 0.02
            safe.send_setpoints(np.array([900, 900]))
        assert len(fake.sent) == n and safe.stats.held == 3
        safe.note_observation(True, 0.8)
        clock.t += 0.02
        safe.send_setpoints(np.array([900, 900]))
        assert fake.sent[-1] == [900, 900] and not safe.holding


def test_drive_fault_trips_and_requires_explicit_enable():
    fake, clock, safe = make(max_rate=100.0)
    with safe:
        safe.home()
        safe.send_setpoints(np.array([10, 10]))
        fake.fault_text = "node 1: EMCY 0x2310 (continuous over-current)"
        with pytest.raises(SafetyTrip, match="0x2310"):
            safe.send_setpoints(np.array([20, 20]))
        assert fake.disables == 1 and "0x2310" in safe.fault()
        fake.fault_text = None                        # the fault went away by itself ...
        with pytest.raises(SafetyTrip):               # ... but the supervisor stays tripped
            safe.send_setpoints(np.array([20, 20]))
        with pytest.raises(SafetyTrip):
            safe.home()
        safe.enable()
        assert fake.enables == 1 and safe.fault() is None
        clock.t += 0.02
        safe.send_setpoints(np.array([20, 20]))
        assert fake.sent[-1] == [20, 20]


def test_exceptions_from_the_drives_trip_bus_and_heartbeat_loss():
    fake, clock, safe = make(max_rate=100.0)
    with safe:
        safe.home()
        fake.fail_send = DriveFault("node 2: heartbeat lost (none for more than 100 ms)")
        with pytest.raises(SafetyTrip, match="heartbeat lost"):
            safe.send_setpoints(np.array([10, 10]))
        assert fake.disables == 1 and "heartbeat lost" in safe.fault()
        fake.fail_send = None
        fake.persistent = True
        with pytest.raises(SafetyTrip, match="enable failed"):
            safe.enable()
        assert safe.tripped
        fake.persistent = False
        safe.enable()
        assert not safe.tripped


def test_monitor_thread_trips_without_any_call():
    fake, clock, safe = make(monitor=0.01)
    with safe:
        safe.home()
        fake.fault_text = "CAN bus error: interface down"
        deadline = time.monotonic() + 1.0
        while fake.disables == 0 and time.monotonic() < deadline:
            time.sleep(0.005)
        assert fake.disables >= 1 and safe.tripped
        assert "interface down" in safe.fault()


def test_emergency_stop_from_another_thread_is_immediate_and_final():
    fake, clock, safe = make(max_rate=1000.0)
    safe.home()
    errors = []
    sent_after_stop = []
    stopped = threading.Event()

    def loop():
        k = 0
        while k < 100000:
            k += 1
            clock.t += 0.001
            try:
                safe.send_setpoints(np.array([k % 900, 0]))
                if stopped.is_set() and fake.disables:
                    sent_after_stop.append(k)
            except SafetyTrip:
                return
            except Exception as exc:   # noqa: BLE001
                errors.append(exc)
                return

    t = threading.Thread(target=loop)
    t.start()
    time.sleep(0.05)
    safe.emergency_stop("operator pressed stop")
    stopped.set()
    t.join(2.0)
    assert not t.is_alive() and not errors
    assert fake.disables >= 1 and not fake.powered
    assert "operator pressed stop" in safe.fault()
    assert len(sent_after_stop) <= 1                # at most the one already in flight
    # the drives' last command is a disable; a set-point in flight during the stop is followed by one
    first_disable = fake.events.index("disable")
    after = fake.events[first_disable:]
    assert after[-1] == "disable"
    assert after.count("send-while-disabled") <= 1
    safe.close()


def test_emergency_stop_race_many_times():
    for _ in range(30):
        fake, clock, safe = make(max_rate=1000.0)
        safe.home()
        go = threading.Event()

        def loop():
            go.wait()
            for k in range(2000):
                try:
                    safe.send_setpoints(np.array([k % 50, 0]))
                except SafetyTrip:
                    return

        t = threading.Thread(target=loop)
        t.start()
        go.set()
        time.sleep(0.002)
        safe.emergency_stop()
        t.join(2.0)
        assert fake.events[-1] == "disable", fake.events[-5:]
        assert "send" not in fake.events[fake.events.index("disable") + 1:]
        safe.close()


def test_context_manager_disables_on_exception_and_ctrl_c():
    for exc in (RuntimeError("controller crashed"), KeyboardInterrupt()):
        fake, clock, safe = make()
        with pytest.raises(type(exc)):
            with safe:
                safe.home()
                raise exc
        assert fake.disables == 1 and fake.closed and not fake.powered
        safe.close()                                  # idempotent
        assert fake.disables == 1
        with pytest.raises(SafetyTrip):
            safe.send_setpoints(np.array([0, 0]))


def test_disable_requires_enable():
    fake, clock, safe = make()
    with safe:
        safe.home()
        safe.disable()
        with pytest.raises(SafetyTrip, match="disabled on request"):
            safe.send_setpoints(np.array([0, 0]))
        safe.enable()
        safe.send_setpoints(np.array([0, 0]))


def test_around_the_canopen_driver():
    """Emergency stop while a loop streams set-points to the simulated drives; explicit enable resumes."""
    with rig() as (cfg, sims, drives):
        safe = SafeDrives(drives, SafetyConfig(monitor_period=0.01), close_inner=False)
        with safe:
            safe.home()
            stop = threading.Event()
            failures = []

            def loop():
                k = 0
                while not stop.is_set():
                    k += 1
                    try:
                        safe.send_setpoints(np.array([20 * k, -20 * k]))
                    except SafetyTrip:
                        failures.append(k)
                    time.sleep(0.01)

            t = threading.Thread(target=loop)
            t.start()
            time.sleep(0.15)
            safe.emergency_stop()
            time.sleep(0.05)
            assert [s.state for s in sims.drives] == [State.SWITCH_ON_DISABLED] * 2
            assert failures
            safe.enable()
            time.sleep(0.1)
            stop.set()
            t.join(2.0)
            assert [s.state for s in sims.drives] == [State.OPERATION_ENABLED] * 2
            # a drive fault found by the monitor thread, not by a call
            sims[cfg.node_ids[0]].inject_fault(0x7121)
            deadline = time.monotonic() + 1.0
            while not safe.tripped and time.monotonic() < deadline:
                time.sleep(0.005)
            assert safe.tripped and "0x7121" in safe.fault()
        assert sims[cfg.node_ids[1]].state == State.SWITCH_ON_DISABLED
