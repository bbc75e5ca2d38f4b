"""Exceptions shared by the hardware interfaces."""
from __future__ import annotations

from ..rig.base import DriveFault

__all__ = ["MotionRefused", "BusError"]


class MotionRefused(DriveFault):
    """A motion command was refused before reaching the drives: not homed, disabled, stopped,
    or an invalid set-point. Nothing was sent; the drives hold their last set-point."""


class BusError(DriveFault):
    """The CAN bus itself failed (interface down, send or receive error)."""
