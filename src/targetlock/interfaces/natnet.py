"""OptiTrack NatNet client: rigid-body poses from Motive's frame-of-data stream (NatNet 3.x and 4.x).

Packets start with a message id (uint16) and the payload size in bytes (uint16), little endian.
A frame of data (``NAT_FRAMEOFDATA`` = 7) holds, in order (NatNet >= 3.0):

=====================  ==============================================================================
frame number           int32
marker sets            int32 count, [4.1+: int32 byte size], per set: name (NUL-terminated),
                       int32 n, n x 3 float32
legacy other markers   int32 count, [4.1+: int32 byte size], count x 3 float32
rigid bodies           int32 count, [4.1+: int32 byte size], per body (38 bytes): int32 id, 3 float32
                       position (m), 4 float32 quaternion qx qy qz qw, float32 mean marker error (m),
                       int16 params (bit 0: tracking valid)
skeletons              int32 count, [4.1+: size], per skeleton: int32 id, int32 n, n rigid bodies
assets (4.1+ only)     int32 count, int32 size, per asset: int32 id, int32 n, n rigid bodies (38 bytes),
                       int32 m, m markers (26 bytes)
labeled markers        int32 count, [4.1+: size], per marker (26 bytes): int32 id, 3 float32, float32
                       size, int16 params, float32 residual
force plates, devices  int32 count, [4.1+: size], per item: int32 id, int32 channels, per channel:
                       int32 frames, frames x float32
suffix                 uint32 timecode, uint32 timecode sub-frame, float64 timestamp (s),
                       uint64 camera mid-exposure, uint64 data received, uint64 transmit (high-resolution
                       clock ticks), [4.1+: uint32 precision timestamp s, uint32 fraction],
                       int16 params (bit 0 recording, bit 1 tracked models changed), [int32 end tag]
=====================  ==============================================================================

From 4.1 on every section carries its byte size, so sections we do not need are skipped by size;
before 4.1 they are walked by their counts. Every count and size is checked against the bytes
left, so a truncated or corrupted packet raises :class:`NatNetParseError` (counted as malformed by
the client and skipped), never an unrelated exception. The layout follows the stream version only:
the precision timestamp is read from 4.1 on (as the official 4.x C++ client does), and anything
after the suffix other than the 4-byte end tag is an error.

Command port (:meth:`NatNetClient.start`): the client sends ``NAT_CONNECT`` (0) with its name, its
NatNet version and the connection options (the bit-stream version it asks for); the server answers
``NAT_SERVERINFO`` (1): application name (256 bytes), application version and NatNet version (4
bytes each), then (NatNet 3+) the high-resolution clock frequency (uint64, Hz), data port (uint16),
multicast flag (uint8) and multicast group (4 bytes). If the server streams another version than
the configured one, the client sends the SDK's ``NAT_REQUEST`` "Bitstream,M.m" and needs the answer
int32 0, else it refuses to start. It then requests the model definitions (``NAT_REQUEST_MODELDEF``
→ ``NAT_MODELDEF``) to find the configured rigid bodies by id or asset name, and syncs the clocks
with ``NAT_ECHOREQUEST`` (uint64 stamp) → ``NAT_ECHORESPONSE`` (the stamp, the server's clock in
ticks when the request arrived): :class:`ClockSync` keeps the offset of the echo with the smallest
round trip, so Motive's mid-exposure stamp maps to the local clock including network transit.
latency = (transmit - mid-exposure) / frequency is Motive's own part of it.

:class:`NatNetClient` receives in its own thread (multicast joined on the configured local
interface, or unicast on the command socket with keep-alives), drops packets from any address but
the server's, reports frames that parse to nonsense for the expected version (configured bodies
absent, impossible timestamps or positions) as malformed, and hands the control loop only the
newest sample through :class:`LatestSample`.
"""
from __future__ import annotations

import ipaddress
import logging
import math
import select
import socket
import struct
import threading
import time
from dataclasses import dataclass
from typing import Callable, Generic, TypeVar

import numpy as np

from ..config import ConfigError, param

__all__ = ["NAT_CONNECT", "NAT_SERVERINFO", "NAT_REQUEST", "NAT_RESPONSE", "NAT_REQUEST_MODELDEF", "NAT_MODELDEF",
           "NAT_FRAMEOFDATA", "NAT_KEEPALIVE", "NAT_ECHOREQUEST", "NAT_ECHORESPONSE", "NAT_DISCOVERY",
           "NAT_UNRECOGNIZED_REQUEST", "NatNetParseError", "RigidBodyDescription", "parse_model_definitions",
           "encode_model_definitions", "encode_echo_response", "parse_echo_response", "parse_connect",
           "ClockSync", "NatNetStartError", "RigidBody", "MocapFrame", "ServerInfo", "MocapSample",
           "LatestSample", "NatNetConfig", "NatNetClient", "ClientStats", "parse_packet", "parse_frame_of_data",
           "parse_server_info", "encode_packet", "encode_frame_of_data", "encode_server_info", "encode_connect",
           "parse_version"]

log = logging.getLogger(__name__)

NAT_CONNECT = 0
NAT_SERVERINFO = 1
NAT_REQUEST = 2
NAT_RESPONSE = 3
NAT_REQUEST_MODELDEF = 4
NAT_MODELDEF = 5
NAT_REQUEST_FRAMEOFDATA = 6
NAT_FRAMEOFDATA = 7
NAT_MESSAGESTRING = 8
NAT_DISCONNECT = 9
NAT_KEEPALIVE = 10
NAT_DISCONNECTBYTIMEOUT = 11
NAT_ECHOREQUEST = 12
NAT_ECHORESPONSE = 13
NAT_DISCOVERY = 14
NAT_UNRECOGNIZED_REQUEST = 100

MAX_PACKET_BYTES = 65535 + 4
"""Largest NatNet packet (bytes): the size field is 16 bits."""
RECV_POLL_S = 0.05
"""Receive thread wake-up period (s); bounds the time stop() takes."""
KEEPALIVE_PERIOD_S = 1.0
"""Unicast keep-alive period (s): Motive stops streaming to silent unicast clients."""
MAX_FRAME_GAP = 1000
"""Frame-number jumps beyond this many frames count as a restart of Motive's counter, not as loss."""

_HEADER = struct.Struct("<HH")
_I32 = struct.Struct("<i")
_I32x2 = struct.Struct("<ii")
_RB = struct.Struct("<i3f4ffh")          # one rigid body, NatNet >= 3.0: 38 bytes
_RB_SIZE = _RB.size
_LABELED_SIZE = 26                       # int32 id, 3 float, float size, int16 params, float residual
_SUFFIX_BASE = struct.Struct("<IIdQQQ")  # timecode, sub, timestamp, mid-exposure, received, transmit
_PRECISION = struct.Struct("<II")
_PARAMS = struct.Struct("<h")


class NatNetParseError(ValueError):
    """A NatNet packet is truncated, inconsistent or of an unsupported version."""


def parse_version(text: str) -> tuple[int, int]:
    """'4.1' -> (4, 1)."""
    try:
        major, minor = (int(x) for x in text.split(".")[:2])
    except ValueError:
        raise ValueError(f"NatNet version {text!r} is not of the form MAJOR.MINOR") from None
    return major, minor


@dataclass(frozen=True)
class RigidBody:
    """One rigid body of a frame: position (m) and orientation quaternion (qx, qy, qz, qw) in Motive's frame."""
    id: int
    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]
    mean_error: float
    """Mean marker error (m)."""
    tracking_valid: bool

    @property
    def usable(self) -> bool:
        """Tracked, finite, and the quaternion has (nearly) unit length."""
        if not self.tracking_valid:
            return False
        vals = self.position + self.orientation
        if not all(np.isfinite(vals)):
            return False
        n = sum(q * q for q in self.orientation)
        return abs(n - 1.0) < 1e-2


@dataclass(frozen=True)
class MocapFrame:
    """The parts of a frame of data targetlock uses."""
    frame_number: int
    rigid_bodies: dict[int, RigidBody]
    """Top-level rigid bodies by id (skeleton bones and asset bodies are skipped)."""
    timestamp: float
    """Motive's frame timestamp (s since its start)."""
    camera_mid_exposure: int
    """High-resolution clock ticks at the cameras' mid-exposure."""
    data_received: int
    transmit: int
    """High-resolution clock ticks when the frame was sent."""
    timecode: int = 0
    timecode_sub: int = 0
    precision_timestamp: tuple[int, int] | None = None
    params: int = 0
    version: tuple[int, int] = (4, 1)

    @property
    def is_recording(self) -> bool:
        return bool(self.params & 0x01)

    @property
    def tracked_models_changed(self) -> bool:
        return bool(self.params & 0x02)

    def latency(self, clock_hz: float | None) -> float | None:
        """Mid-exposure to transmit (s), or None without the server's clock frequency."""
        if not clock_hz or self.transmit < self.camera_mid_exposure or self.camera_mid_exposure == 0:
            return None
        return (self.transmit - self.camera_mid_exposure) / clock_hz


@dataclass(frozen=True)
class ServerInfo:
    """Answer to NAT_CONNECT."""
    application: str
    app_version: tuple[int, int, int, int]
    natnet_version: tuple[int, int, int, int]
    clock_hz: int | None = None
    data_port: int | None = None
    multicast: bool | None = None
    multicast_group: str | None = None


# ------------------------------------------------------------------------------- parsing

class _Cursor:
    __slots__ = ("buf", "pos", "end")

    def __init__(self, buf: bytes | memoryview, pos: int, end: int) -> None:
        self.buf, self.pos, self.end = buf, pos, end

    def need(self, n: int, what: str) -> None:
        if n < 0 or self.pos + n > self.end:
            raise NatNetParseError(f"truncated at byte {self.pos}: {what} needs {n} bytes, {self.end - self.pos} left")

    def i32(self, what: str) -> int:
        self.need(4, what)
        v = _I32.unpack_from(self.buf, self.pos)[0]
        self.pos += 4
        return v

    def count(self, what: str, item_size: int) -> int:
        n = self.i32(what)
        if n < 0 or n * item_size > self.end - self.pos:
            raise NatNetParseError(f"{what} = {n} does not fit in the {self.end - self.pos} bytes left")
        return n

    def skip(self, n: int, what: str) -> None:
        self.need(n, what)
        self.pos += n

    def cstring(self, what: str, limit: int = 256) -> bytes:
        stop = min(self.end, self.pos + limit)
        raw = bytes(self.buf[self.pos:stop])
        k = raw.find(b"\0")
        if k < 0:
            raise NatNetParseError(f"{what}: no NUL terminator within {limit} bytes")
        self.pos += k + 1
        return raw[:k]


def _section_size(cur: _Cursor, sized: bool, what: str) -> int | None:
    if not sized:
        return None
    size = cur.i32(f"{what} byte size")
    if size < 0 or size > cur.end - cur.pos:
        raise NatNetParseError(f"{what} byte size {size} does not fit in the {cur.end - cur.pos} bytes left")
    return size


def _skip_channels(cur: _Cursor, what: str) -> None:
    n = cur.count(f"{what} count", 8)
    for _ in range(n):
        cur.skip(4, f"{what} id")
        channels = cur.count(f"{what} channel count", 4)
        for _ in range(channels):
            frames = cur.count(f"{what} frame count", 4)
            cur.skip(4 * frames, f"{what} values")


def parse_frame_of_data(payload: bytes | memoryview, version: tuple[int, int]) -> MocapFrame:
    """Parse the payload of a NAT_FRAMEOFDATA packet (after the 4-byte header)."""
    major, minor = version
    if major < 3:
        raise NatNetParseError(f"NatNet {major}.{minor} is not supported (3.0 or later needed)")
    sized = (major, minor) >= (4, 1)
    cur = _Cursor(payload, 0, len(payload))
    frame_number = cur.i32("frame number")

    # marker sets
    n = cur.count("marker set count", 5)
    size = _section_size(cur, sized, "marker sets")
    if size is not None:
        cur.skip(size, "marker sets")
    else:
        for _ in range(n):
            cur.cstring("marker set name")
            cur.skip(12 * cur.count("marker count", 12), "marker positions")
    # legacy "other" markers
    n = cur.count("other marker count", 12)
    size = _section_size(cur, sized, "other markers")
    if size is not None and size != 12 * n:
        raise NatNetParseError(f"other markers: size {size} != 12 x {n}")
    cur.skip(12 * n, "other markers")
    # rigid bodies
    n = cur.count("rigid body count", _RB_SIZE)
    size = _section_size(cur, sized, "rigid bodies")
    if size is not None and size != _RB_SIZE * n:
        raise NatNetParseError(f"rigid bodies: size {size} != {_RB_SIZE} x {n}")
    bodies: dict[int, RigidBody] = {}
    buf, pos = payload, cur.pos
    for _ in range(n):
        rid, x, y, z, qx, qy, qz, qw, err, params = _RB.unpack_from(buf, pos)
        pos += _RB_SIZE
        bodies[rid] = RigidBody(rid, (x, y, z), (qx, qy, qz, qw), err, bool(params & 0x01))
    cur.pos = pos
    # skeletons
    n = cur.count("skeleton count", 8)
    size = _section_size(cur, sized, "skeletons")
    if size is not None:
        cur.skip(size, "skeletons")
    else:
        for _ in range(n):
            cur.skip(4, "skeleton id")
            cur.skip(_RB_SIZE * cur.count("skeleton rigid body count", _RB_SIZE), "skeleton rigid bodies")
    # assets (4.1+)
    if sized:
        cur.count("asset count", 12)
        cur.skip(_section_size(cur, True, "assets"), "assets")
    # labeled markers
    n = cur.count("labeled marker count", _LABELED_SIZE)
    size = _section_size(cur, sized, "labeled markers")
    if size is not None and size != _LABELED_SIZE * n:
        raise NatNetParseError(f"labeled markers: size {size} != {_LABELED_SIZE} x {n}")
    cur.skip(_LABELED_SIZE * n, "labeled markers")
    # force plates and devices
    for what in ("force plates", "devices"):
        if sized:
            cur.count(f"{what} count", 8)
            cur.skip(_section_size(cur, True, what), what)
        else:
            _skip_channels(cur, what)
    # suffix
    cur.need(_SUFFIX_BASE.size, "frame suffix")
    timecode, timecode_sub, timestamp, mid, received, transmit = _SUFFIX_BASE.unpack_from(payload, cur.pos)
    cur.pos += _SUFFIX_BASE.size
    precision = None
    if sized:       # 4.1 on, as the official 4.x clients read it; never guessed from the bytes left
        cur.need(_PRECISION.size, "precision timestamp")
        precision = _PRECISION.unpack_from(payload, cur.pos)
        cur.pos += _PRECISION.size
    cur.need(2, "frame params")
    params = _PARAMS.unpack_from(payload, cur.pos)[0]
    cur.pos += 2
    left = cur.end - cur.pos
    if left not in (0, 4):      # nothing, or the int32 end-of-data tag
        raise NatNetParseError(f"frame of NatNet {major}.{minor} has {left} bytes after its suffix (0 or 4 expected)")
    return MocapFrame(frame_number, bodies, timestamp, mid, received, transmit, timecode, timecode_sub,
                      precision, params, (major, minor))


def parse_server_info(payload: bytes | memoryview) -> ServerInfo:
    """Parse the payload of a NAT_SERVERINFO packet."""
    if len(payload) < 264:
        raise NatNetParseError(f"server info has {len(payload)} bytes, at least 264 expected")
    name = bytes(payload[:256]).split(b"\0", 1)[0].decode("utf-8", "replace")
    app = tuple(payload[256:260])
    nn = tuple(payload[260:264])
    clock = port = multicast = group = None
    if len(payload) >= 272:
        clock = struct.unpack_from("<Q", payload, 264)[0] or None
    if len(payload) >= 279:
        port, mc = struct.unpack_from("<HB", payload, 272)
        multicast = bool(mc)
        group = ".".join(str(b) for b in payload[275:279])
    return ServerInfo(name, app, nn, clock, port, multicast, group)


def parse_packet(packet: bytes | memoryview) -> tuple[int, memoryview]:
    """Split a packet into (message id, payload); checks the size field against the packet length."""
    if len(packet) < 4:
        raise NatNetParseError(f"packet of {len(packet)} bytes has no header")
    msg_id, size = _HEADER.unpack_from(packet)
    if 4 + size > len(packet):
        raise NatNetParseError(f"packet says {size} payload bytes but has {len(packet) - 4}")
    return msg_id, memoryview(packet)[4:4 + size]


@dataclass(frozen=True)
class RigidBodyDescription:
    """One rigid body of Motive's model definitions (its asset name and streaming id)."""
    name: str
    id: int
    parent_id: int = -1
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Offset from the parent body (m)."""


_MODEL_MARKERSET, _MODEL_RIGIDBODY, _MODEL_SKELETON = 0, 1, 2


def _rigid_body_description(cur: _Cursor, major: int) -> RigidBodyDescription:
    name = cur.cstring("rigid body name").decode("utf-8", "replace")
    rid = cur.i32("rigid body id")
    parent = cur.i32("rigid body parent id")
    cur.need(12, "rigid body offset")
    offset = struct.unpack_from("<3f", cur.buf, cur.pos)
    cur.pos += 12
    if major >= 3:                        # markers: positions, required active labels, (4.0+) names
        n = cur.count("rigid body marker count", 16)
        cur.skip(16 * n, "rigid body markers")
        if major >= 4:
            for _ in range(n):
                cur.cstring("rigid body marker name")
    return RigidBodyDescription(name, rid, parent, offset)


def parse_model_definitions(payload: bytes | memoryview, version: tuple[int, int]) -> list[RigidBodyDescription]:
    """The top-level rigid bodies of a NAT_MODELDEF payload (skeleton bones are not top level).

    Data sets: int32 count, per set int32 type (0 marker set, 1 rigid body, 2 skeleton, 3 force
    plate, 4 device, 5 camera, 6 asset), from 4.1 on an int32 byte size, then the description.
    From 4.1 every set is checked against its size and unknown ones are skipped by it; before 4.1
    the walk ends at the first set of another type (Motive sends marker sets, rigid bodies and
    skeletons first, so the rigid bodies are complete by then).
    """
    major, minor = version
    sized = (major, minor) >= (4, 1)
    cur = _Cursor(payload, 0, len(payload))
    n = cur.count("data set count", 4)
    out: list[RigidBodyDescription] = []
    for _ in range(n):
        kind = cur.i32("data set type")
        size = _section_size(cur, sized, "data set")
        start = cur.pos
        if kind == _MODEL_MARKERSET:
            cur.cstring("marker set name")
            for _ in range(cur.count("marker set marker count", 1)):
                cur.cstring("marker name")
        elif kind == _MODEL_RIGIDBODY:
            out.append(_rigid_body_description(cur, major))
        elif kind == _MODEL_SKELETON:
            cur.cstring("skeleton name")
            cur.i32("skeleton id")
            for _ in range(cur.count("skeleton bone count", 24)):
                _rigid_body_description(cur, major)
        elif size is not None:
            cur.skip(size, f"data set of type {kind}")
        else:
            break
        if size is not None and cur.pos - start != size:
            raise NatNetParseError(f"data set of type {kind}: {cur.pos - start} bytes read, its size says {size}")
    return out


def parse_connect(payload: bytes | memoryview) -> tuple[int, int] | None:
    """The bit-stream version a NAT_CONNECT asks for (sConnectionOptions after the sender), or None."""
    if len(payload) < 264:
        raise NatNetParseError(f"connect packet has {len(payload)} bytes, at least 264 expected")
    if len(payload) >= 269:
        major, minor = payload[265], payload[266]
        if major:
            return int(major), int(minor)
    return None


def parse_echo_response(payload: bytes | memoryview) -> tuple[int, int]:
    """(the client's request stamp, Motive's clock in ticks when the request arrived)."""
    if len(payload) < 16:
        raise NatNetParseError(f"echo response has {len(payload)} bytes, 16 expected")
    return struct.unpack_from("<QQ", payload)


# ------------------------------------------------------------------------------- encoding

def encode_packet(msg_id: int, payload: bytes) -> bytes:
    if len(payload) > 65535:
        raise ValueError("NatNet payload larger than 65535 bytes")
    return _HEADER.pack(msg_id, len(payload)) + payload


def _sender(name: str, app_version: tuple[int, ...], natnet_version: tuple[int, ...]) -> bytes:
    raw = name.encode("utf-8")[:255]
    return raw + b"\0" * (256 - len(raw)) + bytes(app_version[:4]) + bytes(natnet_version[:4])


def encode_connect(name: str = "targetlock", natnet_version: tuple[int, int] = (4, 1),
                   requested: tuple[int, int] | None = None) -> bytes:
    """NAT_CONNECT packet as the client sends it: its name, the NatNet version it speaks, and the
    connection options (subscribed data only = 0, the bit-stream version it asks for; zeros: the server's)."""
    options = struct.pack("<B4B", 0, *((*requested, 0, 0) if requested else (0, 0, 0, 0)))
    return encode_packet(NAT_CONNECT, _sender(name, (0, 1, 0, 0), (*natnet_version, 0, 0)) + options)


def encode_echo_response(request_stamp: int, server_ticks: int) -> bytes:
    """NAT_ECHORESPONSE: the client's stamp echoed and the server's clock (ticks) when it arrived."""
    return encode_packet(NAT_ECHORESPONSE, struct.pack("<QQ", request_stamp & (2**64 - 1), server_ticks))


def encode_model_definitions(bodies: list[RigidBodyDescription], version: tuple[int, int] = (4, 1)) -> bytes:
    """NAT_MODELDEF as Motive sends it: an "all" marker set, the rigid bodies (3 markers each) and a
    camera description (a data set the client must skip)."""
    major, minor = version
    sized = (major, minor) >= (4, 1)

    def data_set(kind: int, body: bytes) -> bytes:
        return _I32.pack(kind) + (_I32.pack(len(body)) if sized else b"") + body

    markers = [f"{b.name}_{k + 1}" for b in bodies for k in range(3)]
    sets = [data_set(_MODEL_MARKERSET, b"all\0" + _I32.pack(len(markers))
                     + b"".join(m.encode() + b"\0" for m in markers))]
    for b in bodies:
        d = b.name.encode("utf-8") + b"\0" + struct.pack("<ii3f", b.id, b.parent_id, *b.offset)
        if major >= 3:
            d += _I32.pack(3) + struct.pack("<9f", 0.02, 0, 0, 0, 0.02, 0, 0, 0, 0.02) + struct.pack("<3i", 0, 0, 0)
            if major >= 4:
                d += b"".join(f"Marker{k + 1}".encode() + b"\0" for k in range(3))
        sets.append(data_set(_MODEL_RIGIDBODY, d))
    sets.append(data_set(5, b"Camera 1\0" + struct.pack("<7f", 1.0, 2.5, 1.0, 0.0, 0.0, 0.0, 1.0)))
    return encode_packet(NAT_MODELDEF, _I32.pack(len(sets)) + b"".join(sets))


def encode_server_info(info: ServerInfo) -> bytes:
    """NAT_SERVERINFO packet (sSender plus the NatNet 3+ connection info)."""
    payload = _sender(info.application, info.app_version, info.natnet_version)
    group = bytes(int(x) for x in (info.multicast_group or "0.0.0.0").split("."))
    payload += struct.pack("<QHB", info.clock_hz or 0, info.data_port or 0, 1 if info.multicast else 0) + group
    return encode_packet(NAT_SERVERINFO, payload)


def _sized(count: int, body: bytes, sized: bool) -> bytes:
    return _I32.pack(count) + (_I32.pack(len(body)) if sized else b"") + body


def _rb_bytes(rid: int, pos, quat, err: float, valid: bool) -> bytes:
    return _RB.pack(rid, *[float(v) for v in pos], *[float(v) for v in quat], float(err), 1 if valid else 0)


def encode_frame_of_data(frame_number: int, rigid_bodies: list[tuple[int, tuple, tuple, float, bool]], *,
                         version: tuple[int, int] = (4, 1), timestamp: float = 0.0, camera_mid_exposure: int = 0,
                         data_received: int = 0, transmit: int = 0, params: int = 0, extras: bool = False,
                         precision: tuple[int, int] = (0, 0), end_tag: bool = True) -> bytes:
    """A NAT_FRAMEOFDATA packet with ``rigid_bodies`` = [(id, (x, y, z), (qx, qy, qz, qw), error, valid)].

    ``extras`` adds a marker set, other markers, a skeleton, an asset (4.1+), labeled markers, a
    force plate and a device, so parsers meet every section.
    """
    major, minor = version
    if major < 3:
        raise ValueError("only NatNet 3.0 and later can be encoded")
    sized = (major, minor) >= (4, 1)
    out = [_I32.pack(frame_number)]
    if extras:
        ms = b"endoscope\0" + _I32.pack(2) + struct.pack("<6f", 0.1, 0.2, 0.3, 0.4, 0.5, 0.6)
        ms += b"all\0" + _I32.pack(1) + struct.pack("<3f", 1.0, 2.0, 3.0)
        out.append(_sized(2, ms, sized))
        out.append(_sized(1, struct.pack("<3f", 7.0, 8.0, 9.0), sized))
    else:
        out.append(_sized(0, b"", sized))
        out.append(_sized(0, b"", sized))
    out.append(_sized(len(rigid_bodies), b"".join(_rb_bytes(*rb) for rb in rigid_bodies), sized))
    if extras:
        bone = _rb_bytes(1001, (0, 0, 0), (0, 0, 0, 1), 0.0, True)
        sk = _I32.pack(7) + _I32.pack(2) + bone + bone
        out.append(_sized(1, sk, sized))
        if sized:
            asset = _I32.pack(42) + _I32.pack(1) + bone + _I32.pack(1) + struct.pack("<i3ffhf", 5, 1, 2, 3, 0.01, 0, 0.0)
            out.append(_sized(1, asset, True))
        lm = b"".join(struct.pack("<i3ffhf", 100 + k, k, k, k, 0.012, 0, 0.0001) for k in range(3))
        out.append(_sized(3, lm, sized))
        fp = _I32.pack(3) + _I32.pack(2) + _I32.pack(1) + struct.pack("<f", 9.81) + _I32.pack(2) + struct.pack("<2f", 1, 2)
        out.append(_sized(1, fp, sized))
        dev = _I32.pack(9) + _I32.pack(1) + _I32.pack(3) + struct.pack("<3f", 1, 2, 3)
        out.append(_sized(1, dev, sized))
    else:
        out.append(_sized(0, b"", sized))
        if sized:
            out.append(_sized(0, b"", True))
        out.append(_sized(0, b"", sized))
        out.append(_sized(0, b"", sized))
        out.append(_sized(0, b"", sized))
    out.append(_SUFFIX_BASE.pack(0, 0, timestamp, camera_mid_exposure, data_received, transmit))
    if sized:
        out.append(_PRECISION.pack(*precision))
    out.append(_PARAMS.pack(params))
    if end_tag:
        out.append(_I32.pack(0))
    return encode_packet(NAT_FRAMEOFDATA, b"".join(out))


# ------------------------------------------------------------------------------- hand-off

T = TypeVar("T")


class LatestSample(Generic[T]):
    """A newest-only slot between a receive thread and the control loop: never a queue that fills.

    :meth:`put` overwrites; :meth:`get` returns the newest value or None. :attr:`sequence` counts
    puts, so a reader can tell a new sample from one it has seen.
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._value: T | None = None
        self._seq = 0

    def put(self, value: T) -> None:
        with self._cond:
            self._value = value
            self._seq += 1
            self._cond.notify_all()

    def get(self) -> T | None:
        with self._cond:
            return self._value

    def get_with_sequence(self) -> tuple[int, T | None]:
        with self._cond:
            return self._seq, self._value

    @property
    def sequence(self) -> int:
        with self._cond:
            return self._seq

    def wait_newer(self, sequence: int, timeout: float) -> tuple[int, T] | None:
        """Block until a value newer than ``sequence`` arrives (or ``timeout`` s pass: None)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._seq <= sequence:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)
            return self._seq, self._value


@dataclass(frozen=True)
class MocapSample:
    """A frame as the control loop sees it, with local times (s, ``time.monotonic`` clock)."""
    frame: MocapFrame
    received_at: float
    """When the packet arrived (s, local monotonic clock)."""
    latency: float | None
    """Motive's mid-exposure-to-transmit time (s), None without the server's clock frequency."""
    mapped_capture_time: float | None = None
    """The cameras' mid-exposure mapped through the echo clock sync (s, local clock), None without it."""

    @property
    def capture_time(self) -> float:
        """Mid-exposure time on the local clock (s): Motive's mid-exposure stamp mapped through the
        clock sync, or (no sync) the arrival time minus Motive's own latency."""
        if self.mapped_capture_time is not None:
            return self.mapped_capture_time
        return self.received_at - (self.latency or 0.0)

    def rigid_body(self, body_id: int) -> RigidBody | None:
        return self.frame.rigid_bodies.get(body_id)


class ClockSync:
    """Offset between Motive's high-resolution clock and the local clock, from echo round trips.

    Each echo gives the local send and receive times and Motive's clock when the request arrived;
    the offset is taken from the echo with the smallest round trip among the last ``window`` (its
    error is at most half that round trip, and a recent window follows slow drift between the clocks).
    """

    def __init__(self, clock_hz: float, window: int = 16) -> None:
        self.clock_hz = float(clock_hz)
        self.window = window
        self._echoes: list[tuple[float, float]] = []     # (round trip s, offset s)
        self._lock = threading.Lock()
        self.count = 0

    def add(self, t_send: float, t_receive: float, server_ticks: int) -> None:
        rtt = t_receive - t_send
        if not rtt >= 0.0:
            return
        offset = server_ticks / self.clock_hz - 0.5 * (t_send + t_receive)
        with self._lock:
            self._echoes.append((rtt, offset))
            del self._echoes[:-self.window]
            self.count += 1

    @property
    def ready(self) -> bool:
        with self._lock:
            return bool(self._echoes)

    def best(self) -> tuple[float, float]:
        """(round trip s, offset s) of the echo used: server time = local time + offset."""
        with self._lock:
            if not self._echoes:
                raise RuntimeError("no echo answered yet")
            return min(self._echoes)

    def to_local(self, ticks: int) -> float:
        """Motive clock ticks -> local clock (s)."""
        return ticks / self.clock_hz - self.best()[1]


# ------------------------------------------------------------------------------- client

_VERSIONS = ("auto", "3.0", "3.1", "4.0", "4.1", "4.2", "4.3")


@dataclass(frozen=True)
class NatNetConfig:
    """Where Motive streams and which rigid bodies are the endoscope's base and tip."""
    server_ip: str = param("127.0.0.1", doc="address of the Motive computer (command port); packets from any other "
                                            "address are ignored")
    local_ip: str = param("127.0.0.1", doc="this computer's address on the mocap network (multicast join, unicast bind)")
    multicast: bool = param(True, doc="Motive streams to a multicast group (else unicast to this client)")
    multicast_group: str = param("239.255.42.99", doc="Motive's multicast group")
    command_port: int = param(1510, lo=0, hi=65535, doc="Motive's command port")
    data_port: int = param(1511, lo=0, hi=65535, doc="Motive's data port (multicast)")
    version: str = param("auto", choices=_VERSIONS, doc="NatNet bit-stream version; auto = the server's; another "
                                                        "version is requested from Motive at connect")
    connect_timeout: float = param(1.0, unit="s", lo=0.01, hi=60.0, doc="wait for each answer of Motive this long")
    base_body_id: int = param(1, lo=0, hi=1000000, doc="Motive streaming id of the rigid body on the endoscope's base")
    tip_body_id: int = param(2, lo=0, hi=1000000, doc="Motive streaming id of the rigid body on the endoscope's tip")
    base_body_name: str = param("", doc="Motive asset name of the base rigid body (overrides base_body_id)")
    tip_body_name: str = param("", doc="Motive asset name of the tip rigid body (overrides tip_body_id)")
    clock_sync: bool = param(True, doc="map Motive's mid-exposure stamps to the local clock by echo requests; off: "
                                       "capture time = arrival minus Motive's latency")
    calibrate_straight: bool = param(False, doc="at start-up (after homing, bending section straight) take the tip "
                                                "body's orientation as the straight camera frame")
    calibrate_max_angle: float = param(0.35, unit="rad", lo=0.0, hi=3.2,
                                       doc="refuse the straight calibration when the tip reads further from straight")
    max_sample_age: float = param(0.1, unit="s", lo=0.001, hi=10.0, doc="older samples count as no sample")

    def check(self, prefix: str = "") -> None:
        for name in ("server_ip", "local_ip", "multicast_group"):
            try:
                ipaddress.IPv4Address(getattr(self, name))
            except ValueError:
                raise ConfigError(f"{prefix}{name} = {getattr(self, name)!r} is not an IPv4 address") from None
        if self.multicast and not ipaddress.IPv4Address(self.multicast_group).is_multicast:
            raise ConfigError(f"{prefix}multicast_group = {self.multicast_group!r} is not a multicast address")
        if self.base_body_name or self.tip_body_name:
            if self.base_body_name == self.tip_body_name:
                raise ConfigError(f"{prefix}base_body_name and tip_body_name must differ")
        elif self.base_body_id == self.tip_body_id:
            raise ConfigError(f"{prefix}base_body_id and tip_body_id must differ")


class NatNetStartError(ConnectionError):
    """Motive did not answer, refused the configured version, or lacks a configured rigid body."""


@dataclass
class ClientStats:
    """Counters of the receive thread (read them any time; they only grow)."""
    packets: int = 0
    frames: int = 0
    malformed: int = 0
    """Packets that did not parse, or frames that parse to nonsense for the expected version."""
    implausible: int = 0
    """Of ``malformed``: frames that parsed but make no sense (configured bodies absent, impossible
    timestamp or positions): the sign of a version mismatch."""
    lost: int = 0
    """Frames missing between consecutive received frame numbers."""
    out_of_order: int = 0
    discontinuities: int = 0
    """Frame-number jumps too large to be loss (Motive restarted or rewound its frame counter)."""
    server_infos: int = 0
    other_messages: int = 0
    foreign: int = 0
    """Packets from an address other than the server's (dropped before parsing)."""
    echoes: int = 0
    clock_outliers: int = 0
    """Frames whose mapped mid-exposure lay after their arrival or > 1 s before it (arrival minus latency used)."""
    last_error: str = ""
    server_info: ServerInfo | None = None


ECHO_PERIOD_S = 0.5
"""Clock-sync echo period while streaming (s)."""
START_ECHOES = 8
"""Echo round trips at start-up before the first offset is trusted."""
MAX_TIMESTAMP_S = 1e7
"""Motive frame timestamps (s since its start) beyond this are impossible (~116 days)."""
MAX_POSITION_M = 1e3
"""Tracked rigid-body positions beyond this distance from Motive's origin are impossible (m)."""
_REPLY_IDS = (NAT_SERVERINFO, NAT_RESPONSE, NAT_MODELDEF, NAT_UNRECOGNIZED_REQUEST)


class NatNetClient:
    """Receives NatNet frames in a thread; the newest parsed sample is in :attr:`latest`.

    ``clock``: local monotonic clock (s) used for arrival times and the clock sync; ``on_sample``:
    optional callback run in the receive thread after each new sample (keep it short);
    ``extra_bodies``: further rigid bodies the rig needs, ``{label: (asset name or "", id)}``,
    checked at start like the base and tip (e.g. ``{"target": ("", 3)}``).

    :meth:`start` connects (asking for the configured version), checks the answer, requests the
    model definitions and resolves the bodies (:attr:`body_ids`), and syncs the clocks.
    """

    def __init__(self, config: NatNetConfig, *, clock: Callable[[], float] = time.monotonic,
                 on_sample: Callable[[MocapSample], None] | None = None,
                 extra_bodies: dict[str, tuple[str, int]] | None = None) -> None:
        self.config = config
        self.clock = clock
        self.on_sample = on_sample
        self.latest: LatestSample[MocapSample] = LatestSample()
        self.stats = ClientStats()
        self.version: tuple[int, int] | None = None if config.version == "auto" else parse_version(config.version)
        self.clock_hz: int | None = None
        self.wanted_bodies: dict[str, tuple[str, int]] = {
            "base": (config.base_body_name, config.base_body_id), "tip": (config.tip_body_name, config.tip_body_id),
            **(extra_bodies or {})}
        self.body_ids: dict[str, int] = {}
        """Streaming ids of the base, tip and extra bodies, resolved at start."""
        self.model: list[RigidBodyDescription] | None = None
        """Motive's rigid bodies from the model definitions (None if it did not answer)."""
        self.clock_sync: ClockSync | None = None
        self._required: frozenset[int] = frozenset()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._cmd: socket.socket | None = None
        self._data: socket.socket | None = None
        self._last_frame: int | None = None
        self._last_keepalive = 0.0
        self._last_echo = 0.0
        self._reply_cond = threading.Condition()
        self._reply: tuple[int, bytes] | None = None
        self._echo_sent: dict[int, float] = {}
        self._echo_seq = 0
        self._last_warning = -math.inf
        self._negotiating = False

    # ---------------------------------------------------------------- life cycle

    def start(self) -> "NatNetClient":
        """Open sockets, start the receive thread, connect, negotiate the version, check the bodies and
        sync the clocks; raises :class:`NatNetStartError` (a ConnectionError) with what to do."""
        c = self.config
        cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
        cmd.bind((c.local_ip, 0))
        cmd.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        self._cmd = cmd
        if c.multicast:
            data = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
            data.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if hasattr(socket, "SO_REUSEPORT"):
                data.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
            data.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
            data.bind((c.multicast_group, c.data_port))
            mreq = struct.pack("4s4s", socket.inet_aton(c.multicast_group), socket.inet_aton(c.local_ip))
            data.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
            self._data = data
        self._stop.clear()
        self._negotiating = True        # frames wait until the version and the bodies are settled
        self._thread = threading.Thread(target=self._run, name="natnet-receive", daemon=True)
        self._thread.start()
        try:
            self._handshake()
        except BaseException:
            self.stop()
            raise
        finally:
            self._negotiating = False
        return self

    def _handshake(self) -> None:
        c = self.config
        where = f"{c.server_ip}:{c.command_port}"
        wanted = None if c.version == "auto" else parse_version(c.version)
        reply = self._request(encode_connect("targetlock", wanted or (4, 1), wanted))
        if reply is None or reply[0] != NAT_SERVERINFO or self.stats.server_info is None:
            raise NatNetStartError(f"no NAT_SERVERINFO from {where} within {c.connect_timeout} s; is Motive "
                                   f"running and streaming, and is natnet.server_ip its address?")
        self._last_keepalive = time.monotonic()
        served = tuple(self.stats.server_info.natnet_version[:2])
        if wanted is not None and served != wanted:
            # Motive 3+ switches its bit stream on the SDK's "Bitstream" command; 0 = done.
            answer = self._request(encode_packet(NAT_REQUEST, f"Bitstream,{wanted[0]}.{wanted[1]}\0".encode()))
            if answer is None or answer[0] != NAT_RESPONSE or answer[1][:4] != b"\0\0\0\0":
                what = ("no answer" if answer is None else "unrecognized request" if answer[0] == NAT_UNRECOGNIZED_REQUEST
                        else f"answer {answer[1][:16]!r}")
                raise NatNetStartError(
                    f"Motive at {where} streams NatNet {served[0]}.{served[1]} and did not switch to natnet.version = "
                    f"{c.version} ({what}); set natnet.version = \"auto\" or \"{served[0]}.{served[1]}\"")
        self.version = wanted or served
        self._resolve_bodies(self._request(encode_packet(NAT_REQUEST_MODELDEF, b"")))
        if c.clock_sync and self.clock_hz:
            self.clock_sync = ClockSync(self.clock_hz)
            deadline = time.monotonic() + c.connect_timeout
            while self.clock_sync.count < START_ECHOES and time.monotonic() < deadline:
                self._send_echo()
                with self._reply_cond:
                    n = self.clock_sync.count
                    self._reply_cond.wait_for(lambda: self.clock_sync.count > n,
                                              min(0.1, max(deadline - time.monotonic(), 0.0)))
            if not self.clock_sync.ready:
                log.warning("Motive at %s answers no echo request: capture times are arrival minus Motive's latency "
                            "(network transit not included)", where)

    def _resolve_bodies(self, reply: tuple[int, bytes] | None) -> None:
        """Match the configured bodies against Motive's model definitions; refuse to start on a missing one."""
        c = self.config
        named = any(name for name, _ in self.wanted_bodies.values())
        if reply is None or reply[0] != NAT_MODELDEF:
            if named:
                raise NatNetStartError(f"Motive at {c.server_ip}:{c.command_port} sent no model definitions, so rigid "
                                       f"bodies cannot be found by name; use base_body_id / tip_body_id")
            log.warning("Motive sent no model definitions: rigid body ids are not checked at start")
            self.body_ids = {label: rid for label, (_, rid) in self.wanted_bodies.items()}
        else:
            try:
                self.model = parse_model_definitions(reply[1], self.version)
            except NatNetParseError as exc:
                raise NatNetStartError(f"Motive's model definitions do not parse as NatNet "
                                       f"{self.version[0]}.{self.version[1]}: {exc}") from None
            by_name = {d.name: d.id for d in self.model}
            ids = {d.id for d in self.model}
            missing = []
            for label, (name, rid) in self.wanted_bodies.items():
                if name:
                    if name in by_name:
                        self.body_ids[label] = by_name[name]
                    else:
                        missing.append(f"{label} {name!r}")
                elif rid in ids:
                    self.body_ids[label] = rid
                else:
                    missing.append(f"{label} id {rid}")
            if missing:
                have = ", ".join(f"{d.name!r} (id {d.id})" for d in self.model) or "no rigid bodies"
                raise NatNetStartError(f"Motive has no rigid body for {', '.join(missing)}; it streams {have}. "
                                       f"Fix the rig file's [natnet] / [observations] body names or ids, or enable "
                                       f"the asset in Motive")
        self._required = frozenset(self.body_ids.values())

    def _request(self, packet: bytes) -> tuple[int, bytes] | None:
        """Send a command and wait for its answer (server info, response, model definitions or
        unrecognized request) up to the connect timeout."""
        with self._reply_cond:
            self._reply = None
        self._send(packet)
        with self._reply_cond:
            self._reply_cond.wait_for(lambda: self._reply is not None, self.config.connect_timeout)
            return self._reply

    def _send(self, packet: bytes) -> None:
        if self._cmd is not None:
            self._cmd.sendto(packet, (self.config.server_ip, self.config.command_port))

    def _send_echo(self) -> None:
        self._echo_seq += 1
        stamp = self._echo_seq
        with self._reply_cond:
            self._echo_sent[stamp] = self.clock()
            for old in [k for k in self._echo_sent if k < stamp - 8]:
                del self._echo_sent[old]
        try:
            self._send(encode_packet(NAT_ECHOREQUEST, struct.pack("<Q", stamp)))
        except OSError as exc:
            log.debug("echo request not sent: %s", exc)
        self._last_echo = time.monotonic()

    def connect(self) -> None:
        """Send NAT_CONNECT again (the 'ping' of the command port; Motive answers with NAT_SERVERINFO)."""
        wanted = None if self.config.version == "auto" else parse_version(self.config.version)
        self._send(encode_connect("targetlock", wanted or (4, 1), wanted))
        self._last_keepalive = time.monotonic()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for s in (self._cmd, self._data):
            if s is not None:
                s.close()
        self._cmd = self._data = None

    def __enter__(self) -> "NatNetClient":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ---------------------------------------------------------------- loop side

    def get(self, max_age: float | None = None) -> MocapSample | None:
        """Newest sample, or None if there is none or it is older than ``max_age`` s (default: config)."""
        sample = self.latest.get()
        if sample is None:
            return None
        limit = self.config.max_sample_age if max_age is None else max_age
        if self.clock() - sample.received_at > limit:
            return None
        return sample

    # ---------------------------------------------------------------- receive thread

    def _run(self) -> None:
        c = self.config
        socks = [s for s in (self._cmd, self._data) if s is not None]
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select(socks, [], [], RECV_POLL_S)
            except (OSError, ValueError):
                break
            for s in ready:
                try:
                    packet, addr = s.recvfrom(MAX_PACKET_BYTES)
                except OSError:
                    continue
                if addr[0] != c.server_ip:      # another sender on the network (or on this host)
                    self.stats.packets += 1
                    self.stats.foreign += 1
                    continue
                # Command answers come from the command port; unicast frames from Motive's data socket.
                self.handle_packet(packet, self.clock(), from_command_port=s is self._cmd and addr[1] == c.command_port)
            now = time.monotonic()
            if not c.multicast and now - self._last_keepalive > KEEPALIVE_PERIOD_S and self._cmd is not None:
                try:
                    self._send(encode_packet(NAT_KEEPALIVE, b""))
                except OSError as exc:
                    log.debug("keep-alive not sent: %s", exc)
                self._last_keepalive = now
            if self.clock_sync is not None and now - self._last_echo > ECHO_PERIOD_S:
                self._send_echo()

    def _command_reply(self, msg_id: int, payload: memoryview, received_at: float) -> None:
        if msg_id == NAT_ECHORESPONSE:
            stamp, ticks = parse_echo_response(payload)
            with self._reply_cond:
                sent = self._echo_sent.pop(stamp, None)
                if sent is not None and self.clock_sync is not None:
                    self.clock_sync.add(sent, received_at, ticks)
                    self.stats.echoes += 1
                self._reply_cond.notify_all()
            return
        with self._reply_cond:
            self._reply = (msg_id, bytes(payload))
            self._reply_cond.notify_all()

    def _implausible(self, frame: MocapFrame) -> str | None:
        """Why a parsed frame cannot be what Motive sent (a version mismatch parses to such nonsense), or None."""
        ts = frame.timestamp
        if not (ts == 0.0 or 1e-4 <= ts <= MAX_TIMESTAMP_S):
            return f"timestamp {ts!r} s"
        if frame.frame_number < 0:
            return f"frame number {frame.frame_number}"
        missing = self._required - frame.rigid_bodies.keys()
        if missing:
            return f"configured rigid bodies {sorted(missing)} absent (frame has {sorted(frame.rigid_bodies)})"
        for b in frame.rigid_bodies.values():
            if b.tracking_valid and not all(abs(v) <= MAX_POSITION_M for v in b.position):
                return f"rigid body {b.id} at {b.position} m"
        return None

    def handle_packet(self, packet: bytes, received_at: float, from_command_port: bool = True) -> MocapSample | None:
        """Parse one packet (receive thread; public for tests). Malformed packets are counted, never raised.

        Server info and other command answers are only taken from the command port (a data packet
        can never reconfigure the client).
        """
        st = self.stats
        st.packets += 1
        try:
            msg_id, payload = parse_packet(packet)
            if msg_id == NAT_FRAMEOFDATA:
                if self.version is None or self._negotiating:
                    st.other_messages += 1      # cannot parse before the version is known
                    return None
                frame = parse_frame_of_data(payload, self.version)
                why = self._implausible(frame)
                if why is not None:
                    st.implausible += 1
                    raise NatNetParseError(f"frame {frame.frame_number} makes no sense as NatNet "
                                           f"{self.version[0]}.{self.version[1]}: {why}")
            elif msg_id == NAT_SERVERINFO and from_command_port:
                info = parse_server_info(payload)
                major, minor = info.natnet_version[:2]
                if not 3 <= major <= 4:
                    raise NatNetParseError(f"server speaks NatNet {major}.{minor}; 3.x or 4.x supported")
                if info.clock_hz is not None and not 1_000 <= info.clock_hz <= 10**12:
                    raise NatNetParseError(f"implausible server clock frequency {info.clock_hz} Hz")
                st.server_infos += 1
                st.server_info = info
                if self.config.version == "auto" and self.version is None:
                    self.version = (major, minor)
                self.clock_hz = info.clock_hz
                self._command_reply(msg_id, payload, received_at)
                return None
            elif from_command_port and (msg_id in _REPLY_IDS or msg_id == NAT_ECHORESPONSE):
                st.other_messages += 1
                self._command_reply(msg_id, payload, received_at)
                return None
            else:
                st.other_messages += 1
                return None
        except NatNetParseError as exc:
            st.malformed += 1
            st.last_error = str(exc)
            if time.monotonic() - self._last_warning > 5.0:     # reported, but not once per frame
                self._last_warning = time.monotonic()
                log.warning("NatNet packet skipped: %s", exc)
            return None
        except (struct.error, IndexError, ValueError, OverflowError) as exc:   # defence in depth
            st.malformed += 1
            st.last_error = f"{type(exc).__name__}: {exc}"
            return None
        last = self._last_frame
        if last is not None:
            gap = frame.frame_number - last
            if -MAX_FRAME_GAP < gap <= 0:
                st.out_of_order += 1
                return None
            if gap > MAX_FRAME_GAP or gap <= -MAX_FRAME_GAP:
                st.discontinuities += 1     # Motive restarted / rewound: count afresh from here
            elif gap > 1:
                st.lost += gap - 1
        self._last_frame = frame.frame_number
        st.frames += 1
        sample = MocapSample(frame, received_at, frame.latency(self.clock_hz), self._map_capture(frame, received_at))
        self.latest.put(sample)
        if self.on_sample is not None:
            self.on_sample(sample)
        return sample

    def _map_capture(self, frame: MocapFrame, received_at: float) -> float | None:
        sync = self.clock_sync
        if sync is None or not sync.ready or frame.camera_mid_exposure == 0:
            return None
        t = sync.to_local(frame.camera_mid_exposure)
        if not received_at - 1.0 <= t <= received_at + 0.001:   # Motive's clock restarted, or a sync outlier
            self.stats.clock_outliers += 1
            return None
        return t
