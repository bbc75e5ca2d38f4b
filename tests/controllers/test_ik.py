import math

import numpy as np
import pytest

from targetlock.controllers import ControllerConfig, IKController, nominal_knowledge
from targetlock.controllers.ik import aim_angles
from targetlock.model.camera import CameraParams, project, world_to_camera
from targetlock.model.kinematics import tip_pose
from targetlock.rig.base import Observation

CAM = CameraParams()
L, N = 0.12, 30


@pytest.mark.parametrize("target", [(0.03, 0.0, 0.2), (-0.05, 0.04, 0.15), (0.0, -0.08, 0.2), (0.0, -0.08, 0.1)])
def test_aim_angles_put_the_target_on_the_optical_axis(target):
    phi = aim_angles(np.array(target), np.zeros(2), L, N, -2.5, 2.5)
    px = project(world_to_camera(tip_pose(phi[0], phi[1], L, N), np.array(target)), CAM)
    np.testing.assert_allclose(px, [CAM.cx, CAM.cy], atol=1e-4)


def make(**kw):
    cfg = ControllerConfig(kind="ik", tip_gain=1.0, **kw)
    return IKController(cfg, knowledge=nominal_knowledge(), rad_per_tick=1.6e-5,
                        lower=np.full(2, -2.0), upper=np.full(2, 2.0), control_dt=0.02)


def test_goal_centres_the_target_seen_at_capture_time():
    c = make(ik_damping=0.0, max_rate=100.0)
    motor = np.array([-0.3, 0.1])
    c.reset(motor, 0.0)
    for k in range(30):
        c.step(None, motor, 0.02 * (k + 1))
    # a target 12 cm in front of the camera at the capture-time pose, seen at (-120, 40) px
    pose = tip_pose(motor[0], motor[1], L, N)
    offset = np.array([-120.0, 40.0])
    d = 0.12
    p_cam = np.array([offset[0] / CAM.fx * d, offset[1] / CAM.fy * d, d])
    target = pose[:3, :3] @ p_cam + pose[:3, 3]
    sp = c.step(Observation(capture_time=0.2, offset=offset, valid=True), motor, 0.62)
    px = project(world_to_camera(tip_pose(sp[0], sp[1], L, N), target), CAM)
    np.testing.assert_allclose(px, [CAM.cx, CAM.cy], atol=1e-3)


def test_damping_moves_a_fraction_of_the_way_eq_4_6():
    c = make(ik_damping=0.7, max_rate=100.0)
    motor = np.zeros(2)
    c.reset(motor, 0.0)
    sp = c.step(Observation(capture_time=0.0, offset=np.array([60.0, 0.0]), valid=True), motor, 0.02)
    np.testing.assert_allclose(sp, 0.3 * c.goal)
    assert c.goal[0] > 0


def test_ik_holds_when_the_target_is_lost():
    c = make()
    c.reset(np.array([0.2, 0.2]), 0.0)
    sp = c.step(Observation(capture_time=0.0, offset=np.array([math.nan, math.nan]), valid=False), np.array([0.2, 0.2]), 0.02)
    np.testing.assert_array_equal(sp, [0.2, 0.2])
