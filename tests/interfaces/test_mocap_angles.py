"""Bending angles from motion-capture rigid bodies."""
from __future__ import annotations

import numpy as np
import pytest

from targetlock.interfaces.mocap import (MocapBendingSensor, bending_angles_from_sample, pose_from_rigid_body,
                                         quaternion_to_rotation, rotation_to_quaternion)
from targetlock.interfaces.natnet import MocapFrame, MocapSample, RigidBody
from targetlock.model.kinematics import tip_pose


def random_rotation(rng):
    q = rng.normal(size=4)
    return quaternion_to_rotation(q / np.linalg.norm(q))


def sample_from(rotations: dict[int, np.ndarray], valid=True, received_at=10.0, latency=0.004) -> MocapSample:
    bodies = {rid: RigidBody(rid, (0.0, 0.0, 1.0), tuple(rotation_to_quaternion(r).tolist()), 0.0, valid)
              for rid, r in rotations.items()}
    return MocapSample(MocapFrame(1, bodies, 0.0, 0, 0, 0), received_at, latency)


def test_quaternion_round_trip_and_orthonormality():
    rng = np.random.default_rng(0)
    for _ in range(500):
        r = random_rotation(rng)
        q = rotation_to_quaternion(r)
        assert q[3] >= 0 and np.isclose(np.linalg.norm(q), 1.0)
        assert np.allclose(quaternion_to_rotation(q), r, atol=1e-12)
        assert np.allclose(r @ r.T, np.eye(3), atol=1e-12)
    # the branches for small trace: rotations by pi about each axis
    for axis in np.eye(3):
        r = 2 * np.outer(axis, axis) - np.eye(3)
        assert np.allclose(quaternion_to_rotation(rotation_to_quaternion(r)), r, atol=1e-12)
    with pytest.raises(ValueError):
        quaternion_to_rotation((0, 0, 0, 0))


@pytest.mark.parametrize("phi", [(0.0, 0.0), (0.4, 0.0), (0.0, -0.6), (1.2, 0.0), (0.0, 1.1)])
def test_pure_bends_are_recovered_exactly_in_any_world_frame(phi):
    rng = np.random.default_rng(1)
    world_base = random_rotation(rng)
    tip = world_base @ tip_pose(phi[0], phi[1], 0.05, 30)[:3, :3]
    angles = bending_angles_from_sample(sample_from({1: world_base, 2: tip}), 1, 2)
    assert np.allclose(angles, phi, atol=1e-9)


def test_missing_or_untracked_bodies_give_none():
    r = np.eye(3)
    assert bending_angles_from_sample(sample_from({1: r}), 1, 2) is None
    assert bending_angles_from_sample(sample_from({1: r, 2: r}, valid=False), 1, 2) is None
    s = sample_from({1: r, 2: r})
    bad = dict(s.frame.rigid_bodies)
    bad[2] = RigidBody(2, (0.0, 0.0, 0.0), (float("nan"), 0.0, 0.0, 1.0), 0.0, True)
    nan_sample = MocapSample(MocapFrame(1, bad, 0.0, 0, 0, 0), 0.0, None)
    assert bending_angles_from_sample(nan_sample, 1, 2) is None


def test_calibration_absorbs_marker_frames():
    """Rigid bodies defined with arbitrary local axes: one straight sample fixes the tip correction."""
    rng = np.random.default_rng(2)
    world_base = random_rotation(rng)
    body_in_tip = random_rotation(rng)          # how the tip markers' frame sits on the camera frame

    def observe(phi):
        cam = world_base @ tip_pose(phi[0], phi[1], 0.05, 30)[:3, :3]
        return sample_from({1: world_base, 2: cam @ body_in_tip})

    class Source:
        def __init__(self):
            self.sample = None

        def get(self, max_age=None):
            return self.sample

    src = Source()
    sensor = MocapBendingSensor(src, 1, 2)
    src.sample = observe((0.3, 0.2))
    assert not np.allclose(sensor.read().angles, (0.3, 0.2), atol=1e-3)   # uncalibrated: wrong
    sensor.calibrate_straight(observe((0.0, 0.0)))
    for phi in ((0.3, 0.0), (0.0, -0.5), (0.0, 0.0)):
        src.sample = observe(phi)
        m = sensor.read()
        assert np.allclose(m.angles, phi, atol=1e-9)
        assert m.capture_time == pytest.approx(10.0 - 0.004)


def test_pose_from_rigid_body():
    body = RigidBody(1, (1.0, 2.0, 3.0), (0.0, 0.0, np.sin(0.25), np.cos(0.25)), 0.0, True)
    pose = pose_from_rigid_body(body)
    assert np.allclose(pose[:3, 3], (1, 2, 3))
    assert np.allclose(pose[:3, :3], [[np.cos(0.5), -np.sin(0.5), 0], [np.sin(0.5), np.cos(0.5), 0], [0, 0, 1]])
