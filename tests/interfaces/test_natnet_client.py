"""NatNet client against the simulated NatNet server on loopback (multicast with TTL 0, and unicast)."""
from __future__ import annotations

import socket
import struct
import threading
import time

import numpy as np
import pytest

from targetlock.interfaces.mocap import MocapBendingSensor, rotation_to_quaternion
from targetlock.interfaces.natnet import LatestSample, NatNetClient, NatNetConfig
from targetlock.interfaces.sim_natnet import SimNatNetConfig, SimNatNetServer
from targetlock.model.kinematics import tip_pose

from iface_helpers import free_udp_port, wait_until

PHI = (0.31, -0.22)


def base_pose():
    b = np.eye(4)
    c, s = np.cos(0.4), np.sin(0.4)
    b[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]      # base turned about the vertical
    b[:3, 3] = (0.25, -0.1, 1.2)
    return b


def poses():
    b = base_pose()
    return b, b @ tip_pose(PHI[0], PHI[1], 0.05, 30)


def pair(multicast=True, version="4.1", client_version="auto", **server_kw):
    port = free_udp_port()
    source = server_kw.pop("source", poses)
    srv = SimNatNetServer(SimNatNetConfig(command_port=0, data_port=port, multicast=multicast, version=version,
                                          **server_kw), source)
    cfg = NatNetConfig(command_port=srv.command_port, data_port=port, multicast=multicast, version=client_version)
    return srv, cfg


@pytest.mark.parametrize("multicast", [True, False], ids=["multicast", "unicast"])
@pytest.mark.parametrize("version", ["3.1", "4.0", "4.1"])
def test_poses_arrive_within_float32_precision(multicast, version):
    tip_pose(0.1, 0.1, 0.05, 30)                  # compile the kinematics before streaming starts
    srv, cfg = pair(multicast, version, rate_hz=200, extras=True)
    with srv, NatNetClient(cfg) as client:
        assert client.version == tuple(int(x) for x in version.split("."))
        assert client.clock_hz == 10_000_000
        assert wait_until(lambda: client.stats.frames >= 5, 2.0)
        sample = client.get()
        assert sample is not None
        b, t = poses()
        for rid, pose in ((1, b), (2, t)):
            body = sample.rigid_body(rid)
            assert body.tracking_valid
            assert body.position == tuple(np.float32(pose[:3, 3]).tolist())
            assert body.orientation == tuple(np.float32(rotation_to_quaternion(pose)).tolist())
        sensor = MocapBendingSensor(client, 1, 2)
        m = sensor.read()
        assert m is not None
        assert np.allclose(m.angles, PHI, atol=2e-6)
        assert 0.004 <= sample.latency < 0.1         # the frame leaves >= 4 ms after mid-exposure
        # the mid-exposure stamp mapped through the echo clock sync is the true exposure time
        assert sample.capture_time == pytest.approx(srv.ticks_to_local(sample.frame.camera_mid_exposure), abs=2e-3)
        assert sample.capture_time < sample.received_at
        assert client.stats.malformed == 0
        if not multicast:
            assert srv.stats.connects == 1


def test_latest_sample_slot_keeps_only_the_newest():
    slot: LatestSample[int] = LatestSample()
    assert slot.get() is None
    for k in range(1000):
        slot.put(k)
    assert slot.get() == 999 and slot.sequence == 1000
    assert slot.wait_newer(1000, 0.01) is None
    threading.Timer(0.02, slot.put, args=(5,)).start()
    assert slot.wait_newer(1000, 1.0) == (1001, 5)


def test_newest_only_handoff_to_a_slow_consumer():
    srv, cfg = pair(rate_hz=500)
    with srv, NatNetClient(cfg) as client:
        assert wait_until(lambda: client.stats.frames > 0, 2.0)
        numbers = []
        for _ in range(8):
            # a loop much slower than the stream: at least 5 frames arrive between two looks (counted, not a fixed
            # sleep: a loaded host can stall the streaming thread for longer than the loop's period)
            n = client.stats.frames
            assert wait_until(lambda: client.stats.frames >= n + 5, 5.0)
            numbers.append(client.latest.get().frame.frame_number)
        assert min(b - a for a, b in zip(numbers, numbers[1:])) >= 5     # skipped straight to the newest
        # the slot never lags the receive thread by more than one frame (read once the stream has stopped: while
        # it runs the receive thread may take several frames between the two reads)
        srv.stop()
        time.sleep(0.1)
        assert abs(client.latest.sequence - client.stats.frames) <= 1


def test_packet_loss_is_counted():
    received = []
    srv, cfg = pair(rate_hz=400, loss=0.2, seed=3, max_frames=400)
    client = NatNetClient(cfg, on_sample=lambda s: received.append(s.frame.frame_number))
    with srv, client:
        assert srv.finished.wait(5.0)
        time.sleep(0.05)
    assert srv.stats.dropped and received
    first, last = received[0], received[-1]
    dropped_inside = [n for n in srv.stats.dropped if first < n < last]
    assert client.stats.lost == len(dropped_inside)
    assert len(dropped_inside) > 20
    assert received == sorted(set(range(first, last + 1)) - set(srv.stats.dropped))


def test_jitter_keeps_frames_flowing_and_accounted():
    received = []
    srv, cfg = pair(rate_hz=200, jitter=0.004, seed=1, max_frames=200)
    client = NatNetClient(cfg, on_sample=lambda s: received.append((time.monotonic(), s.frame.frame_number)))
    with srv, client:
        assert srv.finished.wait(5.0)
        time.sleep(0.05)
    st = client.stats
    assert st.frames + st.lost + st.out_of_order >= len(received) > 100
    gaps = np.diff([t for t, _ in received])
    assert gaps.std() > 0.0005                  # arrival times really jitter


def test_garbage_on_the_wire_is_counted_and_skipped():
    srv, cfg = pair(rate_hz=200)
    with srv, NatNetClient(cfg) as client:
        assert wait_until(lambda: client.stats.frames > 2, 2.0)
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
        tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
        rng = np.random.default_rng(0)
        for k in range(50):
            junk = struct.pack("<HH", 7, 500) + rng.integers(0, 256, int(rng.integers(0, 300)), np.uint8).tobytes()
            tx.sendto(junk, (cfg.multicast_group, cfg.data_port))
        tx.close()
        frames = client.stats.frames
        assert wait_until(lambda: client.stats.malformed == 50, 2.0)
        assert wait_until(lambda: client.stats.frames > frames + 5, 2.0)   # the stream goes on


def test_untracked_bodies_give_no_angles():
    srv, cfg = pair(rate_hz=200, source=lambda: None)
    with srv, NatNetClient(cfg) as client:
        assert wait_until(lambda: client.get() is not None, 2.0)
        assert not client.get().rigid_body(1).tracking_valid
        assert MocapBendingSensor(client, 1, 2).read() is None


def test_stale_sample_is_not_returned():
    srv, cfg = pair(rate_hz=200)
    with srv, NatNetClient(cfg) as client:
        assert wait_until(lambda: client.get() is not None, 2.0)
        srv.stop()                                 # Motive stops streaming
        time.sleep(cfg.max_sample_age + 0.02)
        assert client.get() is None
        assert client.latest.get() is not None


def test_connect_timeout_without_server():
    port = free_udp_port()
    cfg = NatNetConfig(command_port=port, data_port=free_udp_port(), connect_timeout=0.2)
    t0 = time.monotonic()
    with pytest.raises(ConnectionError, match="NAT_SERVERINFO"):
        NatNetClient(cfg).start()
    assert time.monotonic() - t0 < 1.5


