"""Console pieces without a browser: engage/release and live controller replacement, the movable target."""
from __future__ import annotations

import numpy as np
import pytest

from targetlock.config import ConfigError
from targetlock.console.session import LockSwitch, MovableScene
from targetlock.controllers import ControllerConfig, make_controller
from targetlock.controllers.knowledge import nominal_knowledge
from targetlock.model.camera import CameraParams
from targetlock.model.scene import SceneParams
from targetlock.rig.base import Observation


def _pi(i_gain: float = 300.0):
    return make_controller(ControllerConfig(kind="pi", i_gain=i_gain), rad_per_tick=1e-4, lower=np.full(2, -3.0),
                           upper=np.full(2, 3.0), control_dt=0.02, knowledge=nominal_knowledge())


def _obs(t: float, off=(40.0, -20.0)) -> Observation:
    return Observation(capture_time=t, offset=np.array(off), valid=True, arrival_time=t)


def test_released_holds_engaged_moves_and_a_new_controller_starts_at_the_setpoint():
    sw = LockSwitch(_pi())
    motor = np.array([0.1, -0.2])
    sw.reset(motor, 0.0)
    t = 0.0
    for _ in range(20):                       # released: the handle holds still whatever the error
        t += 0.02
        assert np.array_equal(sw.step(_obs(t), motor, t), motor)
    sw.engage()
    for _ in range(20):
        t += 0.02
        sp = sw.step(_obs(t), motor, t)
    assert sw.locked and np.abs(sp - motor).max() > 1e-3          # engaged: the integrator moves the handle
    before = sp.copy()
    sw.replace(_pi(i_gain=10.0))
    t += 0.02
    after = sw.step(_obs(t), motor, t)
    assert sw.inner.cfg.i_gain == 10.0
    assert np.abs(after - before).max() < 10.0 * 1e-4 * 40 * 0.02 + 1e-9   # one small I step, no jump
    sw.release()
    t += 0.02
    held = sw.step(_obs(t), motor, t)
    t += 0.02
    assert np.array_equal(sw.step(_obs(t), motor, t), held) and not sw.locked


def test_target_path_switch_is_continuous_and_nudge_moves_by_pixels():
    cam = CameraParams()
    scene = MovableScene(SceneParams(path="linear", start_delay=0.0), cam, np.eye(4))
    p = scene.target_position(3.0)
    scene.set_path("static", 3.0)
    assert np.allclose(scene.target_position(3.0), p) and np.allclose(scene.target_position(9.0), p)
    scene.nudge(30.0, 0.0, 9.0)
    d = SceneParams().distance
    assert np.allclose(scene.target_position(9.0) - p, [30.0 * d / cam.fx, 0.0, 0.0])
    with pytest.raises(ConfigError, match="target path = 'spiral' is not allowed"):
        scene.set_path("spiral", 9.0)


def test_tuning_and_recording_keep_the_scope_the_running_lock_identified(tmp_path):
    """The console's tuning replaces the controller on the same scope: when the running `adaptive` lock
    has found a candidate scope other than the assumed one, the new controller (here pi-smith, which
    models the scope too) assumes that one and says so; a recording leaves it in identified_scope.toml
    for the next run, as `targetlock run` does."""
    import tomllib
    from pathlib import Path

    from targetlock.config import from_dict, to_dict
    from targetlock.console.session import ConsoleSession
    from targetlock.experiments.target_lock import RunConfig

    cfg = from_dict(RunConfig, {"controller": {"kind": "adaptive"}, "twin": {"scene": {"path": "static"}}})
    session = ConsoleSession(cfg, runs_root=str(tmp_path))
    adaptive = session.switch.inner
    adaptive.reset(np.zeros(2), 0.0)
    found = 3
    adaptive.tip_model.member = adaptive.selector.best = found      # what the selector switches to
    identified = adaptive.tip_model.endoscope
    assert identified != adaptive.knowledge.endoscope
    session.tune({"kind": "pi-smith"})
    new = session.switch._pending
    assert new is not None and new.knowledge.endoscope == identified
    assert "identified by the running lock" in new.knowledge.label
    session.record_start()
    summary = session.record_stop()
    path = Path(summary["run_folder"]) / summary["identified_scope"]
    assert tomllib.loads(path.read_text())["knowledge"]["endoscope"] == to_dict(identified)


def test_a_selection_that_cannot_be_tracked_says_why_and_keeps_the_target():
    """A click on a spot the tracker cannot follow (here the dark corner outside the round view) says why
    and loses nothing: the target selected before is still followed on the next frames."""
    from targetlock.console.session import TapTracker
    from targetlock.vision import FeatureTracker, PlanarTarget, Renderer, RenderSettings, endoscope_camera, make_pose

    cam = endoscope_camera()
    renderer = Renderer(cam, RenderSettings(), PlanarTarget.mucosa(seed=3), seed=11)
    point = (0.003, 0.001)                    # m on the tissue plane

    def frame(x: float):
        return renderer.render(np.eye(4), make_pose((x, 0.0, 0.05), (0.0, 0.0, 0.0)), point_m=point)

    tap = TapTracker(FeatureTracker())
    first = frame(0.0)
    assert tap.select(first.image, first.truth_px, 96) and tap.failure is None and not tap.kept_previous
    tap.update(first.image, 0.0)
    assert not tap.select(first.image, (3.0, 3.0), 96)
    assert "field of view" in tap.failure and tap.kept_previous and not tap.last_selection_ok
    for k in range(1, 6):                     # the view moves on: the old target is still tracked
        f = frame(0.0004 * k)
        r = tap.update(f.image, 0.05 * k)
        assert r.valid and np.hypot(*(r.position_px - f.truth_px)) < 2.0
