import threading
import time

import numpy as np
import pytest

from targetlock.controllers import ControllerConfig, KnowledgeConfig
from targetlock.experiments.target_lock import RunConfig, build_controller, build_rig
from targetlock.loop.clock import SimClock, WallClock
from targetlock.loop.runner import ControlLoop
from targetlock.model.twin import twin_config
from targetlock.rig.base import HandoffSource, Observation, Rig


def rig_and_ctrl(latency=0.4, **scene):
    import dataclasses
    twin = twin_config()
    twin = dataclasses.replace(twin, camera=dataclasses.replace(twin.camera, latency=latency),
                               scene=dataclasses.replace(twin.scene, **scene))
    # The lab measured the latency: the rig stamps frames with the true one.
    cfg = RunConfig(twin=twin, controller=ControllerConfig(kind="pi"), knowledge=KnowledgeConfig(latency=latency))
    rig = build_rig(cfg)
    return rig, build_controller(cfg, rig)


@pytest.mark.parametrize("latency", [0.0, 0.1, 0.4, 0.75])
def test_observations_arrive_after_the_configured_latency(latency):
    rig, ctrl = rig_and_ctrl(latency)
    ages = []
    ControlLoop(rig, ctrl, rate=50).run(3.0, lambda tick: tick.observation is not None and
                                         ages.append(tick.time - tick.observation.capture_time))
    ages = np.array(ages)
    assert ages.min() >= latency - 1e-9
    assert ages.max() <= latency + 0.02 + 1e-9   # delivered at the first tick after arrival
    assert len(ages) == pytest.approx(3.0 * 22 - latency * 22, abs=2)


class WorkClock(SimClock):
    """Simulated time in which the work of a tick takes time too (``work`` s are added by the test)."""

    def sleep_until(self, deadline):
        late = max(0.0, self._t - deadline)
        self._t = max(self._t, deadline)
        return late


def test_a_late_tick_does_not_shift_the_deadlines_after_it():
    rig, ctrl = rig_and_ctrl()
    clock = WorkClock()
    late = []

    def slow_once(tick):
        late.append(tick.lateness)
        if tick.index == 5:
            clock._t += 0.05  # this tick overruns by 2.5 periods

    assert ControlLoop(rig, ctrl, rate=50, clock=clock).run(0.6, slow_once) == 30
    np.testing.assert_allclose(late[5:7], [0.03, 0.01], atol=1e-12)   # the next two start late...
    assert max(late[:5]) == 0.0 and max(late[7:]) == 0.0              # ...then on the original grid again
    assert clock.now() == pytest.approx(0.6)


def test_ticks_run_on_absolute_deadlines_on_the_wall_clock():
    rig, ctrl = rig_and_ctrl()
    times = []

    def slow_sometimes(tick):
        times.append(tick.time)
        if tick.index == 5:
            time.sleep(0.1)  # one tick overruns by 5 periods

    t0 = time.perf_counter()
    n = ControlLoop(rig, ctrl, rate=50, clock=WallClock()).run(0.6, slow_sometimes)
    wall = time.perf_counter() - t0
    assert n == 30
    np.testing.assert_allclose(times, np.arange(1, 31) * 0.02)
    assert 0.6 <= wall < 0.68          # shifted deadlines would end at 0.7 s


def test_a_starved_wall_clock_loop_skips_slots_instead_of_falling_behind_without_bound():
    from targetlock.loop.runner import MAX_BEHIND
    rig, ctrl = rig_and_ctrl()
    late, skipped, times = [], [], []

    def starved(tick):                 # every tick takes two periods: the host cannot keep 50 Hz
        late.append(tick.lateness)
        skipped.append(tick.skipped)
        times.append(tick.time)
        time.sleep(0.04)

    t0 = time.perf_counter()
    n = ControlLoop(rig, ctrl, rate=50, clock=WallClock()).run(1.0, starved)
    wall = time.perf_counter() - t0
    assert n < 50 and sum(skipped) > 0           # slots were skipped...
    assert max(late) < MAX_BEHIND + 0.2          # ...so the loop stays near the wall clock (catching up: ~1 s behind)
    assert wall < 1.6                            # and the run ends on time (catching up: 2 s)
    assert np.all(np.diff(times) > 0) and times[-1] == pytest.approx(1.0, abs=0.3)


def test_sim_clock_runs_deterministically():
    def once():
        rig, ctrl = rig_and_ctrl()
        rows = []
        ControlLoop(rig, ctrl, rate=50, clock=SimClock()).run(5.0, lambda t: rows.append(t.setpoint.copy()))
        return np.array(rows)
    np.testing.assert_array_equal(once(), once())


def test_no_motion_before_homing_and_the_loop_homes_first():
    rig, ctrl = rig_and_ctrl()
    with pytest.raises(RuntimeError, match="homing"):
        rig.drives.send_setpoints(np.array([1000, 0]))
    ControlLoop(rig, ctrl, rate=50).run(0.1)
    assert rig.drives.homed


def test_an_exception_in_a_tick_leaves_the_drives_disabled():
    rig, ctrl = rig_and_ctrl()
    disabled = []
    rig.drives.disable = lambda: disabled.append(True)

    def boom(tick):
        if tick.index == 10:
            raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        ControlLoop(rig, ctrl, rate=50).run(1.0, boom)
    assert disabled == [True]


def test_the_loop_calls_the_declared_hooks_start_clock_and_note_observation():
    rig, ctrl = rig_and_ctrl()
    calls = []
    rig.start_clock = lambda: calls.append(("start_clock", rig.drives.homed))
    rig.drives.note_observation = lambda valid, now: calls.append(("note", valid, now))
    ControlLoop(rig, ctrl, rate=50).run(1.0)
    assert calls[0] == ("start_clock", True)                 # after homing, before the first tick
    notes = [c[1:] for c in calls if c[0] == "note"]
    first_frame = next(t for valid, t in notes if valid)
    assert first_frame == pytest.approx(0.4, abs=0.021)     # the first frame, after the 0.4 s latency
    silent = [t for valid, t in notes if t < first_frame]
    assert silent and min(silent) > 0.25 and not any(v for v, t in notes if t < first_frame)  # silence = lost
    assert all(valid for valid, t in notes if t >= first_frame)


class PacedSource(HandoffSource):
    """A live source: a thread delivers an observation every 1/fps s of wall time."""

    def __init__(self, fps):
        super().__init__()
        self.fps, self.t0, self.stop = fps, time.monotonic(), threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        k, w0 = 0, time.monotonic()
        while not self.stop.wait(max(0.0, w0 + k / self.fps - time.monotonic())):
            now = time.monotonic() - self.t0
            self.deliver(Observation(capture_time=now - 0.05, offset=np.array([3.0, 1.0]), valid=True,
                                     frame_index=k, arrival_time=now))
            k += 1

    def close(self):
        self.stop.set()
        self.thread.join()


class LiveTwin(Rig):
    def __init__(self, fps):
        self.sim, _ = rig_and_ctrl()
        self.drives, self.camera = self.sim.drives, self.sim.camera
        self.observations = PacedSource(fps)

    def start_clock(self):
        self.observations.t0 = time.monotonic()

    def advance(self, until):
        self.sim.advance(until)


@pytest.mark.parametrize("early", [True, False])
def test_on_the_wall_clock_an_arrival_runs_the_next_tick_at_once_at_most_one_per_period(early):
    rig = LiveTwin(fps=7.3)                      # not locked to the loop: arrivals at every phase
    ctrl = build_controller(RunConfig(controller=ControllerConfig(kind="pi")), rig)
    ticks = []
    try:
        n = ControlLoop(rig, ctrl, rate=20, clock=WallClock(), step_on_arrival=early).run(
            1.5, lambda tk: ticks.append((tk.index, tk.time, tk.early, tk.observation is not None)))
    finally:
        rig.observations.close()
    assert n == 30 and [t[0] for t in ticks] == list(range(1, 31))
    period = 0.05
    for k, t, is_early, _ in ticks:              # tick k runs in its own slot ((k-1)·period, k·period]
        assert (k - 1) * period < t <= k * period + 1e-12
        assert is_early == (t < k * period)
    with_obs = [t for t in ticks if t[3]]
    assert len(with_obs) >= 8
    if early:
        assert sum(t[2] for t in with_obs) >= 0.7 * len(with_obs)   # served on arrival, not at the deadline
        assert not any(t[2] for t in ticks if not t[3])             # no early tick without an arrival
    else:
        assert not any(t[2] for t in ticks)


def test_the_simulated_clock_never_runs_early_ticks():
    rig, ctrl = rig_and_ctrl()
    times = []
    ControlLoop(rig, ctrl, rate=50, step_on_arrival=True).run(1.0, lambda tk: times.append(tk.time))
    np.testing.assert_allclose(times, np.arange(1, 51) * 0.02)
