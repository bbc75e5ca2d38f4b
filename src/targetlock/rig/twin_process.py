"""The digital twin served over the real protocols (``targetlock sim-rig``).

Simulated CiA 402 drives on a CAN bus that crosses processes move the twin's handles; the
endoscope model turns handle angles into tip bending; a simulated NatNet server streams the base,
the tip (camera) and the target as rigid bodies. The unchanged hardware driver, NatNet client and
loop (``targetlock run --rig FILE``) then run against it exactly as against a rig.

The target's path starts when both drives have been homed, which is when the loop starts.
Homing on the current position makes that position zero: the twin therefore powers up with the
handles at neutral and the tip straight, whatever ``scene.start_tip_deg`` says.
"""
from __future__ import annotations

import dataclasses
import math
import threading
from typing import Callable

import numpy as np

from ..interfaces.rigfile import HardwareRigConfig
from ..interfaces.sim_cia402 import SimDriveSet, run_sim_drives
from ..interfaces.sim_natnet import SimNatNetConfig, SimNatNetServer
from ..model.drives import DriveParams
from ..model.endoscope import advance, pack_params
from ..model.twin import TwinConfig
from .simulated import SimulatedRig

__all__ = ["TwinPhysics", "serve_twin_rig"]


class TwinPhysics:
    """Endoscope + scene of the twin, advanced by the simulated drives' handle angles (thread-safe)."""

    def __init__(self, twin: TwinConfig, target_id: int) -> None:
        self.target_id = target_id
        twin = dataclasses.replace(twin, scene=dataclasses.replace(twin.scene, start_tip_deg=(0.0, 0.0)))
        self.twin = twin
        self.sim = SimulatedRig(twin)            # settled, scene anchored at the start camera pose
        # The drives' own model runs in the simulated drives; here the handle is where they say.
        self.params = pack_params(twin.endoscope, DriveParams(time_constant=0.0, max_velocity_ticks=1e12,
                                                              min_angle=-6.3, max_angle=6.3))
        self.lock = threading.Lock()
        self.last_t: float | None = None
        self.t_start: float | None = None
        self.is_started: Callable[[], bool] = lambda: False

    def on_angles(self, angles: np.ndarray, t: float) -> None:
        """Called by the drive simulator every physics tick with handle angles (rad) at time t (s)."""
        with self.lock:
            if self.last_t is not None and t > self.last_t:
                dt = t - self.last_t
                n = max(1, int(math.ceil(dt / self.twin.model_dt - 1e-9)))
                advance(self.sim.state, self.params, np.asarray(angles[:2], dtype=float)[None, :], dt / n, n)
            self.last_t = t
            if self.t_start is None and self.is_started():
                self.t_start = t

    def poses(self) -> tuple[np.ndarray, np.ndarray, dict[int, np.ndarray]]:
        """Base (identity), camera (tip) and target poses in the base frame (m)."""
        with self.lock:
            camera = self.sim.camera_pose()
            t_scene = 0.0 if self.t_start is None or self.last_t is None else self.last_t - self.t_start
        target = self.sim.scene.target_pose(t_scene)
        return np.eye(4), camera, {self.target_id: target}


def serve_twin_rig(rig: HardwareRigConfig, twin: TwinConfig, stop: threading.Event, *,
                   on_ready: Callable[[str], None] | None = None, mocap_rate: float = 120.0) -> None:
    """Run the twin's drives and motion capture until ``stop`` is set."""
    physics = TwinPhysics(twin, rig.observations.target_body_id)
    n = rig.natnet
    server = SimNatNetServer(SimNatNetConfig(
        multicast=n.multicast, multicast_group=n.multicast_group, data_port=n.data_port, command_port=n.command_port,
        server_ip=n.server_ip, rate_hz=mocap_rate, base_body_id=n.base_body_id, tip_body_id=n.tip_body_id,
        base_name=n.base_body_name or "EndoscopeBase", tip_name=n.tip_body_name or "EndoscopeTip"),
        physics.poses, names={rig.observations.target_body_id: rig.observations.target_body_name or "Target"})
    server.start()

    def ready(sims: SimDriveSet) -> None:
        nodes = [sims[i] for i in rig.can.node_ids]
        physics.is_started = lambda: all(d.homed for d in nodes)
        if on_ready is not None:
            bus = rig.can.bus
            on_ready(f"sim-rig ready: twin preset {twin.preset!r}, drives {list(rig.can.node_ids)} on "
                     f"{bus.interface}:{bus.channel} port {bus.port}; NatNet {server.describe()}")

    try:
        run_sim_drives(rig.can.bus, rig.can.node_ids, dataclasses.replace(rig.can.drive_params(),
                                                                           time_constant=twin.drive.time_constant),
                       stop, physics.on_angles, initial_angles=[0.0] * len(rig.can.node_ids), on_ready=ready)
    finally:
        server.stop()
