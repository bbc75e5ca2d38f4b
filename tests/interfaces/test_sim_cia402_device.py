"""The simulated CiA 402 drive seen from a plain canopen master (no targetlock driver in between)."""
from __future__ import annotations

import struct
import time
from contextlib import contextmanager

import canopen
import numpy as np
import pytest
from canopen.sdo import SdoAbortedError

from targetlock.interfaces import od402 as o
from targetlock.interfaces.canbus import open_bus
from targetlock.interfaces.od402 import State, decode_state
from targetlock.interfaces.sim_cia402 import SimDriveSet
from targetlock.model.drives import DriveParams

from iface_helpers import virtual_bus, wait_until

PARAMS = DriveParams()


@contextmanager
def device(initial_angle=0.0, offset=0):
    bus = virtual_bus()
    sims = SimDriveSet(bus, [5], PARAMS, initial_angles=[initial_angle], encoder_offsets=[offset]).start()
    net = canopen.Network(open_bus(bus))
    net.NOTIFIER_CYCLE = 0.05
    net.connect()
    node = canopen.RemoteNode(5, o.build_object_dictionary(5))
    net.add_node(node)
    try:
        yield sims[5], node, net
    finally:
        net.disconnect()
        sims.stop()


def state(node) -> State:
    return decode_state(node.sdo[o.STATUSWORD].raw)


def cw(node, value: int) -> None:
    node.sdo[o.CONTROLWORD].raw = value


def enable(node):
    for value in (o.CW_SHUTDOWN, o.CW_SWITCH_ON, o.CW_ENABLE_OPERATION):
        cw(node, value)
    assert state(node) == State.OPERATION_ENABLED


def test_boot_up_and_state_machine_transitions():
    with device() as (sim, node, net):
        assert sim.nmt_state == "PRE-OPERATIONAL"
        assert state(node) == State.SWITCH_ON_DISABLED
        cw(node, o.CW_ENABLE_OPERATION)                  # not allowed from switch on disabled: ignored
        assert state(node) == State.SWITCH_ON_DISABLED
        cw(node, o.CW_SHUTDOWN)
        assert state(node) == State.READY_TO_SWITCH_ON
        cw(node, o.CW_SWITCH_ON)
        assert state(node) == State.SWITCHED_ON
        assert node.sdo[o.STATUSWORD].raw & o.SW_VOLTAGE_ENABLED
        cw(node, o.CW_ENABLE_OPERATION)
        assert state(node) == State.OPERATION_ENABLED
        cw(node, o.CW_SWITCH_ON)                         # disable operation
        assert state(node) == State.SWITCHED_ON
        cw(node, o.CW_ENABLE_OPERATION)
        cw(node, o.CW_SHUTDOWN)
        assert state(node) == State.READY_TO_SWITCH_ON
        cw(node, o.CW_ENABLE_OPERATION)                  # ready -> switched on -> operation enabled
        assert state(node) == State.OPERATION_ENABLED
        cw(node, o.CW_QUICK_STOP)
        assert decode_state(node.sdo[o.STATUSWORD].raw) in (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED)
        assert wait_until(lambda: state(node) == State.SWITCH_ON_DISABLED, 0.5)   # option code 2
        enable(node)
        cw(node, o.CW_DISABLE_VOLTAGE)
        assert state(node) == State.SWITCH_ON_DISABLED


def test_unsupported_mode_and_read_only_objects_are_refused():
    with device() as (sim, node, net):
        with pytest.raises(SdoAbortedError) as e:
            node.sdo[o.MODES_OF_OPERATION].raw = 3
        assert e.value.code == 0x06090030
        with pytest.raises(SdoAbortedError) as e:
            node.sdo[o.STATUSWORD].raw = 0
        assert e.value.code == 0x06010002
        with pytest.raises(SdoAbortedError) as e:
            node.sdo.upload(0x2345, 0)
        assert e.value.code == 0x06020000


def test_pdo_mapping_follows_cia301_rules():
    with device() as (sim, node, net):
        with pytest.raises(SdoAbortedError) as e:       # TPDO1 is valid: its mapping is locked
            node.sdo[o.TPDO_MAP][0].raw = 0
        assert e.value.code == 0x08000022
        node.sdo[o.TPDO_COMM][1].raw = 0x185 | o.PDO_COB_INVALID
        node.sdo[o.TPDO_MAP][0].raw = 0
        with pytest.raises(SdoAbortedError) as e:       # home offset is not PDO-mappable
            node.sdo[o.TPDO_MAP][1].raw = o.HOME_OFFSET << 16 | 32
        assert e.value.code == 0x06040041
        with pytest.raises(SdoAbortedError) as e:       # wrong length for the statusword
            node.sdo[o.TPDO_MAP][1].raw = o.STATUSWORD << 16 | 32
        assert e.value.code == 0x06040041
        for k in range(1, 4):
            node.sdo[o.TPDO_MAP][k].raw = o.POSITION_ACTUAL << 16 | 32
        with pytest.raises(SdoAbortedError) as e:       # 96 bits do not fit in 8 bytes
            node.sdo[o.TPDO_MAP][0].raw = 3
        assert e.value.code == 0x06040042
        node.sdo[o.TPDO_MAP][0].raw = 2
        node.sdo[o.TPDO_COMM][1].raw = 0x185
        assert sim._tpdos[0].mapped() == [(o.POSITION_ACTUAL, 0, 32)] * 2


def test_rpdo_target_and_controlword_in_one_message_and_handshake():
    with device() as (sim, node, net):
        rp = node.rpdo[1]
        rp.read()
        rp.clear()
        rp.add_variable(o.CONTROLWORD)
        rp.add_variable(o.TARGET_POSITION)
        rp.enabled = True
        rp.save()
        tp = node.tpdo[1]
        tp.read()
        tp.clear()
        tp.add_variable(o.STATUSWORD)
        tp.add_variable(o.POSITION_ACTUAL)
        tp.trans_type = 255
        tp.event_timer = 5
        tp.enabled = True
        tp.save()
        node.sdo[o.HOMING_METHOD].raw = 37
        node.sdo[o.MODES_OF_OPERATION].raw = o.MODE_HOMING
        enable(node)
        cw(node, o.CW_ENABLE_OPERATION | o.CW_HOMING_START)
        assert node.sdo[o.STATUSWORD].raw & o.SW_HOMING_ATTAINED
        node.sdo[o.MODES_OF_OPERATION].raw = o.MODE_PROFILE_POSITION
        cw(node, o.CW_ENABLE_OPERATION)
        node.nmt.state = "OPERATIONAL"
        time.sleep(0.02)
        received = []
        tp.add_callback(lambda m: received.append(struct.unpack_from("<Hi", bytes(m.data))))
        net.send_message(0x205, struct.pack("<Hi", o.CW_ENABLE_OPERATION | o.CW_NEW_SETPOINT, 4000))
        assert wait_until(lambda: any(sw & o.SW_SETPOINT_ACK for sw, _ in received), 0.2)
        assert sim._target_active == 4000                 # the target of the same message was latched
        net.send_message(0x205, struct.pack("<Hi", o.CW_ENABLE_OPERATION, 4000))
        assert wait_until(lambda: not received[-1][0] & o.SW_SETPOINT_ACK, 0.2)
        assert wait_until(lambda: received[-1][0] & o.SW_TARGET_REACHED and abs(received[-1][1] - 4000) <= 20, 1.0)
        # relative set-point on top of the last target
        net.send_message(0x205, struct.pack("<Hi", o.CW_ENABLE_OPERATION | o.CW_NEW_SETPOINT | o.CW_RELATIVE, -1000))
        assert wait_until(lambda: sim._target_active == 3000, 0.2)


def test_setpoint_without_change_immediately_is_buffered_until_reached():
    with device() as (sim, node, net):
        node.sdo[o.HOMING_METHOD].raw = 35
        node.sdo[o.MODES_OF_OPERATION].raw = o.MODE_HOMING
        enable(node)
        cw(node, o.CW_ENABLE_OPERATION | o.CW_HOMING_START)
        node.sdo[o.MODES_OF_OPERATION].raw = o.MODE_PROFILE_POSITION
        cw(node, o.CW_ENABLE_OPERATION)
        node.sdo[o.TARGET_POSITION].raw = 30000
        cw(node, o.CW_ENABLE_OPERATION | o.CW_NEW_SETPOINT)
        cw(node, o.CW_ENABLE_OPERATION)
        node.sdo[o.TARGET_POSITION].raw = 0
        cw(node, o.CW_ENABLE_OPERATION | o.CW_NEW_SETPOINT)      # buffered: first move still running
        assert sim._target_active == 30000 and sim._pending_target == 0
        assert node.sdo[o.STATUSWORD].raw & o.SW_SETPOINT_ACK      # buffer full: ack stays
        cw(node, o.CW_ENABLE_OPERATION)
        assert wait_until(lambda: sim._pending_target is None, 1.5)
        assert wait_until(lambda: abs(node.sdo[o.POSITION_ACTUAL].raw) <= 20, 1.5)


def test_homing_methods():
    with device(initial_angle=0.04, offset=1000) as (sim, node, net):
        node.sdo[o.MODES_OF_OPERATION].raw = o.MODE_HOMING
        node.sdo[o.HOMING_METHOD].raw = 0               # no such method: homing error
        node.sdo[o.HOME_OFFSET].raw = 250
        enable(node)
        cw(node, o.CW_ENABLE_OPERATION | o.CW_HOMING_START)
        sw = node.sdo[o.STATUSWORD].raw
        assert sw & o.SW_HOMING_ERROR and not sw & o.SW_HOMING_ATTAINED
        cw(node, o.CW_ENABLE_OPERATION)
        node.sdo[o.HOMING_METHOD].raw = 19               # home switch: motion to the neutral
        cw(node, o.CW_ENABLE_OPERATION | o.CW_HOMING_START)
        sw = node.sdo[o.STATUSWORD].raw
        assert sw & (o.SW_HOMING_ATTAINED | o.SW_HOMING_ERROR | o.SW_TARGET_REACHED) == 0   # in progress
        assert wait_until(lambda: node.sdo[o.STATUSWORD].raw & o.SW_HOMING_ATTAINED, 1.0)
        assert abs(sim.angle) < 4e-4 and sim.homed
        # the home offset is reported at the neutral
        assert abs(node.sdo[o.POSITION_ACTUAL].raw - 250) <= 25


def test_fault_injection_emcy_and_reset():
    with device() as (sim, node, net):
        enable(node)
        sim.inject_fault(0x7121)
        assert wait_until(lambda: len(node.emcy.log) == 1, 0.5)
        assert node.emcy.log[0].code == 0x7121
        assert node.sdo[o.ERROR_CODE].raw == 0x7121
        assert node.sdo[o.ERROR_REGISTER].raw & 0x01
        assert state(node) == State.FAULT
        cw(node, o.CW_FAULT_RESET)
        assert state(node) == State.SWITCH_ON_DISABLED
        assert wait_until(lambda: len(node.emcy.log) == 2, 0.5)
        assert node.emcy.log[1].code == 0                # error reset EMCY
        assert node.sdo[o.ERROR_CODE].raw == 0


def test_heartbeat_producer_and_stop():
    with device() as (sim, node, net):
        node.sdo[o.PRODUCER_HEARTBEAT].raw = 10
        assert node.nmt.wait_for_heartbeat(0.5) == "PRE-OPERATIONAL"
        node.nmt.state = "OPERATIONAL"
        assert wait_until(lambda: node.nmt.state == "OPERATIONAL" and sim.nmt_state == "OPERATIONAL", 0.5)
        sim.stop_heartbeat()
        time.sleep(0.05)
        from canopen.nmt import NmtError
        with pytest.raises(NmtError):
            node.nmt.wait_for_heartbeat(0.1)


def test_sync_driven_tpdo():
    with device() as (sim, node, net):
        tp = node.tpdo[2]
        tp.read()
        tp.clear()
        tp.add_variable(o.POSITION_ACTUAL)
        tp.cob_id = 0x285
        tp.trans_type = 2                     # every second SYNC
        tp.enabled = True
        tp.save()
        node.nmt.state = "OPERATIONAL"
        time.sleep(0.02)
        got = []
        tp.add_callback(lambda m: got.append(1))
        for _ in range(6):
            net.sync.transmit()
            time.sleep(0.005)
        assert wait_until(lambda: len(got) == 3, 0.5)


def test_motor_follows_the_drive_model():
    """Position actual after a step equals the drive model integrated at 1 ms (rate limit + lag)."""
    with device() as (sim, node, net):
        node.sdo[o.HOMING_METHOD].raw = 37
        node.sdo[o.MODES_OF_OPERATION].raw = o.MODE_HOMING
        enable(node)
        cw(node, o.CW_ENABLE_OPERATION | o.CW_HOMING_START)
        node.sdo[o.MODES_OF_OPERATION].raw = o.MODE_PROFILE_POSITION
        cw(node, o.CW_ENABLE_OPERATION)
        node.sdo[o.TARGET_POSITION].raw = 50000                # 0.8 rad: 0.5 s at the rate limit
        cw(node, o.CW_ENABLE_OPERATION | o.CW_NEW_SETPOINT | o.CW_CHANGE_IMMEDIATELY)
        samples = []
        t0 = time.monotonic()
        while time.monotonic() - t0 < 0.3:
            samples.append((time.monotonic() - t0, sim.angle))
            time.sleep(0.01)
        t = np.array([s[0] for s in samples])
        a = np.array([s[1] for s in samples])
        vmax = PARAMS.max_velocity
        assert np.all(a <= vmax * (t + 0.005) + 1e-6)          # never faster than the rate limit
        assert np.all(a >= vmax * (t - 0.05) - 0.01)           # and in the rate-limited phase close to it
