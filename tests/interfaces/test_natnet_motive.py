"""The NatNet client against a simulated server that behaves like Motive (issue 10 items 11-15,
issue 11 item 8): version negotiation, model definitions and body names, Motive's command answers
and time stamps, clock sync, and packets from other senders. Loopback only."""
from __future__ import annotations

import socket
import struct
import time

import numpy as np
import pytest

from targetlock.interfaces.natnet import (NAT_CONNECT, NAT_DISCOVERY, NAT_ECHOREQUEST, NAT_ECHORESPONSE, NAT_MODELDEF,
                                          NAT_REQUEST, NAT_REQUEST_MODELDEF, NAT_RESPONSE, NAT_SERVERINFO,
                                          NAT_UNRECOGNIZED_REQUEST, ClockSync, NatNetClient, NatNetConfig,
                                          NatNetParseError, NatNetStartError, encode_connect, encode_frame_of_data,
                                          encode_packet, parse_echo_response, parse_model_definitions,
                                          parse_packet, parse_server_info)
from targetlock.interfaces.sim_natnet import CLOCK_HZ, SimNatNetConfig, SimNatNetServer

from iface_helpers import free_udp_port, wait_until

TARGET = np.eye(4)
TARGET[:3, 3] = (0.1, 0.0, 1.5)


def poses_with_target():
    base, tip = np.eye(4), np.eye(4)
    tip[:3, 3] = (0.0, 0.0, 0.05)
    return base, tip, {3: TARGET}


def pair(client_kw=None, source=poses_with_target, names=None, **server_kw):
    """A simulated Motive (unicast by default: no shared multicast port between tests) and a client config."""
    server_kw.setdefault("multicast", False)
    server_kw.setdefault("rate_hz", 200.0)
    port = free_udp_port()
    srv = SimNatNetServer(SimNatNetConfig(command_port=0, data_port=port, **server_kw), source, names=names)
    cfg = NatNetConfig(command_port=srv.command_port, data_port=port, multicast=server_kw["multicast"],
                       connect_timeout=0.5, **(client_kw or {}))
    return srv, cfg


class RawClient:
    """A bare UDP socket speaking to the server's command port, like a third-party client."""

    def __init__(self, srv: SimNatNetServer, local_ip: str = "127.0.0.1") -> None:
        self.addr = (srv.config.server_ip, srv.command_port)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((local_ip, 0))
        self.sock.settimeout(2.0)

    def ask(self, packet: bytes, want: int | None = None) -> tuple[int, memoryview]:
        self.sock.sendto(packet, self.addr)
        while True:
            msg, payload = parse_packet(self.sock.recv(70000))
            if want is None or msg == want:
                return msg, payload

    def close(self) -> None:
        self.sock.close()


# ------------------------------------------------------------------ item 11: version negotiation

@pytest.mark.parametrize("honours", ["both", "bitstream"])
def test_configured_version_is_requested_and_streamed(honours):
    """Server streams 4.1, rig file says 3.1: the client asks for 3.1 (connect option or the SDK's
    'Bitstream,3.1' command) and gets a 3.1 stream it parses without a single bad frame."""
    srv, cfg = pair({"version": "3.1"}, version="4.1", version_requests=honours)
    with srv, NatNetClient(cfg) as client:
        assert srv.version == (3, 1) and client.version == (3, 1)
        assert ("Bitstream,3.1" in srv.stats.requests) == (honours == "bitstream")
        assert wait_until(lambda: client.stats.frames > 5, 3.0)
        assert client.stats.malformed == 0
        assert client.get().frame.version == (3, 1)
        assert client.get().rigid_body(3).position == pytest.approx((0.1, 0.0, 1.5))


def test_server_that_ignores_the_version_request_is_refused():
    srv, cfg = pair({"version": "3.1"}, version="4.1", version_requests="none")
    with srv:
        with pytest.raises(NatNetStartError, match=r'streams NatNet 4\.1 .*natnet\.version = 3\.1.*"auto"'):
            NatNetClient(cfg).start()


def test_stream_switched_under_the_client_is_reported_not_taken_as_data():
    """Another client switches the shared stream to 4.1 while ours expects 3.1: every such frame is
    counted as malformed with a reason, and no new sample reaches the loop."""
    srv, cfg = pair({"version": "3.1"}, version="3.1")
    with srv, NatNetClient(cfg) as client:
        assert wait_until(lambda: client.stats.frames > 3, 3.0)
        other = RawClient(srv)
        assert other.ask(encode_packet(NAT_REQUEST, b"Bitstream,4.1\0"), NAT_RESPONSE)[1].tobytes() == b"\0\0\0\0"
        other.close()
        time.sleep(0.05)
        frames, malformed = client.stats.frames, client.stats.malformed
        assert wait_until(lambda: client.stats.malformed > malformed + 10, 3.0)
        assert client.stats.frames <= frames + 1
        assert client.stats.last_error                  # the reason is kept for the report


def test_frames_that_parse_to_nonsense_are_errors():
    """A frame consistent in its lengths but with an impossible timestamp (the 1e-309 seen with a
    version mismatch) or without the configured bodies is an error, not data."""
    srv, cfg = pair()
    with srv, NatNetClient(cfg, extra_bodies={"target": ("", 3)}) as client:
        assert client.body_ids == {"base": 1, "tip": 2, "target": 3}
        body = [(k, (0.0, 0.0, 1.0), (0.0, 0.0, 0.0, 1.0), 0.0, True) for k in (1, 2, 3)]
        bad = encode_frame_of_data(10**6, body, version=(4, 1), timestamp=1e-309)
        assert client.handle_packet(bad, 0.0, from_command_port=False) is None
        assert "timestamp" in client.stats.last_error and client.stats.implausible == 1
        no_target = encode_frame_of_data(10**6 + 1, body[:2], version=(4, 1), timestamp=1.0)
        assert client.handle_packet(no_target, 0.0, from_command_port=False) is None
        assert "[3] absent" in client.stats.last_error and client.stats.implausible == 2
        far = encode_frame_of_data(10**6 + 2, [(1, (0, 0, 3e30), (0, 0, 0, 1), 0, True)] + body[1:],
                                   version=(4, 1), timestamp=1.0)
        assert client.handle_packet(far, 0.0, from_command_port=False) is None
        assert client.stats.implausible == 3
        assert client.handle_packet(encode_frame_of_data(10**6 + 3, body, version=(4, 1), timestamp=1.0),
                                    0.0, from_command_port=False) is not None


def test_target_body_disappearing_mid_run_is_reported():
    state = {"target": True}

    def source():
        b, t, extra = poses_with_target()
        return (b, t, extra) if state["target"] else (b, t, {})

    srv, cfg = pair(source=source)
    with srv, NatNetClient(cfg, extra_bodies={"target": ("", 3)}) as client:
        assert wait_until(lambda: client.stats.frames > 3, 3.0)
        state["target"] = False
        assert wait_until(lambda: client.stats.implausible > 5, 3.0)
        assert "absent" in client.stats.last_error


# ------------------------------------------------------------------ item 12: model definitions, names

def test_bodies_by_motive_asset_name():
    srv, cfg = pair({"base_body_name": "EndoscopeBase", "tip_body_name": "EndoscopeTip", "base_body_id": 7,
                     "tip_body_id": 8}, names={3: "Target"})
    with srv, NatNetClient(cfg, extra_bodies={"target": ("Target", 0)}) as client:
        assert srv.stats.model_requests == 1
        assert client.body_ids == {"base": 1, "tip": 2, "target": 3}
        assert [(d.name, d.id) for d in client.model] == [("EndoscopeBase", 1), ("EndoscopeTip", 2), ("Target", 3)]
        assert wait_until(lambda: client.stats.frames > 3, 3.0)


@pytest.mark.parametrize("client_kw, extra, missing", [
    ({"tip_body_name": "Tip"}, None, "tip 'Tip'"),
    ({"base_body_id": 9}, None, "base id 9"),
    ({}, {"target": ("", 4)}, "target id 4"),
])
def test_missing_body_refuses_to_start_and_lists_what_motive_has(client_kw, extra, missing):
    srv, cfg = pair(client_kw)
    with srv:
        with pytest.raises(NatNetStartError) as err:
            NatNetClient(cfg, extra_bodies=extra).start()
    msg = str(err.value)
    assert missing in msg
    assert "'EndoscopeBase' (id 1), 'EndoscopeTip' (id 2), 'RigidBody3' (id 3)" in msg


def test_server_without_model_definitions():
    """An old server without model definitions: ids still work (checked per frame), names cannot."""
    srv, cfg = pair(motive_replies=False)
    with srv, NatNetClient(cfg) as client:
        assert client.model is None and client.body_ids == {"base": 1, "tip": 2}
        assert client.clock_sync is not None and not client.clock_sync.ready      # no echo either
        assert wait_until(lambda: client.stats.frames > 3, 3.0)
        s = client.get()
        assert s.mapped_capture_time is None and s.capture_time == s.received_at - s.latency
    srv, cfg = pair({"base_body_name": "EndoscopeBase", "tip_body_name": "EndoscopeTip"}, motive_replies=False)
    with srv:
        with pytest.raises(NatNetStartError, match="no model definitions"):
            NatNetClient(cfg).start()


@pytest.mark.parametrize("version", [(3, 0), (3, 1), (4, 0), (4, 1), (4, 2)])
def test_model_definitions_round_trip_and_truncation(version):
    srv, _ = pair(names={3: "Target"})
    with srv:
        srv.version = version
        raw = RawClient(srv)
        _, payload = raw.ask(encode_packet(NAT_REQUEST_MODELDEF, b""), NAT_MODELDEF)
        raw.close()
    payload = bytes(payload)
    got = parse_model_definitions(payload, version)
    assert [(d.name, d.id, d.parent_id) for d in got] == [("EndoscopeBase", 1, -1), ("EndoscopeTip", 2, -1),
                                                          ("Target", 3, -1)]
    for n in range(len(payload)):           # every truncation: an error or a subset, never another exception
        try:
            part = parse_model_definitions(payload[:n], version)
        except NatNetParseError:
            continue
        assert [d.id for d in part] == [d.id for d in got][:len(part)]


# ------------------------------------------------------------------ item 13: answers like Motive

def test_simulated_server_answers_like_motive():
    srv, _ = pair(names={3: "Target"}, rate_hz=120.0, multicast=True)
    with srv:
        raw = RawClient(srv)
        msg, info = raw.ask(encode_packet(NAT_DISCOVERY, encode_connect()[4:]))
        assert msg == NAT_SERVERINFO and parse_server_info(info).natnet_version[:2] == (4, 1)
        msg, rate = raw.ask(encode_packet(NAT_REQUEST, b"FrameRate\0"))
        assert msg == NAT_RESPONSE and struct.unpack("<f", rate)[0] == 120.0
        t_send = time.monotonic()
        msg, echo = raw.ask(encode_packet(NAT_ECHOREQUEST, struct.pack("<Q", 0xDEADBEEF12345678)))
        t_recv = time.monotonic()
        assert msg == NAT_ECHORESPONSE
        stamp, ticks = parse_echo_response(echo)
        assert stamp == 0xDEADBEEF12345678
        assert srv.ticks(t_send) <= ticks <= srv.ticks(t_recv)
        msg, mdef = raw.ask(encode_packet(NAT_REQUEST_MODELDEF, b""))
        assert msg == NAT_MODELDEF
        assert [d.name for d in parse_model_definitions(mdef, (4, 1))] == ["EndoscopeBase", "EndoscopeTip", "Target"]
        msg, _ = raw.ask(encode_packet(NAT_REQUEST, b"NoSuchCommand\0"))
        assert msg == NAT_UNRECOGNIZED_REQUEST
        raw.close()
    # the legacy server (before this fix) answers only connect: clients must cope
    srv, _ = pair(motive_replies=False)
    with srv:
        raw = RawClient(srv)
        assert raw.ask(encode_packet(NAT_ECHOREQUEST, bytes(8)))[0] == NAT_UNRECOGNIZED_REQUEST
        assert raw.ask(encode_packet(NAT_CONNECT, encode_connect()[4:]))[0] == NAT_SERVERINFO
        raw.close()


def test_frame_timestamps_behave_like_motives():
    srv, cfg = pair(rate_hz=100.0, latency=0.004)
    frames = []
    with srv, NatNetClient(cfg, on_sample=frames.append) as client:
        assert wait_until(lambda: len(frames) > 20, 3.0)
    f = [s.frame for s in frames]
    for fr in f:
        assert fr.timestamp == pytest.approx(fr.frame_number / 100.0)           # frame number / frame rate
        assert fr.data_received - fr.camera_mid_exposure == int(0.002 * CLOCK_HZ)
        assert fr.transmit - fr.camera_mid_exposure >= int(0.004 * CLOCK_HZ)    # a few ms after mid-exposure
    mids = np.diff([fr.camera_mid_exposure for fr in f]) / np.diff([fr.frame_number for fr in f])
    assert np.allclose(mids, CLOCK_HZ / 100.0, atol=2)                           # exposures on the frame grid
    assert client.stats.malformed == 0


# ------------------------------------------------------------------ item 15: clock sync

def test_clock_sync_takes_the_minimum_round_trip():
    rng = np.random.default_rng(4)
    true_offset = 1234.5678            # server clock - local clock (s)
    sync = ClockSync(CLOCK_HZ, window=16)
    for k in range(16):
        t0 = 10.0 + k
        up, down = rng.uniform(0.0002, 0.02, 2)        # asymmetric, host-load-like delays
        if k == 9:
            up = down = 0.0001                         # one quick, symmetric round trip
        sync.add(t0, t0 + up + down, int((t0 + up + true_offset) * CLOCK_HZ))
    rtt, offset = sync.best()
    assert rtt == pytest.approx(0.0002)
    assert offset == pytest.approx(true_offset, abs=1e-6)
    assert sync.to_local(int((20.0 + true_offset) * CLOCK_HZ)) == pytest.approx(20.0, abs=1e-6)


def test_capture_time_is_mapped_mid_exposure_including_network_transit():
    """10 ms of network transit each way: arrival minus Motive's latency is >= 10 ms late; the
    echo-synced mapping of the mid-exposure stamp is within a few ms of the true exposure time."""
    srv, cfg = pair(transit_delay=0.010, clock_offset=5000.0, latency=0.004)
    samples = []
    with srv, NatNetClient(cfg, on_sample=samples.append) as client:
        assert client.clock_sync.count >= 4
        del samples[:]                  # frames during start-up came before the sync
        assert wait_until(lambda: len(samples) > 30, 3.0)
        rtt, _ = client.clock_sync.best()
    assert rtt >= 0.02
    truth = np.array([srv.ticks_to_local(s.frame.camera_mid_exposure) for s in samples])
    mapped = np.array([s.capture_time for s in samples])
    old = np.array([s.received_at - s.latency for s in samples])
    assert np.all(old - truth > 0.009)
    assert np.median(np.abs(mapped - truth)) < 0.002
    assert np.max(np.abs(mapped - truth)) < 0.005
    assert client.stats.clock_outliers == 0


# ------------------------------------------------------------------ issue 11 item 8: other senders

@pytest.mark.parametrize("multicast", [True, False], ids=["multicast", "unicast"])
def test_packets_from_another_sender_are_ignored(multicast):
    srv, cfg = pair(multicast=multicast)
    with srv, NatNetClient(cfg) as client:
        assert wait_until(lambda: client.stats.frames > 3, 3.0)
        intruder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        intruder.bind(("127.0.0.2", 0))              # another host's address on the loopback net
        intruder.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
        intruder.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
        fake = encode_frame_of_data(10**7, [(1, (9.0, 9.0, 9.0), (0, 0, 0, 1), 0, True),
                                            (2, (9.0, 9.0, 9.0), (0, 0, 0, 1), 0, True)], version=(4, 1),
                                    timestamp=1.0)
        dest = (cfg.multicast_group, cfg.data_port) if multicast else client._cmd.getsockname()
        for _ in range(20):
            intruder.sendto(fake, dest)
        intruder.close()
        assert wait_until(lambda: client.stats.foreign >= 20, 2.0)
        frames = client.stats.frames
        assert wait_until(lambda: client.stats.frames > frames + 3, 2.0)          # the real stream goes on
        assert client.get().rigid_body(1).position != (9.0, 9.0, 9.0)
        assert client.stats.discontinuities == 0
