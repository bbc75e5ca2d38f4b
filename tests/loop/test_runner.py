import time

import numpy as np
import pytest

from targetlock.controllers import ControllerConfig, make_controller
from targetlock.experiments.target_lock import RunConfig, build_controller, build_rig
from targetlock.loop.clock import SimClock, WallClock
from targetlock.loop.runner import ControlLoop
from targetlock.model.twin import twin_config


def rig_and_ctrl(latency=0.4, **scene):
    import dataclasses
    twin = twin_config()
    twin = dataclasses.replace(twin, camera=dataclasses.replace(twin.camera, latency=latency),
                               scene=dataclasses.replace(twin.scene, **scene))
    cfg = RunConfig(twin=twin, controller=ControllerConfig(kind="pi"))
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


def test_ticks_run_on_absolute_deadlines_on_the_wall_clock():
    rig, ctrl = rig_and_ctrl()
    times, late = [], []

    def slow_sometimes(tick):
        times.append(tick.time)
        late.append(tick.lateness)
        if tick.index == 5:
            time.sleep(0.05)  # one tick overruns by 2.5 periods

    clock = WallClock()
    t0 = time.perf_counter()
    n = ControlLoop(rig, ctrl, rate=50, clock=clock).run(0.6, slow_sometimes)
    wall = time.perf_counter() - t0
    assert n == 30
    np.testing.assert_allclose(times, np.arange(1, 31) * 0.02)
    assert wall == pytest.approx(0.6, abs=0.06)          # the overrun did not shift later deadlines
    assert max(late[6:9]) > 0.0 and max(late[12:]) < 0.01  # late right after, on time again later


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
