"""A hardware rig built from a rig file: CiA 402 drives behind the safety supervisor, NatNet motion
capture, and an observation source — the same interfaces the loop uses on the twin.

Observation sources:

* ``mocap``: the target's rigid body projected into the tip camera (the tip body's frame is the
  camera frame), sampled at the camera frame rate and delivered after the configured video latency.
  It validates a rig against motion capture, and it is how the twin in another process
  (``targetlock sim-rig``) is seen.
* ``camera``: endoscope frames from a capture device or video file through the tracker, in a thread
  with a newest-only hand-off (see :mod:`targetlock.vision`).

Times: the loop's clock (s since the loop started) for observations; the NatNet client's samples
carry monotonic times, converted with the offset taken at start.

Start-up: the NatNet client checks that Motive streams the base, tip and (``mocap`` observations)
target bodies, by id or asset name. With ``natnet.calibrate_straight`` the tip body's orientation
is taken as the straight camera frame in :meth:`HardwareRig.start_clock`, i.e. right after homing,
when the handles are at home and the bending section is straight; the correction then applies to
the measured bending angles and to the camera frame of the projected target.
"""
from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING

import numpy as np

from ..interfaces.cia402 import CanopenDrives
from ..interfaces.mocap import MocapBendingSensor, quaternion_to_rotation
from ..interfaces.natnet import NatNetClient
from ..interfaces.rigfile import HardwareRigConfig
from ..interfaces.safety import SafeDrives
from ..model.camera import CameraParams, LatencyLine, project, world_to_camera
from ..model.kinematics import bending_angles_from_poses
from .base import FrameLog, Observation, ObservationSource, Rig

if TYPE_CHECKING:   # vision loads only for a camera source
    from ..vision.tracker import TrackerSettings

__all__ = ["HardwareRig", "MocapObservations", "pose_of", "calibrate_straight", "CALIBRATION_WAIT_S"]

CALIBRATION_WAIT_S = 1.0
"""Wait this long for a sample with base and tip tracked for the straight calibration (s)."""


def pose_of(body) -> np.ndarray:
    """4x4 pose (m) of a NatNet rigid body."""
    h = np.eye(4)
    h[:3, :3] = quaternion_to_rotation(body.orientation)
    h[:3, 3] = body.position
    return h


class MocapObservations(ObservationSource):
    """The target as an ideal camera at the tip would see it, from motion capture."""

    def __init__(self, client: NatNetClient, camera: CameraParams, *, base_id: int, tip_id: int, target_id: int,
                 clock_offset: float) -> None:
        self.client, self.camera = client, camera
        self.base_id, self.tip_id, self.target_id = base_id, tip_id, target_id
        self.line = LatencyLine(camera.latency)
        self.clock_offset = clock_offset      # monotonic time of loop time zero
        self.tip_correction = np.eye(3)
        """Tip body frame -> camera frame (3x3), from :func:`calibrate_straight`."""
        self.next_frame = 0
        self.frame_log = FrameLog()
        self._cache: tuple[object, tuple[np.ndarray, np.ndarray, float] | None] = (None, None)

    def measure(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(offset px from the image centre, bending angles rad) now, or None without a usable sample."""
        m = self.measure_with_time()
        return None if m is None else m[:2]

    def measure_with_time(self) -> tuple[np.ndarray, np.ndarray, float] | None:
        """Like :meth:`measure`, plus the sample's capture time (s, monotonic clock).

        Computed once per motion-capture sample: the loop asks for the frame, the truth and the
        bending angles in the same tick, and the bending fit is the costly part."""
        s = self.client.get()
        if s is None:
            return None
        if self._cache[0] is s:
            return self._cache[1]
        self._cache = (s, self._compute(s))
        return self._cache[1]

    def _compute(self, s) -> tuple[np.ndarray, np.ndarray, float] | None:
        bodies = [s.rigid_body(i) for i in (self.base_id, self.tip_id, self.target_id)]
        if any(b is None or not b.usable for b in bodies):
            return None
        base, tip, target = (pose_of(b) for b in bodies)
        tip[:3, :3] = tip[:3, :3] @ self.tip_correction
        cam_in_base = np.linalg.inv(base) @ tip
        target_in_base = (np.linalg.inv(base) @ target)[:3, 3]
        px = project(world_to_camera(cam_in_base, target_in_base), self.camera)
        c = self.camera
        if not (0 <= px[0] < c.width and 0 <= px[1] < c.height):
            px = np.array([np.nan, np.nan])
        return px - (c.cx, c.cy), bending_angles_from_poses(base, tip), s.capture_time

    def poll(self, now: float) -> list[Observation]:
        period = 1.0 / self.camera.fps
        while self.next_frame * period <= now + 1e-9:
            m = self.measure()
            valid = m is not None and bool(np.all(np.isfinite(m[0])))
            offset = m[0] if m is not None and valid else np.array([np.nan, np.nan])
            t = self.next_frame * period
            self.line.push(t, Observation(capture_time=t, offset=offset, valid=valid, frame_index=self.next_frame,
                                          truth=offset, arrival_time=t + self.camera.latency))
            self.frame_log.record(t, valid)
            self.next_frame += 1
        return [item for _, item in self.line.pop_ready(now)]


def calibrate_straight(client: NatNetClient, observations: MocapObservations, max_angle: float,
                       wait: float = CALIBRATION_WAIT_S) -> np.ndarray:
    """Take the newest sample as the straight bending section: the tip body's orientation becomes the
    camera frame (its correction is returned and set on ``observations``). Raises RuntimeError with
    what to do when no sample has both bodies tracked or the tip reads more than ``max_angle`` rad
    from straight."""
    sensor = MocapBendingSensor(client, observations.base_id, observations.tip_id)
    deadline = time.monotonic() + wait
    while True:
        sample = client.get()
        if sample is not None and sensor.angles(sample) is not None:
            break
        if time.monotonic() > deadline:
            raise RuntimeError(f"straight calibration: no motion-capture sample with the base (id {sensor.base_id}) and "
                               f"tip (id {sensor.tip_id}) bodies tracked within {wait:g} s; check Motive")
        time.sleep(0.005)
    try:
        sensor.calibrate_straight(sample, max_angle=max_angle)
    except ValueError as exc:
        raise RuntimeError(f"straight calibration refused: {exc} (or raise natnet.calibrate_max_angle, or set "
                           f"natnet.calibrate_straight = false)") from None
    observations.tip_correction = sensor.tip_correction
    return sensor.tip_correction


class HardwareRig(Rig):
    """Drives on CANopen (behind :class:`SafeDrives`), NatNet and an observation source."""

    def __init__(self, config: HardwareRigConfig, camera: CameraParams, *, loop_rate: float | None = None,
                 tracker_settings: TrackerSettings | None = None) -> None:
        """``loop_rate`` (Hz): the control loop's rate; the drives' timing settings are checked against
        it (``CanopenRigConfig.check_timing``) before anything is opened. ``tracker_settings``: the
        feature tracker's settings for a camera source (the run's ``feature_tracker``; the rig file
        says which device and tracker, the run config how the tracker is tuned, as on the twin)."""
        if loop_rate is not None:
            config.can.check_timing(loop_rate)
        self.config = config
        self.camera = camera
        # Load the JIT-compiled kinematics now, not in the loop's first tick (~0.3 s).
        bending_angles_from_poses(np.eye(4), np.eye(4))
        self._t0 = time.monotonic()
        obs = config.observations
        extra = {"target": (obs.target_body_name, obs.target_body_id)} if obs.kind == "mocap" else {}
        self.client = NatNetClient(config.natnet, extra_bodies=extra)
        self.client.start()         # refuses to start when Motive lacks a configured body
        try:
            inner = CanopenDrives(config.can)
        except BaseException:
            self.client.stop()
            raise
        self.drives: SafeDrives = SafeDrives(inner, config.safety, clock=lambda: time.monotonic() - self._t0)
        ids = self.client.body_ids
        if obs.kind == "mocap":
            self.observations: MocapObservations | CameraObservations = MocapObservations(self.client, camera, base_id=ids["base"], tip_id=ids["tip"],
                                                  target_id=ids["target"], clock_offset=self._t0)
        else:
            from ..vision.live import CameraObservations
            self.observations = CameraObservations(obs, camera, tracker_settings=tracker_settings)

    def start_clock(self) -> None:
        """Loop time zero is now (called by the loop right after homing). With
        ``natnet.calibrate_straight`` the straight calibration happens here: the drives are at home."""
        n = self.config.natnet
        if n.calibrate_straight and isinstance(self.observations, MocapObservations):
            calibrate_straight(self.client, self.observations, n.calibrate_max_angle)
        self._t0 = time.monotonic()
        if isinstance(self.observations, MocapObservations):
            self.observations.clock_offset = self._t0
        else:
            self.observations.start_clock(self._t0)

    @property
    def time(self) -> float:
        return time.monotonic() - self._t0

    def advance(self, until: float) -> None:
        pass  # the wall clock moves the hardware; the loop sleeps until each deadline

    def truth_offset(self, t: float | None = None) -> np.ndarray:
        """Where motion capture sees the target now (px from centre); NaN without mocap."""
        if isinstance(self.observations, MocapObservations):
            m = self.observations.measure()
            if m is not None:
                return m[0]
        return np.array([math.nan, math.nan])

    def tip_angles(self) -> np.ndarray:
        """Bending angles (rad) measured by motion capture; NaN without a sample."""
        if isinstance(self.observations, MocapObservations):
            m = self.observations.measure()
            if m is not None:
                return m[1]
        return np.array([math.nan, math.nan])

    def tip_measurement(self) -> tuple[np.ndarray, float]:
        """Bending angles (rad) from motion capture with their capture time (s, monotonic clock);
        NaN angles without a sample."""
        if isinstance(self.observations, MocapObservations):
            m = self.observations.measure_with_time()
            if m is not None:
                return m[1], m[2]
        return np.array([math.nan, math.nan]), time.monotonic()

    def close(self) -> None:
        try:
            self.drives.close()
        finally:
            self.client.stop()
            self.observations.close()
