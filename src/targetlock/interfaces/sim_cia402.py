"""Simulated CiA 402 steering drives: the device side of the CANopen link, with the twin's motor.

Each :class:`SimCiA402Drive` is a canopen :class:`~canopen.LocalNode` with the object dictionary
of :func:`.od402.build_object_dictionary` and implements what the driver needs from an Elmo drive:

* NMT slave with boot-up message and heartbeat producer (0x1017); NMT reset node / communication;
* the CiA 402 power state machine, driven by controlword (0x6040) writes, shown in the
  statusword (0x6041);
* profile position mode (0x6060 = 1) with the new-set-point handshake (controlword bit 4 new
  set-point, bit 5 change set immediately, bit 6 relative, bit 8 halt; statusword bit 12 set-point
  acknowledge, bit 10 target reached, bit 11 internal limit);
* cyclic synchronous position mode (0x6060 = 8): each target (0x607A, normally by a SYNC-driven
  RPDO) becomes the motor's demand at once; statusword bit 12 shows that the drive follows;
* homing mode (0x6060 = 6): methods 35/37 take the current position as home; methods 1-34 run a
  short homing motion to the handle's neutral (angle 0) at the homing speed (0x6099:1) and declare
  the home offset (0x607C) there; other methods end in a homing error (statusword bit 13);
* PDOs configured by SDO as CiA 301 prescribes (mapping only while the PDO is not valid):
  event-driven TPDOs (transmission type 254/255) sent on every statusword change and on their event
  timer (0x1800:5) with the inhibit time (0x1800:3); SYNC-driven TPDOs (1-240) and RPDOs;
* EMCY producer (0x1014), fault injection (:meth:`SimCiA402Drive.inject_fault`), fault reset, heartbeat
  consumer (0x1016) for the master's heartbeat with the reaction the master configured: abort
  connection option 0x6007 (none / fault / disable voltage / quick stop) and error behaviour
  0x1029:1 (NMT pre-operational / no change / stopped), and a "silent" mode that cuts the node off the bus;
* optional real-device behaviours (:class:`SimDriveBehaviour`) that independent drives showed:
  a strict set-point handshake processed in the drive's cycle, status PDOs on their timer only,
  slow SDO answers and a node that stops answering SDO.

The motor follows the twin's drive model (:func:`targetlock.model.drives.drive_step`): the handle
angle theta (rad) approaches the demanded angle with the model's time constant and rate limit
(the profile velocity 0x6081, at most the model's ``max_velocity_ticks``). Positions are ticks of
an incremental encoder: ``position = round(theta / rad_per_tick) + offset``; the offset is
arbitrary at power-up and set by homing.

:class:`SimDriveSet` runs several drives on one bus with a real-time physics thread (1 kHz by
default); :func:`run_sim_drives` wraps it for the rig twin and :func:`main` is the ``targetlock
sim-rig`` command (drives in their own process on ``udp_loopback``, optionally with a simulated
NatNet server streaming the tip pose).
"""
from __future__ import annotations

import argparse
import logging
import math
import signal
import struct
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import canopen
import can
import numpy as np
from canopen.sdo import SdoAbortedError

from ..config import ConfigError, load_toml, validate
from ..model.drives import DriveParams, drive_step
from ..rig.base import DriveFault
from . import od402 as o
from .canbus import CanBusConfig, open_bus
from .od402 import Command, State, decode_command

__all__ = ["SimCiA402Drive", "SimDriveBehaviour", "SimDriveSet", "run_sim_drives", "main", "add_sim_rig_arguments", "run_sim_rig",
           "PHYSICS_STEP_S"]

log = logging.getLogger(__name__)

PHYSICS_STEP_S = 0.001
"""Largest integration step of the motor model (s): 1 kHz simulated time."""
MAX_CATCH_UP_S = 0.05
"""If the physics thread was not scheduled for longer than this (s), the excess is dropped."""
NOTIFIER_CYCLE_S = 0.05
"""Receive-thread wake-up period of the simulated drives' network (s); bounds shutdown time."""

_ABORT_RANGE = 0x06090030
_ABORT_STATE = 0x08000022
_ABORT_NOT_MAPPABLE = 0x06040041
_ABORT_PDO_LENGTH = 0x06040042
_ABORT_INCOMPATIBLE = 0x06040043


@dataclass(frozen=True)
class SimDriveBehaviour:
    """Options that make the simulated drive behave like stricter real devices (defaults: lenient).

    ``strict_setpoint``: controlword bit 4 is read in the drive's cycle (the physics tick), not when
    the frame arrives; a rising edge is taken only when the set-point acknowledge (statusword bit
    12) is already low, and the acknowledge drops one cycle after bit 4 went low (CiA 402 profile
    position handshake as Elmo documents it). ``status_on_change``: False = TPDOs go out on their
    event timer only, not when the statusword changes (Elmo's default unless 0x2F20 selects events).
    ``sdo_delay``: seconds before each SDO answer (a busy drive).
    """
    strict_setpoint: bool = False
    status_on_change: bool = True
    sdo_delay: float = 0.0


@dataclass
class _Pdo:
    """Configuration and run-time state of one PDO (device side)."""
    cob: int
    trans_type: int = o.TRANS_EVENT_PROFILE
    inhibit_100us: int = 0
    event_timer_ms: int = 0
    sync_start: int = 0
    count: int = 0
    entries: list[int] = field(default_factory=lambda: [0] * 8)
    last_tx: float = -1e9
    pending_event: bool = False
    rx_buffer: bytes | None = None

    @property
    def valid(self) -> bool:
        return not self.cob & o.PDO_COB_INVALID

    @property
    def can_id(self) -> int:
        return self.cob & 0x7FF

    def mapped(self) -> list[tuple[int, int, int]]:
        return [(e >> 16, (e >> 8) & 0xFF, e & 0xFF) for e in self.entries[:self.count]]


class SimCiA402Drive:
    """One simulated CiA 402 drive (device side) whose motor is the twin's drive model.

    ``params``: the twin's drive parameters (rad/tick, rate limit, time constant, angle range);
    ``initial_angle``: handle angle at power-up (rad); ``encoder_offset``: position reading
    (ticks) at angle 0 before homing; ``master_node_id``: node id whose heartbeat 0x1016 refers to.
    """

    def __init__(self, node_id: int, params: DriveParams, *, initial_angle: float = 0.0,
                 encoder_offset: int = 0, behaviour: SimDriveBehaviour = SimDriveBehaviour()) -> None:
        self.node_id = int(node_id)
        self.params = params
        self.behaviour = behaviour
        self._cw_seen = 0              # strict handshake: controlword as of the last drive cycle
        self._ack_drop_due = False
        self._sdo_mute = False
        self.node = canopen.LocalNode(self.node_id, o.build_object_dictionary(self.node_id))
        self.network: canopen.Network | None = None
        self._lock = threading.RLock()
        # motor (SI)
        self.angle = float(initial_angle)
        """Handle angle (rad): the twin's physical truth."""
        self._demand = float(initial_angle)
        self._velocity_ticks = 0.0
        self._offset = int(encoder_offset)
        # device state
        self.state = State.NOT_READY_TO_SWITCH_ON
        self._cw = 0
        self._mode = o.MODE_PROFILE_POSITION
        self._target_raw = 0
        self._target_active = 0
        self._pending_target: int | None = None
        self._ack = False
        self._limited = False
        self._homing = "idle"          # idle | running | attained | error | interrupted
        self.homed = False
        """True once a homing procedure has completed since power-up / reset node."""
        self._error_code = 0
        self._error_register = 0
        self._persistent_fault = False
        self._qs_deadline: float | None = None
        self._fault_pending: tuple[int, int, bytes, bool] | None = None
        self._params_od: dict[tuple[int, int], int] = {}
        self._reset_parameters()
        self._rpdos: list[_Pdo] = []
        self._tpdos: list[_Pdo] = []
        self._reset_communication_objects()
        self._rx_subscribed: dict[int, int] = {}
        self._sync_count = 0
        self._last_sw_sent: int | None = None
        self._silent = False
        self._heartbeat_stopped = False
        self._master_hb_seen: float | None = None
        self._master_hb_id = 0
        self._now = time.monotonic()
        self.node.add_read_callback(self._on_read)
        self.node.add_write_callback(self._on_write)
        self.stats = {"rpdo": 0, "tpdo": 0, "sync": 0, "emcy": 0, "setpoints": 0, "ignored_edges": 0}

    # ---------------------------------------------------------------- wiring and NMT

    def attach(self, network: canopen.Network) -> None:
        """Put the node on ``network`` and run the boot-up sequence (boot-up message, pre-operational)."""
        self.network = network
        network[self.node_id] = self.node
        network.unsubscribe(self.node.sdo.rx_cobid, self.node.sdo.on_request)
        network.subscribe(self.node.sdo.rx_cobid, self._on_sdo_request)
        network.subscribe(0, self._on_nmt)
        network.subscribe(0x80, self._on_sync)
        self.boot()

    def boot(self) -> None:
        """Power-up / reset-node behaviour: application and communication reset, boot-up message."""
        with self._lock:
            self.state = State.SWITCH_ON_DISABLED
            self._cw = 0
            self._homing = "idle"
            self._ack = False
            self._pending_target = None
            self._demand = self.angle
        self._boot_communication()

    def _boot_communication(self) -> None:
        with self._lock:
            self._reset_communication_objects()
            self._resubscribe_rpdos()
            self._last_sw_sent = None
        nmt = self.node.nmt
        nmt.stop_heartbeat()
        nmt._state = 0
        nmt.send_command(0x81)            # INITIALISING: sends the boot-up message
        nmt.send_command(0x80)            # -> PRE-OPERATIONAL: starts the heartbeat producer (0x1017)
        if self._heartbeat_stopped:
            nmt.stop_heartbeat()

    def _on_sdo_request(self, can_id: int, data: bytes, timestamp: float) -> None:
        if self._silent or self._sdo_mute:
            return
        if self.behaviour.sdo_delay > 0:
            t = threading.Timer(self.behaviour.sdo_delay, self.node.sdo.on_request, (can_id, data, timestamp))
            t.daemon = True
            t.start()
        else:
            self.node.sdo.on_request(can_id, data, timestamp)

    def _on_nmt(self, can_id: int, data: bytes, timestamp: float) -> None:
        if self._silent or len(data) < 2:
            return
        cmd, target = data[0], data[1]
        if target not in (0, self.node_id):
            return
        if cmd == 0x81:
            log.info("node %d: NMT reset node", self.node_id)
            with self._lock:
                self.homed = False
                self._reset_parameters()
            self.boot()
        elif cmd == 0x82:
            log.info("node %d: NMT reset communication", self.node_id)
            self._boot_communication()
        elif cmd == 0x02:
            pass  # STOPPED: canopen's NmtSlave already changed the state; PDOs stop below

    @property
    def nmt_state(self) -> str:
        return self.node.nmt.state

    def _operational(self) -> bool:
        return self.node.nmt.state == "OPERATIONAL"

    # ---------------------------------------------------------------- test hooks

    def inject_fault(self, code: int = 0x7121, *, persistent: bool = False, data: bytes = b"") -> None:
        """Make the drive fault: fault bit, error code 0x603F, error register 0x1001, EMCY message.

        ``persistent`` faults survive a fault reset until :meth:`clear_fault` (a condition that is
        still present, e.g. STO).
        """
        with self._lock:
            self._enter_fault(code, data, persistent)
        self.service(time.monotonic())

    def clear_fault(self) -> None:
        """Remove the cause of a persistent fault (a following fault reset then succeeds)."""
        with self._lock:
            self._persistent_fault = False

    def stop_heartbeat(self) -> None:
        """Stop the heartbeat producer (the node otherwise keeps working)."""
        self._heartbeat_stopped = True
        self.node.nmt.stop_heartbeat()

    def set_sdo_mute(self, mute: bool = True) -> None:
        """Stop answering SDO requests (PDOs, heartbeat and EMCY go on), as a drive with a hung SDO server."""
        self._sdo_mute = mute

    def set_silent(self, silent: bool = True) -> None:
        """Cut the node off the bus (no heartbeat, no PDO, no SDO answers), as a broken cable would."""
        self._silent = silent
        if self.network is None:
            return
        if silent:
            self.node.nmt.stop_heartbeat()
        else:
            if not self._heartbeat_stopped:
                self.node.nmt.start_heartbeat(self._params_od[(o.PRODUCER_HEARTBEAT, 0)])

    # ---------------------------------------------------------------- values

    @property
    def position_ticks(self) -> int:
        """Position actual value (ticks, encoder frame)."""
        return int(round(self.angle / self.params.rad_per_tick)) + self._offset

    def _ticks_to_angle(self, ticks: int) -> float:
        return (ticks - self._offset) * self.params.rad_per_tick

    def statusword(self) -> int:
        with self._lock:
            sw = o.STATE_BITS.get(self.state, 0) | o.SW_REMOTE
            if self.state == State.OPERATION_ENABLED:
                if self._mode == o.MODE_PROFILE_POSITION:
                    window = self._params_od[(o.POSITION_WINDOW, 0)]
                    reached = self._pending_target is None and abs(self.position_ticks - self._target_active) <= window
                    if self._cw & o.CW_HALT:
                        reached = abs(self._velocity_ticks) < 1.0
                    sw |= (o.SW_TARGET_REACHED if reached else 0) | (o.SW_SETPOINT_ACK if self._ack else 0)
                    sw |= o.SW_INTERNAL_LIMIT if self._limited else 0
                elif self._mode == o.MODE_CYCLIC_SYNC_POSITION:
                    sw |= o.SW_FOLLOWING | (o.SW_INTERNAL_LIMIT if self._limited else 0)
                elif self._mode == o.MODE_HOMING:
                    sw |= {"idle": o.SW_TARGET_REACHED, "interrupted": o.SW_TARGET_REACHED, "running": 0,
                           "attained": o.SW_HOMING_ATTAINED | o.SW_TARGET_REACHED,
                           "error": o.SW_HOMING_ERROR | o.SW_TARGET_REACHED}[self._homing]
            return sw

    def _reset_parameters(self) -> None:
        d = self.node.object_dictionary
        for index in (o.POSITION_WINDOW, o.HOME_OFFSET, o.PROFILE_VELOCITY, o.PROFILE_ACCELERATION,
                      o.PROFILE_DECELERATION, o.QUICK_STOP_DECELERATION, o.HOMING_METHOD, o.HOMING_ACCELERATION,
                      o.QUICK_STOP_OPTION, o.PRODUCER_HEARTBEAT, o.ABORT_CONNECTION_OPTION, o.SHUTDOWN_OPTION,
                      o.DISABLE_OPERATION_OPTION, o.HALT_OPTION, o.FAULT_REACTION_OPTION, o.EMCY_COB_ID):
            self._params_od[(index, 0)] = d[index].default
        for index, subs in ((o.SOFTWARE_LIMITS, (1, 2)), (o.HOMING_SPEEDS, (1, 2)), (o.CONSUMER_HEARTBEAT, (1,)),
                            (o.ERROR_BEHAVIOUR, (1,)), (o.INTERPOLATION_PERIOD, (1, 2))):
            for s in subs:
                self._params_od[(index, s)] = d[index][s].default

    def _reset_communication_objects(self) -> None:
        d = self.node.object_dictionary
        self._rpdos, self._tpdos = [], []
        for n in range(o.N_PDO):
            for comm, mapping, dest in ((o.RPDO_COMM, o.RPDO_MAP, self._rpdos), (o.TPDO_COMM, o.TPDO_MAP, self._tpdos)):
                c, m = d[comm + n], d[mapping + n]
                pdo = _Pdo(cob=c[1].default, trans_type=c[2].default, inhibit_100us=c[3].default,
                           event_timer_ms=c[5].default, count=m[0].default,
                           entries=[m[k].default for k in range(1, 9)])
                dest.append(pdo)
        self._params_od[(o.PRODUCER_HEARTBEAT, 0)] = d[o.PRODUCER_HEARTBEAT].default
        self._params_od[(o.CONSUMER_HEARTBEAT, 1)] = d[o.CONSUMER_HEARTBEAT][1].default
        self._master_hb_seen = None

    # ---------------------------------------------------------------- SDO / OD access

    def _on_read(self, index: int, subindex: int, od) -> int | None:
        with self._lock:
            if index == o.STATUSWORD:
                return self.statusword()
            if index == o.CONTROLWORD:
                return self._cw
            if index == o.POSITION_ACTUAL:
                return self.position_ticks
            if index == o.POSITION_DEMAND:
                return int(round(self._demand / self.params.rad_per_tick)) + self._offset
            if index == o.VELOCITY_ACTUAL:
                return int(round(self._velocity_ticks))
            if index == o.TARGET_POSITION:
                return self._target_raw
            if index in (o.MODES_OF_OPERATION, o.MODES_DISPLAY):
                return self._mode
            if index == o.ERROR_CODE:
                return self._error_code
            if index == o.ERROR_REGISTER:
                return self._error_register
            if (index, subindex) in self._params_od:
                return self._params_od[(index, subindex)]
            pdo = self._pdo_for(index)
            if pdo is not None:
                return self._read_pdo_object(pdo, index, subindex)
        return None

    def _pdo_for(self, index: int) -> _Pdo | None:
        for base, table in ((o.RPDO_COMM, self._rpdos), (o.RPDO_MAP, self._rpdos),
                            (o.TPDO_COMM, self._tpdos), (o.TPDO_MAP, self._tpdos)):
            if base <= index < base + o.N_PDO:
                return table[index - base]
        return None

    @staticmethod
    def _read_pdo_object(pdo: _Pdo, index: int, subindex: int) -> int | None:
        if (index & 0xFF00) in (o.RPDO_MAP, o.TPDO_MAP):
            return pdo.count if subindex == 0 else pdo.entries[subindex - 1]
        return {0: None, 1: pdo.cob, 2: pdo.trans_type, 3: pdo.inhibit_100us, 4: 0,
                5: pdo.event_timer_ms, 6: pdo.sync_start}.get(subindex)

    def _on_write(self, index: int, subindex: int, od, data: bytes) -> None:
        """SDO / RPDO writes; raising SdoAbortedError rejects the write (the SDO client sees the abort)."""
        value = od.decode_raw(data)
        with self._lock:
            if index == o.CONTROLWORD:
                self._apply_controlword(int(value))
            elif index == o.TARGET_POSITION:
                self._target_raw = int(value)
                if self._mode == o.MODE_CYCLIC_SYNC_POSITION and self.state == State.OPERATION_ENABLED:
                    self._target_active = self._clamp_target(int(value))
                    self._demand = self._ticks_to_angle(self._target_active)
                    self.stats["setpoints"] += 1
            elif index == o.MODES_OF_OPERATION:
                if value not in (o.MODE_PROFILE_POSITION, o.MODE_HOMING, o.MODE_CYCLIC_SYNC_POSITION):
                    raise SdoAbortedError(_ABORT_RANGE)
                if value != self._mode:
                    self._mode = int(value)
                    self._demand = self.angle
                    self._pending_target = None
                    self._ack = False
                    self._target_active = self.position_ticks
                    if self._homing == "running":
                        self._homing = "interrupted"
            elif index == o.PRODUCER_HEARTBEAT:
                self._params_od[(index, 0)] = int(value)
                # canopen's NmtSlave (registered first) has restarted the producer already
                if self._heartbeat_stopped or self._silent:
                    self.node.nmt.stop_heartbeat()
            elif index == o.CONSUMER_HEARTBEAT:
                if subindex != 1:
                    raise SdoAbortedError(0x06010002)
                self._set_consumer_heartbeat(int(value))
            elif (index, subindex) in self._params_od:
                self._params_od[(index, subindex)] = int(value)
            else:
                pdo = self._pdo_for(index)
                if pdo is not None:
                    self._write_pdo_object(pdo, index, subindex, int(value))
            self._after_change()

    def _set_consumer_heartbeat(self, value: int) -> None:
        master = (value >> 16) & 0x7F
        if self.network is not None and self._master_hb_id:
            try:
                self.network.unsubscribe(0x700 + self._master_hb_id, self._on_master_heartbeat)
            except (KeyError, ValueError):
                pass
        self._params_od[(o.CONSUMER_HEARTBEAT, 1)] = value
        self._master_hb_id = master
        self._master_hb_seen = None
        if self.network is not None and master:
            self.network.subscribe(0x700 + master, self._on_master_heartbeat)

    def _on_master_heartbeat(self, can_id: int, data: bytes, timestamp: float) -> None:
        self._master_hb_seen = time.monotonic()

    def _write_pdo_object(self, pdo: _Pdo, index: int, subindex: int, value: int) -> None:
        is_map = (index & 0xFF00) in (o.RPDO_MAP, o.TPDO_MAP)
        if is_map:
            if pdo.valid:
                raise SdoAbortedError(_ABORT_STATE)   # CiA 301: map only while the PDO is not valid
            if subindex == 0:
                if value > 8:
                    raise SdoAbortedError(_ABORT_PDO_LENGTH)
                total = 0
                for k in range(value):
                    idx, sub, bits = pdo.entries[k] >> 16, (pdo.entries[k] >> 8) & 0xFF, pdo.entries[k] & 0xFF
                    total += self._check_mappable(idx, sub, bits)
                if total > 64:
                    raise SdoAbortedError(_ABORT_PDO_LENGTH)
                pdo.count = value
            else:
                if pdo.count != 0:
                    raise SdoAbortedError(_ABORT_STATE)
                if value:
                    self._check_mappable(value >> 16, (value >> 8) & 0xFF, value & 0xFF)
                pdo.entries[subindex - 1] = value
            return
        if subindex == 1:
            if pdo.valid and not value & o.PDO_COB_INVALID and (value & 0x7FF) != pdo.can_id:
                raise SdoAbortedError(_ABORT_RANGE)   # COB-ID changes only while not valid
            pdo.cob = value
            self._resubscribe_rpdos()
        elif subindex == 2:
            if not (value <= 240 or value >= 252):
                raise SdoAbortedError(_ABORT_RANGE)
            pdo.trans_type = value
        elif subindex == 3:
            pdo.inhibit_100us = value
        elif subindex == 5:
            pdo.event_timer_ms = value
        elif subindex == 6:
            pdo.sync_start = value

    def _check_mappable(self, index: int, subindex: int, bits: int) -> int:
        var = self.node.object_dictionary.get_variable(index, subindex)
        if var is None or not var.pdo_mappable or bits != len(var):
            raise SdoAbortedError(_ABORT_NOT_MAPPABLE)
        return bits

    # ---------------------------------------------------------------- PDO traffic

    def _resubscribe_rpdos(self) -> None:
        if self.network is None:
            return
        for can_id in list(self._rx_subscribed):
            try:
                self.network.unsubscribe(can_id, self._on_rpdo)
            except (KeyError, ValueError):
                pass
        self._rx_subscribed = {}
        for i, pdo in enumerate(self._rpdos):
            if pdo.valid:
                self._rx_subscribed[pdo.can_id] = i
                self.network.subscribe(pdo.can_id, self._on_rpdo)

    def _on_rpdo(self, can_id: int, data: bytes, timestamp: float) -> None:
        if self._silent or not self._operational():
            return
        i = self._rx_subscribed.get(can_id)
        if i is None:
            return
        pdo = self._rpdos[i]
        self.stats["rpdo"] += 1
        if 1 <= pdo.trans_type <= 240 or pdo.trans_type == 0:
            pdo.rx_buffer = bytes(data)           # applied on the next SYNC
            return
        self._apply_rpdo(pdo, bytes(data))

    def _apply_rpdo(self, pdo: _Pdo, data: bytes) -> None:
        with self._lock:
            offset, cw = 0, None
            for index, subindex, bits in pdo.mapped():
                n = bits // 8
                if offset + n > len(data):
                    return                         # too short: CiA 301 says ignore (EMCY 0x8210 on real drives)
                chunk = data[offset:offset + n]
                offset += n
                if index == o.CONTROLWORD:
                    cw = struct.unpack("<H", chunk)[0]   # applied after the other objects of this PDO
                    continue
                try:
                    self.node.set_data(index, subindex, chunk, check_writable=True)
                except SdoAbortedError:
                    pass
            if cw is not None:
                self.node.set_data(o.CONTROLWORD, 0, struct.pack("<H", cw))

    def _on_sync(self, can_id: int, data: bytes, timestamp: float) -> None:
        if self._silent or not self._operational():
            return
        self.stats["sync"] += 1
        self._sync_count += 1
        for pdo in self._rpdos:
            if pdo.valid and pdo.rx_buffer is not None:
                buf, pdo.rx_buffer = pdo.rx_buffer, None
                self._apply_rpdo(pdo, buf)
        for pdo in self._tpdos:
            if pdo.valid and (pdo.trans_type == 0 or 1 <= pdo.trans_type <= 240):
                if pdo.trans_type == 0 or self._sync_count % pdo.trans_type == 0:
                    self._transmit(pdo, time.monotonic())

    def _tpdo_payload(self, pdo: _Pdo) -> bytes:
        return b"".join(self.node.get_data(index, subindex) for index, subindex, _ in pdo.mapped())

    def _transmit(self, pdo: _Pdo, now: float) -> None:
        if self.network is None or self._silent:
            return
        payload = self._tpdo_payload(pdo)
        pdo.last_tx = now
        pdo.pending_event = False
        try:
            self.network.send_message(pdo.can_id, payload)
            self.stats["tpdo"] += 1
        except (can.CanError, RuntimeError) as exc:
            log.debug("node %d: TPDO not sent: %s", self.node_id, exc)

    def _after_change(self) -> None:
        """Send event-driven TPDOs when the statusword changed (CiA 301 'application event')."""
        sw = self.statusword()
        if sw == self._last_sw_sent:
            return
        self._last_sw_sent = sw
        if not self._operational() or not self.behaviour.status_on_change:
            return
        now = time.monotonic()
        for pdo in self._tpdos:
            if pdo.valid and pdo.trans_type >= 254:
                if now - pdo.last_tx >= pdo.inhibit_100us * 1e-4:
                    self._transmit(pdo, now)
                else:
                    pdo.pending_event = True

    # ---------------------------------------------------------------- state machine

    def _enter_fault(self, code: int, data: bytes = b"", persistent: bool = False) -> None:
        if self.state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            return
        self.state = State.FAULT_REACTION_ACTIVE
        self._demand = self.angle
        self._pending_target = None
        self._ack = False
        if self._homing == "running":
            self._homing = "error"
        self._error_code = code & 0xFFFF
        category = {0x2: 0x02, 0x3: 0x04, 0x4: 0x08, 0x8: 0x10}.get(code >> 12, 0x80)
        self._error_register = 0x01 | category
        self._persistent_fault = persistent
        self._fault_pending = (code, self._error_register, data[:5], persistent)

    def _leave_operation(self) -> None:
        self._demand = self.angle
        self._pending_target = None
        self._ack = False
        if self._homing == "running":
            self._homing = "interrupted"

    def _apply_controlword(self, cw: int) -> None:
        prev, self._cw = self._cw, cw
        rising = cw & ~prev
        falling = prev & ~cw
        if cw & o.CW_FAULT_RESET:
            if rising & o.CW_FAULT_RESET and self.state == State.FAULT and not self._persistent_fault:
                self.state = State.SWITCH_ON_DISABLED
                self._error_code = 0
                self._error_register = 0
                self._send_emcy(0, 0, b"")
            return
        cmd = decode_command(cw)
        st = self.state
        new = st
        if st == State.SWITCH_ON_DISABLED:
            if cmd == Command.SHUTDOWN:
                new = State.READY_TO_SWITCH_ON
        elif st == State.READY_TO_SWITCH_ON:
            new = {Command.SWITCH_ON: State.SWITCHED_ON, Command.ENABLE_OPERATION: State.OPERATION_ENABLED,
                   Command.DISABLE_VOLTAGE: State.SWITCH_ON_DISABLED,
                   Command.QUICK_STOP: State.SWITCH_ON_DISABLED}.get(cmd, st)
        elif st == State.SWITCHED_ON:
            new = {Command.ENABLE_OPERATION: State.OPERATION_ENABLED, Command.SHUTDOWN: State.READY_TO_SWITCH_ON,
                   Command.DISABLE_VOLTAGE: State.SWITCH_ON_DISABLED,
                   Command.QUICK_STOP: State.SWITCH_ON_DISABLED}.get(cmd, st)
        elif st == State.OPERATION_ENABLED:
            new = {Command.SWITCH_ON: State.SWITCHED_ON, Command.SHUTDOWN: State.READY_TO_SWITCH_ON,
                   Command.DISABLE_VOLTAGE: State.SWITCH_ON_DISABLED,
                   Command.QUICK_STOP: State.QUICK_STOP_ACTIVE}.get(cmd, st)
        elif st == State.QUICK_STOP_ACTIVE:
            if cmd == Command.DISABLE_VOLTAGE:
                new = State.SWITCH_ON_DISABLED
            elif cmd == Command.ENABLE_OPERATION and self._params_od[(o.QUICK_STOP_OPTION, 0)] in (5, 6, 7, 8):
                new = State.OPERATION_ENABLED
        if new != st:
            if st == State.OPERATION_ENABLED:
                self._leave_operation()
            if new == State.QUICK_STOP_ACTIVE:
                self._demand = self.angle
                self._qs_deadline = self._now        # stopped (first-order motor, no inertia)
            if new == State.OPERATION_ENABLED:
                self._demand = self.angle
                self._target_active = self.position_ticks
                self._pending_target = None
                self._ack = False
                # a set-point bit already high on enabling is not an edge
                rising &= ~o.CW_NEW_SETPOINT
                self._cw_seen = cw
            self.state = new
            log.debug("node %d: %s -> %s (cw 0x%04X)", self.node_id, st.value, new.value, cw)
        if self.state != State.OPERATION_ENABLED:
            return
        if self._mode == o.MODE_PROFILE_POSITION:
            if self.behaviour.strict_setpoint:
                return                        # bit 4 is sampled in the drive's cycle (_strict_cycle)
            if rising & o.CW_NEW_SETPOINT:
                self._new_setpoint(cw)
            if falling & o.CW_NEW_SETPOINT and self._pending_target is None:
                self._ack = False
            if rising & o.CW_HALT:
                self._demand = self.angle
            if falling & o.CW_HALT:
                self._demand = self._ticks_to_angle(self._target_active)
        elif self._mode == o.MODE_HOMING:
            if rising & o.CW_HOMING_START:
                self._start_homing()
            if falling & o.CW_HOMING_START and self._homing == "running":
                self._homing = "interrupted"
                self._demand = self.angle

    def _strict_cycle(self) -> None:
        """Strict handshake, once per drive cycle: bit 4 is sampled here; an edge counts only when
        the acknowledge is low; the acknowledge drops the cycle after bit 4 went low."""
        cw, prev = self._cw, self._cw_seen
        self._cw_seen = cw
        if self.state != State.OPERATION_ENABLED or self._mode != o.MODE_PROFILE_POSITION:
            return
        if self._ack_drop_due:
            self._ack_drop_due = False
            if not cw & o.CW_NEW_SETPOINT and self._pending_target is None:
                self._ack = False
        if cw & o.CW_NEW_SETPOINT and not prev & o.CW_NEW_SETPOINT:
            if self._ack:
                self.stats["ignored_edges"] += 1      # acknowledge still high: not an edge for this drive
            else:
                self._new_setpoint(cw)
        elif prev & o.CW_NEW_SETPOINT and not cw & o.CW_NEW_SETPOINT:
            self._ack_drop_due = True

    def _clamp_target(self, target: int) -> int:
        p = self.params
        lo, hi = p.min_ticks + self._offset, p.max_ticks + self._offset
        smin, smax = self._params_od[(o.SOFTWARE_LIMITS, 1)], self._params_od[(o.SOFTWARE_LIMITS, 2)]
        if smin < smax:
            lo, hi = max(lo, smin), min(hi, smax)
        clamped = min(max(target, lo), hi)
        self._limited = clamped != target
        return clamped

    def _new_setpoint(self, cw: int) -> None:
        target = self._target_raw
        if cw & o.CW_RELATIVE:
            target = self._target_active + target
        target = self._clamp_target(int(target))
        self.stats["setpoints"] += 1
        window = self._params_od[(o.POSITION_WINDOW, 0)]
        idle = self._pending_target is None and abs(self.position_ticks - self._target_active) <= window
        if cw & o.CW_CHANGE_IMMEDIATELY or idle:
            self._target_active = target
            self._pending_target = None
            if not cw & o.CW_HALT:
                self._demand = self._ticks_to_angle(target)
        else:
            self._pending_target = target
        self._ack = True

    def _start_homing(self) -> None:
        method = self._params_od[(o.HOMING_METHOD, 0)]
        if method in o.HOMING_ON_CURRENT_POSITION:
            self._finish_homing()
        elif 1 <= method <= 34:
            self._homing = "running"
            self._demand = self.angle
        else:
            self._homing = "error"

    def _finish_homing(self, home_angle: float | None = None) -> None:
        """Declare the home position: ``home_angle`` (rad; the neutral's index for switch methods) or here."""
        home = self._params_od[(o.HOME_OFFSET, 0)]
        at = self.angle if home_angle is None else home_angle
        self._offset = home - int(round(at / self.params.rad_per_tick))
        self._homing = "attained"
        self.homed = True
        self._demand = self.angle
        self._target_active = self.position_ticks
        self._target_raw = self._target_active

    def _send_emcy(self, code: int, register: int, data: bytes) -> None:
        if self.network is None or self._silent or self._params_od[(o.EMCY_COB_ID, 0)] & o.PDO_COB_INVALID:
            return
        try:
            self.node.emcy.send(code, register, data.ljust(5, b"\0"))
            self.stats["emcy"] += 1
        except (can.CanError, RuntimeError) as exc:
            log.debug("node %d: EMCY not sent: %s", self.node_id, exc)

    # ---------------------------------------------------------------- physics and timers

    def advance(self, dt: float) -> None:
        """Move the motor by ``dt`` seconds of simulated time (sub-stepped at <= 1 ms)."""
        if dt <= 0.0:
            return
        p = self.params
        with self._lock:
            steps = max(1, int(math.ceil(dt / PHYSICS_STEP_S - 1e-9)))
            h = dt / steps
            powered = self.state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE)
            vmax_ticks = p.max_velocity_ticks
            if self.state == State.OPERATION_ENABLED and self._mode == o.MODE_PROFILE_POSITION:
                vmax_ticks = min(vmax_ticks, max(1.0, float(self._params_od[(o.PROFILE_VELOCITY, 0)])))
            homing = self.state == State.OPERATION_ENABLED and self._mode == o.MODE_HOMING and self._homing == "running"
            if homing:
                vmax_ticks = min(vmax_ticks, max(1.0, float(self._params_od[(o.HOMING_SPEEDS, 1)])))
                self._demand = 0.0                              # the handle's neutral: home switch / index
            start = self.angle
            if powered:
                demand = min(max(self._demand, p.min_angle), p.max_angle)
                theta = self.angle
                vmax = vmax_ticks * p.rad_per_tick
                for _ in range(steps):
                    theta = drive_step(theta, demand, h, p.time_constant, vmax)
                self.angle = theta
            self._velocity_ticks = (self.angle - start) / dt / p.rad_per_tick
            if homing and abs(self.angle) <= self._params_od[(o.POSITION_WINDOW, 0)] * p.rad_per_tick:
                self._finish_homing(home_angle=0.0)
            if (self._pending_target is not None and self.state == State.OPERATION_ENABLED
                    and abs(self.position_ticks - self._target_active) <= self._params_od[(o.POSITION_WINDOW, 0)]):
                self._target_active, self._pending_target = self._pending_target, None
                self._demand = self._ticks_to_angle(self._target_active)
                if not self._cw & o.CW_NEW_SETPOINT:
                    self._ack = False

    def _host_lost(self) -> tuple[int, int, bytes, bool] | None:
        """The drive's own reaction to a lost master heartbeat (0x6007); returns a fault to report."""
        option = self._params_od[(o.ABORT_CONNECTION_OPTION, 0)]
        if option == 1 and self.state not in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            self._enter_fault(0x8130)
            self.state = State.FAULT
            fault, self._fault_pending = self._fault_pending, None
            return fault
        if option == 2:
            self._apply_controlword(o.CW_DISABLE_VOLTAGE)
        elif option == 3:
            self._apply_controlword(o.CW_QUICK_STOP)
        return None

    def service(self, now: float) -> None:
        """Timers: automatic state transitions, EMCY, heartbeat consumer, TPDO event timers."""
        self._now = now
        fault = None
        with self._lock:
            if self.state == State.FAULT_REACTION_ACTIVE:
                self.state = State.FAULT
                fault, self._fault_pending = self._fault_pending, None
            if self.state == State.QUICK_STOP_ACTIVE and self._qs_deadline is not None and now >= self._qs_deadline:
                if self._params_od[(o.QUICK_STOP_OPTION, 0)] in (0, 1, 2, 3):
                    self.state = State.SWITCH_ON_DISABLED
                    self._qs_deadline = None
            if self.behaviour.strict_setpoint:
                self._strict_cycle()
            hb = self._params_od[(o.CONSUMER_HEARTBEAT, 1)]
            hb_ms = hb & 0xFFFF
            lost = False
            if hb_ms and self._master_hb_seen is not None and now - self._master_hb_seen > hb_ms * 1e-3:
                log.warning("node %d: master heartbeat lost", self.node_id)
                self._master_hb_seen = None
                lost = True
                fault = self._host_lost()
            if fault is not None:
                self._send_emcy(fault[0], fault[1], fault[2])
            elif lost:
                self._send_emcy(0x8130, 0x11, b"")
            if lost:
                behaviour = self._params_od[(o.ERROR_BEHAVIOUR, 1)]
                if behaviour == 0 and self._operational():
                    self.node.nmt.state = "PRE-OPERATIONAL"
                elif behaviour == 2:
                    self.node.nmt.state = "STOPPED"
            self._after_change()
            if self._operational():
                for pdo in self._tpdos:
                    if not pdo.valid or pdo.trans_type < 254:
                        continue
                    inhibit = pdo.inhibit_100us * 1e-4
                    if pdo.pending_event and now - pdo.last_tx >= inhibit:
                        self._transmit(pdo, now)
                    elif pdo.event_timer_ms and now - pdo.last_tx >= pdo.event_timer_ms * 1e-3:
                        self._transmit(pdo, now)


class SimDriveSet:
    """Several simulated drives on one CAN bus, advanced in real time by a physics thread.

    ``bus``: a :class:`CanBusConfig` (opened here) or an open python-can bus;
    ``node_ids``: one drive per id, in axis order; ``params``: the twin's drive parameters;
    ``tick_s``: physics/timer period (s); ``on_angles(angles, t)``: called after every tick with
    the handle angles (rad, array in ``node_ids`` order) and the monotonic time ``t`` (s).
    """

    def __init__(self, bus: CanBusConfig | can.BusABC, node_ids: Sequence[int], params: DriveParams, *,
                 tick_s: float = PHYSICS_STEP_S, initial_angles: Sequence[float] | None = None,
                 encoder_offsets: Sequence[int] | None = None,
                 on_angles: Callable[[np.ndarray, float], None] | None = None,
                 behaviour: SimDriveBehaviour = SimDriveBehaviour()) -> None:
        self._bus_arg = bus
        self.params = params
        self.tick_s = float(tick_s)
        self.on_angles = on_angles
        n = len(node_ids)
        initial_angles = list(initial_angles) if initial_angles is not None else [0.0] * n
        encoder_offsets = list(encoder_offsets) if encoder_offsets is not None else [0] * n
        self.drives = [SimCiA402Drive(nid, params, initial_angle=a, encoder_offset=e, behaviour=behaviour)
                       for nid, a, e in zip(node_ids, initial_angles, encoder_offsets)]
        self.network: canopen.Network | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.ticks = 0
        self.error: BaseException | None = None

    def __getitem__(self, node_id: int) -> SimCiA402Drive:
        for d in self.drives:
            if d.node_id == node_id:
                return d
        raise KeyError(node_id)

    def angles(self) -> np.ndarray:
        """Handle angles (rad) in node order."""
        return np.array([d.angle for d in self.drives])

    def start(self) -> "SimDriveSet":
        drive_step(0.0, 1.0, PHYSICS_STEP_S, 0.01, 1.0)   # compile the motor model before any thread needs it
        bus = open_bus(self._bus_arg) if isinstance(self._bus_arg, CanBusConfig) else self._bus_arg
        net = canopen.Network(bus)
        net.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
        net.connect()
        self.network = net
        for d in self.drives:
            d.attach(net)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="sim-cia402-physics", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        last = time.monotonic()
        next_tick = last
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                dt = min(now - last, MAX_CATCH_UP_S)
                last = now
                for d in self.drives:
                    d.advance(dt)
                for d in self.drives:
                    d.service(now)
                self.ticks += 1
                if self.on_angles is not None:
                    self.on_angles(self.angles(), now)
                next_tick += self.tick_s
                delay = next_tick - time.monotonic()
                if delay < -MAX_CATCH_UP_S:
                    next_tick = time.monotonic()
                elif delay > 0:
                    self._stop.wait(delay)
        except BaseException as exc:  # reported by stop(); the drives simply freeze, as a crashed drive would
            log.exception("simulated drives stopped")
            self.error = exc

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self.network is not None:
            for d in self.drives:
                d.node.nmt.stop_heartbeat()
            try:
                self.network.disconnect()
            except Exception as exc:  # noqa: BLE001 - shutting down; nothing left to protect
                log.debug("sim network disconnect: %s", exc)
            self.network = None

    def __enter__(self) -> "SimDriveSet":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def run_sim_drives(bus_config: CanBusConfig | can.BusABC, node_ids: Sequence[int], drive_params: DriveParams,
                   stop_event: threading.Event, on_angles: Callable[[np.ndarray, float], None] | None = None, *,
                   tick_s: float = PHYSICS_STEP_S, initial_angles: Sequence[float] | None = None,
                   encoder_offsets: Sequence[int] | None = None,
                   on_ready: Callable[[SimDriveSet], None] | None = None) -> np.ndarray:
    """Run simulated drives until ``stop_event`` is set; returns the final handle angles (rad).

    ``on_angles(angles, t)`` receives the handle angles (rad, in ``node_ids`` order) after every
    physics tick (``tick_s``, default 1 ms) with the monotonic time ``t`` (s): the rig twin turns
    them into bending angles and camera poses. ``on_ready(drive_set)`` is called once the nodes
    have booted (e.g. to inject faults in tests or report readiness).
    """
    sims = SimDriveSet(bus_config, node_ids, drive_params, tick_s=tick_s, initial_angles=initial_angles,
                       encoder_offsets=encoder_offsets, on_angles=on_angles)
    with sims:
        if on_ready is not None:
            on_ready(sims)
        while not stop_event.wait(0.05):
            if sims.error is not None:
                raise RuntimeError("simulated drives failed") from sims.error
        return sims.angles()


SIM_RIG_DESCRIPTION = ("Simulated TeleFLEX steering drives (CiA 402 over CANopen) for the hardware driver, "
                       "optionally with a simulated OptiTrack NatNet server streaming the tip pose.")


def add_sim_rig_arguments(ap: argparse.ArgumentParser) -> None:
    """Options of ``targetlock sim-rig`` (for the CLI's sub-command parser)."""
    ap.add_argument("--rig", help="rig file (TOML): its [can] and [natnet] sections set the bus, node ids, scaling "
                                  "and mocap addresses; command-line options below override")
    ap.add_argument("--interface", default=None, help="CAN interface (default udp_loopback)")
    ap.add_argument("--channel", default=None, help="channel / multicast group (default 239.255.0.1)")
    ap.add_argument("--port", type=int, default=None, help="UDP port of udp_loopback (default 43113)")
    ap.add_argument("--nodes", type=int, nargs="+", default=None, help="node ids, axis order (default 1 2)")
    ap.add_argument("--tick", type=float, default=PHYSICS_STEP_S, help="physics period, s (default 0.001)")
    ap.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: until Ctrl-C)")
    ap.add_argument("--initial-angle", type=float, nargs="+", default=None, help="handle angles at power-up, rad")
    ap.add_argument("--encoder-offset", type=int, nargs="+", default=None,
                    help="position reading at angle 0 before homing, ticks")
    ap.add_argument("--mocap", action="store_true", help="also stream base and tip poses over NatNet")
    ap.add_argument("--bend-ratio", type=float, default=1.0,
                    help="bending angle per handle angle for the streamed tip pose (rad/rad)")
    ap.add_argument("--length", type=float, default=0.05, help="bending-section length for the tip pose, m")
    ap.add_argument("--elements", type=int, default=30, help="element pairs of the kinematic chain")
    ap.add_argument("--mocap-rate", type=float, default=120.0, help="NatNet frame rate, Hz")
    ap.add_argument("--mocap-ip", default="127.0.0.1", help="address the NatNet server serves on (default 127.0.0.1)")
    ap.add_argument("--mocap-command-port", type=int, default=None, help="NatNet command port (default: rig file, 1510)")
    ap.add_argument("--mocap-data-port", type=int, default=None, help="NatNet data port (default: rig file, 1511)")
    ap.add_argument("--mocap-group", default=None, help="NatNet multicast group (default: rig file, 239.255.42.99)")
    ap.add_argument("--mocap-unicast", action="store_true", help="stream unicast to connected clients")
    ap.add_argument("--quiet", action="store_true", help="warnings only")
    ap.add_argument("--verbose", action="store_true", help="also log canopen / python-can internals")


def main(argv: Sequence[str] | None = None) -> int:
    """``targetlock sim-rig [options]``: parse ``argv`` (default: sys.argv[1:]) and run :func:`run_sim_rig`."""
    ap = argparse.ArgumentParser(prog="targetlock sim-rig", description=SIM_RIG_DESCRIPTION)
    add_sim_rig_arguments(ap)
    return run_sim_rig(ap.parse_args(argv))


def run_sim_rig(args: argparse.Namespace) -> int:
    """Run simulated drives (and with ``--mocap`` a NatNet server) in this process until stopped; exit code."""
    try:
        return _run_sim_rig(args)
    except (ConfigError, DriveFault, OSError) as exc:
        print(f"targetlock sim-rig: {exc}", file=sys.stderr)
        return 2


def _run_sim_rig(args: argparse.Namespace) -> int:
    from .rigfile import HardwareRigConfig      # imports the driver too; only the command needs it
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO,
                        format="%(asctime)s %(name)s: %(message)s")
    if not args.verbose:
        for name in ("canopen", "can"):
            logging.getLogger(name).setLevel(logging.WARNING)
    rig = load_toml(HardwareRigConfig, args.rig) if args.rig else HardwareRigConfig()
    bus = rig.can.bus
    if not args.rig:
        bus = CanBusConfig(interface="udp_loopback", channel="239.255.0.1")
    overrides = {k: v for k, v in (("interface", args.interface), ("channel", args.channel), ("port", args.port))
                 if v is not None}
    if overrides:
        bus = validate(replace(bus, **overrides))
    if bus.interface not in ("udp_loopback", "udp_multicast", "virtual"):
        print(f"warning: simulating drives on a real bus ({bus.interface}:{bus.channel})", file=sys.stderr)
    node_ids = tuple(args.nodes) if args.nodes else tuple(rig.can.node_ids)
    for name in ("initial_angle", "encoder_offset"):
        values = getattr(args, name)
        if values is not None and len(values) != len(node_ids):
            raise ConfigError(f"--{name.replace('_', '-')} needs {len(node_ids)} values (one per node), got {len(values)}")
    params = rig.can.drive_params()
    stop = threading.Event()
    server = None
    angles_lock = threading.Lock()
    latest = {"angles": np.zeros(len(node_ids))}

    def on_angles(angles: np.ndarray, t: float) -> None:
        with angles_lock:
            latest["angles"] = angles

    if args.mocap:
        from ..model.kinematics import tip_pose
        from .sim_natnet import SimNatNetServer, SimNatNetConfig

        def poses() -> tuple[np.ndarray, np.ndarray]:
            with angles_lock:
                a = latest["angles"]
            base = np.eye(4)
            base[:3, 3] = (0.0, 0.0, 1.0)
            phi = a[:2] * args.bend_ratio if a.size >= 2 else np.zeros(2)
            return base, base @ tip_pose(float(phi[0]), float(phi[1]), args.length, args.elements)

        n = rig.natnet
        server = SimNatNetServer(validate(SimNatNetConfig(
            multicast=n.multicast and not args.mocap_unicast,
            multicast_group=args.mocap_group or n.multicast_group,
            data_port=args.mocap_data_port if args.mocap_data_port is not None else n.data_port,
            command_port=args.mocap_command_port if args.mocap_command_port is not None else n.command_port,
            server_ip=args.mocap_ip, rate_hz=args.mocap_rate,
            base_body_id=n.base_body_id, tip_body_id=n.tip_body_id)), poses)
        server.start()

    def ready(sims: SimDriveSet) -> None:
        print(f"sim-rig ready: nodes {list(node_ids)} on {bus.interface}:{bus.channel}"
              + (f" port {bus.port}" if bus.interface.startswith("udp") else "")
              + (f"; NatNet on {server.describe()}" if server is not None else ""), flush=True)

    previous_sigterm = None
    if threading.current_thread() is threading.main_thread():
        previous_sigterm = signal.signal(signal.SIGTERM, lambda *_: stop.set())   # `kill` stops the drives cleanly
    if args.duration > 0:
        timer = threading.Timer(args.duration, stop.set)
        timer.daemon = True
        timer.start()
    try:
        run_sim_drives(bus, node_ids, params, stop, on_angles, tick_s=args.tick, initial_angles=args.initial_angle,
                       encoder_offsets=args.encoder_offset, on_ready=ready)
    except KeyboardInterrupt:
        pass
    finally:
        stop.set()
        if server is not None:
            server.stop()
        if previous_sigterm is not None:
            signal.signal(signal.SIGTERM, previous_sigterm)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
