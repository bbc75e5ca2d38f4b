"""NatNet packet parsing: layouts of NatNet 3.x / 4.x, server info, and fuzzing (never crash, always count)."""
from __future__ import annotations

import struct
import time

import numpy as np
import pytest

from targetlock.interfaces.natnet import (NAT_FRAMEOFDATA, NAT_SERVERINFO, NatNetClient, NatNetConfig, NatNetParseError,
                                          ServerInfo, encode_frame_of_data, encode_server_info, parse_frame_of_data,
                                          parse_packet, parse_server_info)

I = struct.Struct("<i")


def rb(rid, pos, quat, err=0.0005, params=1):
    return struct.pack("<i3f4ffh", rid, *pos, *quat, err, params)


def section(count, body, sized):
    return I.pack(count) + (I.pack(len(body)) if sized else b"") + body


def handmade_frame(version):
    """A frame written field by field from the published NatNet layout (independent of the encoder)."""
    sized = version >= (4, 1)
    p = I.pack(4711)                                                      # frame number
    ms = b"Rig\0" + I.pack(2) + struct.pack("<6f", 1, 2, 3, 4, 5, 6) + b"all\0" + I.pack(0)
    p += section(2, ms, sized)                                            # marker sets
    p += section(1, struct.pack("<3f", 0.5, 0.5, 0.5), sized)             # legacy other markers
    bodies = rb(1, (0.1, 0.2, 0.3), (0.0, 0.0, 0.0, 1.0)) + rb(2, (1.5, -0.25, 2.0), (0.5, 0.5, 0.5, 0.5), 0.001, 0)
    p += section(2, bodies, sized)                                        # rigid bodies
    skel = I.pack(77) + I.pack(1) + rb(3, (9, 9, 9), (0, 0, 0, 1))
    p += section(1, skel, sized)                                          # skeletons
    if sized:
        asset = I.pack(8) + I.pack(1) + rb(4, (0, 0, 0), (0, 0, 0, 1)) + I.pack(1) + struct.pack("<i3ffhf", 1, 0, 0, 0, .01, 0, 0)
        p += section(1, asset, True)                                      # assets
    lm = struct.pack("<i3ffhf", 65537, 1, 2, 3, 0.014, 4, 0.0002)
    p += section(1, lm, sized)                                            # labeled markers
    fp = I.pack(1) + I.pack(2) + I.pack(1) + struct.pack("<f", 3.0) + I.pack(0)
    p += section(1, fp, sized)                                            # force plates
    dev = I.pack(2) + I.pack(1) + I.pack(2) + struct.pack("<2f", 1, 2)
    p += section(1, dev, sized)                                           # devices
    p += struct.pack("<II", 0x01020304, 5)                                # timecode, subframe
    p += struct.pack("<d", 12.5)                                          # timestamp
    p += struct.pack("<QQQ", 1_000_000, 1_020_000, 1_045_000)             # mid-exposure, received, transmit
    if sized:
        p += struct.pack("<II", 1700000000, 123)                          # precision timestamp
    p += struct.pack("<h", 0x02)                                          # params: models changed
    p += I.pack(0)                                                        # end-of-data tag
    return struct.pack("<HH", NAT_FRAMEOFDATA, len(p)) + p


@pytest.mark.parametrize("version", [(3, 0), (3, 1), (4, 0), (4, 1), (4, 2)])
def test_handmade_frame_layout(version):
    msg, payload = parse_packet(handmade_frame(version))
    assert msg == NAT_FRAMEOFDATA
    f = parse_frame_of_data(payload, version)
    assert f.frame_number == 4711
    assert sorted(f.rigid_bodies) == [1, 2]                  # skeleton bones and asset bodies are not top level
    b = f.rigid_bodies[2]
    assert b.position == pytest.approx((1.5, -0.25, 2.0))
    assert b.orientation == (0.5, 0.5, 0.5, 0.5)
    assert b.mean_error == pytest.approx(0.001)
    assert not b.tracking_valid and f.rigid_bodies[1].tracking_valid
    assert f.timestamp == 12.5 and f.timecode == 0x01020304 and f.timecode_sub == 5
    assert (f.camera_mid_exposure, f.data_received, f.transmit) == (1_000_000, 1_020_000, 1_045_000)
    assert f.latency(10_000_000) == pytest.approx(0.0045)
    assert f.tracked_models_changed and not f.is_recording
    assert f.precision_timestamp == ((1700000000, 123) if version >= (4, 1) else None)


def test_natnet_40_frame_layout_follows_the_version_not_the_length():
    """Item 14: a 4.0 frame never carries the precision timestamp (as the official 4.x client reads
    it); bytes left over after the suffix other than the end tag are an error, not a guess."""
    _, payload = parse_packet(handmade_frame((4, 0)))
    body = bytes(payload)
    assert parse_frame_of_data(body, (4, 0)).precision_timestamp is None
    assert parse_frame_of_data(body[:-4], (4, 0)).tracked_models_changed        # without the end tag
    # a frame with a precision stamp inserted: the old parser took it from the suffix length
    with_prec = body[:-6] + struct.pack("<II", 7, 8) + body[-6:]
    with pytest.raises(NatNetParseError, match="after its suffix"):
        parse_frame_of_data(with_prec, (4, 0))
    # cut by 6 bytes (header-consistent): the old parser read the frame flags from the stamp
    with pytest.raises(NatNetParseError):
        parse_frame_of_data(with_prec[:-6], (4, 0))
    for extra in (1, 2, 3, 5, 8):
        with pytest.raises(NatNetParseError):
            parse_frame_of_data(body + bytes(extra), (4, 0))
    # a 4.1 frame must carry the stamp: cut it out and the frame is refused
    _, p41 = parse_packet(handmade_frame((4, 1)))
    p41 = bytes(p41)
    with pytest.raises(NatNetParseError):
        parse_frame_of_data(p41[:-14] + p41[-6:], (4, 1))


def test_version_2_is_refused():
    with pytest.raises(NatNetParseError, match="not supported"):
        parse_frame_of_data(parse_packet(handmade_frame((3, 0)))[1], (2, 10))


@pytest.mark.parametrize("version", [(3, 0), (3, 1), (4, 0), (4, 1)])
@pytest.mark.parametrize("extras", [False, True])
def test_encoder_round_trip(version, extras):
    rng = np.random.default_rng(1)
    bodies = []
    for rid in (1, 2, 17):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        bodies.append((rid, tuple(rng.normal(size=3)), tuple(q), 0.0003, rid != 17))
    pkt = encode_frame_of_data(99, bodies, version=version, timestamp=3.25, camera_mid_exposure=10,
                               data_received=20, transmit=50, extras=extras, params=1)
    f = parse_frame_of_data(parse_packet(pkt)[1], version)
    assert f.frame_number == 99 and f.is_recording
    for rid, pos, quat, err, valid in bodies:
        got = f.rigid_bodies[rid]
        assert got.position == tuple(np.float32(pos).tolist())       # exact float32 round trip
        assert got.orientation == tuple(np.float32(quat).tolist())
        assert got.tracking_valid == valid


def test_server_info_round_trip():
    info = ServerInfo("Motive", (3, 1, 2, 0), (4, 1, 0, 0), 10_000_000, 1511, True, "239.255.42.99")
    msg, payload = parse_packet(encode_server_info(info))
    assert msg == NAT_SERVERINFO
    assert parse_server_info(payload) == info
    short = parse_server_info(bytes(payload)[:264])           # pre-3.0 servers end after the versions
    assert short.natnet_version == (4, 1, 0, 0) and short.clock_hz is None
    with pytest.raises(NatNetParseError):
        parse_server_info(bytes(payload)[:200])


def test_size_field_and_section_sizes_are_checked():
    pkt = handmade_frame((4, 1))
    with pytest.raises(NatNetParseError):
        parse_packet(pkt[:-1])                                # header says more than there is
    _, payload = parse_packet(pkt)
    body = bytearray(payload)
    # rigid-body section size that disagrees with the count (count at offset after frame number +
    # marker sets + other markers)
    off = 4 + 8 + len(b"Rig\0") + 4 + 24 + len(b"all\0") + 4 + 8 + 12
    assert struct.unpack_from("<ii", body, off) == (2, 76)
    struct.pack_into("<i", body, off + 4, 75)
    with pytest.raises(NatNetParseError, match="rigid bodies"):
        parse_frame_of_data(bytes(body), (4, 1))
    struct.pack_into("<ii", body, off, 2**30, 76)                  # absurd count
    with pytest.raises(NatNetParseError):
        parse_frame_of_data(bytes(body), (4, 1))


def fuzz_client(version):
    return NatNetClient(NatNetConfig(version=f"{version[0]}.{version[1]}"))


@pytest.mark.parametrize("version", [(3, 1), (4, 0), (4, 1)])
def test_every_truncation_is_counted_as_malformed(version):
    pkt = handmade_frame(version)
    client = fuzz_client(version)
    for n in range(len(pkt)):
        assert client.handle_packet(pkt[:n], 0.0) is None
    assert client.stats.malformed == len(pkt)
    assert client.stats.frames == 0
    # the payload cut short but with a consistent header is malformed too
    payload = pkt[4:]
    for n in range(0, len(payload) - 6):
        cut = struct.pack("<HH", NAT_FRAMEOFDATA, n) + payload[:n]
        assert client.handle_packet(cut, 0.0) is None
    assert client.stats.frames == 0
    assert client.handle_packet(pkt, 0.0) is not None


def test_fuzz_random_bytes_and_bit_flips():
    """Tens of thousands of corrupted packets: the parser raises only NatNetParseError, the client counts them."""
    rng = np.random.default_rng(12345)
    versions = [(3, 0), (3, 1), (4, 0), (4, 1)]
    t0 = time.monotonic()
    cases = 0
    for version in versions:
        client = fuzz_client(version)
        good = [handmade_frame(version),
                encode_frame_of_data(5, [(1, (0, 0, 1), (0, 0, 0, 1), 0, True)], version=version, extras=True)]
        # random bytes, with a plausible header half of the time
        for _ in range(3000):
            n = int(rng.integers(0, 400))
            raw = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
            if n >= 4 and rng.random() < 0.5:
                raw = struct.pack("<HH", NAT_FRAMEOFDATA, n - 4) + raw[4:]
            client.handle_packet(raw, 0.0, from_command_port=False)
            cases += 1
        # bit flips and byte overwrites of valid packets
        for _ in range(6000):
            pkt = bytearray(good[int(rng.integers(0, len(good)))])
            for _ in range(int(rng.integers(1, 6))):
                k = int(rng.integers(0, len(pkt)))
                if rng.random() < 0.7:
                    pkt[k] ^= 1 << int(rng.integers(0, 8))
                else:
                    pkt[k] = int(rng.integers(0, 256))
            client.handle_packet(bytes(pkt), 0.0, from_command_port=False)
            cases += 1
        # inflated counts / sizes at every 4-byte aligned position
        base = good[0]
        for k in range(4, len(base) - 4, 2):
            for value in (-1, 2**31 - 1, 10**6, len(base)):
                pkt = bytearray(base)
                struct.pack_into("<i", pkt, k, value)
                client.handle_packet(bytes(pkt), 0.0, from_command_port=False)
                cases += 1
        st = client.stats
        assert st.packets == st.frames + st.malformed + st.other_messages + st.out_of_order + st.server_infos
        assert st.malformed > 0
        assert client.version == version and client.clock_hz is None      # data never reconfigures the client
    elapsed = time.monotonic() - t0
    print(f"\nfuzzed {cases} packets in {elapsed:.2f} s")
    assert cases > 30000
    assert elapsed < 30


def test_parser_never_raises_anything_but_parse_errors():
    rng = np.random.default_rng(7)
    pkt = handmade_frame((3, 1))
    _, payload = parse_packet(pkt)
    body = bytes(payload)
    for _ in range(5000):
        b = bytearray(body)
        k = int(rng.integers(0, len(b)))
        b[k] = int(rng.integers(0, 256))
        try:
            parse_frame_of_data(bytes(b), (3, 1))
        except NatNetParseError:
            pass


def test_parse_rate(record_property):
    pkt = encode_frame_of_data(1, [(1, (0, 0, 1), (0, 0, 0, 1), 0, True), (2, (0, 0, 1.1), (0, 0, 0, 1), 0, True)],
                               version=(4, 1))
    client = fuzz_client((4, 1))
    n = 20000
    buf = bytearray(pkt)
    t0 = time.perf_counter()
    for k in range(n):
        struct.pack_into("<i", buf, 4, k + 1)                 # a new frame number each time
        assert client.handle_packet(bytes(buf), float(k)) is not None
    rate = n / (time.perf_counter() - t0)
    record_property("natnet_frames_per_s", rate)
    print(f"\nNatNet parse + hand-off: {rate:,.0f} frames/s (2 rigid bodies, NatNet 4.1)")
    assert rate > 5000


def test_fuzz_server_info_on_the_command_port():
    rng = np.random.default_rng(99)
    good = encode_server_info(ServerInfo("Motive", (3, 1, 0, 0), (4, 1, 0, 0), 10_000_000, 1511, True, "239.255.42.99"))
    client = NatNetClient(NatNetConfig(version="auto"))
    frame = encode_frame_of_data(1, [(1, (0, 0, 1), (0, 0, 0, 1), 0, True)], version=(4, 1))
    assert client.handle_packet(frame, 0.0) is None and client.stats.other_messages == 1   # version unknown yet
    for _ in range(5000):
        pkt = bytearray(good)
        for _ in range(int(rng.integers(1, 4))):
            pkt[int(rng.integers(0, len(pkt)))] ^= 1 << int(rng.integers(0, 8))
        client.handle_packet(bytes(pkt[:int(rng.integers(0, len(pkt) + 1))]), 0.0, from_command_port=True)
        assert client.version is None or client.version[0] in (3, 4)
        assert client.clock_hz is None or 1_000 <= client.clock_hz <= 10**12
    client.handle_packet(good, 0.0, from_command_port=True)
    assert client.version == (4, 1) and client.clock_hz == 10_000_000
