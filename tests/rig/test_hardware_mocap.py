"""The hardware rig's motion-capture part: bodies by name, the straight calibration at start-up
(issue 11 item 12), on simulated drives (virtual CAN) and a simulated Motive (loopback)."""
from __future__ import annotations

import socket
import time
import uuid
from dataclasses import replace

import numpy as np
import pytest

from targetlock.interfaces.canbus import CanBusConfig
from targetlock.interfaces.cia402 import CanopenRigConfig
from targetlock.interfaces.natnet import NatNetConfig, NatNetStartError
from targetlock.interfaces.rigfile import HardwareRigConfig, ObservationSourceConfig
from targetlock.interfaces.sim_cia402 import SimDriveSet
from targetlock.interfaces.sim_natnet import SimNatNetConfig, SimNatNetServer
from targetlock.model.camera import CameraParams, project, world_to_camera
from targetlock.model.kinematics import tip_pose
from targetlock.rig.hardware import HardwareRig

LENGTH, ELEMENTS = 0.12, 30


def rot(axis, angle):
    c, s = np.cos(angle), np.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    r = np.eye(3)
    r[i, i] = r[j, j] = c
    r[i, j], r[j, i] = -s, s
    return r


# How the tip rigid body sits on the camera: Motive's body axes are not the camera's.
MOUNT = rot(2, 0.25) @ rot(0, 0.1)


class Endoscope:
    """Base, tip body (camera frame rotated by the marker mount) and target, in Motive's frame."""

    def __init__(self) -> None:
        self.phi = np.zeros(2)
        self.base = np.eye(4)
        self.base[:3, :3] = rot(2, 0.4)
        self.base[:3, 3] = (0.2, -0.1, 1.0)

    def camera(self) -> np.ndarray:
        return self.base @ tip_pose(self.phi[0], self.phi[1], LENGTH, ELEMENTS)

    def target(self) -> np.ndarray:
        t = np.eye(4)
        t[:3, 3] = (self.base @ tip_pose(0.0, 0.0, LENGTH, ELEMENTS) @ [0.02, -0.01, 0.3, 1.0])[:3]
        return t

    def poses(self):
        tip = self.camera()
        tip[:3, :3] = tip[:3, :3] @ MOUNT.T        # the tip body's frame = camera frame @ mount^-1
        return self.base, tip, {3: self.target()}


@pytest.fixture
def world():
    scope = Endoscope()
    port = sock_port()
    srv = SimNatNetServer(SimNatNetConfig(command_port=0, data_port=port, multicast=False, rate_hz=200.0),
                          scope.poses, names={3: "Target"})
    bus = CanBusConfig(interface="virtual", channel=f"tl-test-{uuid.uuid4().hex[:12]}")
    can = CanopenRigConfig(bus=bus, sdo_timeout=1.0, heartbeat_timeout=1.0)   # generous: a loaded test machine
    sims = SimDriveSet(can.bus, can.node_ids, can.drive_params())
    sims.start()
    srv.start()
    yield scope, srv, can
    srv.stop()
    sims.stop()


def sock_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rig_config(srv, can, **natnet) -> HardwareRigConfig:
    n = NatNetConfig(command_port=srv.command_port, multicast=False, connect_timeout=0.5,
                     base_body_name="EndoscopeBase", tip_body_name="EndoscopeTip", **natnet)
    return HardwareRigConfig(can=can, natnet=n, observations=ObservationSourceConfig(kind="mocap",
                                                                                      target_body_name="Target"))


def wait_measurement(rig):
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline:
        m = rig.observations.measure()
        if m is not None:
            return m
        time.sleep(0.01)
    raise AssertionError("no motion-capture measurement")


def test_start_clock_calibrates_the_straight_tip_and_corrects_angles_and_camera(world):
    scope, srv, can = world
    camera = CameraParams()
    rig = HardwareRig(rig_config(srv, can, calibrate_straight=True), camera)
    try:
        assert rig.client.body_ids == {"base": 1, "tip": 2, "target": 3}
        raw_angles = wait_measurement(rig)[1]
        assert np.abs(raw_angles).max() > 0.05          # uncalibrated: the marker mount reads as a bend
        rig.start_clock()                               # right after homing: the section is straight
        assert np.allclose(rig.observations.tip_correction, MOUNT, atol=1e-5)
        scope.phi = np.array([0.3, -0.2])
        time.sleep(0.05)                                # newer samples: the bent section
        offset, angles = wait_measurement(rig)
        assert np.allclose(angles, scope.phi, atol=1e-4)
        cam = np.linalg.inv(scope.base) @ scope.camera()
        target = (np.linalg.inv(scope.base) @ scope.target())[:3, 3]
        truth = project(world_to_camera(cam, target), camera) - (camera.cx, camera.cy)
        assert np.allclose(offset, truth, atol=0.05)
    finally:
        rig.close()


def test_calibration_refuses_a_bent_section(world):
    scope, srv, can = world
    scope.phi = np.array([0.6, 0.3])
    rig = HardwareRig(rig_config(srv, can, calibrate_straight=True, calibrate_max_angle=0.35), CameraParams())
    try:
        wait_measurement(rig)
        with pytest.raises(RuntimeError, match="straight calibration refused.*straighten"):
            rig.start_clock()
    finally:
        rig.close()


def test_without_calibration_the_body_frames_are_used_as_they_are(world):
    scope, srv, can = world
    rig = HardwareRig(rig_config(srv, can), CameraParams())
    try:
        rig.start_clock()
        assert np.array_equal(rig.observations.tip_correction, np.eye(3))
    finally:
        rig.close()


def test_rig_refuses_to_start_without_the_target_body(world):
    scope, srv, can = world
    cfg = rig_config(srv, can)
    cfg = replace(cfg, observations=replace(cfg.observations, target_body_name="Ball"))
    with pytest.raises(NatNetStartError, match=r"target 'Ball'.*'Target' \(id 3\)"):
        HardwareRig(cfg, CameraParams())


def test_a_camera_source_tracks_with_the_runs_tracker_settings(world, tmp_path):
    # The rig file names the device and the tracker; how the feature tracker is tuned comes from the run's
    # config (`feature_tracker`), as on the twin, so a setting tuned in `vision-eval` also holds on the rig.
    from targetlock.vision.render import PlanarTarget, Renderer, make_pose
    from targetlock.vision.sources import write_video
    from targetlock.vision.tracker import TrackerSettings

    scope, srv, can = world
    camera = CameraParams()
    r = Renderer(camera, target=PlanarTarget.mucosa(size_m=(0.3, 0.3), seed=2, texture_px=512), seed=2)
    frames = [r.render(np.eye(4), make_pose((0.001 * k - 0.02, 0.0, 0.12)), point_m=(0.02, 0.0)).image for k in range(20)]
    video = write_video(tmp_path / "v.avi", frames, fps=20.0, codec="MJPG")
    cfg = replace(rig_config(srv, can), observations=ObservationSourceConfig(kind="camera", device=str(video), window_px=80))
    settings = TrackerSettings(max_misses=9, context_isotropy=0.0)
    for given, expected in ((settings, settings), (None, TrackerSettings())):
        rig = HardwareRig(cfg, camera, tracker_settings=given)
        try:
            assert rig.observations.tracker.settings == expected
            rig.start_clock()
            deadline, got = time.monotonic() + 10.0, []
            while time.monotonic() < deadline and not any(o.valid for o in got):
                if rig.observations.wait_arrival(0.05):
                    got.extend(rig.observations.poll(0.0))
            assert any(o.valid for o in got)                       # frames tracked through the rig
        finally:
            rig.close()
    # A marker tracker has settings of its own: the feature tracker's are not handed to it.
    marker = replace(cfg, observations=replace(cfg.observations, tracker="marker"))
    rig = HardwareRig(marker, camera, tracker_settings=settings)
    try:
        assert not isinstance(rig.observations.tracker.settings, TrackerSettings)
    finally:
        rig.close()
