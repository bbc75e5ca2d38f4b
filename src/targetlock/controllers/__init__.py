"""Controllers of the target lock: PI (+ hysteresis compensation), inverse kinematics, PI + prediction."""
from __future__ import annotations

import numpy as np

from .adaptive import AdaptiveController
from .base import CONTROLLERS, Controller, ControllerConfig
from .ik import IKController
from .knowledge import Knowledge, KnowledgeConfig, nominal_knowledge, resolve_knowledge
from .pi import PIController

__all__ = ["Controller", "ControllerConfig", "CONTROLLERS", "make_controller", "PIController", "IKController", "AdaptiveController",
           "Knowledge", "KnowledgeConfig", "resolve_knowledge", "nominal_knowledge"]


def make_controller(cfg: ControllerConfig, *, rad_per_tick: float, lower: np.ndarray, upper: np.ndarray,
                    control_dt: float, knowledge: Knowledge, model_dt: float = 0.001) -> Controller:
    """Build the controller ``cfg.kind`` with the rig's limits (rad) and what it assumes about the plant."""
    common = dict(rad_per_tick=rad_per_tick, lower=lower, upper=upper, control_dt=control_dt, knowledge=knowledge)
    if cfg.kind == "ik":
        return IKController(cfg, **common)
    if cfg.kind == "adaptive":
        return AdaptiveController(cfg, **common)
    return PIController(cfg, model_dt=model_dt, **common)
