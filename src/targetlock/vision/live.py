"""Live observations on a rig: frames from a capture device (or video file) tracked in their own thread.

The thread reads frames as fast as they come, tracks each one and leaves only the newest result in a
one-slot hand-off (:class:`~targetlock.rig.base.HandoffSource`), so the loop never waits for vision,
never works through a backlog (the report's buffering problem, §3.1), and is woken as soon as a
result is ready. The target is selected at the image centre on the first frame, where the endoscope
was pointed when the lock engaged.

Times are on the loop's clock (s since the loop started, told with :meth:`start_clock`), and an
observation's ``capture_time`` means what it means on the twin: when the scene was imaged, i.e. the
grab time minus the video ``latency`` (the configured or measured capture-to-host delay). A capture
device is stamped with the host's monotonic clock at grab; a video file (or any source whose
timestamps are positions in a stream) is paced at its frame rate — frame k is released k/fps
after the first — and stamped at its release, as a camera delivering it then would be.
"""
from __future__ import annotations

import threading
import time

from ..model.camera import CameraParams
from ..rig.base import HandoffSource, Observation
from .sources import CaptureSource, FrameSource, VideoFileSource
from .tracker import TrackerSettings, make_tracker, to_observation

__all__ = ["CameraObservations", "open_source"]


def open_source(device: str) -> FrameSource:
    """A capture device for a number ("0"), else a video file."""
    return CaptureSource(int(device)) if device.strip().isdigit() else VideoFileSource(device)


class CameraObservations(HandoffSource):
    """Tracker thread over a frame source with a newest-only hand-off to the loop.

    ``latency`` (s): capture-to-grab delay subtracted from each grab time (default: the camera's
    configured video latency). ``tracker_settings``: the feature tracker's settings (the run's
    ``feature_tracker`` section; default :class:`~targetlock.vision.tracker.TrackerSettings`), used
    when ``config.tracker`` is ``"feature"``."""

    def __init__(self, config, camera: CameraParams, *, source: FrameSource | None = None,
                 latency: float | None = None, tracker_settings: TrackerSettings | None = None) -> None:
        super().__init__()
        self.camera = camera
        self.latency = float(camera.latency if latency is None else latency)
        self.source = source or open_source(config.device)
        self.live = isinstance(self.source, CaptureSource)   # stamps on the monotonic clock
        self.tracker = make_tracker(config.tracker, tracker_settings if config.tracker == "feature" else None,
                                    camera=camera)
        self.window_px = config.window_px
        self._stop = threading.Event()
        self._t0 = time.monotonic()
        self.frames = 0
        self.track_seconds = 0.0
        self._thread = threading.Thread(target=self._run, name="targetlock-vision", daemon=True)
        self._thread.start()

    def start_clock(self, t0: float) -> None:
        """Monotonic time (s) of loop time zero; frames counted before it are forgotten."""
        self._t0 = t0
        self.frame_log.reset()

    def _grab(self, pace_origin: list[float]) -> tuple[bool, object, float]:
        """Next frame and its grab time (s, monotonic). A stream's frames are released at their
        timestamps after the first frame's release (``pace_origin`` holds that origin)."""
        ok, frame, stamp = self.source.read()
        if not ok or self.live:
            return ok, frame, stamp if ok else time.monotonic()
        if not pace_origin:
            pace_origin.append(time.monotonic() - stamp)
        release = pace_origin[0] + stamp
        self._stop.wait(max(0.0, release - time.monotonic()))
        return True, frame, release

    def _run(self) -> None:
        selected = False
        cam = self.camera
        pace_origin: list[float] = []
        while not self._stop.is_set():
            ok, frame, t_grab = self._grab(pace_origin)
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
            t0 = self._t0
            obs = to_observation(result, t_grab - t0 - self.latency, cam.cx, cam.cy, frame_index=self.frames)
            obs = Observation(capture_time=obs.capture_time, offset=obs.offset, valid=obs.valid,
                              confidence=obs.confidence, frame_index=obs.frame_index,
                              arrival_time=time.monotonic() - t0)
            self.frame_log.record(obs.capture_time, obs.valid)
            self.deliver(obs)
            self.frames += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.source.close()
