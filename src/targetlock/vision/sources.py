"""Frame sources: where the tracker's images come from.

One interface, :class:`FrameSource`: ``read() -> (ok, frame, timestamp)`` and ``close()``.
``frame`` is BGR uint8 (None when ``ok`` is False), ``timestamp`` the capture time in seconds:
simulated time for the twin, the position in the file for a video, the host's monotonic clock
for a live device. Implementations:

* :class:`RenderedSource` - the digital twin: a :class:`~targetlock.vision.render.Renderer` fed
  by a pose callback; the last :class:`~targetlock.vision.render.Frame` (with ground truth) stays
  available as ``last_frame``.
* :class:`VideoFileSource` - a video file (``cv2.VideoCapture``).
* :class:`CaptureSource` - an OpenCV capture device (frame grabber, USB camera).

:func:`write_video` writes frames to a video file (e.g. an MP4 of the loop with overlays).
"""
from __future__ import annotations

import abc
import time
from pathlib import Path
from typing import Callable, Iterable

import cv2
import numpy as np

from .render import Frame, Renderer

__all__ = ["FrameSource", "RenderedSource", "VideoFileSource", "CaptureSource", "write_video"]


class FrameSource(abc.ABC):
    """A stream of frames; usable as a context manager and as an iterator of (frame, timestamp)."""

    @abc.abstractmethod
    def read(self) -> tuple[bool, np.ndarray | None, float]:
        """Next frame: (ok, BGR uint8 image or None, capture timestamp in s)."""

    def close(self) -> None:
        """Release the underlying device or file (idempotent)."""

    def __enter__(self) -> "FrameSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __iter__(self):
        while True:
            ok, frame, t = self.read()
            if not ok:
                return
            yield frame, t


class RenderedSource(FrameSource):
    """Frames rendered by the twin at a fixed rate.

    ``poses(t)`` is called with the capture time t (s) and returns either
    ``(camera_pose, target_pose)`` (4x4, world frame, m) or a dict with those keys and optionally
    ``light_gain`` and ``occluders`` (see :meth:`Renderer.render`). With ``exposure_s`` > 0 the
    poses at ``t + exposure_s`` give the end of the exposure (motion blur). Frame k is captured at
    ``start_time + k / fps``; ``n_frames`` (None: endless) ends the stream.
    """

    def __init__(self, renderer: Renderer, poses: Callable[[float], object], *, fps: float | None = None,
                 exposure_s: float = 0.0, start_time: float = 0.0, n_frames: int | None = None) -> None:
        self.renderer = renderer
        self.poses = poses
        self.fps = float(fps if fps is not None else renderer.cam.fps)
        if not self.fps > 0:
            raise ValueError(f"fps = {fps!r}; allowed: (0, inf) 1/s")
        if not exposure_s >= 0:
            raise ValueError(f"exposure_s = {exposure_s!r}; allowed: [0, inf) s")
        self.exposure_s = float(exposure_s)
        self.start_time = float(start_time)
        self.n_frames = n_frames
        self.index = 0
        self.last_frame: Frame | None = None
        self._closed = False

    @staticmethod
    def _unpack(p) -> dict:
        if isinstance(p, dict):
            return dict(p)
        cam, tgt = p
        return {"camera_pose": cam, "target_pose": tgt}

    def read(self) -> tuple[bool, np.ndarray | None, float]:
        t = self.start_time + self.index / self.fps
        if self._closed or (self.n_frames is not None and self.index >= self.n_frames):
            return False, None, t
        a = self._unpack(self.poses(t))
        kw = {"light_gain": a.get("light_gain", 1.0), "occluders": a.get("occluders", ())}
        if self.exposure_s > 0:
            b = self._unpack(self.poses(t + self.exposure_s))
            kw["camera_pose_end"] = b["camera_pose"]
            kw["target_pose_end"] = b["target_pose"]
        self.last_frame = self.renderer.render(a["camera_pose"], a["target_pose"], **kw)
        self.index += 1
        return True, self.last_frame.image, t

    def close(self) -> None:
        self._closed = True


class VideoFileSource(FrameSource):
    """Frames of a video file; timestamps are frame index / fps (file's rate unless ``fps`` is given)."""

    def __init__(self, path: str | Path, *, fps: float | None = None) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"video file {self.path} does not exist")
        self._cap = cv2.VideoCapture(str(self.path))
        if not self._cap.isOpened():
            raise RuntimeError(f"OpenCV cannot open video file {self.path}")
        file_fps = self._cap.get(cv2.CAP_PROP_FPS)
        self.fps = float(fps if fps is not None else (file_fps if file_fps and file_fps > 0 else 25.0))
        self.index = 0

    @property
    def frame_count(self) -> int:
        """Number of frames the container declares (may be approximate for some codecs)."""
        return int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT))

    def read(self) -> tuple[bool, np.ndarray | None, float]:
        t = self.index / self.fps
        if self._cap is None:
            return False, None, t
        ok, frame = self._cap.read()
        if not ok:
            return False, None, t
        self.index += 1
        return True, frame, t

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


class CaptureSource(FrameSource):
    """A live OpenCV capture device; timestamps are the host's monotonic clock (s) after the grab."""

    def __init__(self, device: int | str = 0, *, width: int | None = None, height: int | None = None,
                 fps: float | None = None, api: int = cv2.CAP_ANY) -> None:
        self._cap = cv2.VideoCapture(device, api)
        if not self._cap.isOpened():
            raise RuntimeError(f"OpenCV cannot open capture device {device!r}")
        if width:
            self._cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
        if height:
            self._cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        if fps:
            self._cap.set(cv2.CAP_PROP_FPS, fps)

    def read(self) -> tuple[bool, np.ndarray | None, float]:
        if self._cap is None:
            return False, None, time.monotonic()
        ok, frame = self._cap.read()
        t = time.monotonic()
        return (True, frame, t) if ok else (False, None, t)

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


def write_video(path: str | Path, frames: Iterable[np.ndarray], fps: float = 22.0, codec: str = "mp4v") -> Path:
    """Write BGR uint8 frames (all the same size) to ``path`` with FourCC ``codec``
    (``"mp4v"`` for .mp4, ``"MJPG"`` for .avi). Returns the path; raises if nothing was written."""
    path = Path(path)
    writer = None
    n = 0
    try:
        for f in frames:
            if writer is None:
                h, w = f.shape[:2]
                writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*codec), float(fps), (w, h))
                if not writer.isOpened():
                    raise RuntimeError(f"OpenCV cannot write {path} with codec {codec!r}")
            writer.write(np.ascontiguousarray(f))
            n += 1
    finally:
        if writer is not None:
            writer.release()
    if n == 0:
        raise ValueError("write_video: no frames")
    return path
