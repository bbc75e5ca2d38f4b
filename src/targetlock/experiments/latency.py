"""Latency measurement of the whole loop (report §3.4.2).

The camera looks at the control handle. From frame n on, the tracker output is replaced by a
programmed target offset; a proportional controller answers it at once and the handle moves. We
count the frames until the *video* shows the handle moving: m - n frames, i.e. (m - n)/fps seconds,
is the latency from capture to motion (video path + control tick + drive response).

On the twin the camera "sees" the handle angle at each capture time; on a rig the same count comes
from image differences of the handle in the recorded frames (``motion_in_frames``).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..controllers import ControllerConfig
from ..loop.runner import ControlLoop, LoopConfig
from ..rig.base import Observation
from .target_lock import RunConfig, build_controller, build_rig

__all__ = ["measure_latency", "motion_in_frames"]


def motion_in_frames(frames: list[np.ndarray], threshold: float = 8.0) -> int:
    """Index of the first frame that differs from the first one (mean absolute grey-level change
    above ``threshold``), or -1. For recorded video of the handle on a real rig."""
    ref = frames[0].astype(np.float32)
    for i, f in enumerate(frames[1:], start=1):
        if float(np.mean(np.abs(f.astype(np.float32) - ref))) > threshold:
            return i
    return -1


def measure_latency(cfg: RunConfig | None = None, *, inject_frame: int = 20, offset_px: float = 100.0,
                    seconds: float = 4.0, motion_threshold_rad: float = 1e-4) -> dict:
    """Run the procedure on the twin; returns frames counted and the measured latency (s)."""
    cfg = cfg or RunConfig()
    cfg = dataclasses.replace(cfg, controller=ControllerConfig(kind="pi", i_gain=0.0, p_gain=500.0, max_rate=100.0),
                              loop=LoopConfig(seconds=seconds, metrics_after=0.0))
    cfg = dataclasses.replace(cfg, twin=dataclasses.replace(cfg.twin, scene=dataclasses.replace(cfg.twin.scene, path="static")))
    seen_handle: list[tuple[int, float]] = []

    def programmed(rig, t, truth):
        # What the camera captures now: the handle at its current angle.
        seen_handle.append((rig.frame_index, float(rig.handle_angles()[0])))
        offset = np.array([offset_px, 0.0]) if rig.frame_index >= inject_frame else np.zeros(2)
        return Observation(capture_time=t, offset=offset, valid=True, frame_index=rig.frame_index)

    rig = build_rig(cfg, frame_hook=programmed)
    ctrl = build_controller(cfg, rig)
    ControlLoop(rig, ctrl, rate=cfg.loop.rate).run(seconds)
    start = seen_handle[0][1]
    moved = [i for i, a in seen_handle if abs(a - start) > motion_threshold_rad]
    if not moved:
        raise RuntimeError(f"the handle did not move within {seconds} s: latency longer than the run")
    frames = moved[0] - inject_frame
    fps = cfg.twin.camera.fps
    return {"inject_frame": inject_frame, "first_moving_frame": moved[0], "frames": frames,
            "measured_latency_s": frames / fps, "configured_latency_s": cfg.twin.camera.latency, "fps": fps,
            "resolution_s": 1.0 / fps, "control_period_s": 1.0 / cfg.loop.rate}
