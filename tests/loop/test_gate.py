"""The plausibility gate: impossible observations never reach a controller, are counted and logged."""
from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np
import pytest

from targetlock.controllers import CONTROLLERS, ControllerConfig
from targetlock.experiments.target_lock import RunConfig, build_controller, build_rig
from targetlock.loop.gate import GateConfig, ObservationGate
from targetlock.loop.runner import ControlLoop
from targetlock.model.camera import CameraParams
from targetlock.rig.base import Observation

CAM = CameraParams()


def obs(t, x=10.0, y=-5.0, valid=True, confidence=1.0):
    return Observation(capture_time=t, offset=np.array([x, y]), valid=valid, confidence=confidence)


def gate():
    return ObservationGate.for_camera(GateConfig(margin_px=20.0, max_extra_age=1.0, max_future=0.05), CAM)


@pytest.mark.parametrize("bad, reason", [
    (obs(math.nan), "time_not_finite"),
    (obs(math.inf), "time_not_finite"),
    (obs(10.2), "time_in_future"),
    (obs(10.0 - CAM.latency - 1.01), "too_old"),
    (obs(9.5, x=1e300), "outside_image"),
    (obs(9.5, x=CAM.width - CAM.cx + 21.0), "outside_image"),
    (obs(9.5, y=-CAM.cy - 21.0), "outside_image"),
    (obs(9.5, x=math.nan), "offset_not_finite"),
    (obs(9.5, confidence=math.nan), "confidence_not_finite"),
])
def test_implausible_observations_are_rejected_with_their_reason(bad, reason):
    g = gate()
    assert g.reason(bad, now=10.0) == reason
    assert g.admit([bad], now=10.0) == [] and g.rejected == {reason: 1}


def test_plausible_observations_pass_including_a_lost_target_and_the_image_edge():
    g = gate()
    ok = [obs(9.5, x=CAM.width - CAM.cx + 19.0), obs(9.55, valid=False, x=math.nan, y=math.nan),
          obs(9.6, x=-CAM.cx, y=CAM.height - CAM.cy), obs(10.04)]
    assert g.admit(ok, now=10.0) == ok and g.n_rejected == 0


def test_a_capture_time_going_backwards_is_rejected_and_the_next_good_one_passes(caplog):
    g = gate()
    with caplog.at_level(logging.WARNING, logger="targetlock.loop.gate"):
        assert len(g.admit([obs(9.6)], now=10.0)) == 1
        assert g.admit([obs(9.5)], now=10.0) == []
        assert len(g.admit([obs(9.7)], now=10.1)) == 1
    assert g.rejected == {"time_backwards": 1}
    assert "time backwards" in caplog.text


class Injecting:
    """The twin's observations with implausible ones mixed in (the newest of a poll, so the loop would
    use them), at several moments of the run."""

    def __init__(self, inner, bad_at):
        self.inner, self.bad_at = inner, dict(bad_at)
        self.signals_arrivals = False

    def poll(self, now):
        got = self.inner.poll(now)
        for t in [t for t in self.bad_at if t <= now]:
            got.append(self.bad_at.pop(t)(now))
        return got

    def __getattr__(self, name):
        return getattr(self.inner, name)


BAD = {
    1.0: lambda now: obs(now - 0.4, x=1e300, y=1e300),            # the wild tracker output
    1.5: lambda now: obs(math.nan),                                # a non-finite capture time
    2.0: lambda now: obs(now + 100.0),                             # from the future
    2.5: lambda now: obs(now - 50.0),                              # ages old
    3.0: lambda now: obs(-math.inf, x=-1e300),
    3.5: lambda now: obs(now - 0.4, x=math.inf),
}


def trajectory(kind, bad_at=None):
    cfg = RunConfig(controller=ControllerConfig(kind=kind))
    cfg = dataclasses.replace(cfg, twin=dataclasses.replace(cfg.twin, scene=dataclasses.replace(
        cfg.twin.scene, path="step", start_tip_deg=(0.0, 0.0), start_delay=0.5)))
    rig = build_rig(cfg)
    if bad_at:
        rig.observations = Injecting(rig.observations, bad_at)
    loop = ControlLoop(rig, build_controller(cfg, rig), rate=50)
    rows = []
    loop.run(6.0, lambda tick: rows.append(tick.setpoint.copy()))
    return np.array(rows), loop.gate


@pytest.mark.parametrize("kind", CONTROLLERS)
def test_wild_observations_neither_freeze_nor_nan_any_controller(kind):
    clean, _ = trajectory(kind)
    hit, g = trajectory(kind, BAD)
    assert np.all(np.isfinite(hit))
    np.testing.assert_array_equal(hit, clean)                 # the controller never saw them
    assert np.abs(hit[-1] - hit[50]).max() > 1e-3              # it kept steering after the first one
    assert g.n_rejected == len(BAD)


def test_a_late_tick_judges_capture_times_against_the_clock_not_the_tick_time():
    from targetlock.loop.clock import SimClock

    class LateClock(SimClock):
        def now(self):
            return self._t + 0.2          # every tick runs 0.2 s after its deadline (a loaded host)

    rig = build_rig(RunConfig())
    fresh = {1.0: lambda now: obs(now + 0.15)}   # captured after the tick's nominal time, before now
    rig.observations = Injecting(rig.observations, fresh)
    loop = ControlLoop(rig, build_controller(RunConfig(), rig), rate=50, clock=LateClock())
    seen = []
    loop.run(1.5, lambda tick: tick.observation is not None and seen.append(tick.observation.capture_time))
    assert "time_in_future" not in loop.gate.rejected
    assert max(seen) == pytest.approx(1.15)               # the fresh one reached the controller
