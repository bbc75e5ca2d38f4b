"""What a target-lock run records in ``run.mcap`` besides its rows: the scene they describe."""
from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np

from .mcap_log import McapLog

__all__ = ["RunMcap"]


class RunMcap:
    """Rows of a run plus the scene they describe: ``base → tip`` from the tip angles (chained
    kinematics), ``base → target`` where known, the camera calibration, frames with annotations.

    ``columns``: the time series' columns (a ``tip_x_deg``/``tip_y_deg`` pair gives the tip pose);
    ``tip_length`` (m) and ``n_elements``: the kinematic chain; ``camera``: CameraParams or None;
    ``target_pose``: t (s) → 4x4 pose of the target in the base frame (m), or None."""

    def __init__(self, log: McapLog, columns: Sequence[str], *, tip_length: float, n_elements: int, camera=None,
                 target_pose: Callable[[float], np.ndarray] | None = None, config_toml: str = "") -> None:
        self.log = log
        self.columns = list(columns)
        self.tip_length, self.n_elements = float(tip_length), int(n_elements)
        self.camera = camera
        self.target_pose = target_pose
        cols = {c: i for i, c in enumerate(self.columns)}
        self._tip = (cols["tip_x_deg"], cols["tip_y_deg"]) if {"tip_x_deg", "tip_y_deg"} <= cols.keys() else None
        self._next_calibration = 0.0
        if config_toml:
            log.metadata("config", {"config.toml": config_toml})

    def tick(self, t: float, row: Sequence[float]) -> None:
        """The scene of one time-series row (``columns``) at run time ``t`` (s); the row itself is
        written by the run folder's time series."""
        from ..model.kinematics import tip_pose
        if self._tip is not None:
            px, py = row[self._tip[0]], row[self._tip[1]]
            if math.isfinite(px) and math.isfinite(py):
                pose = tip_pose(math.radians(px), math.radians(py), self.tip_length, self.n_elements)
                self.log.transform(t, "base", "tip", pose)
        if self.target_pose is not None:
            self.log.transform(t, "base", "target", self.target_pose(t))
        if self.camera is not None and t >= self._next_calibration:
            self.log.calibration(t, self.camera)
            self._next_calibration = t + 1.0

    def frame(self, t: float, image: np.ndarray, *, target_px: Sequence[float] | None, label: str = "",
              quality: int = 80) -> None:
        """An endoscope frame (BGR or grey, uint8) as JPEG with the target, the centre and the error drawn
        as annotations (image pixels)."""
        import cv2
        ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            return
        self.log.image(t, jpeg.tobytes())
        centre = (self.camera.cx, self.camera.cy) if self.camera is not None else (image.shape[1] / 2, image.shape[0] / 2)
        self.log.annotations(t, target_px=target_px, centre_px=centre, label=label)
