"""Programmable target motion in the world (report §5.3, Fig. 5.2).

Paths are described in the **start camera frame**: offsets (m) from the *anchor*, the point
``distance`` in front of the camera at the start of the run, along the start camera's image axes
(x right, y down, z away). So a path means the same thing wherever the tip starts, and the target
is centred at t = 0 unless the path says otherwise (the step).

* ``linear``  — the report's straight path: ``linear_length`` (12 cm) out and back at
  ``linear_frequency`` (0.1 Hz), with ``stop_duration`` (1 s) stops at both ends; smooth
  (cosine) speed profile as a robot arm moves.
* ``ellipse`` — ``ellipse_size`` (13 cm left-right x 12 cm top-bottom) at ``ellipse_frequency``
  (0.05 Hz), with two stops per revolution.
* ``step``    — a static target that appears at ``step_offset_px`` from the image centre
  (report §5.2: -180 px, a quarter of the image width).
* ``static``  — the anchor itself.
* ``waypoints`` — timed waypoints from a CSV file with header ``t,x,y,z`` (s, m, start camera
  frame, offsets from the anchor), linearly interpolated and held after the last one. UTF-8 with or
  without a BOM (Excel's "CSV UTF-8"); the file is read and checked when the config is validated,
  and run folders keep a copy of it.

The target is a plane facing the start camera; its pose's origin is the selected target point.

The tissue surface (``surface``, :class:`SurfaceParams`) is that plane (``kind = "plane"``, the
default) or, with ``kind = "folds"``, the plane displaced along its normal (away from the start
camera) by a radial height field: a lumen (a deep funnel around an axis beside the target point)
with haustra-like ring folds, which breathes (the whole surface moves ~2 mm at ~0.25 Hz) and
carries a peristalsis-like wave travelling out from the lumen. A plane point (x, y) (m, in the
target's frame) sits at (x, y, w(x, y, t)); the target point (0, 0) too, so
:meth:`Scene.target_position` moves with the deformation while :meth:`Scene.target_pose` stays the
undeformed plane's frame.
"""
from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..config import ConfigError, param, read_text_file
from ..errors import InputFileError
from .camera import CameraParams, unproject

__all__ = ["SceneParams", "SurfaceParams", "Scene", "PATHS", "SURFACES"]

PATHS = ("linear", "ellipse", "step", "static", "waypoints")
SURFACES = ("plane", "folds")


@dataclass(frozen=True)
class SurfaceParams:
    """Shape of the tissue surface and how it deforms (see the module docstring)."""
    kind: str = param("plane", choices=SURFACES, doc="'plane' or 'folds' (a lumen with folds that breathes)")
    amplitude: float = param(1.0, lo=0.0, hi=10.0, doc="scales every displacement of 'folds' (0: the plane)")
    lumen_offset: tuple[float, float] = param((0.012, -0.008), unit="m", lo=-1.0, hi=1.0,
                                              doc="lumen axis from the target point, in the plane (x right, y down)")
    lumen_depth: float = param(0.02, unit="m", lo=0.0, hi=0.5, doc="depth of the lumen on its axis")
    lumen_radius: float = param(0.018, unit="m", lo=1e-3, hi=0.5, doc="radius at which the lumen is half as deep")
    fold_amplitude: float = param(0.001, unit="m", lo=0.0, hi=0.05, doc="height of the ring folds (haustra)")
    fold_spacing: float = param(0.012, unit="m", lo=1e-3, hi=0.5, doc="distance between ring folds")
    breathing_amplitude: float = param(0.002, unit="m", lo=0.0, hi=0.05, doc="breathing displacement (peak)")
    breathing_rate: float = param(0.25, unit="Hz", lo=0.0, hi=5.0, doc="breathing frequency")
    peristalsis_amplitude: float = param(0.001, unit="m", lo=0.0, hi=0.05, doc="peristaltic wave height")
    peristalsis_wavelength: float = param(0.03, unit="m", lo=1e-3, hi=1.0, doc="peristaltic wavelength")
    peristalsis_speed: float = param(0.01, unit="m/s", lo=0.0, hi=1.0, doc="speed of the wave out from the lumen")

    @property
    def flat(self) -> bool:
        """The surface is the undeformed plane (w = 0 everywhere, always)."""
        return self.kind == "plane" or self.amplitude == 0.0

    def profile(self, r: np.ndarray | float, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Displacement w (m, along the plane normal away from the start camera) at distance ``r``
        (m) from the lumen axis at time ``t`` (s), and dw/dr."""
        r = np.asarray(r, dtype=float)
        if self.flat:
            return np.zeros_like(r), np.zeros_like(r)
        a, r2 = self.amplitude, self.lumen_radius ** 2
        kf = 2 * math.pi / self.fold_spacing
        kp = 2 * math.pi / self.peristalsis_wavelength
        phase = kp * r - kp * self.peristalsis_speed * t
        w = a * (self.lumen_depth * r2 / (r2 + r * r) + self.fold_amplitude * np.cos(kf * r)
                 + self.peristalsis_amplitude * np.sin(phase)
                 + self.breathing_amplitude * math.sin(2 * math.pi * self.breathing_rate * t))
        dw = a * (-2 * self.lumen_depth * r2 * r / (r2 + r * r) ** 2 - self.fold_amplitude * kf * np.sin(kf * r)
                  + self.peristalsis_amplitude * kp * np.cos(phase))
        return w, dw

    def height(self, x: np.ndarray | float, y: np.ndarray | float, t: float) -> np.ndarray:
        """Displacement w (m) of plane point(s) (x, y) (m, target frame) at time ``t`` (s)."""
        cx, cy = self.lumen_offset
        return self.profile(np.hypot(np.asarray(x, float) - cx, np.asarray(y, float) - cy), t)[0]


@dataclass(frozen=True)
class SceneParams:
    """Where the target is and how it moves."""
    path: str = param("linear", choices=PATHS, doc="target path")
    waypoints_file: str = param("", file=True, doc="CSV file (t,x,y,z) for path = 'waypoints'")
    distance: float = param(0.12, unit="m", lo=0.005, hi=2.0, doc="target distance in front of the camera at the start (report: 12 cm)")
    start_tip_deg: tuple[float, float] = param((-10.0, 0.0), unit="deg", lo=-150.0, hi=150.0,
                                               doc="tip bending (x, y) at the start, where the target is selected")
    start_delay: float = param(1.0, unit="s", lo=0.0, hi=3600.0, doc="the target rests this long before it moves")
    linear_length: float = param(0.12, unit="m", lo=0.0, hi=2.0, doc="straight path length (report: 12 cm)")
    linear_frequency: float = param(0.1, unit="Hz", lo=0.001, hi=10.0, doc="straight path out-and-back rate (report: 0.1 Hz)")
    linear_direction_deg: float = param(180.0, unit="deg", lo=-360.0, hi=360.0,
                                        doc="direction in the start image plane (0: image +x, 90: image +y)")
    stop_duration: float = param(1.0, unit="s", lo=0.0, hi=60.0, doc="stop at each end of the straight path / twice per ellipse")
    ellipse_size: tuple[float, float] = param((0.13, 0.12), unit="m", lo=0.0, hi=2.0,
                                              doc="ellipse extent left-right, top-bottom (report: 13 x 12 cm)")
    ellipse_frequency: float = param(0.05, unit="Hz", lo=0.001, hi=10.0, doc="revolutions per second (report: 0.05 Hz)")
    step_offset_px: tuple[float, float] = param((-180.0, 0.0), unit="px", lo=-4096.0, hi=4096.0,
                                                doc="where the step target appears, from the image centre")
    tissue_tilt_deg: tuple[float, float] = param((0.0, 0.0), unit="deg", lo=-75.0, hi=75.0,
                                                 doc="tilt of the tissue plane from facing the start camera, about the "
                                                     "start image's x axis, then its y axis (0, 0: face-on); the "
                                                     "target point and its path do not change, only what is rendered "
                                                     "around it (its light, glints and perspective)")
    surface: SurfaceParams = field(default_factory=SurfaceParams)

    def check(self, prefix: str = "") -> None:
        if self.path == "waypoints" and not self.waypoints_file:
            raise ConfigError(f"{prefix}waypoints_file must name a CSV file when {prefix}path = 'waypoints'")
        if self.path == "waypoints":
            _load_waypoints(self.waypoints_file, f"{prefix}waypoints_file")
        period = 1.0 / self.linear_frequency
        if self.path == "linear" and 2 * self.stop_duration >= period:
            raise ConfigError(f"{prefix}stop_duration = {self.stop_duration} s leaves no time to move in a "
                              f"{period:g} s period; allowed: [0, {period / 2:g}) s")


def _smooth(u: float) -> float:
    """Cosine speed profile on [0, 1] (zero speed at both ends)."""
    return 0.5 - 0.5 * math.cos(math.pi * min(max(u, 0.0), 1.0))


def _load_waypoints(path: str, name: str = "scene.waypoints_file") -> tuple[np.ndarray, np.ndarray]:
    """Times (s) and offsets (m) of a waypoint CSV; ConfigError naming the setting, file and row if bad."""
    if not Path(path).is_file() and not Path(path).is_dir():
        raise ConfigError(f"{name} = {path!r}: no such file")
    try:
        text = read_text_file(path, f"{name} =")     # utf-8-sig: Excel's BOM is accepted
    except InputFileError as exc:   # said as a config problem, with the setting's name
        raise ConfigError(str(exc)) from None
    header, *rows = [r for r in csv.reader(io.StringIO(text)) if r] or [[]]
    header = [h.strip() for h in header]
    if not {"t", "x", "y", "z"} <= set(header):
        raise ConfigError(f"{name} = {path!r}: header must name columns t,x,y,z, found {','.join(header)!r}")
    cols = [header.index(c) for c in "txyz"]
    short = [k for k, r in enumerate(rows) if len(r) <= max(cols)]
    if short:
        raise ConfigError(f"{name} = {path!r}: row {short[0] + 2} has {len(rows[short[0]])} values, "
                          f"{len(header)} columns expected")
    try:
        values = np.array([[float(r[i]) for i in cols] for r in rows], dtype=float).reshape(-1, 4)
    except ValueError as exc:
        raise ConfigError(f"{name} = {path!r}: needs numeric columns t,x,y,z ({exc})") from None
    t, xyz = values[:, 0], values[:, 1:]
    if t.size == 0:
        raise ConfigError(f"{name} = {path!r}: has no waypoint rows")
    bad = np.flatnonzero(~np.isfinite(t) | ~np.all(np.isfinite(xyz), axis=1))
    if bad.size:
        raise ConfigError(f"{name} = {path!r}: row {bad[0] + 2} is not finite (NaN or inf); all values must be numbers")
    if np.any(np.diff(t) <= 0):
        row = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 3
        raise ConfigError(f"{name} = {path!r}: t must increase strictly (row {row})")
    return t, xyz


class Scene:
    """Target motion anchored to the camera pose at the start of a run."""

    def __init__(self, params: SceneParams, camera: CameraParams, start_camera_pose: np.ndarray) -> None:
        self.params = params
        self.camera = camera
        self.start_pose = np.array(start_camera_pose, dtype=float)
        self.rotation = self.start_pose[:3, :3]
        self.anchor = self.start_pose[:3, 3] + params.distance * self.rotation[:, 2]
        # the tissue plane's axes (its z: the normal, away from the camera): turned about the start
        # image's x axis, then about the turned y axis
        tilt = Rotation.from_euler("XY", params.tissue_tilt_deg, degrees=True).as_matrix()
        self.plane_rotation = self.rotation @ tilt
        self._waypoints = _load_waypoints(params.waypoints_file) if params.path == "waypoints" else None
        if params.path == "step":
            self._step = unproject(np.array(params.step_offset_px) + [camera.cx, camera.cy], params.distance,
                                   camera, distort=False) - [0.0, 0.0, params.distance]

    def offset(self, t: float | np.ndarray) -> np.ndarray:
        """Target offset(s) from the anchor in the start camera frame (m), shape (..., 3)."""
        if np.ndim(t) == 0:
            return np.array(self._offset(float(t)))
        t = np.asarray(t, dtype=float)
        return np.array([self._offset(x) for x in t.ravel()]).reshape(t.shape + (3,))

    def _offset(self, t: float) -> tuple[float, float, float]:
        # Scalar on purpose: the control loop asks for one time per tick, where numpy costs more than math.
        p = self.params
        tau = max(t - p.start_delay, 0.0)
        if p.path == "linear":
            period = 1.0 / p.linear_frequency
            move = period / 2.0 - p.stop_duration
            ph = tau % period
            if ph < move:
                s = _smooth(ph / move)
            elif ph < move + p.stop_duration:
                s = 1.0
            else:
                s = 1.0 - _smooth((ph - move - p.stop_duration) / move)
            d = math.radians(p.linear_direction_deg)
            return (s * p.linear_length * math.cos(d), s * p.linear_length * math.sin(d), 0.0)
        if p.path == "ellipse":
            period = 1.0 / p.ellipse_frequency
            half_move = period / 2.0 - p.stop_duration
            ph = tau % period
            if ph < half_move + p.stop_duration:
                frac = 0.5 * _smooth(ph / half_move)
            else:
                frac = 0.5 + 0.5 * _smooth((ph - half_move - p.stop_duration) / half_move)
            alpha = 2.0 * math.pi * frac
            a, b = p.ellipse_size[0] / 2.0, p.ellipse_size[1] / 2.0
            return (a * (math.cos(alpha) - 1.0), b * math.sin(alpha), 0.0)
        if p.path == "step":
            return (float(self._step[0]), float(self._step[1]), float(self._step[2]))
        if p.path == "waypoints" and self._waypoints is not None:
            wt, wxyz = self._waypoints
            return (float(np.interp(t, wt, wxyz[:, 0])), float(np.interp(t, wt, wxyz[:, 1])),
                    float(np.interp(t, wt, wxyz[:, 2])))
        return (0.0, 0.0, 0.0)

    def target_position(self, t: float | np.ndarray) -> np.ndarray:
        """Selected target point in the world (base) frame (m), shape (..., 3): on the surface, so
        displaced with it when the surface is not flat."""
        pos = self.anchor + self.offset(t) @ self.rotation.T
        surf = self.params.surface
        if surf.flat:
            return pos
        w = np.vectorize(lambda tt: float(surf.height(0.0, 0.0, tt)))(t)
        return pos + np.multiply.outer(w, self.plane_rotation[:, 2])

    def target_pose(self, t: float) -> np.ndarray:
        """4x4 pose of the target plane: origin at the selected point (of the undeformed plane when
        the surface is not flat), facing the start camera, tilted by ``tissue_tilt_deg``."""
        pose = np.eye(4)
        pose[:3, :3] = self.plane_rotation
        pose[:3, 3] = self.anchor + self.offset(t) @ self.rotation.T
        return pose
