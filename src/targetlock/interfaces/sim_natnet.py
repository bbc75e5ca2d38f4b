"""Simulated OptiTrack NatNet server: streams the twin's base and tip rigid bodies on this host.

It answers NAT_CONNECT on its command port with NAT_SERVERINFO (NatNet version, 10 MHz clock, data
port, multicast group), and streams NAT_FRAMEOFDATA at ``rate_hz`` either to a multicast group on
the loopback interface (``IP_MULTICAST_IF`` = ``server_ip``, TTL 0) or, in unicast mode, to each
client that connected (as Motive does). Optional seeded jitter (each frame delayed by U(0, jitter))
and packet loss (each frame dropped with probability ``loss``) exercise the client.

The pose source is a callback returning ``(base, tip)`` 4x4 poses in metres (world frame), or
None when the bodies are not tracked (they are then sent with tracking valid = 0).
"""
from __future__ import annotations

import logging
import select
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..config import param
from .mocap import rotation_to_quaternion
from .natnet import (NAT_CONNECT, NAT_KEEPALIVE, NAT_REQUEST, NAT_RESPONSE, NAT_UNRECOGNIZED_REQUEST, ServerInfo,
                     encode_frame_of_data, encode_packet, encode_server_info, parse_packet, parse_version,
                     NatNetParseError)

__all__ = ["SimNatNetConfig", "SimNatNetServer", "ServerStats", "CLOCK_HZ"]

log = logging.getLogger(__name__)

CLOCK_HZ = 10_000_000
"""Frequency of the simulated high-resolution clock (Hz), as Motive's performance counter."""
UNICAST_CLIENT_TIMEOUT_S = 10.0
"""Unicast clients silent (no connect / keep-alive) for this long are dropped (s)."""


@dataclass(frozen=True)
class SimNatNetConfig:
    multicast: bool = param(True, doc="stream to the multicast group (else unicast to connected clients)")
    multicast_group: str = param("239.255.42.99", doc="multicast group")
    data_port: int = param(1511, lo=1, hi=65535, doc="multicast data port")
    command_port: int = param(1510, lo=0, hi=65535, doc="command port; 0 picks a free one")
    server_ip: str = param("127.0.0.1", doc="address to serve on (and to send multicast from)")
    rate_hz: float = param(120.0, unit="Hz", lo=1.0, hi=2000.0, doc="frame rate")
    jitter: float = param(0.0, unit="s", lo=0.0, hi=0.1, doc="each frame is delayed by U(0, jitter)")
    loss: float = param(0.0, lo=0.0, hi=1.0, doc="probability that a frame is not sent")
    seed: int = param(0, doc="seed of jitter and loss")
    version: str = param("4.1", choices=("3.0", "3.1", "4.0", "4.1", "4.2"), doc="NatNet version streamed")
    latency: float = param(0.004, unit="s", lo=0.0, hi=1.0, doc="simulated mid-exposure to transmit time")
    base_body_id: int = param(1, lo=0, hi=1000000)
    tip_body_id: int = param(2, lo=0, hi=1000000)
    extras: bool = param(False, doc="also send marker sets, skeleton, asset, labeled markers, force plate, device")
    max_frames: int = param(0, lo=0, doc="stop streaming after this many frames (0: until stop())")
    ttl: int = param(0, lo=0, hi=255, doc="multicast TTL; 0 keeps frames on this host")


@dataclass
class ServerStats:
    frames: int = 0
    """Frames generated (sent or dropped)."""
    sent: int = 0
    dropped: list[int] = field(default_factory=list)
    """Frame numbers dropped by the simulated loss."""
    connects: int = 0
    keepalives: int = 0


class SimNatNetServer:
    """Streams ``pose_source()`` until :meth:`stop` (or ``max_frames``): it returns (base 4x4, tip 4x4)
    or (base, tip, {body_id: 4x4}) with further rigid bodies, in metres, or None."""

    def __init__(self, config: SimNatNetConfig,
                 pose_source: Callable[[], tuple[np.ndarray, np.ndarray] | None]) -> None:
        self.config = config
        self.pose_source = pose_source
        self.version = parse_version(config.version)
        self.stats = ServerStats()
        self._rng = np.random.default_rng(config.seed)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._clients: dict[tuple[str, int], float] = {}
        self._clients_lock = threading.Lock()
        self._t0 = time.monotonic()
        self.finished = threading.Event()
        """Set when streaming ended (max_frames reached or stopped)."""
        cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
        cmd.bind((config.server_ip, config.command_port))
        self._cmd = cmd
        self.command_port = cmd.getsockname()[1]
        out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
        out.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(config.server_ip))
        out.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, config.ttl)
        out.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
        self._out = out

    def describe(self) -> str:
        c = self.config
        where = f"multicast {c.multicast_group}:{c.data_port}" if c.multicast else "unicast"
        return f"{c.server_ip}:{self.command_port} (command), {where}, NatNet {c.version}, {c.rate_hz:g} Hz"

    def start(self) -> "SimNatNetServer":
        self._stop.clear()
        self._t0 = time.monotonic()
        for target, name in ((self._serve_commands, "sim-natnet-command"), (self._stream, "sim-natnet-stream")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads = []
        for s in (self._cmd, self._out):
            try:
                s.close()
            except OSError:
                pass
        self.finished.set()

    def __enter__(self) -> "SimNatNetServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ---------------------------------------------------------------- command port

    def server_info(self) -> ServerInfo:
        c = self.config
        return ServerInfo("Motive (targetlock sim)", (3, 1, 0, 0), (*self.version, 0, 0), CLOCK_HZ,
                          c.data_port, c.multicast, c.multicast_group)

    def _serve_commands(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._cmd], [], [], 0.05)
                if not ready:
                    continue
                packet, addr = self._cmd.recvfrom(65535 + 4)
            except OSError:
                break
            try:
                msg_id, payload = parse_packet(packet)
            except NatNetParseError:
                continue
            if msg_id == NAT_CONNECT:
                self.stats.connects += 1
                with self._clients_lock:
                    self._clients[addr] = time.monotonic()
                reply = encode_server_info(self.server_info())
            elif msg_id == NAT_KEEPALIVE:
                self.stats.keepalives += 1
                with self._clients_lock:
                    if addr in self._clients:
                        self._clients[addr] = time.monotonic()
                continue
            elif msg_id == NAT_REQUEST:
                text = bytes(payload).split(b"\0", 1)[0]
                if text.lower().startswith(b"ping"):
                    reply = encode_packet(NAT_RESPONSE, b"Pong\0")
                else:
                    reply = encode_packet(NAT_UNRECOGNIZED_REQUEST, b"")
            else:
                reply = encode_packet(NAT_UNRECOGNIZED_REQUEST, b"")
            try:
                self._cmd.sendto(reply, addr)
            except OSError as exc:
                log.debug("reply to %s not sent: %s", addr, exc)

    # ---------------------------------------------------------------- stream

    def _bodies(self) -> list[tuple[int, tuple, tuple, float, bool]]:
        c = self.config
        poses = self.pose_source()
        if poses is None:
            zero = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), 0.0, False)
            return [(c.base_body_id, *zero), (c.tip_body_id, *zero)]
        out = []
        bodies = [(c.base_body_id, poses[0]), (c.tip_body_id, poses[1])]
        if len(poses) > 2:  # further rigid bodies, e.g. the target on the robot arm: {id: pose}
            bodies += sorted(poses[2].items())
        for rid, pose in bodies:
            pose = np.asarray(pose, dtype=float)
            out.append((rid, tuple(pose[:3, 3]), tuple(rotation_to_quaternion(pose[:3, :3])), 0.0002, True))
        return out

    def encode_frame(self, frame_number: int) -> bytes:
        now = time.monotonic()
        transmit = int((now - self._t0) * CLOCK_HZ) + CLOCK_HZ
        mid = transmit - int(self.config.latency * CLOCK_HZ)
        return encode_frame_of_data(frame_number, self._bodies(), version=self.version, timestamp=now - self._t0,
                                    camera_mid_exposure=mid, data_received=mid + CLOCK_HZ // 1000,
                                    transmit=transmit, extras=self.config.extras)

    def _destinations(self) -> list[tuple[str, int]]:
        c = self.config
        if c.multicast:
            return [(c.multicast_group, c.data_port)]
        now = time.monotonic()
        with self._clients_lock:
            for addr in [a for a, t in self._clients.items() if now - t > UNICAST_CLIENT_TIMEOUT_S]:
                del self._clients[addr]
            return list(self._clients)

    def _stream(self) -> None:
        c = self.config
        period = 1.0 / c.rate_hz
        next_t = time.monotonic()
        frame_number = 0
        try:
            while not self._stop.is_set():
                if c.max_frames and frame_number >= c.max_frames:
                    break
                frame_number += 1
                self.stats.frames += 1
                drop = c.loss > 0 and self._rng.random() < c.loss
                delay = self._rng.uniform(0.0, c.jitter) if c.jitter > 0 else 0.0
                if delay and self._stop.wait(delay):
                    break
                if drop:
                    self.stats.dropped.append(frame_number)
                else:
                    packet = self.encode_frame(frame_number)
                    for dest in self._destinations():
                        try:
                            self._out.sendto(packet, dest)
                        except OSError as exc:
                            log.debug("frame to %s not sent: %s", dest, exc)
                    self.stats.sent += 1
                next_t += period
                wait = next_t - time.monotonic()
                if wait > 0:
                    if self._stop.wait(wait):
                        break
                elif wait < -10 * period:
                    next_t = time.monotonic()
        finally:
            self.finished.set()
