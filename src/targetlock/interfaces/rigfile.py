"""The hardware rig file: CAN drives, NatNet motion capture and safety settings in one TOML file.

Sections ``[can]`` (with ``[can.bus]``), ``[natnet]`` and ``[safety]``; see
``examples/elmo_rig.toml`` and ``docs/hardware.md``. Unknown keys and out-of-range values are
refused with the dotted name of the setting and its allowed range.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..config import load_toml, param
from .cia402 import CanopenRigConfig
from .natnet import NatNetConfig
from .safety import SafetyConfig

__all__ = ["HardwareRigConfig", "load_rig_file"]


@dataclass(frozen=True)
class HardwareRigConfig:
    """Everything targetlock needs to talk to the TeleFLEX rig's drives and motion capture."""
    can: CanopenRigConfig = param(CanopenRigConfig(), doc="steering drives on CANopen")
    natnet: NatNetConfig = param(NatNetConfig(), doc="OptiTrack Motive stream")
    safety: SafetyConfig = param(SafetyConfig(), doc="safety supervisor around the drives")


def load_rig_file(path: str | Path) -> HardwareRigConfig:
    """Read and validate a rig file; raises ConfigError naming the bad setting."""
    return load_toml(HardwareRigConfig, path)
