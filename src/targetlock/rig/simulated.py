"""The digital twin behind the rig interfaces: simulated drives, camera, target and an ideal tracker.

Frames are captured at the camera frame rate on the model's time grid. Each capture computes
where the target really is in the image (the ideal tracker), optionally corrupted by noise,
dropped frames and outliers, and puts the observation on the latency line; the loop receives it
``camera.latency`` seconds after capture (plus up to ``camera.latency_jitter``). A vision pipeline
can replace the ideal tracker through ``frame_hook`` (see :mod:`targetlock.vision`).

Time stamps are a real rig's: a frame's ``capture_time`` is its arrival time minus the latency the
rig was *told* (``stamp_latency``, e.g. the controller's nominal 0.4 s), not the true capture
time, which no rig knows. Only ``stamp_latency=None`` (oracle) stamps with the true latency.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..config import param
from ..model.camera import LatencyLine, project, world_to_camera
from ..model.endoscope import advance, handle_for_tip, initial_state, pack_params
from ..model.kinematics import tip_pose
from ..model.scene import Scene
from ..model.twin import TwinConfig
from ..interfaces.errors import MotionRefused
from .base import Drives, FrameLog, Observation, ObservationSource, Rig

__all__ = ["ObservationNoise", "SimulatedRig", "SimDrives"]


@dataclass(frozen=True)
class ObservationNoise:
    """Imperfections of the ideal tracker."""
    noise_px: float = param(0.0, unit="px", lo=0.0, hi=500.0, doc="standard deviation of Gaussian pixel noise")
    drop_probability: float = param(0.0, lo=0.0, hi=1.0, doc="probability that a frame yields no observation")
    outlier_probability: float = param(0.0, lo=0.0, hi=1.0, doc="probability of a wrong but 'valid' observation")
    outlier_px: float = param(150.0, unit="px", lo=0.0, hi=2000.0, doc="size of an outlier's error")
    scale_noise: float = param(0.0, lo=0.0, hi=1.0, doc="relative standard deviation of the reported target scale")
    seed: int = param(0, lo=0, hi=2**63 - 1, doc="random seed of the imperfections")


class SimDrives(Drives):
    """The twin's drives: ticks in, ticks out; no motion before homing or after :meth:`disable`
    (the handles hold where they are); setpoints clamped."""

    def __init__(self, rig: "SimulatedRig") -> None:
        self._rig = rig
        self._homed = False
        p = rig.twin.drive
        self._lo = np.array([p.min_ticks, p.min_ticks], dtype=np.int64)
        self._hi = np.array([p.max_ticks, p.max_ticks], dtype=np.int64)
        self.last_ticks = np.zeros(2, dtype=np.int64)
        self._disabled = False

    @property
    def homed(self) -> bool:
        return self._homed

    def home(self) -> None:
        # The twin's encoders are absolute: homing only declares the reference valid.
        self._homed = True

    def send_setpoints(self, ticks: np.ndarray) -> None:
        if not self._homed:
            raise MotionRefused("drives are not homed: no motion before homing")
        if self._disabled:
            raise MotionRefused("drives are disabled: call enable() to resume")
        t = np.clip(np.asarray(ticks, dtype=np.int64), self._lo, self._hi)
        self.last_ticks = t
        self._rig.setpoint_rad[:] = t * self.rad_per_tick

    def disable(self) -> None:
        # The twin's set-point stays where it is: the handles hold, as a braked drive would.
        self._disabled = True

    def enable(self) -> None:
        self._disabled = False

    def is_disabled(self) -> bool:
        return self._disabled

    def positions(self) -> np.ndarray:
        return np.rint(self._rig.state[0, 0:2] / self.rad_per_tick).astype(np.int64)

    @property
    def limits(self) -> tuple[np.ndarray, np.ndarray]:
        return self._lo.copy(), self._hi.copy()

    @property
    def rad_per_tick(self) -> float:
        return self._rig.twin.drive.rad_per_tick


class _LatencySource(ObservationSource):
    def __init__(self, latency: float) -> None:
        self.line = LatencyLine(latency)
        self.frame_log = FrameLog()

    def poll(self, now: float) -> list[Observation]:
        return [item for _, item in self.line.pop_ready(now)]


class SimulatedRig(Rig):
    """The twin: endoscope + drives + camera + moving target, stepping on the model's grid.

    ``frame_hook(rig, t, truth_offset) -> Observation | None`` replaces the ideal tracker (vision).
    """

    def __init__(self, twin: TwinConfig, noise: ObservationNoise | None = None, *,
                 frame_hook: Callable[["SimulatedRig", float, np.ndarray], Observation | None] | None = None,
                 settle_seconds: float = 4.0, stamp_latency: float | None = None) -> None:
        """``stamp_latency`` (s): the video latency the rig subtracts from each frame's arrival time to
        stamp its capture time (what the lab configured or measured); ``None``: the true latency."""
        self.twin = twin
        if stamp_latency is not None and not 0.0 <= stamp_latency <= 5.0:
            raise ValueError(f"stamp_latency = {stamp_latency!r} s; allowed: [0, 5] s")
        self.stamp_latency = twin.camera.latency if stamp_latency is None else float(stamp_latency)
        self._last_arrival = -math.inf
        # The camera as the rig knows it: its latency is the one it stamps with.
        self.camera = dataclasses.replace(twin.camera, latency=self.stamp_latency)
        self.noise = noise or ObservationNoise()
        # Its own stream, so turning jitter on does not change the tracker noise's draws.
        self._jitter_rng = np.random.default_rng([self.noise.seed, 1])
        self._scale_rng = np.random.default_rng([self.noise.seed, 2])
        self.rng = np.random.default_rng(self.noise.seed)
        self.params = pack_params(twin.endoscope, twin.drive)
        self.state = initial_state(1)
        self.setpoint_rad = np.zeros(2)
        self.dt = twin.model_dt
        self.frame_hook = frame_hook
        self.drives: SimDrives = SimDrives(self)
        self.observations: _LatencySource = _LatencySource(twin.camera.latency)
        self._settle(settle_seconds)
        self.start_camera_pose = self.camera_pose()
        self.scene = Scene(twin.scene, twin.camera, self.start_camera_pose)
        self.steps = 0
        self.frame_index = 0

    # -------------------------------------------------------------------------------- physics
    def _settle(self, seconds: float) -> None:
        """Bend the tip to the scene's start angles before t = 0, as a clinician would have."""
        e = self.twin.endoscope
        goal = np.array([handle_for_tip(e, math.radians(a)) for a in self.twin.scene.start_tip_deg])
        n_ramp = int(round(0.75 * seconds / self.dt))
        for k in range(0, n_ramp, 10):
            advance(self.state, self.params, (goal * (k + 10) / n_ramp)[None, :], self.dt, 10)
        advance(self.state, self.params, goal[None, :], self.dt, int(round(0.25 * seconds / self.dt)))
        self.state[0, 4:6] = 0.0
        self.setpoint_rad[:] = self.state[0, 0:2]

    @property
    def time(self) -> float:
        return self.steps * self.dt

    def _integrate_to(self, t: float) -> None:
        n = int(round(t / self.dt)) - self.steps
        if n > 0:
            advance(self.state, self.params, self.setpoint_rad[None, :], self.dt, n)
            self.steps += n

    def camera_pose(self) -> np.ndarray:
        e = self.twin.endoscope
        return tip_pose(self.state[0, 2], self.state[0, 3], e.tip_length, e.n_elements)

    def tip_angles(self) -> np.ndarray:
        return self.state[0, 2:4].copy()

    def handle_angles(self) -> np.ndarray:
        return self.state[0, 0:2].copy()

    def truth_offset(self, t: float | None = None) -> np.ndarray:
        """Where the target really is in the image now (px from centre); NaN if not in view."""
        return self._image_offset(self._target_in_camera(self.time if t is None else t))

    def _target_in_camera(self, t: float) -> np.ndarray:
        """The target in the camera frame at time ``t`` (m)."""
        return world_to_camera(self.camera_pose(), self.scene.target_position(t))

    def _image_offset(self, p: np.ndarray) -> np.ndarray:
        """Image offset (px from centre) of the camera-frame point ``p``; NaN outside the image."""
        cam = self.twin.camera
        px = project(p, cam)
        if not (0.0 <= px[0] < cam.width and 0.0 <= px[1] < cam.height):
            return np.array([np.nan, np.nan])
        return px - (cam.cx, cam.cy)

    # -------------------------------------------------------------------------------- rig API
    def advance(self, until: float) -> None:
        period = 1.0 / self.twin.camera.fps
        while True:
            t_frame = self.frame_index * period
            if t_frame > until + 1e-12:
                break
            self._integrate_to(t_frame)
            self._capture(t_frame)
            self.frame_index += 1
        self._integrate_to(until)

    def _capture(self, t: float) -> None:
        target = self._target_in_camera(t)
        truth = self._image_offset(target)
        if self.frame_hook is not None:
            obs = self.frame_hook(self, t, truth)
        else:
            obs = self._ideal_observation(t, truth, float(target[2]))
        self.observations.frame_log.record(t, obs is not None and obs.valid)
        if obs is not None:
            cam = self.twin.camera
            arrival = t + cam.latency
            if cam.latency_jitter > 0.0:
                arrival += cam.latency_jitter * self._jitter_rng.random()
            arrival = max(arrival, self._last_arrival)      # a video stream delivers in order
            self._last_arrival = arrival
            stamped = arrival - self.stamp_latency
            self.observations.line.push(t, dataclasses.replace(obs, capture_time=stamped, arrival_time=arrival),
                                        arrival=arrival)

    def _ideal_observation(self, t: float, truth: np.ndarray, depth: float) -> Observation | None:
        """The ideal tracker's report of a frame: ``truth`` offset (px) and the target's ``depth`` in
        the camera (m), with the configured imperfections."""
        nz = self.noise
        rng = self.rng
        if nz.drop_probability and rng.random() < nz.drop_probability:
            return None
        visible = bool(np.all(np.isfinite(truth)))
        offset = truth.copy()
        if visible and nz.noise_px:
            offset = offset + rng.normal(0.0, nz.noise_px, 2)
        if visible and nz.outlier_probability and rng.random() < nz.outlier_probability:
            angle = rng.uniform(0, 2 * np.pi)
            offset = offset + nz.outlier_px * np.array([np.cos(angle), np.sin(angle)])
        # Relative apparent size: the target's depth when it was selected (the scene distance) over its
        # depth in the camera now, as a template tracker's scale would report it.
        scale = self.twin.scene.distance / depth if visible and depth > 0 else math.nan
        if visible and nz.scale_noise:
            scale *= 1.0 + self._scale_rng.normal(0.0, nz.scale_noise)
        return Observation(capture_time=t, offset=offset if visible else np.array([np.nan, np.nan]),
                           valid=visible, confidence=1.0 if visible else 0.0, frame_index=self.frame_index,
                           truth=truth, scale=scale)
