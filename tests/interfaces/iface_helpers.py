"""Helpers for the hardware-interface tests: simulated drives on an in-process virtual CAN bus."""
from __future__ import annotations

import socket
import time
import uuid
from contextlib import contextmanager
from dataclasses import replace

from targetlock.interfaces.canbus import CanBusConfig
from targetlock.interfaces.cia402 import CanopenDrives, CanopenRigConfig
from targetlock.interfaces.sim_cia402 import SimDriveBehaviour, SimDriveSet


def virtual_bus() -> CanBusConfig:
    """A virtual CAN bus of its own (unique channel name), so tests never hear each other."""
    return CanBusConfig(interface="virtual", channel=f"tl-test-{uuid.uuid4().hex[:12]}")


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def rig(initial_angles=(0.0, 0.0), encoder_offsets=(0, 0), start_driver=True,
        behaviour: SimDriveBehaviour = SimDriveBehaviour(), **cfg_overrides):
    """Simulated drives (with ``behaviour``) plus the driver on a fresh virtual bus; both closed afterwards."""
    # generous link-loss times: a loaded test machine can pause the simulated drives' threads
    for name, value in (("status_timeout", 0.3), ("heartbeat_timeout", 0.5), ("sdo_timeout", 0.5)):
        cfg_overrides.setdefault(name, value)
    cfg = replace(CanopenRigConfig(bus=virtual_bus()), **cfg_overrides)
    sims = SimDriveSet(cfg.bus, cfg.node_ids, cfg.drive_params(), initial_angles=initial_angles,
                       encoder_offsets=encoder_offsets, behaviour=behaviour)
    sims.start()
    drives = None
    try:
        if start_driver:
            drives = CanopenDrives(cfg)
        yield cfg, sims, drives
    finally:
        if drives is not None:
            drives.close()
        sims.stop()


def wait_until(pred, timeout: float, period: float = 0.005) -> bool:
    """Poll ``pred`` until it is true or ``timeout`` (s) has passed; its last value."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(period)
    return pred()
