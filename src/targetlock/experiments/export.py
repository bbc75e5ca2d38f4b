"""``targetlock export``: ``run.mcap`` for run folders recorded before MCAP logging existed."""
from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np

from ..config import ConfigError, from_dict
from ..recording import McapLog, RunMcap
from .target_lock import RunConfig

__all__ = ["export_run_folder"]


def export_run_folder(folder: str | Path, *, overwrite: bool = False) -> Path:
    """Write ``run.mcap`` for a run folder made before MCAP recording existed (or without it):
    its time series, the resolved config as metadata, and for target-lock runs on the twin the tip and
    target poses. Returns the file's path."""
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
        cfg = from_dict(RunConfig, data)
        e = cfg.twin.endoscope
        tip_length, n_elements, camera = e.tip_length, e.n_elements, cfg.twin.camera
        if not (folder / "rig.toml").exists():           # the twin: its scene is known exactly
            from ..rig.simulated import SimulatedRig
            target_pose = SimulatedRig(cfg.twin, cfg.tracker).scene.target_pose
    with McapLog(out) as log:
        scene = RunMcap(log, columns, tip_length=tip_length, n_elements=n_elements, camera=camera,
                        target_pose=target_pose, config_toml=config_text)
        t_col = columns.index("t") if "t" in columns else None
        for k, row in enumerate(rows):
            t = float(row[t_col]) if t_col is not None else float(k)
            log.row("/timeseries", t, columns, row)
            scene.tick(t, row)
    return out
