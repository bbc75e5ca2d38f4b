"""Pinhole camera at the endoscope tip, its projection (Eq. 3.35-3.38) and the video latency line.

Image space is pixels, origin top-left, x right, y down; the target *offset* is measured from the
image centre (cx, cy). The default intrinsics are those of a PAL (720x576) flexible-endoscope
video chain: a ~100 deg horizontal field of view pinhole (fx = fy = 300 px) with the moderate
barrel distortion calibrations of flexible endoscopes typically find (k1 = -0.25, k2 = 0.05 in
the normalised Brown-Conrady model). Distortion is off by default in the loop (the report's
model has none) and on in the renderer, which matches what a real endoscope delivers.
"""
from __future__ import annotations

import heapq
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..config import ConfigError, param

__all__ = ["CameraParams", "project", "unproject", "world_to_camera", "LatencyLine"]


@dataclass(frozen=True)
class CameraParams:
    """Intrinsics (pixels), distortion, frame rate and video latency of the tip camera."""
    width: int = param(720, unit="px", lo=16, hi=8192, doc="image width")
    height: int = param(576, unit="px", lo=16, hi=8192, doc="image height")
    fx: float = param(300.0, unit="px", lo=1.0, hi=1e5, doc="focal length along x")
    fy: float = param(300.0, unit="px", lo=1.0, hi=1e5, doc="focal length along y")
    cx: float = param(360.0, unit="px", lo=0.0, hi=8192.0, doc="principal point x (image centre)")
    cy: float = param(288.0, unit="px", lo=0.0, hi=8192.0, doc="principal point y (image centre)")
    k1: float = param(0.0, lo=-1.0, hi=1.0, doc="radial distortion r^2 coefficient (0: none)")
    k2: float = param(0.0, lo=-1.0, hi=1.0, doc="radial distortion r^4 coefficient")
    fps: float = param(22.0, unit="1/s", lo=0.1, hi=1000.0, doc="frame rate (report: 22 fps)")
    latency: float = param(0.4, unit="s", lo=0.0, hi=5.0, doc="capture-to-controller video latency (report: 0.4 s)")
    latency_jitter: float = param(0.0, unit="s", lo=0.0, hi=1.0,
                                  doc="extra delay of each frame, uniform in [0, jitter] (grabber, USB, encoder); frames stay in order")

    def check(self, prefix: str = "") -> None:
        for axis, c, size in (("x", self.cx, self.width), ("y", self.cy, self.height)):
            if not 0.0 <= c <= size:
                raise ConfigError(f"{prefix}c{axis} = {c:g} px lies outside the image (0 to {size} px wide); "
                                  f"allowed: [0, {size}] px")

    @property
    def matrix(self) -> np.ndarray:
        """3x3 camera matrix K (pixels)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        """OpenCV distortion vector (k1, k2, p1, p2, k3)."""
        return np.array([self.k1, self.k2, 0.0, 0.0, 0.0])


def world_to_camera(camera_pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Express world points (..., 3) in the camera frame whose pose in the world is 4x4 ``camera_pose``."""
    r, t = camera_pose[:3, :3], camera_pose[:3, 3]
    return (np.asarray(points, dtype=float) - t) @ r


def project(points_cam: np.ndarray, cam: CameraParams, *, distort: bool = True) -> np.ndarray:
    """Pixel coordinates (..., 2) of camera-frame points (..., 3) in metres (Eq. 3.36-3.38).

    Points at or behind the camera plane give NaN: they are not in the image.
    """
    p = np.asarray(points_cam, dtype=float)
    if p.shape == (3,):  # one point: plain floats are several times faster than array ops
        u, v, w = float(p[0]), float(p[1]), float(p[2])
        if not w > 1e-9:
            return np.array([np.nan, np.nan])
        u, v = u / w, v / w
        if distort and (cam.k1 or cam.k2):
            r2 = u * u + v * v
            f = 1.0 + cam.k1 * r2 + cam.k2 * r2 * r2
            u, v = u * f, v * f
        return np.array([cam.fx * u + cam.cx, cam.fy * v + cam.cy])
    z = p[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.where(z > 1e-9, p[..., 0] / z, np.nan)
        y = np.where(z > 1e-9, p[..., 1] / z, np.nan)
    if distort and (cam.k1 or cam.k2):
        r2 = x * x + y * y
        f = 1.0 + cam.k1 * r2 + cam.k2 * r2 * r2
        x, y = x * f, y * f
    return np.stack([cam.fx * x + cam.cx, cam.fy * y + cam.cy], axis=-1)


def unproject(pixels: np.ndarray, depth: float | np.ndarray, cam: CameraParams, *, distort: bool = True) -> np.ndarray:
    """Camera-frame points (..., 3) in metres at ``depth`` (m, along z) for pixels (..., 2)."""
    px = np.asarray(pixels, dtype=float)
    x = (px[..., 0] - cam.cx) / cam.fx
    y = (px[..., 1] - cam.cy) / cam.fy
    if distort and (cam.k1 or cam.k2):
        xd, yd = x.copy(), y.copy()
        for _ in range(20):  # fixed-point inversion of the radial model; converges for |k1| r^2 < 0.5
            r2 = x * x + y * y
            f = 1.0 + cam.k1 * r2 + cam.k2 * r2 * r2
            x, y = xd / f, yd / f
    d = np.asarray(depth, dtype=float)
    return np.stack([x * d, y * d, np.broadcast_to(d, x.shape)], axis=-1)


class LatencyLine:
    """Holds observations until they would arrive at the controller on the real rig.

    ``push(capture_time, item)`` at capture; ``pop_ready(now)`` returns, oldest first, every item
    whose capture_time + latency <= now (s). Items keep their capture time, so a consumer always
    knows how old its newest observation is.
    """

    def __init__(self, latency: float) -> None:
        if not latency >= 0.0:
            raise ValueError(f"latency = {latency!r} s; allowed: [0, inf) s")
        self.latency = float(latency)
        self._heap: list[tuple[float, int, Any]] = []
        self._count = 0

    def push(self, capture_time: float, item: Any, arrival: float | None = None) -> None:
        """Hold ``item`` until ``arrival`` (s; default ``capture_time + latency``)."""
        when = capture_time + self.latency if arrival is None else arrival
        heapq.heappush(self._heap, (when, self._count, (capture_time, item)))
        self._count += 1

    def pop_ready(self, now: float) -> list[tuple[float, Any]]:
        out = []
        # A tolerance of 1 ns absorbs float rounding of t + latency on exact multiples.
        while self._heap and self._heap[0][0] <= now + 1e-9:
            out.append(heapq.heappop(self._heap)[2])
        return out

    def __len__(self) -> int:
        return len(self._heap)
