"""CiA 402 statusword / controlword decoding and the object dictionary."""
from __future__ import annotations

import numpy as np
import pytest

from targetlock.interfaces import od402 as o
from targetlock.interfaces.od402 import Command, State, decode_command, decode_state


@pytest.mark.parametrize("bits, state", [
    (0b0000000, State.NOT_READY_TO_SWITCH_ON),
    (0b1000000, State.SWITCH_ON_DISABLED),
    (0b0100001, State.READY_TO_SWITCH_ON),
    (0b0100011, State.SWITCHED_ON),
    (0b0100111, State.OPERATION_ENABLED),
    (0b0000111, State.QUICK_STOP_ACTIVE),
    (0b0001111, State.FAULT_REACTION_ACTIVE),
    (0b0001000, State.FAULT),
])
def test_statusword_states_ignore_the_other_bits(bits, state):
    rng = np.random.default_rng(bits)
    # bits that do not take part in the pattern of this state may be anything
    care = 0x4F if state in (State.NOT_READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED,
                             State.FAULT_REACTION_ACTIVE, State.FAULT) else 0x6F
    for _ in range(200):
        noise = int(rng.integers(0, 1 << 16)) & ~care
        assert decode_state(bits | noise) == state
    assert decode_state(o.STATE_BITS[state] | o.SW_REMOTE | o.SW_TARGET_REACHED) == state


def test_invalid_statusword_pattern_is_unknown():
    assert decode_state(0b0000001) == State.UNKNOWN


@pytest.mark.parametrize("cw, cmd", [
    (0x06, Command.SHUTDOWN), (0x0E, Command.SHUTDOWN),
    (0x07, Command.SWITCH_ON),
    (0x0F, Command.ENABLE_OPERATION), (0x1F, Command.ENABLE_OPERATION), (0x3F, Command.ENABLE_OPERATION),
    (0x00, Command.DISABLE_VOLTAGE), (0x0D, Command.DISABLE_VOLTAGE), (0x04, Command.DISABLE_VOLTAGE),
    (0x02, Command.QUICK_STOP), (0x0B, Command.QUICK_STOP),
    (0x80, Command.FAULT_RESET), (0x8F, Command.FAULT_RESET),
])
def test_controlword_commands(cw, cmd):
    assert decode_command(cw) == cmd


def test_object_dictionary_has_the_objects_the_driver_uses():
    d = o.build_object_dictionary(3)
    for index in (o.CONTROLWORD, o.STATUSWORD, o.MODES_OF_OPERATION, o.MODES_DISPLAY, o.POSITION_ACTUAL,
                  o.TARGET_POSITION, o.PROFILE_VELOCITY, o.PROFILE_ACCELERATION, o.PROFILE_DECELERATION,
                  o.HOMING_METHOD, o.HOMING_SPEEDS, o.HOMING_ACCELERATION, o.ERROR_CODE, o.PRODUCER_HEARTBEAT,
                  o.CONSUMER_HEARTBEAT, o.SOFTWARE_LIMITS):
        assert index in d
    for index in (o.CONTROLWORD, o.STATUSWORD, o.POSITION_ACTUAL, o.TARGET_POSITION):
        assert d[index].pdo_mappable
    assert not d[o.HOME_OFFSET].pdo_mappable
    assert d[o.TPDO_COMM][1].default == 0x183 and d[o.TPDO_COMM + 1][1].default == 0x283 | o.PDO_COB_INVALID
    assert d[o.STATUSWORD].access_type == "ro"


def test_error_code_texts():
    assert o.emcy_text(0x2310) == "continuous over-current"
    assert o.emcy_text(0x2311) == "continuous over-current"          # by its 0xFFF0 group
    assert o.emcy_text(0x9123) == "unknown error"
    assert "read-only" in o.sdo_abort_text(0x06010002)
