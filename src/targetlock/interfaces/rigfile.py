"""The hardware rig file: CAN drives, NatNet motion capture and safety settings in one TOML file.

Sections ``[can]`` (with ``[can.bus]``), ``[natnet]``, ``[safety]`` and ``[observations]``; see
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

__all__ = ["HardwareRigConfig", "ObservationSourceConfig", "load_rig_file"]


@dataclass(frozen=True)
class ObservationSourceConfig:
    """Where the loop's target observations come from on this rig."""
    kind: str = param("mocap", choices=("mocap", "camera"),
                      doc="'mocap': the target rigid body projected into the tip camera (validation; the twin in "
                          "another process); 'camera': endoscope frames through the tracker")
    target_body_id: int = param(3, lo=0, hi=1000000, doc="Motive id of the target's rigid body (kind = 'mocap')")
    target_body_name: str = param("", doc="Motive asset name of the target's rigid body (overrides target_body_id)")
    device: str = param("0", doc="OpenCV capture device index, or a video file (kind = 'camera')")
    tracker: str = param("feature", choices=("feature", "marker"), doc="tracker for kind = 'camera'")
    window_px: int = param(96, unit="px", lo=8, hi=512, doc="target window selected at the image centre (kind = 'camera')")


@dataclass(frozen=True)
class HardwareRigConfig:
    """Everything targetlock needs to talk to the TeleFLEX rig's drives and motion capture."""
    can: CanopenRigConfig = param(CanopenRigConfig(), doc="steering drives on CANopen")
    natnet: NatNetConfig = param(NatNetConfig(), doc="OptiTrack Motive stream")
    safety: SafetyConfig = param(SafetyConfig(), doc="safety supervisor around the drives")
    observations: ObservationSourceConfig = param(ObservationSourceConfig(), doc="target observations")


def load_rig_file(path: str | Path) -> HardwareRigConfig:
    """Read and validate a rig file; raises ConfigError naming the bad setting."""
    return load_toml(HardwareRigConfig, path, "rig file")
