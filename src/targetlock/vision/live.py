"""Live observations on a rig: frames from a capture device (or video file) tracked in their own thread.

The thread reads frames as fast as they come, tracks each one and leaves only the newest result in a
one-slot hand-off, so the 50 Hz loop never waits for vision and never works through a backlog (the
report's buffering problem, §3.1). The target is selected at the image centre on the first frame,
where the endoscope was pointed when the lock engaged.

Times: frames carry the host's monotonic clock at grab; ``poll(now)`` takes loop time, so the source
is told the loop's time zero with :meth:`start_clock`.
"""
from __future__ import annotations

import threading
import time

import numpy as np

from ..model.camera import CameraParams
from ..rig.base import Observation, ObservationSource
from .sources import CaptureSource, FrameSource, VideoFileSource
from .tracker import make_tracker, to_observation

__all__ = ["CameraObservations", "open_source"]


def open_source(device: str) -> FrameSource:
    """A capture device for a number ("0"), else a video file."""
    return CaptureSource(int(device)) if device.strip().isdigit() else VideoFileSource(device)


class CameraObservations(ObservationSource):
    """Tracker thread over a frame source with a newest-only hand-off to the loop."""

    def __init__(self, config, camera: CameraParams, *, source: FrameSource | None = None) -> None:
        self.camera = camera
        self.source = source or open_source(config.device)
        self.tracker = make_tracker(config.tracker, camera=camera)
        self.window_px = config.window_px
        self._slot: Observation | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._t0 = time.monotonic()
        self.frame_log: list[tuple[float, bool]] = []
        self.frames = 0
        self.track_seconds = 0.0
        self._thread = threading.Thread(target=self._run, name="targetlock-vision", daemon=True)
        self._thread.start()

    def start_clock(self, t0: float) -> None:
        """Monotonic time (s) of loop time zero."""
        self._t0 = t0

    def _run(self) -> None:
        selected = False
        cam = self.camera
        while not self._stop.is_set():
            ok, frame, t_grab = self.source.read()
            if not ok:
                if isinstance(self.source, VideoFileSource):
                    break  # end of the file
                time.sleep(0.005)
                continue
            start = time.perf_counter()
            if not selected:
                selected = self.tracker.select(frame, (cam.cx, cam.cy), self.window_px)
            result = self.tracker.update(frame)
            self.track_seconds += time.perf_counter() - start
            now = time.monotonic() - self._t0
            obs = to_observation(result, t_grab - self._t0, cam.cx, cam.cy, frame_index=self.frames)
            obs = Observation(capture_time=obs.capture_time, offset=obs.offset, valid=obs.valid,
                              confidence=obs.confidence, frame_index=obs.frame_index, arrival_time=now)
            with self._lock:
                self._slot = obs
                self.frame_log.append((obs.capture_time, obs.valid))
            self.frames += 1

    def poll(self, now: float) -> list[Observation]:
        with self._lock:
            obs, self._slot = self._slot, None
        return [] if obs is None else [obs]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.source.close()
