"""Vision in the closed loop: the twin renders each frame at capture time, the tracker measures it.

:class:`VisionPipeline` is a ``frame_hook`` for :class:`~targetlock.rig.simulated.SimulatedRig`:
at every capture it renders the endoscope view from the twin's camera and target poses (motion
blur from the motion over the exposure), runs the tracker and returns the observation; the rig
puts it on the latency line. The target is selected on the first frame where the clinician would
click it (the target's true position), with a square window. Optionally every frame is written to
an MP4 with the tracked target, the image centre and the error drawn on it.

With ``regions=True`` (for runs where nothing but the tracker reads the frames: no video, no
``on_frame``) a tracked frame is rendered only in a square around the last tracked position and
where it is heading (the tracker's declared footprint plus :data:`REGION_MARGIN_PX`); the first
frame and every frame after a miss or loss are rendered whole (selection and re-acquisition search it all).
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from ..model.twin import TwinConfig
from ..rig.base import Observation
from .overlay import draw_overlay
from .render import PlanarTarget, RenderSettings, Renderer, interpolate_pose
from .tracker import TrackerSettings, TrackResult, make_tracker, to_observation

__all__ = ["VisionPipeline", "REGION_MARGIN_PX", "TEXTURE_PX", "tissue_side_m"]

REGION_MARGIN_PX = 8
"""Margin (px) of a partly rendered frame's square beyond the tracker's declared footprint
(:attr:`~targetlock.vision.tracker.Tracker.footprint_px`) about the last tracked position and where
it is heading."""


TEXTURE_PX = 4096
"""Side of the loop's tissue texture (texels)."""


def tissue_side_m(twin: TwinConfig) -> float:
    """Side (m) of the loop's square mucosa plane: 40 cm, so that the tip's whole working range sees
    tissue rather than the plane's edge, but no more than :data:`TEXTURE_PX` texels per pixel
    footprint at the target's distance (``twin.scene.distance / fx``), and at least 10 cm.

    Tissue has detail at every scale, a texture only down to its texel: 4096 texels over 40 cm are
    0.1 mm each, and a target at 1-3 cm (0.03-0.1 mm per pixel) was drawn as smooth blobs with a
    third less image detail than at 3 cm, which the tracker lost where a real view would hold it
    (docs/vision.md, "Vision in the closed loop"). A near scene is therefore the same mucosa at a finer
    scale: the texture's physical scale follows the distance, its look in the image does not."""
    return float(min(0.4, max(0.1, TEXTURE_PX * twin.scene.distance / twin.camera.fx)))


class VisionPipeline:
    """Render -> track -> observation, called by the simulated rig at each frame capture.
    ``tracker_settings``: the feature tracker's settings (``RunConfig.feature_tracker``; default
    :class:`TrackerSettings`)."""

    def __init__(self, twin: TwinConfig, *, tracker: str = "feature", window_px: int = 96, seed: int = 0,
                 settings: RenderSettings | None = None, exposure_fraction: float = 0.5,
                 video: str | Path | None = None,
                 on_frame: Callable[[float, np.ndarray, TrackResult], None] | None = None,
                 regions: bool = False, tracker_settings: TrackerSettings | None = None) -> None:
        self.cam = twin.camera
        if tracker == "marker":
            # A 40 cm plane: the tip's whole working range sees tissue, not the plane's edge.
            self.target = PlanarTarget.aruco(seed=seed, size_m=(0.4, 0.4), marker_fraction=0.06, texture_px=TEXTURE_PX)
        else:
            side = tissue_side_m(twin)
            self.target = PlanarTarget.mucosa(size_m=(side, side), seed=seed, texture_px=TEXTURE_PX)
        self.renderer = Renderer(self.cam, settings or RenderSettings(), self.target, seed=seed,
                                 surface=twin.scene.surface)
        self.tracker = make_tracker(tracker, tracker_settings if tracker == "feature" else None, camera=self.cam)
        self.window_px = window_px
        self.exposure = exposure_fraction / self.cam.fps   # s, the shutter is open this long before capture
        self.prev: tuple[float, np.ndarray, np.ndarray] | None = None
        self.selected = False
        self.render_seconds = 0.0
        self.track_seconds = 0.0
        self.frames = 0
        self.partial_frames = 0        # rendered only around the tracker's target (regions=True)
        self.errors: list[float] = []
        self._writer = None
        self.on_frame = on_frame        # (capture time s, BGR image, tracker result) of every frame
        self.last_image: np.ndarray | None = None
        self.regions = regions
        self._tracked: list[np.ndarray] = []   # the last two tracked positions (px) while tracked
        if video is not None:
            fourcc = cv2.VideoWriter_fourcc(*"mp4v")
            self._writer = cv2.VideoWriter(str(video), fourcc, self.cam.fps, (self.cam.width, self.cam.height))
            if not self._writer.isOpened():
                raise OSError(f"cannot write video {video}")

    def __call__(self, rig, t: float, truth: np.ndarray) -> Observation:
        cam_pose = rig.camera_pose()
        target_pose = rig.scene.target_pose(t)
        start_cam, start_target = cam_pose, target_pose
        if self.prev is not None and t > self.prev[0]:
            # Poses at the start of the exposure, interpolated between the previous capture and now.
            f = max(0.0, 1.0 - self.exposure / (t - self.prev[0]))
            start_cam = interpolate_pose(self.prev[1], cam_pose, f)
            start_target = interpolate_pose(self.prev[2], target_pose, f)
        self.prev = (t, cam_pose, target_pose)
        region = self._region()
        self.partial_frames += region is not None
        t0 = time.perf_counter()
        frame = self.renderer.render(start_cam, start_target, camera_pose_end=cam_pose, target_pose_end=target_pose,
                                     region=region, time_s=t - 0.5 * min(self.exposure, t))
        t1 = time.perf_counter()
        if not self.selected:
            self.selected = True
            self.tracker.select(frame.image, frame.truth_px, self.window_px)
        result = self.tracker.update(frame.image, t)
        t2 = time.perf_counter()
        self._tracked = [*self._tracked[-1:], result.position_px.copy()] if result.valid else []
        self.render_seconds += t1 - t0
        self.track_seconds += t2 - t1
        self.frames += 1
        obs = to_observation(result, t, self.cam.cx, self.cam.cy, frame_index=rig.frame_index, truth_px=frame.truth_px)
        if obs.valid and frame.visible:
            self.errors.append(float(np.hypot(*(obs.offset - obs.truth))))
        self.last_image = frame.image
        if self.on_frame is not None:
            self.on_frame(t, frame.image, result)
        if self._writer is not None:
            err = np.hypot(*frame.truth_offset(self.cam))
            self._writer.write(draw_overlay(frame.image, result, centre_px=(self.cam.cx, self.cam.cy),
                                            truth_px=frame.truth_px, lines=(f"t = {t:5.2f} s",
                                                                            f"target error {err:5.1f} px")))
        return obs

    def _region(self) -> tuple[float, float, float, float] | None:
        """Image rectangle (x0, y0, x1, y1) the next frame needs, or None for the whole frame: the
        tracker's footprint about the last tracked position and that plus twice the last frame's
        motion, shifted inside the frame as the tracker shifts its crops (the window the tracker
        settled on at selection may be larger than the one asked for)."""
        if not (self.regions and self._tracked and self._writer is None and self.on_frame is None):
            return None
        footprint = self.tracker.footprint_px
        if footprint is None:
            return None
        p = self._tracked[-1]
        q = p + 2 * (p - self._tracked[0])        # (p itself after one tracked frame)
        h = footprint + REGION_MARGIN_PX
        lo, hi = np.minimum(p, q) - h, np.maximum(p, q) + h
        size = np.array([self.cam.width, self.cam.height], float)
        lo, hi = lo + np.maximum(0.0, -lo), hi + np.maximum(0.0, -lo)   # past the left/top: shifted right/down
        lo, hi = lo - np.maximum(0.0, hi - size), np.minimum(hi, size)  # past the right/bottom: left/up
        return (float(max(lo[0], 0.0)), float(max(lo[1], 0.0)), float(hi[0]), float(hi[1]))

    def stats(self) -> dict:
        e = np.asarray(self.errors)
        n = max(self.frames, 1)
        return {"frames": self.frames, "partial_frames": self.partial_frames, "render_ms": 1e3 * self.render_seconds / n, "track_ms": 1e3 * self.track_seconds / n,
                "tracker_median_px": float(np.median(e)) if e.size else float("nan"),
                "tracker_p95_px": float(np.percentile(e, 95)) if e.size else float("nan")}

    def close(self) -> None:
        if self._writer is not None:
            self._writer.release()
            self._writer = None
