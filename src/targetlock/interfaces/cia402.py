"""CiA 402 drive driver over CANopen (canopen + python-can): the TeleFLEX rig's Elmo drives.

:class:`CiA402Drive` talks to one drive node; :class:`CanopenDrives` drives both axes and
implements the rig's :class:`~targetlock.rig.base.Drives` interface for the control loop.

Start-up (:meth:`CanopenDrives.start`): NMT pre-operational; by SDO the heartbeat producer time
(0x1017), the drive's consumer heartbeat for this computer (0x1016, the drive faults if the host
dies), RPDO1 = controlword + target position and TPDO1 = statusword + position actual (event
driven, event timer ``tpdo_period``) when ``use_pdo``, other PDOs invalidated, profile position
mode (0x6060 = 1) with profile velocity / acceleration / deceleration (0x6081/0x6083/0x6084) and
quick-stop deceleration (0x6085); NMT operational; fault reset if needed; shutdown → switch on →
enable operation. Homing (:meth:`CanopenDrives.home`) switches to homing mode (0x6060 = 6), runs
the configured method (0x6098) and waits for statusword bit 12 (homing attained) or bit 13 (homing
error), then returns to profile position mode and writes the software position limits (0x607D).

Set-points (:meth:`CanopenDrives.send_setpoints`) use the profile-position handshake: target
0x607A with controlword bit 4 (new set-point) and bit 5 (change set immediately) raised, wait for
statusword bit 12 (set-point acknowledge), lower bit 4; both axes in parallel. By RPDO/TPDO when
``use_pdo``, otherwise by SDO. No motion before homing; set-points are clamped to the limits.

Faults: statusword bit 3, EMCY messages, heartbeat loss (no heartbeat within
``heartbeat_timeout``), a node rebooting, the node leaving NMT operational, and bus errors all make
:meth:`~CanopenDrives.fault` non-None and the next command raise :class:`DriveFault` with the
reason (error code 0x603F / EMCY code and its meaning). Leaving a fault takes an explicit
:meth:`~CanopenDrives.enable` (fault reset + enable sequence).

Units: the configuration is SI (rad, rad/s, rad/s², s); ticks exist only at the drive boundary
(``send_setpoints``, ``positions``, ``limits`` and the CANopen objects).
"""
from __future__ import annotations

import logging
import math
import struct
import threading
import time
from dataclasses import dataclass
from typing import Callable

import can
import canopen
import numpy as np
from canopen.emcy import EmcyError
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from ..config import ConfigError, param
from ..model.drives import DriveParams
from ..rig.base import DriveFault, Drives
from . import od402 as o
from .canbus import CanBusConfig, open_bus
from .errors import BusError, MotionRefused
from .od402 import State, decode_state, emcy_text, sdo_abort_text

__all__ = ["CanopenRigConfig", "CiA402Drive", "CanopenDrives", "SDO_TIMEOUT_S", "STATE_TRANSITION_TIMEOUT_S",
           "SETPOINT_ACK_TIMEOUT_S", "BOOT_WAIT_S", "QUICK_STOP_WAIT_S", "STATUS_POLL_PERIOD_S",
           "MAX_MISSED_ACKS"]

log = logging.getLogger(__name__)

# Named time limits (defaults; the configurable ones are copied into CanopenRigConfig).
SDO_TIMEOUT_S = 0.1
"""Time an SDO request may wait for the drive's answer (s)."""
STATE_TRANSITION_TIMEOUT_S = 1.0
"""Time one CiA 402 state transition (e.g. switch on -> operation enabled) may take (s)."""
SETPOINT_ACK_TIMEOUT_S = 0.02
"""Time a drive may take to acknowledge a new set-point (statusword bit 12) (s)."""
BOOT_WAIT_S = 2.0
"""Time to wait for each node's first heartbeat after NMT start (s)."""
QUICK_STOP_WAIT_S = 0.3
"""Time disable() waits for a quick stop to end before removing power (s)."""
STATUS_POLL_PERIOD_S = 0.002
"""Period of statusword polling by SDO when no TPDO is configured (s)."""
MAX_MISSED_ACKS = 3
"""Consecutive unacknowledged set-points that make a drive fault (count)."""
EMCY_LOG_LENGTH = 100
"""EMCY messages kept per drive (count)."""
NOTIFIER_CYCLE_S = 0.05
"""Wake-up period of the CAN receive thread (s); bounds the time close() takes."""


@dataclass(frozen=True)
class CanopenRigConfig:
    """The steering drives of a hardware rig: bus, node ids, scaling, limits and drive settings."""
    bus: CanBusConfig = param(CanBusConfig(), doc="CAN bus")
    node_ids: tuple[int, int] = param((1, 2), lo=1, hi=127, doc="CANopen node id of the x-axis and y-axis drive")
    rad_per_tick: float = param(1.6e-5, unit="rad/tick", lo=1e-9, hi=1.0, lo_open=True,
                                doc="handle angle per encoder tick")
    min_angle: float = param(-2.0, unit="rad", lo=-6.3, hi=0.0, doc="lowest handle angle a set-point may ask for")
    max_angle: float = param(2.0, unit="rad", lo=0.0, hi=6.3, doc="highest handle angle a set-point may ask for")
    profile_velocity: float = param(1.6, unit="rad/s", lo=1e-4, hi=100.0,
                                    doc="path-generator velocity limit (0x6081); 1.6 rad/s = 100000 tick/s")
    profile_acceleration: float = param(160.0, unit="rad/s^2", lo=1e-3, hi=1e5, doc="0x6083")
    profile_deceleration: float = param(160.0, unit="rad/s^2", lo=1e-3, hi=1e5, doc="0x6084")
    quick_stop_deceleration: float = param(320.0, unit="rad/s^2", lo=1e-3, hi=1e5, doc="0x6085")
    position_window: float = param(3.2e-4, unit="rad", lo=0.0, hi=0.1, doc="target-reached window (0x6067)")
    homing_method: int = param(37, lo=-128, hi=37,
                               doc="CiA 402 homing method (0x6098); 37 = current position is home (no motion)")
    homing_speed: float = param(0.32, unit="rad/s", lo=1e-4, hi=10.0, doc="search-for-switch speed (0x6099:1)")
    homing_zero_speed: float = param(0.08, unit="rad/s", lo=1e-4, hi=10.0, doc="search-for-zero speed (0x6099:2)")
    homing_acceleration: float = param(16.0, unit="rad/s^2", lo=1e-3, hi=1e5, doc="0x609A")
    home_offset: float = param(0.0, unit="rad", lo=-6.3, hi=6.3, doc="position reported at home (0x607C)")
    homing_timeout: float = param(30.0, unit="s", lo=0.1, hi=600.0, doc="longest homing procedure")
    use_pdo: bool = param(True, doc="set-points by RPDO and position/status by TPDO; false: everything by SDO")
    tpdo_period: float = param(0.005, unit="s", lo=0.001, hi=1.0, doc="TPDO1 event timer: position feedback period")
    heartbeat_period: float = param(0.02, unit="s", lo=0.001, hi=10.0, doc="drives' heartbeat producer time (0x1017)")
    heartbeat_timeout: float = param(0.1, unit="s", lo=0.005, hi=30.0,
                                     doc="no heartbeat for this long = drive lost (fault)")
    master_node_id: int = param(100, lo=1, hi=127, doc="node id of this computer's heartbeat")
    master_heartbeat_period: float = param(0.05, unit="s", lo=0.0, hi=10.0,
                                           doc="this computer's heartbeat period; 0 = none")
    drive_consumer_timeout: float = param(0.25, unit="s", lo=0.0, hi=60.0,
                                          doc="drives fault if this computer's heartbeat stops this long (0x1016); "
                                              "0 = drives do not watch")
    sdo_timeout: float = param(SDO_TIMEOUT_S, unit="s", lo=0.005, hi=5.0, doc="SDO answer time limit")
    setpoint_ack_timeout: float = param(SETPOINT_ACK_TIMEOUT_S, unit="s", lo=0.001, hi=1.0,
                                        doc="set-point acknowledge time limit")
    enable_timeout: float = param(STATE_TRANSITION_TIMEOUT_S, unit="s", lo=0.01, hi=30.0,
                                  doc="time limit of each state-machine transition")
    eds_file: str = param("", doc="EDS of the drives; empty = targetlock's built-in CiA 402 dictionary")

    def check(self, prefix: str = "") -> None:
        if len(self.node_ids) != 2:
            raise ConfigError(f"{prefix}node_ids must list two node ids (x axis, y axis), got {list(self.node_ids)}")
        if self.min_angle >= self.max_angle:
            raise ConfigError(f"{prefix}min_angle = {self.min_angle} must be below {prefix}max_angle = {self.max_angle}")
        if self.node_ids[0] == self.node_ids[1]:
            raise ConfigError(f"{prefix}node_ids = {list(self.node_ids)} must be two different ids")
        if self.master_node_id in self.node_ids:
            raise ConfigError(f"{prefix}master_node_id = {self.master_node_id} collides with a drive node id")
        if self.heartbeat_timeout <= self.heartbeat_period:
            raise ConfigError(f"{prefix}heartbeat_timeout = {self.heartbeat_timeout} s must exceed "
                              f"{prefix}heartbeat_period = {self.heartbeat_period} s")
        if self.drive_consumer_timeout and self.drive_consumer_timeout <= self.master_heartbeat_period:
            raise ConfigError(f"{prefix}drive_consumer_timeout = {self.drive_consumer_timeout} s must exceed "
                              f"{prefix}master_heartbeat_period = {self.master_heartbeat_period} s (or be 0)")
        if self.drive_consumer_timeout and not self.master_heartbeat_period:
            raise ConfigError(f"{prefix}drive_consumer_timeout needs master_heartbeat_period > 0")

    def ticks(self, rad: float) -> int:
        """Encoder ticks of an angle or angular rate (rad, rad/s, ...)."""
        return int(round(rad / self.rad_per_tick))

    @property
    def min_ticks(self) -> int:
        return int(math.ceil(self.min_angle / self.rad_per_tick - 1e-9))

    @property
    def max_ticks(self) -> int:
        return int(math.floor(self.max_angle / self.rad_per_tick + 1e-9))

    def drive_params(self) -> DriveParams:
        """The twin's drive parameters matching this configuration (for the simulated drives)."""
        return DriveParams(rad_per_tick=self.rad_per_tick,
                           max_velocity_ticks=self.profile_velocity / self.rad_per_tick,
                           min_angle=self.min_angle, max_angle=self.max_angle)


class CiA402Drive:
    """One CiA 402 drive node: SDO/PDO access, state machine, homing, set-point handshake, faults.

    Normally created and used by :class:`CanopenDrives`; thread-safe for one commanding thread plus
    :meth:`quick_stop_now` from any thread. Positions are ticks, times seconds.
    """

    def __init__(self, network: canopen.Network, node_id: int, cfg: CanopenRigConfig) -> None:
        self.cfg = cfg
        self.node_id = int(node_id)
        od = cfg.eds_file or o.build_object_dictionary(self.node_id)
        self.node = canopen.RemoteNode(self.node_id, od)
        network.add_node(self.node)
        self.network = network
        self.node.sdo.RESPONSE_TIMEOUT = cfg.sdo_timeout
        self.node.sdo.MAX_RETRIES = 1
        self._sdo_lock = threading.Lock()
        self._cond = threading.Condition()
        self.statusword: int | None = None
        """Last statusword seen (TPDO or SDO)."""
        self.position: int | None = None
        """Last position actual value seen (ticks)."""
        self.status_time: float | None = None
        """Monotonic time (s) of the last statusword by TPDO."""
        self.tpdo_count = 0
        self.heartbeat_time: float | None = None
        self.heartbeat_state: int | None = None
        self.rebooted = False
        self.heartbeat_lost = False
        self.expect_operational = False
        self.emcy_log: list[EmcyError] = []
        self.emcy_active: list[EmcyError] = []
        self.error_code: int | None = None
        self.controlword = 0
        self.target = 0
        self.homed = False
        self.pdo_active = False
        self.missed_acks = 0
        self._rpdo_cob = 0x200 + self.node_id
        self.node.nmt.add_heartbeat_callback(self._on_heartbeat)
        self.node.emcy.add_callback(self._on_emcy)

    # ---------------------------------------------------------------- receive callbacks (CAN thread)

    def _on_heartbeat(self, state: int) -> None:
        with self._cond:
            self.heartbeat_time = time.monotonic()
            self.heartbeat_state = state
            if state == 0:
                self.rebooted = True
                self.homed = False
                self.pdo_active = False
            self._cond.notify_all()

    def _on_emcy(self, entry: EmcyError) -> None:
        with self._cond:
            self.emcy_log.append(entry)
            del self.emcy_log[:-EMCY_LOG_LENGTH]
            if entry.code & 0xFF00 == 0:
                self.emcy_active.clear()
            else:
                self.emcy_active.append(entry)
                self.error_code = entry.code
                log.error("node %d: EMCY 0x%04X (%s), error register 0x%02X", self.node_id, entry.code,
                          emcy_text(entry.code), entry.register)
            self._cond.notify_all()

    def _on_tpdo(self, pdo_map) -> None:
        data = bytes(pdo_map.data)
        if len(data) < 6:
            return
        sw, pos = struct.unpack_from("<Hi", data)
        with self._cond:
            self.statusword = sw
            self.position = pos
            self.status_time = time.monotonic()
            self.tpdo_count += 1
            self._cond.notify_all()

    # ---------------------------------------------------------------- SDO helpers

    def _sdo(self, what: str, fn: Callable[[], object]) -> object:
        with self._sdo_lock:
            try:
                return fn()
            except SdoAbortedError as exc:
                raise DriveFault(f"node {self.node_id}: {what} refused by the drive: SDO abort 0x{exc.code:08X} "
                                 f"({sdo_abort_text(exc.code)})") from exc
            except SdoCommunicationError as exc:
                raise DriveFault(f"node {self.node_id}: no SDO answer to {what} within "
                                 f"{self.cfg.sdo_timeout * 1e3:.0f} ms (drive or bus lost)") from exc
            except (can.CanError, OSError, RuntimeError) as exc:
                raise BusError(f"node {self.node_id}: CAN bus error during {what}: {exc}") from exc

    def read(self, index: int, subindex: int | None = None) -> int:
        """SDO upload of one object (raw value)."""
        def go():
            var = self.node.sdo[index] if subindex is None else self.node.sdo[index][subindex]
            return var.raw
        return self._sdo(f"reading 0x{index:04X}" + (f":{subindex}" if subindex is not None else ""), go)

    def write(self, index: int, value: int, subindex: int | None = None) -> None:
        """SDO download of one object (raw value), confirmed by the drive."""
        def go():
            var = self.node.sdo[index] if subindex is None else self.node.sdo[index][subindex]
            var.raw = value
        self._sdo(f"writing 0x{index:04X}" + (f":{subindex}" if subindex is not None else "") + f" = {value}", go)

    def read_statusword(self) -> int:
        sw = int(self.read(o.STATUSWORD))
        with self._cond:
            self.statusword = sw
        return sw

    def read_position(self) -> int:
        pos = int(self.read(o.POSITION_ACTUAL))
        with self._cond:
            self.position = pos
        return pos

    # ---------------------------------------------------------------- configuration

    def configure(self, master_node_id: int, master_period: float) -> None:
        """Write the start-up configuration by SDO (node must be pre-operational)."""
        c = self.cfg
        self.write(o.PRODUCER_HEARTBEAT, max(1, int(round(c.heartbeat_period * 1e3))))
        if c.drive_consumer_timeout and master_period:
            self.write(o.CONSUMER_HEARTBEAT, (master_node_id << 16) | int(round(c.drive_consumer_timeout * 1e3)), 1)
        else:
            self.write(o.CONSUMER_HEARTBEAT, 0, 1)
        if c.use_pdo:
            self._configure_pdos()
        else:
            self._invalidate_pdos(range(1, o.N_PDO + 1))
        self.write(o.PROFILE_VELOCITY, max(1, c.ticks(c.profile_velocity)))
        self.write(o.PROFILE_ACCELERATION, max(1, c.ticks(c.profile_acceleration)))
        self.write(o.PROFILE_DECELERATION, max(1, c.ticks(c.profile_deceleration)))
        self.write(o.QUICK_STOP_DECELERATION, max(1, c.ticks(c.quick_stop_deceleration)))
        self.write(o.POSITION_WINDOW, c.ticks(c.position_window))
        self.set_mode(o.MODE_PROFILE_POSITION)

    def _invalidate_pdos(self, numbers) -> None:
        for n in numbers:
            for comm in (o.TPDO_COMM, o.RPDO_COMM):
                cob = int(self.read(comm + n - 1, 1))
                if not cob & o.PDO_COB_INVALID:
                    self.write(comm + n - 1, cob | o.PDO_COB_INVALID, 1)

    def _configure_pdos(self) -> None:
        c = self.cfg
        self._invalidate_pdos(range(2, o.N_PDO + 1))

        def save_maps() -> None:
            tp = self.node.tpdo[1]
            tp.clear()
            tp.add_variable(o.STATUSWORD)
            tp.add_variable(o.POSITION_ACTUAL)
            tp.cob_id = 0x180 + self.node_id
            tp.trans_type = o.TRANS_EVENT_PROFILE
            tp.inhibit_time = 0
            tp.event_timer = max(1, int(round(c.tpdo_period * 1e3)))
            tp.rtr_allowed = False
            tp.enabled = True
            tp.save()
            rp = self.node.rpdo[1]
            rp.clear()
            rp.add_variable(o.CONTROLWORD)
            rp.add_variable(o.TARGET_POSITION)
            rp.cob_id = self._rpdo_cob
            rp.trans_type = o.TRANS_EVENT_PROFILE
            rp.rtr_allowed = False
            rp.enabled = True
            rp.save()

        self._sdo("configuring RPDO1/TPDO1", save_maps)
        tp = self.node.tpdo[1]
        if self._on_tpdo not in tp.callbacks:
            tp.add_callback(self._on_tpdo)

    def set_mode(self, mode: int, timeout: float | None = None) -> None:
        """Write modes of operation (0x6060) and wait until the display (0x6061) shows it."""
        self.write(o.MODES_OF_OPERATION, mode)
        deadline = time.monotonic() + (timeout or self.cfg.enable_timeout)
        while int(self.read(o.MODES_DISPLAY)) != mode:
            if time.monotonic() > deadline:
                raise DriveFault(f"node {self.node_id}: mode {mode} not taken (0x6061 shows another mode)")
            time.sleep(STATUS_POLL_PERIOD_S)

    # ---------------------------------------------------------------- status

    def current_statusword(self, max_age: float | None = None) -> int:
        """Latest statusword: the TPDO value if fresh enough, otherwise read by SDO."""
        age_limit = max_age if max_age is not None else self.pdo_stale_after
        with self._cond:
            fresh = (self.pdo_active and self.status_time is not None
                     and time.monotonic() - self.status_time <= age_limit)
            sw = self.statusword
        if fresh and sw is not None:
            return sw
        return self.read_statusword()

    @property
    def pdo_stale_after(self) -> float:
        """Age (s) beyond which TPDO feedback is not trusted and SDO is used instead."""
        return max(3.0 * self.cfg.tpdo_period, 0.05)

    def state(self) -> State:
        return decode_state(self.current_statusword())

    def wait_status(self, predicate: Callable[[int], bool], timeout: float, what: str,
                    abort: threading.Event | None = None) -> int:
        """Wait until ``predicate(statusword)``; by TPDO when configured, else by SDO polling."""
        deadline = time.monotonic() + timeout
        if self.pdo_active:
            with self._cond:
                while True:
                    sw = self.statusword
                    if sw is not None and predicate(sw):
                        return sw
                    left = deadline - time.monotonic()
                    if left <= 0 or (abort is not None and abort.is_set()):
                        break
                    self._cond.wait(min(left, 0.01))
            sw = self.read_statusword()   # the TPDO may have been lost: ask once by SDO
            if predicate(sw):
                return sw
        else:
            while True:
                sw = self.read_statusword()
                if predicate(sw):
                    return sw
                if time.monotonic() > deadline or (abort is not None and abort.is_set()):
                    break
                time.sleep(STATUS_POLL_PERIOD_S)
        raise DriveFault(f"node {self.node_id}: timed out after {timeout * 1e3:.0f} ms waiting for {what} "
                         f"(statusword 0x{sw:04X}, {decode_state(sw).value})")

    def fault_text(self, now: float | None = None) -> str | None:
        """Why this drive cannot be commanded, or None."""
        now = time.monotonic() if now is None else now
        with self._cond:
            if self.rebooted:
                return f"node {self.node_id}: drive rebooted (boot-up message); homing lost"
            if self.heartbeat_lost:
                return f"node {self.node_id}: heartbeat lost (none for more than {self.cfg.heartbeat_timeout * 1e3:.0f} ms)"
            if self.expect_operational and self.heartbeat_state not in (None, 5):
                name = canopen.nmt.NMT_STATES.get(self.heartbeat_state, str(self.heartbeat_state))
                return f"node {self.node_id}: left NMT operational (now {name})"
            sw = self.statusword
            if self.emcy_active:
                e = self.emcy_active[-1]
                return (f"node {self.node_id}: drive fault, EMCY 0x{e.code:04X} ({emcy_text(e.code)}), "
                        f"error register 0x{e.register:02X}")
        if sw is not None and decode_state(sw) in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            code = self.error_code
            text = f", error code 0x{code:04X} ({emcy_text(code)})" if code else ""
            return f"node {self.node_id}: drive in fault state (statusword 0x{sw:04X}){text}"
        return None

    def check_heartbeat(self, now: float) -> None:
        """Called periodically: mark the heartbeat lost when it is overdue."""
        with self._cond:
            if self.heartbeat_time is None or self.heartbeat_lost:
                return
            if now - self.heartbeat_time > self.cfg.heartbeat_timeout:
                self.heartbeat_lost = True
                log.error("node %d: heartbeat lost (last %.0f ms ago)", self.node_id,
                          (now - self.heartbeat_time) * 1e3)

    def fetch_error_code(self) -> None:
        """Read the error code (0x603F) after a fault for the fault text (best effort)."""
        try:
            code = int(self.read(o.ERROR_CODE))
        except DriveFault:
            return
        if code:
            self.error_code = code

    # ---------------------------------------------------------------- commands

    def send_controlword(self, cw: int, target: int | None = None) -> None:
        """Send a controlword: by RPDO1 (with ``target``) when PDOs are active, else confirmed by SDO."""
        if target is not None:
            self.target = int(target)
        self.controlword = cw
        if self.pdo_active:
            try:
                self.network.send_message(self._rpdo_cob, struct.pack("<Hi", cw, self.target))
            except (can.CanError, OSError, RuntimeError) as exc:
                raise BusError(f"node {self.node_id}: CAN bus error sending RPDO: {exc}") from exc
        else:
            if target is not None:
                self.write(o.TARGET_POSITION, self.target)
            self.write(o.CONTROLWORD, cw)

    def quick_stop_now(self) -> None:
        """Emergency path, any thread: quick-stop controlword by RPDO (no SDO, no waiting).

        Does nothing when PDOs are not active; :meth:`disable` then does it by SDO.
        """
        if self.pdo_active:
            try:
                self.network.send_message(self._rpdo_cob, struct.pack("<Hi", o.CW_QUICK_STOP, self.target))
                self.controlword = o.CW_QUICK_STOP
            except (can.CanError, OSError, RuntimeError) as exc:
                log.error("node %d: quick stop not sent: %s", self.node_id, exc)

    def transition(self, cw: int, want: tuple[State, ...], what: str) -> None:
        self.write(o.CONTROLWORD, cw)   # state machine always by confirmed SDO
        self.controlword = cw
        self.wait_status(lambda sw: decode_state(sw) in want, self.cfg.enable_timeout, what)

    def fault_reset(self) -> None:
        """Fault reset (rising edge of controlword bit 7) and clear the driver's fault memory."""
        state = decode_state(self.read_statusword())
        if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            if state == State.FAULT_REACTION_ACTIVE:
                self.wait_status(lambda sw: decode_state(sw) == State.FAULT, self.cfg.enable_timeout, "fault state")
            self.write(o.CONTROLWORD, o.CW_DISABLE_VOLTAGE)
            self.transition(o.CW_FAULT_RESET, (State.SWITCH_ON_DISABLED,), "fault reset")
        with self._cond:
            self.emcy_active.clear()
            self.error_code = None
            self.missed_acks = 0
            if self.heartbeat_time is not None and time.monotonic() - self.heartbeat_time <= self.cfg.heartbeat_timeout:
                self.heartbeat_lost = False
            self.rebooted = False

    def enable_operation(self) -> None:
        """Walk the CiA 402 state machine to operation enabled (fault reset first if needed)."""
        self.fault_reset()
        for _ in range(6):
            state = decode_state(self.read_statusword())
            if state == State.OPERATION_ENABLED:
                break
            if state == State.NOT_READY_TO_SWITCH_ON:
                self.wait_status(lambda sw: decode_state(sw) != State.NOT_READY_TO_SWITCH_ON,
                                 self.cfg.enable_timeout, "switch on disabled")
            elif state == State.QUICK_STOP_ACTIVE:
                self.transition(o.CW_DISABLE_VOLTAGE, (State.SWITCH_ON_DISABLED,), "disable voltage")
            elif state == State.SWITCH_ON_DISABLED:
                self.transition(o.CW_SHUTDOWN, (State.READY_TO_SWITCH_ON,), "ready to switch on")
            elif state == State.READY_TO_SWITCH_ON:
                self.transition(o.CW_SWITCH_ON, (State.SWITCHED_ON,), "switched on")
            elif state == State.SWITCHED_ON:
                pos = self.read_position()
                self.write(o.TARGET_POSITION, pos)
                self.target = pos
                self.transition(o.CW_ENABLE_OPERATION, (State.OPERATION_ENABLED,), "operation enabled")
            else:
                raise DriveFault(self.fault_text() or f"node {self.node_id}: cannot enable from {state.value}")
        else:
            raise DriveFault(f"node {self.node_id}: did not reach operation enabled")
        self.target = self.read_position()
        self.controlword = o.CW_ENABLE_OPERATION

    def disable_power(self) -> None:
        """Quick stop, then disable voltage (power stage off). Best effort: errors are logged."""
        try:
            state = decode_state(self.read_statusword())
            if state == State.OPERATION_ENABLED:
                self.write(o.CONTROLWORD, o.CW_QUICK_STOP)
                try:
                    self.wait_status(lambda sw: decode_state(sw) != State.OPERATION_ENABLED, QUICK_STOP_WAIT_S,
                                     "quick stop")
                except DriveFault:
                    pass
            if decode_state(self.read_statusword()) not in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                self.write(o.CONTROLWORD, o.CW_DISABLE_VOLTAGE)
            self.controlword = o.CW_DISABLE_VOLTAGE
        except DriveFault as exc:
            log.error("node %d: disable incomplete: %s", self.node_id, exc)

    def start_homing(self) -> None:
        c = self.cfg
        self.set_mode(o.MODE_HOMING)
        self.write(o.HOMING_METHOD, c.homing_method)
        self.write(o.HOMING_SPEEDS, max(1, c.ticks(c.homing_speed)), 1)
        self.write(o.HOMING_SPEEDS, max(1, c.ticks(c.homing_zero_speed)), 2)
        self.write(o.HOMING_ACCELERATION, max(1, c.ticks(c.homing_acceleration)))
        self.write(o.HOME_OFFSET, c.ticks(c.home_offset))
        self.write(o.CONTROLWORD, o.CW_ENABLE_OPERATION)
        self.write(o.CONTROLWORD, o.CW_ENABLE_OPERATION | o.CW_HOMING_START)
        self.controlword = o.CW_ENABLE_OPERATION | o.CW_HOMING_START

    def finish_homing(self, deadline: float) -> None:
        def done(sw: int) -> bool:
            return bool(sw & (o.SW_HOMING_ERROR | o.SW_FAULT)) or (
                sw & (o.SW_HOMING_ATTAINED | o.SW_TARGET_REACHED) == (o.SW_HOMING_ATTAINED | o.SW_TARGET_REACHED))
        sw = self.wait_status(done, max(0.0, deadline - time.monotonic()), "homing attained")
        self.write(o.CONTROLWORD, o.CW_ENABLE_OPERATION)
        self.controlword = o.CW_ENABLE_OPERATION
        if sw & o.SW_FAULT:
            raise DriveFault(self.fault_text() or f"node {self.node_id}: fault during homing")
        if sw & o.SW_HOMING_ERROR:
            raise DriveFault(f"node {self.node_id}: homing error (statusword 0x{sw:04X}, method "
                             f"{self.cfg.homing_method})")
        self.set_mode(o.MODE_PROFILE_POSITION)
        c = self.cfg
        self.write(o.SOFTWARE_LIMITS, c.min_ticks, 1)
        self.write(o.SOFTWARE_LIMITS, c.max_ticks, 2)
        self.target = self.read_position()
        self.write(o.TARGET_POSITION, self.target)
        self.homed = True

    # ---------------------------------------------------------------- set-point handshake

    def request_setpoint(self, target: int, abort: threading.Event) -> None:
        """Phase 1: target + new set-point bit (after the previous acknowledge has dropped)."""
        if self.pdo_active:
            with self._cond:
                sw = self.statusword
                if sw is not None and decode_state(sw) != State.OPERATION_ENABLED:
                    raise DriveFault(f"node {self.node_id}: not in operation enabled but {decode_state(sw).value} "
                                     f"(statusword 0x{sw:04X}); call enable()")
                deadline = time.monotonic() + self.cfg.setpoint_ack_timeout
                while self.statusword is not None and self.statusword & o.SW_SETPOINT_ACK:
                    left = deadline - time.monotonic()
                    if left <= 0 or abort.is_set():
                        break
                    self._cond.wait(left)
        if abort.is_set():
            raise MotionRefused("set-point interrupted: drives are being disabled")
        self.send_controlword(o.CW_ENABLE_OPERATION | o.CW_NEW_SETPOINT | o.CW_CHANGE_IMMEDIATELY, target)

    def await_ack(self, abort: threading.Event) -> bool:
        """Phase 2: wait for statusword bit 12; False when it did not come in time."""
        try:
            self.wait_status(lambda sw: bool(sw & (o.SW_SETPOINT_ACK | o.SW_FAULT)), self.cfg.setpoint_ack_timeout,
                             "set-point acknowledge", abort)
        except DriveFault:
            if abort.is_set():
                return True
            self.missed_acks += 1
            log.warning("node %d: set-point %d not acknowledged within %.0f ms (%d in a row)", self.node_id,
                        self.target, self.cfg.setpoint_ack_timeout * 1e3, self.missed_acks)
            return False
        self.missed_acks = 0
        return True

    def release_setpoint(self) -> None:
        """Phase 3: lower the new set-point bit (keep change-immediately)."""
        self.send_controlword(o.CW_ENABLE_OPERATION | o.CW_CHANGE_IMMEDIATELY)


class CanopenDrives(Drives):
    """Both steering drives of the hardware rig on one CAN bus (axis 0: image x, axis 1: image y).

    ``bus``: an already open python-can bus to use instead of opening ``config.bus`` (tests);
    ``start``: run :meth:`start` now. Use as a context manager or call :meth:`close`: the drives
    end disabled.
    """

    def __init__(self, config: CanopenRigConfig, *, bus: can.BusABC | None = None, start: bool = True) -> None:
        self.config = config
        self._bus = bus
        self.network: canopen.Network | None = None
        self.drives: tuple[CiA402Drive, ...] = ()
        self._lock = threading.RLock()
        self._abort = threading.Event()
        self._monitor_stop = threading.Event()
        self._monitor: threading.Thread | None = None
        self._master_hb = None
        self._enabled = False
        self._bus_error: str | None = None
        self.stats = {"setpoints": 0, "sdo_position_reads": 0, "pdo_position_reads": 0, "missed_acks": 0}
        lo, hi = config.min_ticks, config.max_ticks
        self._limits = (np.full(2, lo, dtype=np.int64), np.full(2, hi, dtype=np.int64))
        if start:
            self.start()

    # ---------------------------------------------------------------- life cycle

    def start(self) -> None:
        """Open the bus, configure both drives, bring them to NMT operational and operation enabled."""
        c = self.config
        bus = self._bus if self._bus is not None else open_bus(c.bus)
        net = canopen.Network(bus)
        net.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
        net.connect()
        self.network = net
        try:
            self.drives = tuple(CiA402Drive(net, nid, c) for nid in c.node_ids)
            if c.master_heartbeat_period > 0:
                self._master_hb = net.send_periodic(0x700 + c.master_node_id, [0x05], c.master_heartbeat_period)
            for d in self.drives:
                d.node.nmt.send_command(0x80)          # pre-operational: configuration by SDO
            for d in self.drives:
                d.configure(c.master_node_id, c.master_heartbeat_period)
            for d in self.drives:
                d.node.nmt.send_command(0x01)          # operational: PDOs run
                d.pdo_active = c.use_pdo
            self._wait_heartbeats()
            for d in self.drives:
                d.expect_operational = True
            self._monitor_stop.clear()
            self._monitor = threading.Thread(target=self._watch, name="cia402-heartbeat-monitor", daemon=True)
            self._monitor.start()
            self.enable()
        except BaseException:
            self.close()
            raise

    def _wait_heartbeats(self) -> None:
        deadline = time.monotonic() + max(BOOT_WAIT_S, 3 * self.config.heartbeat_period)
        for d in self.drives:
            with d._cond:
                while d.heartbeat_state != 5:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        raise DriveFault(f"node {d.node_id}: no heartbeat in NMT operational after start "
                                         f"(last state {d.heartbeat_state})")
                    d._cond.wait(left)
                d.rebooted = False

    def _reconfigure(self, d: CiA402Drive) -> None:
        """A drive rebooted: its PDO mapping and heartbeat settings are gone; write them again."""
        c = self.config
        log.warning("node %d rebooted: configuring it again (homing is lost)", d.node_id)
        d.pdo_active = False
        d.node.nmt.send_command(0x80)
        d.configure(c.master_node_id, c.master_heartbeat_period)
        d.node.nmt.send_command(0x01)
        deadline = time.monotonic() + max(BOOT_WAIT_S, 3 * c.heartbeat_period)
        with d._cond:
            d.heartbeat_state = None
            while d.heartbeat_state != 5:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DriveFault(f"node {d.node_id}: no heartbeat in NMT operational after reconfiguration")
                d._cond.wait(left)
            d.rebooted = False
            d.heartbeat_lost = False
        d.pdo_active = c.use_pdo

    def _watch(self) -> None:
        period = min(0.02, self.config.heartbeat_timeout / 4)
        while not self._monitor_stop.wait(period):
            now = time.monotonic()
            for d in self.drives:
                d.check_heartbeat(now)
            net = self.network
            if net is not None and net.notifier is not None and net.notifier.exception is not None:
                self._bus_error = f"CAN receive failed: {net.notifier.exception}"
            if self.fault() is not None:
                self._abort.set()

    def close(self) -> None:
        """Disable the drives, stop the heartbeat producer and monitor, release the bus."""
        if self.network is None:
            return
        try:
            if self.drives:
                self.disable()
                for d in self.drives:
                    try:
                        d.node.nmt.send_command(0x80)
                    except (can.CanError, OSError, RuntimeError):
                        pass
        finally:
            self._monitor_stop.set()
            if self._monitor is not None:
                self._monitor.join(timeout=1.0)
                self._monitor = None
            if self._master_hb is not None:
                try:
                    self._master_hb.stop()
                except Exception:  # noqa: BLE001 - bus may be gone already
                    pass
                self._master_hb = None
            try:
                self.network.disconnect()
            except Exception as exc:  # noqa: BLE001
                log.debug("network disconnect: %s", exc)
            self.network = None

    def __enter__(self) -> "CanopenDrives":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---------------------------------------------------------------- Drives interface

    @property
    def homed(self) -> bool:
        return bool(self.drives) and all(d.homed for d in self.drives)

    @property
    def limits(self) -> tuple[np.ndarray, np.ndarray]:
        return self._limits[0].copy(), self._limits[1].copy()

    @property
    def rad_per_tick(self) -> float:
        return self.config.rad_per_tick

    def fault(self) -> str | None:
        if self._bus_error:
            return self._bus_error
        texts = [t for t in (d.fault_text() for d in self.drives) if t]
        return "; ".join(texts) if texts else None

    def _raise_if_fault(self) -> None:
        if self.fault() is None:
            return
        self._enabled = False
        for d in self.drives:
            if (not d.error_code and d.statusword is not None
                    and decode_state(d.statusword) in (State.FAULT, State.FAULT_REACTION_ACTIVE)):
                d.fetch_error_code()
        raise DriveFault(self.fault() or "drive fault")

    def _guard(self, fn: Callable[[], object]) -> object:
        try:
            return fn()
        except DriveFault as exc:
            if isinstance(exc, BusError):
                self._bus_error = str(exc)
            self._enabled = False
            for d in self.drives:
                if decode_state(d.statusword or 0) in (State.FAULT, State.FAULT_REACTION_ACTIVE) and not d.error_code:
                    d.fetch_error_code()
            text = self.fault()
            if text and text not in str(exc):
                raise DriveFault(f"{exc} [{text}]") from exc
            raise

    def home(self) -> None:
        """Run the configured homing method on both drives in parallel; positions then read ``home_offset``."""
        with self._lock:
            self._raise_if_fault()
            if not self._enabled:
                raise MotionRefused("drives are disabled: call enable() before homing")

            def go() -> None:
                deadline = time.monotonic() + self.config.homing_timeout
                for d in self.drives:
                    d.homed = False
                for d in self.drives:
                    d.start_homing()
                for d in self.drives:
                    d.finish_homing(deadline)
            self._guard(go)
            log.info("drives homed at %s ticks", self.positions().tolist())

    def send_setpoints(self, ticks: np.ndarray) -> None:
        """Command new position set-points (ticks, one per axis), clamped to :attr:`limits`.

        Raises :class:`MotionRefused` before homing or while disabled, :class:`DriveFault` on a
        fault; returns once both drives acknowledged the set-point.
        """
        t = np.asarray(ticks)
        if t.shape != (len(self.drives) or 2,):
            raise ValueError(f"expected {len(self.drives)} set-points, got shape {t.shape}")
        if not np.all(np.isfinite(t.astype(float))):
            raise MotionRefused(f"non-finite set-point {t.tolist()} refused")
        with self._lock:
            self._raise_if_fault()
            if not self.homed:
                raise MotionRefused("refusing motion: drives are not homed (call home() first)")
            if not self._enabled or self._abort.is_set():
                raise MotionRefused("refusing motion: drives are disabled (call enable() to resume)")
            lo, hi = self._limits
            targets = np.clip(np.rint(t.astype(float)).astype(np.int64), lo, hi)

            def go() -> None:
                for d, target in zip(self.drives, targets):
                    d.request_setpoint(int(target), self._abort)
                acked = [d.await_ack(self._abort) for d in self.drives]
                if self._abort.is_set():
                    raise MotionRefused("set-point interrupted: drives are being disabled")
                for d in self.drives:
                    d.release_setpoint()
                self.stats["missed_acks"] += acked.count(False)
                self.stats["setpoints"] += 1
                for d in self.drives:
                    if d.missed_acks >= MAX_MISSED_ACKS:
                        raise DriveFault(f"node {d.node_id}: {d.missed_acks} set-points in a row not acknowledged")
            self._guard(go)
            self._raise_if_fault()

    def positions(self) -> np.ndarray:
        """Measured positions (ticks): from TPDO1 when fresh, otherwise read by SDO."""
        out = np.empty(len(self.drives), dtype=np.int64)

        def go() -> None:
            now = time.monotonic()
            for i, d in enumerate(self.drives):
                with d._cond:
                    fresh = (d.pdo_active and d.status_time is not None and d.position is not None
                             and now - d.status_time <= d.pdo_stale_after)
                    pos = d.position
                if fresh:
                    out[i] = pos
                    self.stats["pdo_position_reads"] += 1
                else:
                    with self._lock:
                        out[i] = d.read_position()
                    self.stats["sdo_position_reads"] += 1
        self._guard(go)
        return out

    def states(self) -> list[State]:
        """CiA 402 state of each drive (statusword by TPDO when fresh, else SDO)."""
        return [decode_state(d.current_statusword()) for d in self.drives]

    def disable(self) -> None:
        """Stop commanding and remove power: quick stop, then disable voltage. Any thread."""
        self._abort.set()
        self._enabled = False
        for d in self.drives:
            d.quick_stop_now()
        got = self._lock.acquire(timeout=max(1.0, 3 * self.config.sdo_timeout))
        try:
            for d in self.drives:
                d.disable_power()
        finally:
            if got:
                self._lock.release()

    def enable(self) -> None:
        """Explicit (re-)enable: fault reset where needed, then operation enabled on both drives."""
        with self._lock:
            self._bus_error = None
            if self.network is None:
                raise DriveFault("CAN network is closed")
            if self.network.notifier is not None and self.network.notifier.exception is not None:
                self._bus_error = f"CAN receive failed: {self.network.notifier.exception}"
                raise DriveFault(self._bus_error)

            def go() -> None:
                for d in self.drives:
                    if d.rebooted:
                        self._reconfigure(d)
                    d.enable_operation()
            self._guard(go)
            self._abort.clear()
            self._raise_if_fault()
            self._enabled = True
