"""Controllers of the target lock: PI (+ hysteresis compensation), inverse kinematics, PI + prediction."""
from __future__ import annotations

import numpy as np

from .base import CONTROLLERS, Controller, ControllerConfig
from .ik import IKController
from .pi import PIController

__all__ = ["Controller", "ControllerConfig", "CONTROLLERS", "make_controller", "PIController", "IKController"]


def make_controller(cfg: ControllerConfig, *, rad_per_tick: float, lower: np.ndarray, upper: np.ndarray,
                    control_dt: float, camera, tip_length: float, n_elements: int, latency: float,
                    endoscope=None, model_dt: float = 0.001) -> Controller:
    """Build the controller ``cfg.kind`` with the rig's limits (rad) and the camera/tip geometry."""
    common = dict(rad_per_tick=rad_per_tick, lower=lower, upper=upper, control_dt=control_dt)
    if cfg.kind == "ik":
        return IKController(cfg, camera=camera, tip_length=tip_length, n_elements=n_elements, latency=latency, **common)
    return PIController(cfg, latency=latency, endoscope=endoscope, model_dt=model_dt,
                        camera=camera, **common)
