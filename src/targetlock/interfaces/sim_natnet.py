"""Simulated OptiTrack NatNet server: streams the twin's base and tip rigid bodies on this host.

It answers on its command port as Motive does: NAT_CONNECT and NAT_DISCOVERY with NAT_SERVERINFO
(the NatNet version it streams, 10 MHz clock, data port, multicast group), the echo request with
the client's stamp and its own clock, NAT_REQUEST_MODELDEF with the rigid bodies' names and ids,
and the requests "FrameRate" (float32 Hz), "Bitstream,M.m" (int32 0: switched) and "Ping". It
streams NAT_FRAMEOFDATA at ``rate_hz`` either to a multicast group on the loopback interface
(``IP_MULTICAST_IF`` = ``server_ip``, TTL 0) or, in unicast mode, to each client that connected.

Times behave like Motive's: frame k's timestamp is k / rate_hz; the cameras' mid-exposure stamp is
the scheduled exposure time on the server's high-resolution clock (which starts at ``clock_offset``
s, unrelated to the client's clock), the data-received stamp 2 ms later, and the frame leaves
``latency`` s after mid-exposure with the transmit stamp. Options exercise clients: seeded jitter
(each frame delayed by U(0, jitter)), packet loss, a one-way network ``transit_delay`` (frames and
command traffic, both ways), a server that ignores version requests (``version_requests``)
and one that answers only connect and keep-alive (``motive_replies = False``, as before Motive 2).

The pose source is a callback returning ``(base, tip)`` 4x4 poses in metres (world frame), or
None when the bodies are not tracked (they are then sent with tracking valid = 0).
"""
from __future__ import annotations

import heapq
import itertools
import logging
import select
import socket
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..config import param
from .mocap import rotation_to_quaternion
from .natnet import (NAT_CONNECT, NAT_DISCOVERY, NAT_ECHOREQUEST, NAT_KEEPALIVE, NAT_REQUEST, NAT_REQUEST_MODELDEF,
                     NAT_RESPONSE, NAT_UNRECOGNIZED_REQUEST, NatNetParseError, RigidBodyDescription, ServerInfo,
                     encode_echo_response, encode_frame_of_data, encode_model_definitions, encode_packet,
                     encode_server_info, parse_connect, parse_packet, parse_version)

__all__ = ["SimNatNetConfig", "SimNatNetServer", "ServerStats", "CLOCK_HZ"]

log = logging.getLogger(__name__)

CLOCK_HZ = 10_000_000
"""Frequency of the simulated high-resolution clock (Hz), as Motive's performance counter."""
UNICAST_CLIENT_TIMEOUT_S = 10.0
"""Unicast clients silent (no connect / keep-alive) for this long are dropped (s)."""
DATA_RECEIVED_S = 0.002
"""Mid-exposure to camera data received in the simulated server (s)."""
_SUPPORTED = ((3, 0), (3, 1), (4, 0), (4, 1), (4, 2))


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
    version: str = param("4.1", choices=("3.0", "3.1", "4.0", "4.1", "4.2"), doc="NatNet version streamed at start")
    latency: float = param(0.004, unit="s", lo=0.0, hi=1.0, doc="simulated mid-exposure to transmit time")
    transit_delay: float = param(0.0, unit="s", lo=0.0, hi=1.0, doc="one-way network delay of every packet, both ways")
    clock_offset: float = param(1000.0, unit="s", lo=0.0, hi=1e6, doc="the server clock's reading at start (s)")
    version_requests: str = param("both", choices=("both", "bitstream", "none"),
                                  doc="which version requests are honoured: the connect packet's requested version "
                                      "and the 'Bitstream,M.m' command, only the command, or none")
    motive_replies: bool = param(True, doc="answer discovery, echo, model definitions, FrameRate and Bitstream "
                                           "(off: only connect, keep-alive and Ping)")
    base_body_id: int = param(1, lo=0, hi=1000000)
    tip_body_id: int = param(2, lo=0, hi=1000000)
    base_name: str = param("EndoscopeBase", doc="asset name of the base rigid body in the model definitions")
    tip_name: str = param("EndoscopeTip", doc="asset name of the tip rigid body in the model definitions")
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
    echoes: int = 0
    model_requests: int = 0
    requests: list[str] = field(default_factory=list)
    """Text of every NAT_REQUEST, in order."""


class _DelayLine:
    """Runs callables at their due time in one thread (a network that delays every packet)."""

    def __init__(self, stop: threading.Event) -> None:
        self._heap: list[tuple[float, int, Callable[[], None]]] = []
        self._cond = threading.Condition()
        self._seq = itertools.count()
        self._stop = stop

    def put(self, due: float, fn: Callable[[], None]) -> None:
        with self._cond:
            heapq.heappush(self._heap, (due, next(self._seq), fn))
            self._cond.notify()

    def run(self) -> None:
        while not self._stop.is_set():
            with self._cond:
                wait = self._heap[0][0] - time.monotonic() if self._heap else 0.05
                if wait > 0:
                    self._cond.wait(min(wait, 0.05))
                    continue
                _, _, fn = heapq.heappop(self._heap)
            fn()


class SimNatNetServer:
    """Streams ``pose_source()`` until :meth:`stop` (or ``max_frames``): it returns (base 4x4, tip 4x4)
    or (base, tip, {body_id: 4x4}) with further rigid bodies, in metres, or None.

    ``names`` gives the asset names of further bodies (default ``RigidBody<id>``).
    """

    def __init__(self, config: SimNatNetConfig,
                 pose_source: Callable[[], tuple[np.ndarray, np.ndarray]
                                       | tuple[np.ndarray, np.ndarray, dict[int, np.ndarray]] | None],
                 names: dict[int, str] | None = None) -> None:
        self.config = config
        self.pose_source = pose_source
        self.names = {config.base_body_id: config.base_name, config.tip_body_id: config.tip_name, **(names or {})}
        self.version = parse_version(config.version)
        """The NatNet version streamed now (a client may switch it)."""
        self.stats = ServerStats()
        self._rng = np.random.default_rng(config.seed)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._clients: dict[tuple[str, int], float] = {}
        self._clients_lock = threading.Lock()
        self._t0 = time.monotonic()
        self._delay = _DelayLine(self._stop)
        self.finished = threading.Event()
        """Set when streaming ended (max_frames reached or stopped)."""
        cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
        cmd.bind((config.server_ip, config.command_port))
        self._cmd = cmd
        self.command_port = cmd.getsockname()[1]
        out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
        out.bind((config.server_ip, 0))
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
        for target, name in ((self._serve_commands, "sim-natnet-command"), (self._stream, "sim-natnet-stream"),
                             (self._delay.run, "sim-natnet-network")):
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

    # ---------------------------------------------------------------- clock

    def ticks(self, t_local: float) -> int:
        """The server's high-resolution clock (ticks) at local monotonic time ``t_local``."""
        return int(round((t_local - self._t0 + self.config.clock_offset) * CLOCK_HZ))

    def ticks_to_local(self, ticks: int) -> float:
        """Inverse of :meth:`ticks` (the truth a clock sync should find; for tests)."""
        return ticks / CLOCK_HZ - self.config.clock_offset + self._t0

    def _later(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` after the one-way transit delay (at once without one)."""
        d = self.config.transit_delay
        if d > 0:
            self._delay.put(time.monotonic() + d, fn)
        else:
            fn()

    def _sendto(self, sock: socket.socket, packet: bytes, addr: tuple[str, int]) -> None:
        try:
            sock.sendto(packet, addr)
        except OSError as exc:
            log.debug("packet to %s not sent: %s", addr, exc)

    # ---------------------------------------------------------------- command port

    def server_info(self) -> ServerInfo:
        c = self.config
        return ServerInfo("Motive (targetlock sim)", (3, 1, 0, 0), (*self.version, 0, 0), CLOCK_HZ,
                          c.data_port, c.multicast, c.multicast_group)

    def model_bodies(self) -> list[RigidBodyDescription]:
        """The rigid bodies as the model definitions list them (ids from the pose source)."""
        c = self.config
        ids = [c.base_body_id, c.tip_body_id]
        poses = self.pose_source()
        if poses is not None and len(poses) > 2:
            ids += sorted(poses[2])
        return [RigidBodyDescription(self.names.get(i, f"RigidBody{i}"), i) for i in ids]

    def _switch_version(self, version: tuple[int, int] | None, by_connect: bool = False) -> bool:
        allowed = self.config.version_requests == "both" or (self.config.version_requests == "bitstream"
                                                             and not by_connect)
        if version is None or not allowed or version not in _SUPPORTED:
            return False
        self.version = version
        return True

    def _serve_commands(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._cmd], [], [], 0.05)
                if not ready:
                    continue
                packet, addr = self._cmd.recvfrom(65535 + 4)
            except OSError:
                break
            # The request reaches the server one transit delay after it was sent.
            self._later(lambda packet=packet, addr=addr: self._answer(packet, addr))

    def _answer(self, packet: bytes, addr: tuple[str, int]) -> None:
        try:
            msg_id, payload = parse_packet(packet)
        except NatNetParseError:
            return
        full = self.config.motive_replies
        if msg_id == NAT_CONNECT:
            self.stats.connects += 1
            with self._clients_lock:
                self._clients[addr] = time.monotonic()
            try:
                self._switch_version(parse_connect(payload), by_connect=True)
            except NatNetParseError:
                pass
            reply = encode_server_info(self.server_info())
        elif msg_id == NAT_DISCOVERY and full:
            reply = encode_server_info(self.server_info())
        elif msg_id == NAT_KEEPALIVE:
            self.stats.keepalives += 1
            with self._clients_lock:
                if addr in self._clients:
                    self._clients[addr] = time.monotonic()
            return
        elif msg_id == NAT_ECHOREQUEST and full and len(payload) >= 8:
            self.stats.echoes += 1
            reply = encode_echo_response(struct.unpack_from("<Q", payload)[0], self.ticks(time.monotonic()))
        elif msg_id == NAT_REQUEST_MODELDEF and full:
            self.stats.model_requests += 1
            reply = encode_model_definitions(self.model_bodies(), self.version)
        elif msg_id == NAT_REQUEST:
            text = bytes(payload).split(b"\0", 1)[0].decode("utf-8", "replace")
            self.stats.requests.append(text)
            command, _, arg = text.partition(",")
            if command.lower() == "ping":
                reply = encode_packet(NAT_RESPONSE, b"Pong\0")
            elif command == "FrameRate" and full:
                reply = encode_packet(NAT_RESPONSE, struct.pack("<f", self.config.rate_hz))
            elif command == "Bitstream" and full and self.config.version_requests != "none":
                try:
                    ok = self._switch_version(parse_version(arg))
                except ValueError:
                    ok = False
                reply = encode_packet(NAT_RESPONSE, struct.pack("<i", 0 if ok else 1))
            else:
                reply = encode_packet(NAT_UNRECOGNIZED_REQUEST, b"")
        else:
            reply = encode_packet(NAT_UNRECOGNIZED_REQUEST, b"")
        self._later(lambda: self._sendto(self._cmd, reply, addr))

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

    def encode_frame(self, frame_number: int, exposure: float | None = None) -> bytes:
        """Frame ``frame_number`` whose cameras' mid-exposure was at local time ``exposure``
        (default: ``latency`` s ago), transmitted now."""
        now = time.monotonic()
        mid = self.ticks(now - self.config.latency if exposure is None else exposure)
        return encode_frame_of_data(frame_number, self._bodies(), version=self.version,
                                    timestamp=frame_number / self.config.rate_hz, camera_mid_exposure=mid,
                                    data_received=mid + int(DATA_RECEIVED_S * CLOCK_HZ), transmit=self.ticks(now),
                                    extras=self.config.extras)

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
        exposure = time.monotonic()         # mid-exposure of the next frame (local clock)
        frame_number = 0
        try:
            while not self._stop.is_set():
                if c.max_frames and frame_number >= c.max_frames:
                    break
                frame_number += 1
                self.stats.frames += 1
                drop = c.loss > 0 and self._rng.random() < c.loss
                delay = self._rng.uniform(0.0, c.jitter) if c.jitter > 0 else 0.0
                # The frame leaves `latency` after mid-exposure (plus jitter).
                wait = exposure + c.latency + delay - time.monotonic()
                if wait > 0 and self._stop.wait(wait):
                    break
                if drop:
                    self.stats.dropped.append(frame_number)
                else:
                    packet = self.encode_frame(frame_number, exposure)
                    for dest in self._destinations():
                        self._later(lambda dest=dest, packet=packet: self._sendto(self._out, packet, dest))
                    self.stats.sent += 1
                exposure += period
                if exposure < time.monotonic() - 10 * period:      # far behind (a stalled host): resynchronise
                    exposure = time.monotonic()
        finally:
            self.finished.set()
