"""What a target-lock run (or any run folder) records in ``run.mcap``, live or exported afterwards."""
from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from .mcap_log import McapLog

__all__ = ["RunMcap", "export_run_folder"]


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
        """One time-series row at run time ``t`` (s)."""
        from ..model.kinematics import tip_pose
        self.log.row("/timeseries", t, self.columns, row)
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


def export_run_folder(folder: str | Path, *, overwrite: bool = False) -> Path:
    """Write ``run.mcap`` for a run folder made before MCAP recording existed (or without it):
    its time series, the resolved config as metadata, and for target-lock runs on the twin the tip and
    target poses. Returns the file's path."""
    from ..config import ConfigError, from_dict
    folder = Path(folder)
    csv_path, cfg_path = folder / "timeseries.csv", folder / "config.toml"
    for p in (csv_path, cfg_path):
        if not p.is_file():
            raise ConfigError(f"{folder}: not a run folder (no {p.name})")
    out = folder / "run.mcap"
    if out.exists() and not overwrite:
        raise ConfigError(f"{out} exists already; pass --overwrite to replace it")
    config_text = cfg_path.read_text(encoding="utf-8")
    data = tomllib.loads(config_text)
    with csv_path.open(encoding="utf-8") as fh:
        columns = fh.readline().strip().split(",")
    rows = np.loadtxt(csv_path, delimiter=",", skiprows=1, ndmin=2) if csv_path.stat().st_size else np.empty((0, 0))
    tip_length, n_elements, camera, target_pose = 0.12, 30, None, None
    if {"twin", "controller"} <= data.keys():
        from ..experiments.target_lock import RunConfig
        cfg = from_dict(RunConfig, data)
        e = cfg.twin.endoscope
        tip_length, n_elements, camera = e.tip_length, e.n_elements, cfg.twin.camera
        if not (folder / "rig.toml").exists():           # the twin: its scene is known exactly
            from ..rig.simulated import SimulatedRig
            target_pose = SimulatedRig(cfg.twin, cfg.tracker).scene.target_pose
    with McapLog(out) as log:
        rec = RunMcap(log, columns, tip_length=tip_length, n_elements=n_elements, camera=camera,
                      target_pose=target_pose, config_toml=config_text)
        t_col = columns.index("t") if "t" in columns else None
        for k, row in enumerate(rows):
            rec.tick(float(row[t_col]) if t_col is not None else float(k), row)
    return out
