"""The driver against simulated drives running in another process, over the loopback UDP CAN bus."""
from __future__ import annotations

import os
import random
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import targetlock
from targetlock.interfaces.canbus import CanBusConfig, udp_loopback_problem
from targetlock.interfaces.cia402 import CanopenDrives, CanopenRigConfig
from targetlock.interfaces.od402 import State

from iface_helpers import free_udp_port

SRC = str(Path(targetlock.__file__).resolve().parent.parent)


def read_line(proc: subprocess.Popen, timeout: float) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            break
        ready, _, _ = select.select([proc.stdout], [], [], 0.1)
        if ready:
            return proc.stdout.readline()
    return ""


def test_driver_and_sim_drives_in_separate_processes():
    group = f"239.255.{random.randint(100, 250)}.{random.randint(1, 250)}"
    port = free_udp_port()
    problem = udp_loopback_problem(group, port)
    if problem:
        pytest.skip(problem)
    env = dict(os.environ, PYTHONPATH=SRC + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen(
        [sys.executable, "-m", "targetlock.interfaces.sim_cia402", "--interface", "udp_loopback", "--channel", group,
         "--port", str(port), "--nodes", "3", "4", "--duration", "40", "--initial-angle", "0.03", "-0.02",
         "--encoder-offset", "1000", "2000", "--quiet"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = read_line(proc, 30.0)
        assert "sim-rig ready" in line, f"simulated drives did not start: {line!r} {proc.stderr.read() if proc.poll() is not None else ''}"
        cfg = CanopenRigConfig(bus=CanBusConfig(interface="udp_loopback", channel=group, port=port), node_ids=(3, 4),
                               homing_method=21, heartbeat_period=0.05, heartbeat_timeout=0.5,
                               setpoint_ack_timeout=0.1, drive_consumer_timeout=1.0, sdo_timeout=0.5,
                               status_timeout=0.2)
        with CanopenDrives(cfg) as drives:
            assert drives.states() == [State.OPERATION_ENABLED] * 2
            drives.home()
            assert np.all(np.abs(drives.positions()) <= 25)
            target = np.array([6000, -4000])
            drives.send_setpoints(target)
            deadline = time.monotonic() + 3.0
            while time.monotonic() < deadline and np.any(np.abs(drives.positions() - target) > 25):
                time.sleep(0.01)
            assert np.all(np.abs(drives.positions() - target) <= 25)
            assert drives.stats["pdo_position_reads"] > 0
            # the drive process dies: heartbeat loss
            proc.send_signal(signal.SIGKILL)
            proc.wait(5)
            t0 = time.monotonic()
            while drives.fault() is None and time.monotonic() - t0 < 3.0:
                time.sleep(0.005)
            # the status PDOs stop first (status_timeout), the heartbeat a little later
            assert drives.fault() is not None and ("heartbeat lost" in drives.fault()
                                                   or "no status PDO" in drives.fault())
            assert time.monotonic() - t0 <= cfg.heartbeat_timeout + 0.3
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(5)
        proc.stdout.close()
        proc.stderr.close()


def test_sim_rig_command_streams_the_tip_pose_of_the_driven_handles():
    """`targetlock sim-rig --mocap` end to end: the driver moves the handles, NatNet shows the bend."""
    from targetlock.interfaces.mocap import MocapBendingSensor
    from targetlock.interfaces.natnet import NatNetClient, NatNetConfig

    group = f"239.255.{random.randint(100, 250)}.{random.randint(1, 250)}"
    port, cmd_port, data_port = free_udp_port(), free_udp_port(), free_udp_port()
    problem = udp_loopback_problem(group, port)
    if problem:
        pytest.skip(problem)
    env = dict(os.environ, PYTHONPATH=SRC + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen(
        [sys.executable, "-m", "targetlock.interfaces.sim_cia402", "--channel", group, "--port", str(port),
         "--duration", "40", "--quiet", "--mocap", "--bend-ratio", "0.5", "--mocap-rate", "200",
         "--mocap-command-port", str(cmd_port), "--mocap-data-port", str(data_port), "--mocap-group", group],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = read_line(proc, 30.0)
        assert "sim-rig ready" in line, f"sim-rig did not start: {line!r}"
        cfg = CanopenRigConfig(bus=CanBusConfig(interface="udp_loopback", channel=group, port=port),
                               heartbeat_period=0.05, heartbeat_timeout=0.5, setpoint_ack_timeout=0.1,
                               drive_consumer_timeout=1.0, sdo_timeout=0.5, status_timeout=0.2)
        ncfg = NatNetConfig(command_port=cmd_port, data_port=data_port, multicast_group=group, connect_timeout=5.0)
        with CanopenDrives(cfg) as drives, NatNetClient(ncfg) as client:
            drives.home()
            target = np.array([25000, -12500])            # handle angles 0.4 and -0.2 rad
            drives.send_setpoints(target)
            sensor = MocapBendingSensor(client, ncfg.base_body_id, ncfg.tip_body_id)
            want = 0.5 * target * cfg.rad_per_tick
            deadline = time.monotonic() + 3.0
            m = None
            while time.monotonic() < deadline:
                m = sensor.read()
                if m is not None and np.allclose(m.angles, want, atol=2e-3):
                    break
                time.sleep(0.02)
            assert m is not None and np.allclose(m.angles, want, atol=2e-3), (m, want)
            assert client.stats.malformed == 0
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(5)
            except subprocess.TimeoutExpired:
                proc.kill()
        proc.wait(5)
        proc.stdout.close()
        proc.stderr.close()
