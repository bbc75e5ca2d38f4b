"""CAN bus configuration, the bus factory and the loopback UDP CAN transport."""
from __future__ import annotations

import importlib.util
import random
import socket

import can
import pytest

from targetlock.config import ConfigError, from_dict
from targetlock.interfaces.canbus import CanBusConfig, UdpLoopbackBus, open_bus
from targetlock.rig.base import DriveFault

from iface_helpers import free_udp_port


def group() -> str:
    return f"239.255.{random.randint(100, 250)}.{random.randint(1, 250)}"


def test_udp_loopback_bus_carries_frames_between_instances():
    g, port = group(), free_udp_port()
    a, b, c = (UdpLoopbackBus(g, port=port) for _ in range(3))
    try:
        frames = [
            can.Message(arbitration_id=0x181, data=b"\x27\x02\x10\x27\x00\x00", is_extended_id=False),
            can.Message(arbitration_id=0x000, data=b"\x01\x05", is_extended_id=False),
            can.Message(arbitration_id=0x1ABCDE0F, data=b"", is_extended_id=True),
            can.Message(arbitration_id=0x705, data=bytes(range(8)), is_extended_id=False),
            can.Message(arbitration_id=0x605, is_remote_frame=True, dlc=4, is_extended_id=False),
        ]
        for f in frames:
            a.send(f)
        for receiver in (b, c):
            for f in frames:
                got = receiver.recv(1.0)
                assert got is not None
                assert (got.arbitration_id, got.is_extended_id, got.is_remote_frame, got.dlc) == \
                       (f.arbitration_id, f.is_extended_id, f.is_remote_frame, f.dlc)
                if not f.is_remote_frame:
                    assert bytes(got.data) == bytes(f.data)
        assert a.recv(0.05) is None                      # own frames are not returned
    finally:
        for bus in (a, b, c):
            bus.shutdown()


def test_udp_loopback_bus_drops_foreign_datagrams():
    g, port = group(), free_udp_port()
    bus = UdpLoopbackBus(g, port=port)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
        tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
        for junk in (b"", b"hello", b"TLCB" + bytes(40), bytes(300)):
            tx.sendto(junk, (g, port))
        assert bus.recv(0.2) is None
        assert bus.frames_dropped == 4
    finally:
        tx.close()
        bus.shutdown()


def test_open_bus_failure_is_a_drive_fault():
    with pytest.raises(DriveFault, match="cannot open CAN bus socketcan:tl_nosuchcan0"):
        open_bus(CanBusConfig(interface="socketcan", channel="tl_nosuchcan0"))


def test_python_can_udp_multicast_needs_msgpack():
    if importlib.util.find_spec("msgpack") is not None:
        pytest.skip("msgpack is installed: python-can's udp_multicast is usable")
    with pytest.raises(DriveFault, match="msgpack"):
        open_bus(CanBusConfig(interface="udp_multicast", channel=group(), port=free_udp_port()))


def test_bus_config_validation():
    assert from_dict(CanBusConfig, {"interface": "virtual", "channel": "x"}).interface == "virtual"
    with pytest.raises(ConfigError, match="interface"):
        from_dict(CanBusConfig, {"interface": "nonsense"})
    with pytest.raises(ConfigError, match="not a multicast address"):
        from_dict(CanBusConfig, {"interface": "udp_loopback", "channel": "10.1.2.3"})
    with pytest.raises(ConfigError, match="bitrate"):
        from_dict(CanBusConfig, {"bitrate": 2_000_000})
