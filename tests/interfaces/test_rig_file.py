"""The hardware rig file and the interface configs: the example loads, bad values are named."""
from __future__ import annotations

from pathlib import Path

import pytest

from targetlock.config import ConfigError, describe, from_dict, to_dict
from targetlock.interfaces.canbus import CanBusConfig
from targetlock.interfaces.rigfile import HardwareRigConfig, load_rig_file

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "elmo_rig.toml"


def test_example_rig_file_loads():
    rig = load_rig_file(EXAMPLE)
    assert rig.can.bus == CanBusConfig(interface="socketcan", channel="can0", bitrate=1000000)
    assert rig.can.node_ids == (1, 2)
    assert rig.can.rad_per_tick == 1.6e-5
    assert rig.can.max_ticks == 125000 and rig.can.min_ticks == -125000
    assert rig.can.ticks(rig.can.profile_velocity) == 100000
    assert rig.natnet.multicast_group == "239.255.42.99" and rig.natnet.tip_body_id == 2
    assert rig.safety.target_lost_hold == 0.5
    # every setting of the rig file is documented in the example
    text = EXAMPLE.read_text()
    for row in describe(HardwareRigConfig):
        assert row["name"].split(".")[-1] + " =" in text, row["name"]


def test_round_trip_through_dict():
    rig = load_rig_file(EXAMPLE)
    assert from_dict(HardwareRigConfig, to_dict(rig)) == rig


@pytest.mark.parametrize("data, field", [
    ({"can": {"node_ids": [1, 1]}}, "can.node_ids"),
    ({"can": {"node_ids": [1]}}, "can.node_ids"),
    ({"can": {"node_ids": [1, 200]}}, "can.node_ids[1]"),
    ({"can": {"bus": {"interface": "can4linux"}}}, "can.bus.interface"),
    ({"can": {"bus": {"interface": "udp_loopback", "channel": "127.0.0.1"}}}, "can.bus.channel"),
    ({"can": {"min_angle": 0.5, "max_angle": 0.4}}, "can.min_angle"),
    ({"can": {"heartbeat_period": 0.2, "heartbeat_timeout": 0.1}}, "can.heartbeat_timeout"),
    ({"can": {"master_node_id": 2}}, "can.master_node_id"),
    ({"can": {"rad_per_tick": 0.0}}, "can.rad_per_tick"),
    ({"natnet": {"multicast_group": "10.0.0.1"}}, "natnet.multicast_group"),
    ({"natnet": {"version": "2.10"}}, "natnet.version"),
    ({"safety": {"max_rate": -1.0}}, "safety.max_rate"),
    ({"can": {"velocity": 3.0}}, "can.velocity"),
    ({"can": {"tpdo_period": 0.05}}, "can.tpdo_period"),
    ({"can": {"abort_connection_option": 7}}, "can.abort_connection_option"),
    ({"can": {"eds_file": "/nonexistent/drive.eds"}}, "can.eds_file"),
])
def test_bad_settings_are_refused_by_name(data, field):
    with pytest.raises(ConfigError) as e:
        from_dict(HardwareRigConfig, data)
    assert field in str(e.value)


def test_bad_file_names_the_file(tmp_path):
    bad = tmp_path / "rig.toml"
    bad.write_text("[can.bus]\ninterface = 'socketcan'\nbitrate = 5\n")
    with pytest.raises(ConfigError, match=r"rig.toml: can.bus.bitrate = 5 is out of range"):
        load_rig_file(bad)


def test_hardware_rig_refuses_drive_timing_the_loop_rate_cannot_keep():
    from dataclasses import replace
    from targetlock.model.camera import CameraParams
    from targetlock.rig.hardware import HardwareRig
    rig = load_rig_file(EXAMPLE)
    slow = replace(rig, can=replace(rig.can, use_pdo=False))        # every tick waits on SDO (0.1 s timeout)
    with pytest.raises(ConfigError, match="can.sdo_timeout = 0.1 s must be at most half the loop period"):
        HardwareRig(slow, CameraParams(), loop_rate=50.0)          # refused before any device is opened
