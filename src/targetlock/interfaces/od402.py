"""CiA 402 (drives and motion control) and CiA 301 constants, state decoding, object dictionary.

Shared by the driver (:mod:`.cia402`) and the simulated drive (:mod:`.sim_cia402`) so both speak
the same object dictionary. Only the objects targetlock uses are described; a real drive's EDS
has many more, and the driver accesses objects by index, so either dictionary works for it.

Units at this boundary are the drive's: positions in encoder ticks, velocities in tick/s,
accelerations in tick/s², times in ms as CiA 301 defines them.
"""
from __future__ import annotations

import enum

from canopen import objectdictionary as od
from canopen.objectdictionary import ODArray, ODRecord, ODVariable, ObjectDictionary

__all__ = ["State", "decode_state", "Command", "decode_command", "build_object_dictionary", "emcy_text",
           "sdo_abort_text"]

# ---- CiA 301 communication objects ---------------------------------------------------------
DEVICE_TYPE = 0x1000
ERROR_REGISTER = 0x1001
DEVICE_NAME = 0x1008
CONSUMER_HEARTBEAT = 0x1016        # array of u32: (node id << 16) | time (ms)
PRODUCER_HEARTBEAT = 0x1017        # u16, ms
IDENTITY = 0x1018
EMCY_COB_ID = 0x1014               # u32; bit 31 set = EMCY not produced
ERROR_BEHAVIOUR = 0x1029           # array of u8; sub 1: communication error (0 pre-op, 1 no change, 2 stopped)
RPDO_COMM, RPDO_MAP = 0x1400, 0x1600
TPDO_COMM, TPDO_MAP = 0x1800, 0x1A00
N_PDO = 4                          # PDOs 1..4 of each direction
PDO_COB_INVALID = 1 << 31          # COB-ID bit: PDO not valid
PDO_COB_NO_RTR = 1 << 30
TRANS_EVENT_MANUFACTURER, TRANS_EVENT_PROFILE = 254, 255

# ---- CiA 402 objects -----------------------------------------------------------------------
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
ABORT_CONNECTION_OPTION = 0x6007  # i16: reaction to a lost host (0 none, 1 fault, 2 disable voltage, 3 quick stop)
QUICK_STOP_OPTION = 0x605A
SHUTDOWN_OPTION = 0x605B
DISABLE_OPERATION_OPTION = 0x605C
HALT_OPTION = 0x605D
FAULT_REACTION_OPTION = 0x605E
MODES_OF_OPERATION = 0x6060
MODES_DISPLAY = 0x6061
POSITION_DEMAND = 0x6062
POSITION_ACTUAL = 0x6064
POSITION_WINDOW = 0x6067
VELOCITY_ACTUAL = 0x606C
TARGET_POSITION = 0x607A
HOME_OFFSET = 0x607C
SOFTWARE_LIMITS = 0x607D           # sub 1: min, sub 2: max (ticks)
PROFILE_VELOCITY = 0x6081
PROFILE_ACCELERATION = 0x6083
PROFILE_DECELERATION = 0x6084
QUICK_STOP_DECELERATION = 0x6085
HOMING_METHOD = 0x6098
HOMING_SPEEDS = 0x6099             # sub 1: search for switch, sub 2: search for zero (tick/s)
HOMING_ACCELERATION = 0x609A
INTERPOLATION_PERIOD = 0x60C2      # sub 1: value, sub 2: index (period = value x 10^index s)
SUPPORTED_DRIVE_MODES = 0x6502

MODE_PROFILE_POSITION = 1
MODE_HOMING = 6
MODE_CYCLIC_SYNC_POSITION = 8

# Homing methods that take the current position as home without motion (CiA 402-2).
HOMING_ON_CURRENT_POSITION = (35, 37)

# ---- controlword ---------------------------------------------------------------------------
CW_DISABLE_VOLTAGE = 0x0000
CW_QUICK_STOP = 0x0002
CW_SHUTDOWN = 0x0006
CW_SWITCH_ON = 0x0007              # also "disable operation"
CW_ENABLE_OPERATION = 0x000F
CW_NEW_SETPOINT = 1 << 4           # profile position: new set-point; homing: start homing
CW_HOMING_START = 1 << 4
CW_CHANGE_IMMEDIATELY = 1 << 5
CW_RELATIVE = 1 << 6
CW_FAULT_RESET = 1 << 7
CW_HALT = 1 << 8

# ---- statusword ----------------------------------------------------------------------------
SW_READY_TO_SWITCH_ON = 1 << 0
SW_SWITCHED_ON = 1 << 1
SW_OPERATION_ENABLED = 1 << 2
SW_FAULT = 1 << 3
SW_VOLTAGE_ENABLED = 1 << 4
SW_QUICK_STOP = 1 << 5             # active low: 0 while a quick stop is active
SW_SWITCH_ON_DISABLED = 1 << 6
SW_WARNING = 1 << 7
SW_REMOTE = 1 << 9
SW_TARGET_REACHED = 1 << 10
SW_INTERNAL_LIMIT = 1 << 11
SW_SETPOINT_ACK = 1 << 12          # profile position mode
SW_HOMING_ATTAINED = 1 << 12       # homing mode
SW_FOLLOWING_ERROR = 1 << 13       # profile position mode
SW_HOMING_ERROR = 1 << 13          # homing mode
SW_FOLLOWING = 1 << 12             # cyclic synchronous position: the drive follows the target (0 = ignored)

# EMCY codes used by the simulated drive and named in fault messages (CiA 301 / 402).
EMCY_TEXT = {
    0x0000: "error reset / no error",
    0x1000: "generic error",
    0x2310: "continuous over-current",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x4310: "drive over-temperature",
    0x5441: "safe torque off (STO) active",
    0x7121: "motor blocked",
    0x7305: "incremental encoder 1 broken",
    0x8130: "heartbeat or life guard error",
    0x8611: "following error",
    0x8612: "reference limit",
    0xFF00: "manufacturer specific",
}

SDO_ABORT_TEXT = {
    0x05040000: "SDO protocol timed out",
    0x06010000: "unsupported access to an object",
    0x06010001: "attempt to read a write-only object",
    0x06010002: "attempt to write a read-only object",
    0x06020000: "object does not exist",
    0x06040041: "object cannot be mapped to the PDO",
    0x06040042: "number and length of mapped objects exceed the PDO length",
    0x06040043: "general parameter incompatibility",
    0x06070010: "data type does not match, length of service parameter does not match",
    0x06090011: "sub-index does not exist",
    0x06090030: "value range of parameter exceeded",
    0x06090031: "value of parameter written too high",
    0x06090032: "value of parameter written too low",
    0x08000000: "general error",
    0x08000022: "data cannot be transferred or stored because of the present device state",
}


def emcy_text(code: int) -> str:
    """A short description of an EMCY / CiA 402 error code."""
    if code in EMCY_TEXT:
        return EMCY_TEXT[code]
    for mask in (0xFFF0, 0xFF00, 0xF000):
        if code & mask in EMCY_TEXT:
            return EMCY_TEXT[code & mask]
    return "unknown error"


def sdo_abort_text(code: int) -> str:
    return SDO_ABORT_TEXT.get(code, "unknown abort code")


class State(enum.Enum):
    """The CiA 402 power state machine states, as decoded from the statusword."""
    NOT_READY_TO_SWITCH_ON = "not ready to switch on"
    SWITCH_ON_DISABLED = "switch on disabled"
    READY_TO_SWITCH_ON = "ready to switch on"
    SWITCHED_ON = "switched on"
    OPERATION_ENABLED = "operation enabled"
    QUICK_STOP_ACTIVE = "quick stop active"
    FAULT_REACTION_ACTIVE = "fault reaction active"
    FAULT = "fault"
    UNKNOWN = "unknown"


# (mask, value, state) in the order CiA 402 Table 30 gives them.
_STATE_PATTERNS = (
    (0x4F, 0x00, State.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, State.SWITCH_ON_DISABLED),
    (0x6F, 0x21, State.READY_TO_SWITCH_ON),
    (0x6F, 0x23, State.SWITCHED_ON),
    (0x6F, 0x27, State.OPERATION_ENABLED),
    (0x6F, 0x07, State.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, State.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, State.FAULT),
)

# Statusword bits (0-6) the simulated drive shows in each state.
STATE_BITS = {
    State.NOT_READY_TO_SWITCH_ON: 0x00,
    State.SWITCH_ON_DISABLED: 0x40 | SW_QUICK_STOP,
    State.READY_TO_SWITCH_ON: 0x21,
    State.SWITCHED_ON: 0x23 | SW_VOLTAGE_ENABLED,
    State.OPERATION_ENABLED: 0x27 | SW_VOLTAGE_ENABLED,
    State.QUICK_STOP_ACTIVE: 0x07 | SW_VOLTAGE_ENABLED,
    State.FAULT_REACTION_ACTIVE: 0x0F,
    State.FAULT: 0x08,
}


def decode_state(statusword: int) -> State:
    """The power state encoded in a statusword (bits 0-3, 5, 6)."""
    for mask, value, state in _STATE_PATTERNS:
        if statusword & mask == value:
            return state
    return State.UNKNOWN


class Command(enum.Enum):
    """Device-control commands encoded in the controlword (bits 0-3, 7)."""
    SHUTDOWN = "shutdown"
    SWITCH_ON = "switch on"                 # also "disable operation"
    ENABLE_OPERATION = "enable operation"   # "switch on + enable operation"
    DISABLE_VOLTAGE = "disable voltage"
    QUICK_STOP = "quick stop"
    FAULT_RESET = "fault reset"


def decode_command(controlword: int) -> Command:
    """The device-control command in a controlword; bit 7 set reads as fault reset (edge-triggered)."""
    if controlword & CW_FAULT_RESET:
        return Command.FAULT_RESET
    if controlword & 0x02 == 0:
        return Command.DISABLE_VOLTAGE
    if controlword & 0x06 == 0x02:
        return Command.QUICK_STOP
    if controlword & 0x07 == 0x06:
        return Command.SHUTDOWN
    if controlword & 0x0F == 0x07:
        return Command.SWITCH_ON
    return Command.ENABLE_OPERATION


# ---- object dictionary ---------------------------------------------------------------------

def _var(name: str, index: int, subindex: int, data_type: int, access: str = "rw", default=None,
         mappable: bool = False) -> ODVariable:
    v = ODVariable(name, index, subindex)
    v.data_type = data_type
    v.access_type = access
    v.default = default
    v.pdo_mappable = mappable
    return v


def _add(dictionary: ObjectDictionary, *objects) -> None:
    for obj in objects:
        dictionary.add_object(obj)


def _record(name: str, index: int, members: list[ODVariable]) -> ODRecord:
    rec = ODRecord(name, index)
    for m in members:
        rec.add_member(m)
    return rec


def _array(name: str, index: int, members: list[ODVariable]) -> ODArray:
    arr = ODArray(name, index)
    for m in members:
        arr.add_member(m)
    return arr


def build_object_dictionary(node_id: int) -> ObjectDictionary:
    """Object dictionary of one steering drive (CiA 301 communication + CiA 402 motion objects).

    Default PDO mapping at power-up: RPDO1 = controlword, TPDO1 = statusword (both on the
    predefined COB-IDs, event driven); RPDO2-4 and TPDO2-4 empty and not valid.
    """
    d = ObjectDictionary()
    d.node_id = node_id
    _add(d,
         _var("Device type", DEVICE_TYPE, 0, od.UNSIGNED32, "ro", 0x00020192),
         _var("Error register", ERROR_REGISTER, 0, od.UNSIGNED8, "ro", 0, mappable=True),
         _var("Manufacturer device name", DEVICE_NAME, 0, od.VISIBLE_STRING, "const", "targetlock sim drive"),
         _array("Consumer heartbeat time", CONSUMER_HEARTBEAT, [
             _var("Number of entries", CONSUMER_HEARTBEAT, 0, od.UNSIGNED8, "ro", 1),
             _var("Consumer heartbeat time 1", CONSUMER_HEARTBEAT, 1, od.UNSIGNED32, "rw", 0)]),
         _var("Producer heartbeat time", PRODUCER_HEARTBEAT, 0, od.UNSIGNED16, "rw", 0),
         _var("COB-ID EMCY", EMCY_COB_ID, 0, od.UNSIGNED32, "rw", 0x80 + node_id),
         _array("Error behaviour", ERROR_BEHAVIOUR, [
             _var("Number of entries", ERROR_BEHAVIOUR, 0, od.UNSIGNED8, "ro", 1),
             _var("Communication error", ERROR_BEHAVIOUR, 1, od.UNSIGNED8, "rw", 0)]),
         _record("Identity object", IDENTITY, [
             _var("Number of entries", IDENTITY, 0, od.UNSIGNED8, "ro", 4),
             _var("Vendor-ID", IDENTITY, 1, od.UNSIGNED32, "ro", 0),
             _var("Product code", IDENTITY, 2, od.UNSIGNED32, "ro", 0x402),
             _var("Revision number", IDENTITY, 3, od.UNSIGNED32, "ro", 1),
             _var("Serial number", IDENTITY, 4, od.UNSIGNED32, "ro", node_id)]),
         )
    for n in range(N_PDO):
        rx_default = (0x200 + 0x100 * n + node_id) | (0 if n == 0 else PDO_COB_INVALID)
        tx_default = (0x180 + 0x100 * n + node_id) | (0 if n == 0 else PDO_COB_INVALID)
        _add(d,
             _record(f"RPDO{n + 1} communication parameter", RPDO_COMM + n, [
                 _var("Highest sub-index supported", RPDO_COMM + n, 0, od.UNSIGNED8, "ro", 5),
                 _var("COB-ID used by RPDO", RPDO_COMM + n, 1, od.UNSIGNED32, "rw", rx_default),
                 _var("Transmission type", RPDO_COMM + n, 2, od.UNSIGNED8, "rw", TRANS_EVENT_PROFILE),
                 _var("Inhibit time", RPDO_COMM + n, 3, od.UNSIGNED16, "rw", 0),
                 _var("Event timer", RPDO_COMM + n, 5, od.UNSIGNED16, "rw", 0)]),
             _record(f"RPDO{n + 1} mapping parameter", RPDO_MAP + n,
                     [_var("Number of mapped objects", RPDO_MAP + n, 0, od.UNSIGNED8, "rw", 1 if n == 0 else 0)]
                     + [_var(f"Mapped object {k}", RPDO_MAP + n, k, od.UNSIGNED32, "rw",
                             (CONTROLWORD << 16 | 16) if (n == 0 and k == 1) else 0) for k in range(1, 9)]),
             _record(f"TPDO{n + 1} communication parameter", TPDO_COMM + n, [
                 _var("Highest sub-index supported", TPDO_COMM + n, 0, od.UNSIGNED8, "ro", 6),
                 _var("COB-ID used by TPDO", TPDO_COMM + n, 1, od.UNSIGNED32, "rw", tx_default),
                 _var("Transmission type", TPDO_COMM + n, 2, od.UNSIGNED8, "rw", TRANS_EVENT_PROFILE),
                 _var("Inhibit time", TPDO_COMM + n, 3, od.UNSIGNED16, "rw", 0),
                 _var("Reserved", TPDO_COMM + n, 4, od.UNSIGNED8, "rw", 0),
                 _var("Event timer", TPDO_COMM + n, 5, od.UNSIGNED16, "rw", 0),
                 _var("SYNC start value", TPDO_COMM + n, 6, od.UNSIGNED8, "rw", 0)]),
             _record(f"TPDO{n + 1} mapping parameter", TPDO_MAP + n,
                     [_var("Number of mapped objects", TPDO_MAP + n, 0, od.UNSIGNED8, "rw", 1 if n == 0 else 0)]
                     + [_var(f"Mapped object {k}", TPDO_MAP + n, k, od.UNSIGNED32, "rw",
                             (STATUSWORD << 16 | 16) if (n == 0 and k == 1) else 0) for k in range(1, 9)]),
             )
    _add(d,
         _var("Error code", ERROR_CODE, 0, od.UNSIGNED16, "ro", 0, mappable=True),
         _var("Controlword", CONTROLWORD, 0, od.UNSIGNED16, "rw", 0, mappable=True),
         _var("Statusword", STATUSWORD, 0, od.UNSIGNED16, "ro", 0, mappable=True),
         _var("Abort connection option code", ABORT_CONNECTION_OPTION, 0, od.INTEGER16, "rw", 1),
         _var("Quick stop option code", QUICK_STOP_OPTION, 0, od.INTEGER16, "rw", 2),
         _var("Shutdown option code", SHUTDOWN_OPTION, 0, od.INTEGER16, "rw", 0),
         _var("Disable operation option code", DISABLE_OPERATION_OPTION, 0, od.INTEGER16, "rw", 1),
         _var("Halt option code", HALT_OPTION, 0, od.INTEGER16, "rw", 1),
         _var("Fault reaction option code", FAULT_REACTION_OPTION, 0, od.INTEGER16, "rw", 2),
         _var("Modes of operation", MODES_OF_OPERATION, 0, od.INTEGER8, "rw", MODE_PROFILE_POSITION, mappable=True),
         _var("Modes of operation display", MODES_DISPLAY, 0, od.INTEGER8, "ro", MODE_PROFILE_POSITION,
              mappable=True),
         _var("Position demand value", POSITION_DEMAND, 0, od.INTEGER32, "ro", 0, mappable=True),
         _var("Position actual value", POSITION_ACTUAL, 0, od.INTEGER32, "ro", 0, mappable=True),
         _var("Position window", POSITION_WINDOW, 0, od.UNSIGNED32, "rw", 20),
         _var("Velocity actual value", VELOCITY_ACTUAL, 0, od.INTEGER32, "ro", 0, mappable=True),
         _var("Target position", TARGET_POSITION, 0, od.INTEGER32, "rw", 0, mappable=True),
         _var("Home offset", HOME_OFFSET, 0, od.INTEGER32, "rw", 0),
         _array("Software position limit", SOFTWARE_LIMITS, [
             _var("Number of entries", SOFTWARE_LIMITS, 0, od.UNSIGNED8, "ro", 2),
             _var("Min position limit", SOFTWARE_LIMITS, 1, od.INTEGER32, "rw", 0),
             _var("Max position limit", SOFTWARE_LIMITS, 2, od.INTEGER32, "rw", 0)]),
         _var("Profile velocity", PROFILE_VELOCITY, 0, od.UNSIGNED32, "rw", 100000, mappable=True),
         _var("Profile acceleration", PROFILE_ACCELERATION, 0, od.UNSIGNED32, "rw", 10000000),
         _var("Profile deceleration", PROFILE_DECELERATION, 0, od.UNSIGNED32, "rw", 10000000),
         _var("Quick stop deceleration", QUICK_STOP_DECELERATION, 0, od.UNSIGNED32, "rw", 20000000),
         _var("Homing method", HOMING_METHOD, 0, od.INTEGER8, "rw", 37),
         _array("Homing speeds", HOMING_SPEEDS, [
             _var("Number of entries", HOMING_SPEEDS, 0, od.UNSIGNED8, "ro", 2),
             _var("Speed during search for switch", HOMING_SPEEDS, 1, od.UNSIGNED32, "rw", 20000),
             _var("Speed during search for zero", HOMING_SPEEDS, 2, od.UNSIGNED32, "rw", 5000)]),
         _var("Homing acceleration", HOMING_ACCELERATION, 0, od.UNSIGNED32, "rw", 1000000),
         _record("Interpolation time period", INTERPOLATION_PERIOD, [
             _var("Highest sub-index supported", INTERPOLATION_PERIOD, 0, od.UNSIGNED8, "ro", 2),
             _var("Interpolation time period value", INTERPOLATION_PERIOD, 1, od.UNSIGNED8, "rw", 1),
             _var("Interpolation time index", INTERPOLATION_PERIOD, 2, od.INTEGER8, "rw", -3)]),
         _var("Supported drive modes", SUPPORTED_DRIVE_MODES, 0, od.UNSIGNED32, "ro",
              (1 << (MODE_PROFILE_POSITION - 1)) | (1 << (MODE_HOMING - 1)) | (1 << (MODE_CYCLIC_SYNC_POSITION - 1))),
         )
    return d
