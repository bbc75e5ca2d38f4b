"""CiA 402 drive driver over CANopen (canopen + python-can): the TeleFLEX rig's Elmo drives.

:class:`CiA402Drive` talks to one drive node; :class:`CanopenDrives` drives both axes and
implements the rig's :class:`~targetlock.rig.base.Drives` interface for the control loop.

Start-up (:meth:`CanopenDrives.start`): NMT pre-operational; by SDO the heartbeat producer time
(0x1017), the drive's consumer heartbeat for this computer (0x1016), the drive's own reactions to a
lost host and to faults (0x1029:1, 0x6007, 0x605A-0x605E, from the rig file), a check that EMCY is
produced (0x1014), RPDO1 = controlword + target position and TPDO1 = statusword + position actual
(event driven with event timer ``tpdo_period``, or SYNC-driven in cyclic synchronous position mode)
when ``use_pdo``, other PDOs invalidated, the operation mode (0x6060 = 1 profile position, or 8 cyclic
synchronous position with 0x60C2 and a SYNC producer) with profile velocity / acceleration /
deceleration (0x6081/0x6083/0x6084) and quick-stop deceleration (0x6085); NMT operational; fault
reset if needed; shutdown → switch on → enable operation. Homing (:meth:`CanopenDrives.home`)
switches to homing mode (0x6060 = 6), runs the configured method (0x6098) and waits for statusword
bit 12 (homing attained) or bit 13 (homing error), then returns to the operation mode and writes the
software position limits (0x607D).

Every handshake accepts only status received after its command (statuswords are numbered as they
arrive), so a status PDO sent on a timer before the command never completes one. Set-points
(:meth:`CanopenDrives.send_setpoints`) in profile position mode: bit 4 (new set-point, with bit 5
change set immediately) is raised only after a status shows the previous acknowledge (bit 12) low,
the set-point counts as taken when a later status shows the acknowledge high, then bit 4 drops.
One call waits at most ``setpoint_ack_timeout`` for both drives; a late drive is counted (late or
missed, :meth:`CanopenDrives.report`); three misses in a row with none taken for
``status_timeout`` are a fault. By RPDO/TPDO when
``use_pdo``, otherwise by SDO. No motion before homing; set-points are clamped to the limits.

Faults: statusword bit 3, EMCY messages, heartbeat loss (no heartbeat within
``heartbeat_timeout``), no status PDO within ``status_timeout``, an unanswered SDO, a node
rebooting, the node leaving NMT operational, the drive leaving operation enabled on its own, and
bus errors all make :meth:`~CanopenDrives.fault` non-None and the next command raise
:class:`DriveFault` with the reason (error code 0x603F / EMCY code and its meaning). Leaving a fault
takes an explicit :meth:`~CanopenDrives.enable` (NMT start, fault reset, enable sequence); an enable
that fails leaves every drive disabled. :meth:`~CanopenDrives.disable` counts only when a statusword
read afterwards shows the power stage off; until then it is reported in ``fault()`` and repeated.

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
from pathlib import Path
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
SETPOINT_ACK_TIMEOUT_S = 0.01
"""Time one set-point handshake may wait for the drives per call (s); a later drive is reported, not waited for."""
BOOT_WAIT_S = 2.0
"""Time to wait for each node's first heartbeat after NMT start (s)."""
QUICK_STOP_WAIT_S = 0.3
"""Time disable() waits for a quick stop to end before removing power (s)."""
STATUS_POLL_PERIOD_S = 0.002
"""Period of statusword polling by SDO when no TPDO is configured (s)."""
MAX_MISSED_ACKS = 3
"""Consecutive set-points a drive did not take that make it a fault (count), once it has also taken
none for longer than ``status_timeout`` (a drive that is late under load is not a fault)."""
DISABLE_RETRY_S = 0.02
"""Period at which an unconfirmed disable is sent again (s)."""
EMCY_LOG_LENGTH = 100
"""EMCY messages kept per drive (count)."""
MONITOR_PERIOD_S = 0.02
"""Period of the driver's monitor thread: heartbeat check, SDO-only status poll, disable retry (s)."""
CALL_LOG_LENGTH = 10000
"""send_setpoints durations kept for :meth:`CanopenDrives.report` (count)."""
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
    status_timeout: float = param(0.05, unit="s", lo=0.002, hi=5.0,
                                  doc="no status PDO for this long while operational = link lost (fault); "
                                      "0.02 = one 50 Hz loop period on a quiet computer")
    eds_file: str = param("", doc="EDS or DCF of the drives (object types and sizes); "
                                  "empty = targetlock's built-in CiA 402 dictionary")
    operation_mode: str = param("profile_position", choices=("profile_position", "cyclic_sync_position"),
                                doc="profile_position: set-point handshake per target (0x6060 = 1); "
                                    "cyclic_sync_position: a target every SYNC, no handshake (0x6060 = 8)")
    sync_period: float = param(0.005, unit="s", lo=0.001, hi=0.1,
                               doc="cyclic_sync_position: this computer's SYNC period; the drives take the latest "
                                   "target and send their status on every SYNC (0x60C2 interpolation period)")
    comm_error_behaviour: int = param(0, lo=0, hi=2,
                                      doc="0x1029:1, drive's NMT reaction to a communication error such as a lost "
                                          "host heartbeat: 0 pre-operational, 1 no change, 2 stopped")
    abort_connection_option: int = param(1, lo=0, hi=3,
                                         doc="0x6007, drive's reaction to a lost host: 0 none, 1 fault, "
                                             "2 disable voltage, 3 quick stop")
    quick_stop_option: int = param(2, lo=0, hi=8,
                                   doc="0x605A: 1 slow-down ramp, 2 quick-stop ramp (then switch on disabled)")
    shutdown_option: int = param(1, lo=0, hi=1, doc="0x605B: 0 power off at once, 1 slow-down ramp first")
    disable_operation_option: int = param(1, lo=0, hi=1, doc="0x605C: 0 power off at once, 1 slow-down ramp first")
    halt_option: int = param(1, lo=1, hi=4, doc="0x605D: 1 slow-down ramp, 2 quick-stop ramp")
    fault_reaction_option: int = param(2, lo=0, hi=4,
                                       doc="0x605E: 0 power off at once, 1 slow-down ramp, 2 quick-stop ramp")

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
        if self.csp and not self.use_pdo:
            raise ConfigError(f"{prefix}operation_mode = 'cyclic_sync_position' needs {prefix}use_pdo = true")
        if self.csp and self.status_timeout < 2 * self.sync_period:
            raise ConfigError(f"{prefix}status_timeout = {self.status_timeout} s must be at least twice "
                              f"{prefix}sync_period = {self.sync_period} s")
        if self.use_pdo and not self.csp and self.tpdo_period >= self.setpoint_ack_timeout:
            raise ConfigError(f"{prefix}tpdo_period = {self.tpdo_period} s must be shorter than "
                              f"{prefix}setpoint_ack_timeout = {self.setpoint_ack_timeout} s: a drive that sends its "
                              f"status on the timer only answers a set-point up to one tpdo_period later")
        if self.use_pdo and self.status_timeout < 2 * self.tpdo_period:
            raise ConfigError(f"{prefix}status_timeout = {self.status_timeout} s must be at least twice "
                              f"{prefix}tpdo_period = {self.tpdo_period} s")
        if self.eds_file and not Path(self.eds_file).is_file():
            raise ConfigError(f"{prefix}eds_file = {self.eds_file!r}: no such file")

    def check_timing(self, loop_rate: float, prefix: str = "can.") -> None:
        """Refuse timing settings that cannot keep a control loop at ``loop_rate`` (Hz)."""
        period = 1.0 / loop_rate
        if self.csp and self.sync_period > period:
            raise ConfigError(f"{prefix}sync_period = {self.sync_period} s must not exceed the loop period "
                              f"({period:.4g} s at {loop_rate:g} Hz): the drives would skip targets")
        if self.use_pdo and not self.csp and self.setpoint_ack_timeout > 0.5 * period:
            raise ConfigError(f"{prefix}setpoint_ack_timeout = {self.setpoint_ack_timeout} s must be at most half the "
                              f"loop period ({0.5 * period:.4g} s at {loop_rate:g} Hz)")
        if self.use_pdo and self.tpdo_period > 0.5 * period:
            raise ConfigError(f"{prefix}tpdo_period = {self.tpdo_period} s must be at most half the loop period "
                              f"({0.5 * period:.4g} s at {loop_rate:g} Hz): position feedback would be older than a tick")
        if not self.use_pdo and 2 * self.sdo_timeout > period:
            raise ConfigError(f"{prefix}sdo_timeout = {self.sdo_timeout} s must be at most half the loop period "
                              f"({0.5 * period:.4g} s at {loop_rate:g} Hz) with use_pdo = false: every tick waits "
                              f"on SDO answers")

    @property
    def csp(self) -> bool:
        """Cyclic synchronous position mode with SYNC."""
        return self.operation_mode == "cyclic_sync_position"

    @property
    def mode(self) -> int:
        """0x6060 value of the configured operation mode."""
        return o.MODE_CYCLIC_SYNC_POSITION if self.csp else o.MODE_PROFILE_POSITION

    @property
    def status_period(self) -> float:
        """Expected time between status PDOs (s): the SYNC period in cyclic synchronous mode, else the event timer."""
        return self.sync_period if self.csp else self.tpdo_period

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

    Every statusword the driver receives (TPDO or SDO upload) gets a sequence number
    (:attr:`status_seq`); each handshake notes the number when its command went out and accepts
    only status that arrived after it, so a statusword cached from before the command (a status
    PDO sent on a timer) never completes a handshake.
    """

    def __init__(self, network: canopen.Network, node_id: int, cfg: CanopenRigConfig) -> None:
        self.cfg = cfg
        self.node_id = int(node_id)
        # An EDS/DCF path is imported by canopen (object types and sizes from the drive's own file).
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
        self.status_seq = 0
        """Number of statuswords received so far (TPDO or SDO): the order of status against commands."""
        self.position: int | None = None
        """Last position actual value seen (ticks)."""
        self.status_time: float | None = None
        """Monotonic time (s) of the last statusword by TPDO."""
        self.tpdo_count = 0
        self.heartbeat_time: float | None = None
        self.heartbeat_state: int | None = None
        self.heartbeat_seq = 0
        self.rebooted = False
        self.heartbeat_lost = False
        self.expect_operational = False
        self.expect_enabled = False
        """True while the driver holds this drive in operation enabled; leaving it is a fault."""
        self.comm_error: str | None = None
        """Why the last SDO transfer failed (no answer), until the next successful enable."""
        self.emcy_log: list[EmcyError] = []
        self.emcy_active: list[EmcyError] = []
        self.error_code: int | None = None
        self.controlword = 0
        self.target = 0
        self.homed = False
        self.pdo_active = False
        self.missed_acks = 0
        """Consecutive set-points this drive missed: not sent (drive not ready) or never acknowledged."""
        self.missed_total = 0
        self.edges = 0
        """New-set-point edges sent (each one is acknowledged in its call, late, or counted missed)."""
        self.late_acks = 0
        """Set-points acknowledged only after their call had returned (taken, but late)."""
        self.last_taken = time.monotonic()
        """Monotonic time (s) of the last set-point this drive took (or of enabling it)."""
        self._sp_phase = "idle"      # idle | raised (bit 4 high, waiting for ack) | lowered (waiting for ack low)
        self._sp_seq = 0             # status_seq when bit 4 last changed
        self._rpdo_cob = 0x200 + self.node_id
        self.node.nmt.add_heartbeat_callback(self._on_heartbeat)
        self.node.emcy.add_callback(self._on_emcy)

    # ---------------------------------------------------------------- receive callbacks (CAN thread)

    def _on_heartbeat(self, state: int) -> None:
        with self._cond:
            self.heartbeat_time = time.monotonic()
            self.heartbeat_state = state
            self.heartbeat_seq += 1
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
            self.status_seq += 1
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
                text = (f"node {self.node_id}: no SDO answer to {what} within "
                        f"{self.cfg.sdo_timeout * 1e3:.0f} ms (drive or bus lost)")
                with self._cond:
                    self.comm_error = text
                raise DriveFault(text) from exc
            except KeyError as exc:
                raise DriveFault(f"node {self.node_id}: {what}: the object dictionary "
                                 f"({self.cfg.eds_file or 'built-in'}) has no such object") from exc
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
            self.status_seq += 1
            self._cond.notify_all()
        return sw

    def read_position(self) -> int:
        pos = int(self.read(o.POSITION_ACTUAL))
        with self._cond:
            self.position = pos
        return pos

    # ---------------------------------------------------------------- configuration

    def startup_writes(self, master_node_id: int, master_period: float) -> list[tuple[int, int, int, str]]:
        """What :meth:`configure` writes besides the PDOs: (index, subindex, value, meaning) rows."""
        c = self.cfg
        consumer = ((master_node_id << 16) | int(round(c.drive_consumer_timeout * 1e3))
                    if c.drive_consumer_timeout and master_period else 0)
        return [
            (o.PRODUCER_HEARTBEAT, 0, max(1, int(round(c.heartbeat_period * 1e3))), "heartbeat producer time (ms)"),
            (o.CONSUMER_HEARTBEAT, 1, consumer, "watch this computer's heartbeat: (node id << 16) | ms"),
            (o.ERROR_BEHAVIOUR, 1, c.comm_error_behaviour, "NMT reaction to a communication error"),
            (o.ABORT_CONNECTION_OPTION, 0, c.abort_connection_option, "reaction to a lost host"),
            (o.QUICK_STOP_OPTION, 0, c.quick_stop_option, "quick stop option code"),
            (o.SHUTDOWN_OPTION, 0, c.shutdown_option, "shutdown option code"),
            (o.DISABLE_OPERATION_OPTION, 0, c.disable_operation_option, "disable operation option code"),
            (o.HALT_OPTION, 0, c.halt_option, "halt option code"),
            (o.FAULT_REACTION_OPTION, 0, c.fault_reaction_option, "fault reaction option code"),
            (o.PROFILE_VELOCITY, 0, max(1, c.ticks(c.profile_velocity)), "profile velocity (tick/s)"),
            (o.PROFILE_ACCELERATION, 0, max(1, c.ticks(c.profile_acceleration)), "profile acceleration (tick/s²)"),
            (o.PROFILE_DECELERATION, 0, max(1, c.ticks(c.profile_deceleration)), "profile deceleration (tick/s²)"),
            (o.QUICK_STOP_DECELERATION, 0, max(1, c.ticks(c.quick_stop_deceleration)),
             "quick stop deceleration (tick/s²)"),
            (o.POSITION_WINDOW, 0, c.ticks(c.position_window), "position window (ticks)"),
        ]

    def configure(self, master_node_id: int, master_period: float) -> None:
        """Write the start-up configuration by SDO (node must be pre-operational)."""
        for index, sub, value, _ in self.startup_writes(master_node_id, master_period):
            self.write(index, value, sub if sub or index in (o.CONSUMER_HEARTBEAT, o.ERROR_BEHAVIOUR) else None)
        self._check_emcy()
        if self.cfg.use_pdo:
            self._configure_pdos()
        else:
            self._invalidate_pdos(range(1, o.N_PDO + 1))
        if self.cfg.csp:
            self.write(o.INTERPOLATION_PERIOD, max(1, int(round(self.cfg.sync_period * 1e3))), 1)
            self.write(o.INTERPOLATION_PERIOD, -3, 2)
        self.set_mode(self.cfg.mode)

    def _check_emcy(self) -> None:
        """EMCY must be produced (0x1014 bit 31 clear): it is how a drive reports a fault at once."""
        cob = int(self.read(o.EMCY_COB_ID))
        if cob & o.PDO_COB_INVALID:
            log.warning("node %d: EMCY was disabled (0x1014 = 0x%08X); enabling it", self.node_id, cob)
            self.write(o.EMCY_COB_ID, cob & ~o.PDO_COB_INVALID)
            if int(self.read(o.EMCY_COB_ID)) & o.PDO_COB_INVALID:
                raise DriveFault(f"node {self.node_id}: EMCY is disabled (0x1014 bit 31) and the drive refuses "
                                 f"to enable it")

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
            tp.trans_type = 1 if c.csp else o.TRANS_EVENT_PROFILE      # CSP: status on every SYNC
            tp.inhibit_time = 0
            tp.event_timer = 0 if c.csp else max(1, int(round(c.tpdo_period * 1e3)))
            tp.rtr_allowed = False
            tp.enabled = True
            tp.save()
            rp = self.node.rpdo[1]
            rp.clear()
            rp.add_variable(o.CONTROLWORD)
            rp.add_variable(o.TARGET_POSITION)
            rp.cob_id = self._rpdo_cob
            rp.trans_type = 1 if c.csp else o.TRANS_EVENT_PROFILE      # CSP: target taken at the next SYNC
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
        return max(3.0 * self.cfg.status_period, 0.05)

    def state(self) -> State:
        return decode_state(self.current_statusword())

    def wait_status(self, predicate: Callable[[int], bool], timeout: float, what: str,
                    abort: threading.Event | None = None, after: int | None = None) -> int:
        """Wait until a statusword received after sequence number ``after`` (default: now) satisfies
        ``predicate``; by TPDO when configured (an SDO read when no TPDO came for two periods), else
        by SDO polling. Status from before the command never counts."""
        deadline = time.monotonic() + timeout
        with self._cond:
            seen = self.status_seq if after is None else after
            sw = self.statusword or 0
        while True:
            if self.pdo_active:
                with self._cond:
                    quiet_until = min(deadline, time.monotonic() + 2.0 * self.cfg.status_period)
                    while self.status_seq <= seen and time.monotonic() < quiet_until:
                        self._cond.wait(max(0.0, quiet_until - time.monotonic()))
                    fresh = self.status_seq > seen
                    sw, seen = (self.statusword or 0), self.status_seq
                if not fresh:                 # the status PDO did not come: ask by SDO (also after the command)
                    sw = self.read_statusword()
                    with self._cond:
                        seen = self.status_seq
            else:
                sw = self.read_statusword()
                with self._cond:
                    seen = self.status_seq
            if predicate(sw):
                return sw
            if time.monotonic() >= deadline or (abort is not None and abort.is_set()):
                break
            if not self.pdo_active:
                time.sleep(STATUS_POLL_PERIOD_S)
        raise DriveFault(f"node {self.node_id}: timed out after {timeout * 1e3:.0f} ms waiting for {what} "
                         f"(statusword 0x{sw:04X}, {decode_state(sw).value})")

    def fault_text(self, now: float | None = None) -> str | None:
        """Why this drive cannot be commanded, or None."""
        with self._cond:
            if self.rebooted:
                return f"node {self.node_id}: drive rebooted (boot-up message); homing lost"
            if self.heartbeat_lost:
                return f"node {self.node_id}: heartbeat lost (none for more than {self.cfg.heartbeat_timeout * 1e3:.0f} ms)"
            texts = []
            if self.emcy_active:
                e = self.emcy_active[-1]
                texts.append(f"node {self.node_id}: drive fault, EMCY 0x{e.code:04X} ({emcy_text(e.code)}), "
                             f"error register 0x{e.register:02X}")
            if self.expect_operational and self.heartbeat_state not in (None, 5):
                name = canopen.nmt.NMT_STATES.get(self.heartbeat_state, str(self.heartbeat_state))
                texts.append(f"node {self.node_id}: left NMT operational (now {name})")
            if self.comm_error:
                texts.append(self.comm_error)
            now = time.monotonic() if now is None else now
            if (self.pdo_active and self.expect_operational and self.heartbeat_state == 5
                    and self.status_time is not None and now - self.status_time > self.cfg.status_timeout):
                texts.append(f"node {self.node_id}: no status PDO for {(now - self.status_time) * 1e3:.0f} ms "
                             f"(link lost?)")
            sw = self.statusword
            if texts:
                return "; ".join(texts)
        if sw is not None and decode_state(sw) in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            code = self.error_code
            text = f", error code 0x{code:04X} ({emcy_text(code)})" if code else ""
            return f"node {self.node_id}: drive in fault state (statusword 0x{sw:04X}){text}"
        if self.expect_enabled and sw is not None and decode_state(sw) != State.OPERATION_ENABLED:
            return (f"node {self.node_id}: left operation enabled without a fault (now {decode_state(sw).value}, "
                    f"statusword 0x{sw:04X})")
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
        self.expect_enabled = False
        if self.pdo_active:
            try:
                self.network.send_message(self._rpdo_cob, struct.pack("<Hi", o.CW_QUICK_STOP, self.target))
                self.controlword = o.CW_QUICK_STOP
            except (can.CanError, OSError, RuntimeError) as exc:
                log.error("node %d: quick stop not sent: %s", self.node_id, exc)

    def _status_seq_now(self) -> int:
        with self._cond:
            return self.status_seq

    def transition(self, cw: int, want: tuple[State, ...], what: str) -> None:
        self.write(o.CONTROLWORD, cw)   # state machine always by confirmed SDO
        after = self._status_seq_now()  # only status produced after the drive took the command
        self.controlword = cw
        self.wait_status(lambda sw: decode_state(sw) in want, self.cfg.enable_timeout, what, after=after)

    def fault_reset(self) -> None:
        """Fault reset (rising edge of controlword bit 7) and clear the driver's fault memory."""
        state = decode_state(self.read_statusword())
        with self._cond:
            self.comm_error = None          # the drive answered SDO again
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

    def ensure_operational(self) -> None:
        """NMT start, confirmed by a heartbeat sent after it: brings back a node that left operational
        (e.g. pre-operational after a lost host heartbeat); harmless to a node that is operational."""
        with self._cond:
            state, seen = self.heartbeat_state, self.heartbeat_seq
        if state != 5:
            log.warning("node %d is NMT %s: sending NMT start", self.node_id,
                        canopen.nmt.NMT_STATES.get(state, str(state)))
        try:
            self.node.nmt.send_command(0x01)
        except (can.CanError, OSError, RuntimeError) as exc:
            raise BusError(f"node {self.node_id}: CAN bus error sending NMT start: {exc}") from exc
        deadline = time.monotonic() + max(BOOT_WAIT_S, 3 * self.cfg.heartbeat_period)
        with self._cond:
            while self.heartbeat_seq <= seen or self.heartbeat_state != 5:
                left = deadline - time.monotonic()
                if left <= 0:
                    name = canopen.nmt.NMT_STATES.get(self.heartbeat_state, str(self.heartbeat_state))
                    raise DriveFault(f"node {self.node_id}: still NMT {name} after NMT start")
                self._cond.wait(left)

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
        self._ready_for_setpoints()
        self.last_taken = time.monotonic()
        self.expect_enabled = True

    def disable_power(self) -> bool:
        """Quick stop, then disable voltage (power stage off). Best effort: errors are logged.

        True when a statusword read after the command confirms the power stage is off."""
        self.expect_enabled = False
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
            return self.power_off_confirmed(self.read_statusword())
        except DriveFault as exc:
            log.error("node %d: disable by SDO incomplete: %s", self.node_id, exc)
        if not self.pdo_active:
            return False
        # SDO does not get through (a hung SDO server): disable voltage by RPDO, confirmed by a later status PDO
        after = self._status_seq_now()
        try:
            self.send_controlword(o.CW_DISABLE_VOLTAGE)
            return self._status_since(after, self.power_off_confirmed, time.monotonic() + 3 * self.cfg.status_period,
                                      threading.Event()) is not None
        except DriveFault as exc:
            log.error("node %d: disable by RPDO failed: %s", self.node_id, exc)
            return False

    @staticmethod
    def power_off_confirmed(statusword: int) -> bool:
        """The statusword shows the power stage off (or never on)."""
        return decode_state(statusword) in (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON,
                                             State.NOT_READY_TO_SWITCH_ON, State.FAULT)

    def start_homing(self) -> int:
        """Start the homing procedure; returns the status sequence number the answer must come after."""
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
        return self._status_seq_now()

    def finish_homing(self, deadline: float, after: int) -> None:
        """Wait for homing attained (or error) in status received after ``after``, then back to profile position."""
        def done(sw: int) -> bool:
            return bool(sw & (o.SW_HOMING_ERROR | o.SW_FAULT)) or (
                sw & (o.SW_HOMING_ATTAINED | o.SW_TARGET_REACHED) == (o.SW_HOMING_ATTAINED | o.SW_TARGET_REACHED))
        sw = self.wait_status(done, max(0.0, deadline - time.monotonic()), "homing attained", after=after)
        self.write(o.CONTROLWORD, o.CW_ENABLE_OPERATION)
        self.controlword = o.CW_ENABLE_OPERATION
        if sw & o.SW_FAULT:
            raise DriveFault(self.fault_text() or f"node {self.node_id}: fault during homing")
        if sw & o.SW_HOMING_ERROR:
            raise DriveFault(f"node {self.node_id}: homing error (statusword 0x{sw:04X}, method "
                             f"{self.cfg.homing_method})")
        self.set_mode(self.cfg.mode)
        c = self.cfg
        self.write(o.SOFTWARE_LIMITS, c.min_ticks, 1)
        self.write(o.SOFTWARE_LIMITS, c.max_ticks, 2)
        self.target = self.read_position()
        self.write(o.TARGET_POSITION, self.target)
        self._ready_for_setpoints()
        self.homed = True

    # ---------------------------------------------------------------- set-point handshake
    #
    # Profile position, CiA 402 strictly: raise bit 4 only when a status received after bit 4 was
    # last lowered shows the acknowledge (bit 12) low; the set-point is taken when a status received
    # after the raise shows the acknowledge high; then lower bit 4. Nothing here waits past the
    # call's deadline: a drive that is late is counted (missed) and caught up on the next call.

    def _ready_for_setpoints(self) -> None:
        """After the last controlword by SDO (bit 4 low): the first set-point may go at once if the acknowledge is low.

        With status PDOs, the evidence is a status PDO produced after that command, as for every other raise: the
        drive sends it from its cycle, so the cycle has seen bit 4 low and the first raise is an edge for a strict
        drive. An SDO read of the statusword is no such evidence (the drive may not have run a cycle since the
        command; the raise, milliseconds later, would then be no edge and the set-point lost)."""
        if self.cfg.csp:
            self._sp_phase, self._sp_seq = "idle", self._status_seq_now()
            return
        if self.pdo_active:
            seq = self._status_seq_now()
            sw = self._status_since(seq, lambda s: True, time.monotonic() + self.cfg.status_timeout, threading.Event())
            # no status PDO in time: the first call waits for one (the "lowered" phase), within its own budget
            self._sp_phase = "idle" if sw is not None and not sw & o.SW_SETPOINT_ACK else "lowered"
            self._sp_seq = seq if self._sp_phase == "lowered" else self._status_seq_now()
            return
        sw = self.read_statusword()               # read after the command: not a stale status
        self._sp_phase = "lowered" if sw & o.SW_SETPOINT_ACK else "idle"
        self._sp_seq = self._status_seq_now()

    def _status_since(self, seq: int, predicate: Callable[[int], bool], deadline: float,
                      abort: threading.Event) -> int | None:
        """A statusword received after ``seq`` satisfying ``predicate`` before ``deadline``, else None.

        PDO mode waits on the status PDOs (no SDO); SDO mode reads the statusword (each read is after the command)."""
        if self.pdo_active:
            with self._cond:
                while True:
                    sw = self.statusword
                    if self.status_seq > seq and sw is not None and predicate(sw):
                        return sw
                    left = deadline - time.monotonic()
                    if left <= 0 or abort.is_set():
                        return None
                    self._cond.wait(left)
        while True:
            sw = self.read_statusword()
            if predicate(sw):
                return sw
            if time.monotonic() >= deadline or abort.is_set():
                return None
            time.sleep(STATUS_POLL_PERIOD_S)

    def _check_enabled(self, sw: int | None) -> None:
        if sw is not None and decode_state(sw) != State.OPERATION_ENABLED:
            raise DriveFault(f"node {self.node_id}: not in operation enabled but {decode_state(sw).value} "
                             f"(statusword 0x{sw:04X}); call enable()")

    def request_setpoint(self, target: int, deadline: float, abort: threading.Event) -> bool:
        """Phase 1: send ``target`` with a new-set-point edge if the drive is ready for one.

        False when the previous set-point is still unanswered (the drive is late): nothing new is sent."""
        with self._cond:
            self._check_enabled(self.statusword)
        if self._sp_phase == "raised":
            # the previous edge was not acknowledged within its call: if it has been by now, it was late
            if self._status_since(self._sp_seq, lambda sw: bool(sw & o.SW_SETPOINT_ACK), deadline, abort) is not None:
                self.late_acks += 1
                self._taken()
            else:
                self._missed("never acknowledged")
            self._lower()
        if self._sp_phase == "lowered":
            ack_low = self._status_since(self._sp_seq, lambda sw: not sw & o.SW_SETPOINT_ACK or bool(sw & o.SW_FAULT),
                                         deadline, abort)
            if ack_low is None:
                self._missed("not sent: the drive did not show the acknowledge low in time")
                return False
            self._check_enabled(ack_low)
            self._sp_phase = "idle"
        if abort.is_set():
            raise MotionRefused("set-point interrupted: drives are being disabled")
        self._sp_seq = self._status_seq_now()
        self.send_controlword(o.CW_ENABLE_OPERATION | o.CW_NEW_SETPOINT | o.CW_CHANGE_IMMEDIATELY, target)
        self._sp_phase = "raised"
        self.edges += 1
        return True

    def await_ack(self, deadline: float, abort: threading.Event) -> bool:
        """Phase 2: the acknowledge of *this* edge (status after the raise); on it, lower bit 4 (phase 3).

        False when it did not come before ``deadline``: bit 4 stays high and the next call looks again."""
        sw = self._status_since(self._sp_seq, lambda s: bool(s & (o.SW_SETPOINT_ACK | o.SW_FAULT)), deadline, abort)
        if sw is None or sw & o.SW_FAULT:
            return False
        self._taken()
        self._lower()
        return True

    def _lower(self) -> None:
        self._sp_seq = self._status_seq_now()
        self.send_controlword(o.CW_ENABLE_OPERATION | o.CW_CHANGE_IMMEDIATELY)
        self._sp_phase = "lowered"

    def send_cyclic_target(self, target: int) -> bool:
        """Cyclic synchronous position: send the target for the next SYNC (no handshake, no waiting).

        Returns whether the drive followed the previous target: a status received since the
        previous call shows bit 12 ("drive follows the command value"); otherwise it counts as missed."""
        with self._cond:
            sw = self.statusword
            fresh = self.status_seq > self._sp_seq
            self._check_enabled(sw)
            self._sp_seq = self.status_seq
        following = fresh and sw is not None and bool(sw & o.SW_FOLLOWING)
        if following:
            self._taken()
        elif self._sp_phase != "idle":
            self._missed("no status showing the drive following since the last target")
        self._sp_phase = "sent"
        self.send_controlword(o.CW_ENABLE_OPERATION, target)
        self.edges += 1
        return following

    def _taken(self) -> None:
        self.missed_acks = 0
        self.last_taken = time.monotonic()

    def setpoints_lost(self, now: float) -> bool:
        """Persistent misses: several in a row and none taken for longer than ``status_timeout``."""
        return self.missed_acks >= MAX_MISSED_ACKS and now - self.last_taken > self.cfg.status_timeout

    def _missed(self, why: str) -> None:
        self.missed_acks += 1
        self.missed_total += 1
        log.warning("node %d: set-point missed (%s; %d in a row)", self.node_id, why, self.missed_acks)


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
        self.stats = {"setpoints": 0, "acked_in_call": 0, "sdo_position_reads": 0, "pdo_position_reads": 0,
                      "disable_retries": 0}
        self._call_times: list[float] = []      # duration of each send_setpoints call (s), last CALL_LOG_LENGTH
        self._want_disabled = False
        self._disable_unconfirmed: str | None = None
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
            if c.csp:
                net.sync.start(c.sync_period)          # SYNC producer: the drives' cycle
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
        period = min(MONITOR_PERIOD_S, self.config.heartbeat_timeout / 4)
        while not self._monitor_stop.wait(period):
            now = time.monotonic()
            for d in self.drives:
                d.check_heartbeat(now)
            net = self.network
            if net is not None and net.notifier is not None and net.notifier.exception is not None:
                self._bus_error = f"CAN receive failed: {net.notifier.exception}"
            if not self.config.use_pdo and self._enabled and self._lock.acquire(blocking=False):
                # SDO-only: nothing reports the drives' state by itself, so ask every period
                try:
                    for d in self.drives:
                        d.read_statusword()
                except DriveFault:
                    pass                      # recorded in the drive's comm_error, shown by fault()
                finally:
                    self._lock.release()
            if self.fault() is not None:
                self._abort.set()
            if self._want_disabled and self._disable_unconfirmed is not None:
                self._retry_disable()

    def _retry_disable(self) -> None:
        """A disable that was not confirmed is sent again, every monitor period, until the statusword confirms it."""
        if not self._lock.acquire(timeout=DISABLE_RETRY_S):
            return
        try:
            if not self._want_disabled:
                return
            self.stats["disable_retries"] += 1
            self._disable_all()
        finally:
            self._lock.release()

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
            if self.config.csp:
                try:
                    self.network.sync.stop()
                except Exception:  # noqa: BLE001 - bus may be gone already
                    pass
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
        if self._disable_unconfirmed:
            texts.append(self._disable_unconfirmed)
        return "; ".join(texts) if texts else None

    def report(self) -> dict:
        """Figures for a run summary: set-point calls, edges sent, acknowledged in the call, late
        (taken after the call returned) and missed (not sent, or never acknowledged), disable retries,
        and the time each :meth:`send_setpoints` call took (ms, median / p99 / max)."""
        out = dict(self.stats)
        out["edges"] = sum(d.edges for d in self.drives)
        out["late_acks"] = sum(d.late_acks for d in self.drives)
        out["missed"] = sum(d.missed_total for d in self.drives)
        out["missed_per_drive"] = {d.node_id: d.missed_total for d in self.drives}
        times = np.array(self._call_times) * 1e3
        if times.size:
            out["setpoint_call_ms"] = {"p50": float(np.percentile(times, 50)), "p99": float(np.percentile(times, 99)),
                                       "max": float(times.max())}
        return out

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
                started = [d.start_homing() for d in self.drives]
                for d, after in zip(self.drives, started):
                    d.finish_homing(deadline, after)
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
            # clamp in floating point first: a cast of a huge finite value to int64 wraps around
            targets = np.clip(np.rint(t.astype(float)), lo, hi).astype(np.int64)

            def go() -> None:
                start = time.monotonic()
                if self.config.csp:
                    followed = [d.send_cyclic_target(int(target)) for d, target in zip(self.drives, targets)]
                    self.stats["acked_in_call"] += followed.count(True)
                    self.stats["setpoints"] += 1
                    self._book_call(start)
                    return
                deadline = start + self.config.setpoint_ack_timeout   # the whole call's budget, both drives
                raised = [d.request_setpoint(int(target), deadline, self._abort)
                          for d, target in zip(self.drives, targets)]
                taken = [r and d.await_ack(deadline, self._abort) for d, r in zip(self.drives, raised)]
                if self._abort.is_set():
                    raise MotionRefused("set-point interrupted: drives are being disabled")
                self.stats["acked_in_call"] += taken.count(True)
                self.stats["setpoints"] += 1
                self._book_call(start)
            self._guard(go)
            self._raise_if_fault()

    def _book_call(self, start: float) -> None:
        """Record one set-point call's duration; persistent misses on a drive are a fault."""
        now = time.monotonic()
        self._call_times.append(now - start)
        del self._call_times[:-CALL_LOG_LENGTH]
        for d in self.drives:
            if d.setpoints_lost(now):
                raise DriveFault(f"node {d.node_id}: {d.missed_acks} set-points in a row not taken, none for "
                                 f"{(now - d.last_taken) * 1e3:.0f} ms ({d.missed_total} missed in all)")

    def positions(self) -> np.ndarray:
        """Measured positions (ticks): from TPDO1 when fresh, otherwise read by SDO (not when the
        drive is known to be faulty or lost: then :class:`DriveFault` at once)."""
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
                    if d.pdo_active:
                        text = d.fault_text(now)
                        if text:                  # a drive known lost is reported, not waited for by SDO
                            raise DriveFault(text)
                    with self._lock:
                        out[i] = d.read_position()
                    self.stats["sdo_position_reads"] += 1
        self._guard(go)
        return out

    def states(self) -> list[State]:
        """CiA 402 state of each drive (statusword by TPDO when fresh, else SDO)."""
        return [decode_state(d.current_statusword()) for d in self.drives]

    def is_disabled(self) -> bool | None:
        """True when every drive's statusword shows its power stage off, False when one shows it on,
        None when a drive cannot be read (link lost, SDO not answering)."""
        try:
            words = [d.current_statusword() for d in self.drives]
        except DriveFault:
            return None
        return all(CiA402Drive.power_off_confirmed(w) for w in words)

    def disable(self) -> None:
        """Stop commanding and remove power: quick stop, then disable voltage. Any thread.

        The power stage counts as off only when a statusword read after the command shows it; until
        then :meth:`fault` says so (loudly logged) and the monitor sends the disable again every
        period, also after a link came back."""
        self._abort.set()
        self._enabled = False
        self._want_disabled = True
        for d in self.drives:
            d.quick_stop_now()
        got = self._lock.acquire(timeout=max(1.0, 3 * self.config.sdo_timeout))
        try:
            self._disable_all()
        finally:
            if got:
                self._lock.release()

    def _disable_all(self) -> None:
        unconfirmed = [d.node_id for d in self.drives if not d.disable_power()]
        if unconfirmed:
            if self._disable_unconfirmed is None:
                log.error("DISABLE NOT CONFIRMED by node(s) %s: the power stage may still be on; "
                          "retrying every %.0f ms", unconfirmed, MONITOR_PERIOD_S * 1e3)
            self._disable_unconfirmed = (f"disable not confirmed by node(s) {unconfirmed}: power stage may be on "
                                         f"(retrying)")
        else:
            if self._disable_unconfirmed is not None:
                log.warning("disable confirmed by all drives after retries")
            self._disable_unconfirmed = None

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
                    else:
                        d.ensure_operational()
                    d.enable_operation()
            try:
                self._want_disabled = False
                self._disable_unconfirmed = None
                self._guard(go)
                self._abort.clear()
                self._raise_if_fault()
            except BaseException:
                # never leave a drive powered after a failed enable
                self._abort.set()
                self._want_disabled = True
                for d in self.drives:
                    d.quick_stop_now()
                self._disable_all()
                raise
            self._disable_unconfirmed = None
            self._enabled = True
