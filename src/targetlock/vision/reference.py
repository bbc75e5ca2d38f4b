"""OpenCV's own trackers as reference rows for :func:`~targetlock.vision.evaluate.evaluate`.

:func:`reference_trackers` lists what the installed OpenCV offers: MIL is in every
``opencv-python`` 4.x build; CSRT, KCF and MOSSE only in the contrib build (``cv2.legacy`` or
``cv2.Tracker*_create``), so they appear only when that is installed. ``"lk"`` is plain pyramidal
Lucas-Kanade (corners in the window, median motion, forward-backward checked): the baseline the
feature tracker builds on. All run behind the :class:`~targetlock.vision.tracker.Tracker`
interface; none of them has a notion of loss beyond OpenCV's own ``ok`` flag.
"""
from __future__ import annotations

import cv2
import numpy as np

from .tracker import Tracker, TrackResult

__all__ = ["reference_trackers", "make_reference", "OpenCVTracker", "PlainLKTracker"]

_CONTRIB = ("csrt", "kcf", "mosse")


def _factory(name: str):
    """The OpenCV constructor of tracker ``name``, or None when this build lacks it."""
    camel = {"mil": "MIL", "csrt": "CSRT", "kcf": "KCF", "mosse": "MOSSE"}[name]
    for ns in (cv2, getattr(cv2, "legacy", None)):  # contrib builds keep MOSSE (and others) in cv2.legacy
        if ns is not None and hasattr(ns, f"Tracker{camel}_create"):
            return getattr(ns, f"Tracker{camel}_create")
    return None


def reference_trackers() -> tuple[str, ...]:
    """Names of the reference trackers available with the installed OpenCV."""
    return tuple(n for n in ("mil", *_CONTRIB) if _factory(n) is not None) + ("lk",)


def make_reference(name: str) -> Tracker:
    """A reference tracker by name (see :func:`reference_trackers`)."""
    if name == "lk":
        return PlainLKTracker()
    if name not in ("mil", *_CONTRIB):
        raise ValueError(f"reference tracker {name!r}; allowed: {', '.join(reference_trackers())}")
    if _factory(name) is None:
        raise ValueError(f"reference tracker {name!r} needs opencv-contrib-python; available: "
                         f"{', '.join(reference_trackers())}")
    return OpenCVTracker(name)


class OpenCVTracker(Tracker):
    """An OpenCV bounding-box tracker; the target is the box centre plus the selected point's offset."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._make = _factory(name)
        self._cv = None
        self._offset = np.zeros(2)

    def fresh(self) -> "OpenCVTracker":
        return OpenCVTracker(self.name)

    @property
    def footprint_px(self) -> float | None:
        return None  # OpenCV's trackers do not say what they read: always the whole frame

    def select(self, frame_bgr: np.ndarray, point_px, window_px: int) -> bool:
        p = np.asarray(point_px, float).reshape(2)
        half = window_px / 2
        box = (int(round(p[0] - half)), int(round(p[1] - half)), int(window_px), int(window_px))
        self._cv = self._make()
        res = self._cv.init(frame_bgr, box)
        self.lost = res is False  # OpenCV 4.5+ returns None, older builds a bool
        self.failure = f"OpenCV {self.name.upper()} refused the window" if self.lost else None
        self._offset = p - np.array([box[0] + half, box[1] + half])
        return not self.lost

    def update(self, frame_bgr: np.ndarray, capture_time: float | None = None) -> TrackResult:
        if self._cv is None:
            return TrackResult(np.full(2, np.nan), 0.0, False, True)
        ok, (x, y, w, h) = self._cv.update(frame_bgr)
        self.lost = not ok
        if not ok:
            return TrackResult(np.full(2, np.nan), 0.0, False, True)
        return TrackResult(np.array([x + w / 2, y + h / 2]) + self._offset, 1.0, True, False)


class PlainLKTracker(Tracker):
    """Pyramidal Lucas-Kanade of Shi-Tomasi corners in the window, frame to frame; the target
    moves by the median of the forward-backward-checked flow. No keyframes, no re-acquisition."""

    def __init__(self, min_points: int = 6) -> None:
        self.min_points = min_points
        self._prev = None

    def fresh(self) -> "PlainLKTracker":
        return PlainLKTracker(self.min_points)

    @property
    def footprint_px(self) -> float | None:
        return None  # the flow's pyramid is built on the whole frame

    def select(self, frame_bgr: np.ndarray, point_px, window_px: int) -> bool:
        gray = cv2.cvtColor(frame_bgr, cv2.COLOR_BGR2GRAY)
        p = np.asarray(point_px, float).reshape(2)
        mask = np.zeros_like(gray)
        h = window_px // 2
        x, y = int(round(p[0])), int(round(p[1]))
        mask[max(0, y - h):y + h + 1, max(0, x - h):x + h + 1] = 255
        pts = cv2.goodFeaturesToTrack(gray, 40, 0.005, 4, mask=mask, blockSize=5)
        self.lost = pts is None or len(pts) < self.min_points
        self.failure = "too few corners in the window" if self.lost else None
        self._prev, self._pts, self._pos = gray, pts, p.copy()
        return not self.lost

    def update(self, frame_bgr: np.ndarray, capture_time: float | None = None) -> TrackResult:
        if self.lost or self._prev is None:
            return TrackResult(np.full(2, np.nan), 0.0, False, True)
        gray = cv2.cvtColor(frame_bgr, cv2.COLOR_BGR2GRAY)
        kw = dict(winSize=(11, 11), maxLevel=3)
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(self._prev, gray, self._pts, None, **kw)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(gray, self._prev, nxt, None, **kw)
        ok = (st.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm((back - self._pts).reshape(-1, 2), axis=1) < 1.0)
        if ok.sum() < self.min_points:
            self.lost = True
            return TrackResult(np.full(2, np.nan), 0.0, False, True)
        d = np.median((nxt - self._pts).reshape(-1, 2)[ok], axis=0)
        self._pos = self._pos + d
        self._prev, self._pts = gray, nxt[ok].reshape(-1, 1, 2)
        return TrackResult(self._pos.copy(), 1.0, True, False)
