"""CAN bus settings and a bus factory, plus a loopback UDP transport for the simulated rig.

:class:`CanBusConfig` names the python-can interface, channel and bit rate; :func:`open_bus`
opens it. Besides the hardware interfaces (``socketcan``, ``pcan``, ``kvaser``, ``ixxat``,
``vector``, ``slcan``) two software buses are offered:

* ``virtual``: python-can's in-process bus (tests; driver and simulated drives in one process).
* ``udp_loopback``: :class:`UdpLoopbackBus`, CAN frames in UDP datagrams on a multicast group,
  sent and received on the loopback interface only (``IP_MULTICAST_IF`` 127.0.0.1, TTL 0, the
  group joined on 127.0.0.1), so the simulated drives can run in another process on the same
  machine and nothing leaves the host. It needs no extra package.

python-can's own ``udp_multicast`` interface is accepted too; it needs the ``msgpack`` package
(not among targetlock's pinned dependencies) and joins its group on the default interface, so
its membership reports leave the host: prefer ``udp_loopback`` for a twin on the same machine.
"""
from __future__ import annotations

import ipaddress
import os
import select
import socket
import struct
import time
from dataclasses import dataclass
from typing import Any

import can

from ..config import ConfigError, param
from ..rig.base import DriveFault

__all__ = ["CanBusConfig", "open_bus", "UdpLoopbackBus", "INTERFACES"]

INTERFACES = ("socketcan", "pcan", "kvaser", "ixxat", "vector", "slcan", "virtual",
              "udp_loopback", "udp_multicast")
_UDP_INTERFACES = ("udp_loopback", "udp_multicast")


@dataclass(frozen=True)
class CanBusConfig:
    """Which CAN bus the drives are on."""
    interface: str = param("socketcan", choices=INTERFACES,
                           doc="python-can interface; udp_loopback runs the simulated drives in another process")
    channel: str = param("can0", doc="interface channel: can0 (socketcan), PCAN_USBBUS1 (pcan), any name (virtual), "
                                     "a multicast group such as 239.255.0.1 (udp_loopback / udp_multicast)")
    bitrate: int = param(1000000, unit="bit/s", lo=10000, hi=1000000,
                         doc="CAN bit rate (socketcan: set with `ip link`, not here)")
    port: int = param(43113, lo=1024, hi=65535, doc="UDP port of udp_loopback / udp_multicast")
    udp_interface_ip: str = param("127.0.0.1", doc="local address udp_loopback sends and joins on (loopback by default)")
    udp_ttl: int = param(0, lo=0, hi=255, doc="multicast TTL of udp buses; 0 keeps datagrams on this host")

    def check(self, prefix: str = "") -> None:
        if self.interface in _UDP_INTERFACES:
            try:
                group = ipaddress.ip_address(self.channel)
            except ValueError:
                raise ConfigError(f"{prefix}channel = {self.channel!r} must be a multicast address "
                                  f"for interface {self.interface!r}") from None
            if not group.is_multicast:
                raise ConfigError(f"{prefix}channel = {self.channel!r} is not a multicast address (224.0.0.0/4)")
            try:
                ipaddress.IPv4Address(self.udp_interface_ip)
            except ValueError:
                raise ConfigError(f"{prefix}udp_interface_ip = {self.udp_interface_ip!r} is not an IPv4 address") from None
        elif not self.channel:
            raise ConfigError(f"{prefix}channel must not be empty")


def open_bus(cfg: CanBusConfig) -> can.BusABC:
    """Open the bus described by ``cfg``; raises :class:`DriveFault` with the reason if it cannot."""
    try:
        if cfg.interface == "udp_loopback":
            return UdpLoopbackBus(cfg.channel, port=cfg.port, interface_ip=cfg.udp_interface_ip, ttl=cfg.udp_ttl)
        if cfg.interface == "udp_multicast":
            return can.Bus(interface="udp_multicast", channel=cfg.channel, port=cfg.port, hop_limit=cfg.udp_ttl, fd=False)
        if cfg.interface == "virtual":
            return can.Bus(interface="virtual", channel=cfg.channel)
        if cfg.interface == "socketcan":
            return can.Bus(interface="socketcan", channel=cfg.channel)
        return can.Bus(interface=cfg.interface, channel=cfg.channel, bitrate=cfg.bitrate)
    except (can.CanError, OSError, ImportError, ValueError) as exc:
        hint = " (python-can's udp_multicast needs the msgpack package)" if cfg.interface == "udp_multicast" else ""
        raise DriveFault(f"cannot open CAN bus {cfg.interface}:{cfg.channel}: {exc}{hint}") from exc


# Datagram layout of UdpLoopbackBus (little endian): magic "TLCB", version, flags, data length,
# reserved, arbitration id (u32), sender id (u64, to drop our own looped-back frames), send time
# (f64, s since the epoch), then the data bytes.
_HEADER = struct.Struct("<4sBBBBIQd")
_MAGIC = b"TLCB"
_VERSION = 1
_F_EXT, _F_RTR, _F_ERR, _F_FD, _F_BRS, _F_ESI = 1, 2, 4, 8, 16, 32
_MAX_DATAGRAM = _HEADER.size + 64


class UdpLoopbackBus(can.BusABC):
    """A CAN bus carried in UDP multicast datagrams on one host (or one chosen interface).

    Every bus instance on the same group and port sees every frame sent by the others, like
    nodes on a CAN bus; its own frames are not returned. There is no arbitration or error
    signalling: it is a transport for the simulated rig, not a CAN emulator.
    """

    def __init__(self, channel: str = "239.255.0.1", port: int = 43113, interface_ip: str = "127.0.0.1",
                 ttl: int = 0, can_filters: Any = None, **kwargs: Any) -> None:
        self._group = str(channel)
        self._port = int(port)
        self._sender = int.from_bytes(os.urandom(8), "little")
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if hasattr(socket, "SO_REUSEPORT"):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
            sock.bind((self._group, self._port))
            mreq = struct.pack("4s4s", socket.inet_aton(self._group), socket.inet_aton(interface_ip))
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(interface_ip))
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, int(ttl))
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
            sock.setblocking(False)
        except OSError:
            sock.close()
            raise
        self._sock = sock
        self.channel_info = f"UDP loopback CAN {self._group}:{self._port} via {interface_ip}"
        self.frames_dropped = 0
        """Datagrams on the group that were not valid frames (count)."""
        super().__init__(channel=channel, can_filters=can_filters, **kwargs)

    def fileno(self) -> int:
        return self._sock.fileno()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        data = bytes(msg.data)[:64]
        flags = ((_F_EXT if msg.is_extended_id else 0) | (_F_RTR if msg.is_remote_frame else 0)
                 | (_F_ERR if msg.is_error_frame else 0) | (_F_FD if msg.is_fd else 0)
                 | (_F_BRS if msg.bitrate_switch else 0) | (_F_ESI if msg.error_state_indicator else 0))
        length = msg.dlc if msg.is_remote_frame else len(data)
        packet = _HEADER.pack(_MAGIC, _VERSION, flags, length, 0, msg.arbitration_id & 0x1FFFFFFF,
                              self._sender, time.time()) + data
        try:
            self._sock.sendto(packet, (self._group, self._port))
        except OSError as exc:
            raise can.CanOperationError(f"UDP loopback bus send failed: {exc}") from exc

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                ready, _, _ = select.select([self._sock], [], [], wait)
            except (OSError, ValueError) as exc:
                raise can.CanOperationError(f"UDP loopback bus closed: {exc}") from exc
            if not ready:
                return None, False
            try:
                packet = self._sock.recv(_MAX_DATAGRAM + 1)
            except BlockingIOError:
                continue
            except OSError as exc:
                raise can.CanOperationError(f"UDP loopback bus receive failed: {exc}") from exc
            msg = self._decode(packet)
            if msg is not None:
                return msg, False
            if deadline is not None and time.monotonic() >= deadline:
                return None, False

    def _decode(self, packet: bytes) -> can.Message | None:
        if len(packet) < _HEADER.size or len(packet) > _MAX_DATAGRAM:
            self.frames_dropped += 1
            return None
        magic, version, flags, length, _, arb, sender, _sent = _HEADER.unpack_from(packet)
        if magic != _MAGIC or version != _VERSION:
            self.frames_dropped += 1
            return None
        if sender == self._sender:
            return None
        data = packet[_HEADER.size:]
        rtr = bool(flags & _F_RTR)
        if (not rtr and len(data) != length) or length > 64 or (not flags & _F_FD and length > 8):
            self.frames_dropped += 1
            return None
        try:
            return can.Message(timestamp=time.time(), arbitration_id=arb, is_extended_id=bool(flags & _F_EXT),
                               is_remote_frame=rtr, is_error_frame=bool(flags & _F_ERR), dlc=length,
                               data=None if rtr else data, is_fd=bool(flags & _F_FD),
                               bitrate_switch=bool(flags & _F_BRS), error_state_indicator=bool(flags & _F_ESI),
                               channel=self._group, is_rx=True, check=True)
        except ValueError:
            self.frames_dropped += 1
            return None

    def shutdown(self) -> None:
        super().shutdown()
        try:
            self._sock.close()
        except OSError:
            pass


def udp_loopback_problem(group: str, port: int) -> str | None:
    """None if two :class:`UdpLoopbackBus` instances on this host can exchange a frame, else the reason
    (e.g. a sandbox that does not loop multicast back on 127.0.0.1)."""
    try:
        a = UdpLoopbackBus(group, port=port)
        b = UdpLoopbackBus(group, port=port)
    except OSError as exc:
        return f"cannot join multicast group {group} on the loopback interface: {exc}"
    try:
        a.send(can.Message(arbitration_id=0x123, data=b"\x01\x02", is_extended_id=False))
        msg = b.recv(1.0)
        if msg is None or msg.arbitration_id != 0x123:
            return "multicast datagrams are not looped back on 127.0.0.1 on this host"
        return None
    finally:
        a.shutdown()
        b.shutdown()
