"""`targetlock sim-rig` in another process + `run --rig`: the unchanged driver, NatNet client and loop on
the wall clock give the same lock as the in-process twin."""
from __future__ import annotations

import json
import os
import random
import select
import signal
import socket
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path

import pytest

import targetlock
from targetlock.cli import main
from targetlock.interfaces.canbus import udp_loopback_problem

SRC = str(Path(targetlock.__file__).resolve().parent.parent)
SECONDS = 14.0


def free_port(kind=socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rig_file(path: Path) -> Path:
    group = f"239.255.{random.randint(100, 250)}.{random.randint(1, 250)}"
    port = free_port()
    problem = udp_loopback_problem(group, port)
    if problem:
        pytest.skip(f"no CAN bus across processes here: {problem}")
    path.write_text(f"""
[can]
node_ids = [1, 2]
homing_method = 37
status_timeout = 0.5
heartbeat_timeout = 0.5
[can.bus]
interface = "udp_loopback"
channel = "{group}"
port = {port}
[natnet]
multicast = false
command_port = {free_port()}
data_port = {free_port()}
[observations]
kind = "mocap"
target_body_id = 3
""")
    return path


@contextmanager
def sim_rig(*args: str):
    """`targetlock sim-rig ARGS` in another process, ready on entry, stopped (SIGTERM) on exit."""
    env = dict(os.environ, PYTHONPATH=SRC + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, "-m", "targetlock", "sim-rig", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    try:
        ready, _, _ = select.select([proc.stdout], [], [], 30.0)
        line = proc.stdout.readline() if ready else ""
        if "sim-rig ready" not in line:
            proc.kill()
            pytest.fail(f"sim-rig did not start: {line!r} {proc.stderr.read()[-2000:]}")
        yield proc
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()


def test_run_against_the_twin_in_another_process_matches_the_in_process_twin(tmp_path, capsys):
    cfg = tmp_path / "run.toml"
    cfg.write_text("[twin.scene]\nstart_tip_deg = [0.0, 0.0]\n[controller]\nkind = \"pi-hc\"\n")
    rig = rig_file(tmp_path / "rig.toml")
    with sim_rig("--rig", str(rig), "--config", str(cfg), "--duration", str(SECONDS + 30)):
        assert main(["run", "--rig", str(rig), "--config", str(cfg), "--seconds", str(SECONDS),
                     "--out", str(tmp_path / "hw"), "--json"]) == 0
    hw = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert main(["run", "--config", str(cfg), "--seconds", str(SECONDS), "--out", str(tmp_path / "twin"), "--json"]) == 0
    twin = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert hw["rig"] == "hardware" and twin["rig"] == "twin"
    # Stated tolerance (docs/hardware.md): rms and peak within 10 %, tip range within 1 deg.
    assert hw["rms_px"] == pytest.approx(twin["rms_px"], rel=0.10)
    assert hw["peak_px"] == pytest.approx(twin["peak_px"], rel=0.10)
    assert hw["tip_range_deg"] == pytest.approx(twin["tip_range_deg"], abs=1.0)
    # A frame counts lost when the newest motion-capture sample is older than natnet.max_sample_age (0.1 s): a
    # loaded host can stall the streaming or receiving thread that long now and then (seen: 1 frame of 265).
    # A broken link or wrong bodies lose most frames.
    assert hw["lost_fraction"] <= 0.02
    t = hw["timing_ms"]
    assert t["frame_to_setpoint_p50"] < 25.0
    assert (tmp_path / "hw" / "rig.toml").exists()


def test_hysteresis_sweep_through_the_drives_and_natnet_matches_the_twin(tmp_path, capsys):
    rig = rig_file(tmp_path / "rig.toml")
    speed, rate = 60.0, 50.0  # deg/s of the handle, samples per second
    sweep = ["--held", "0", "--amplitudes", "40", "80", "--speed", str(speed), "--sample-rate", str(rate), "--json"]
    with sim_rig("--rig", str(rig), "--duration", "60"):
        assert main(["hysteresis", "--rig", str(rig), "--out", str(tmp_path / "hw"), *sweep]) == 0
    hw = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert main(["hysteresis", "--out", str(tmp_path / "twin"), *sweep]) == 0
    twin = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert hw["source"].startswith("rig") and (tmp_path / "hw" / "hysteresis.png").exists()
    a, b = hw["curves"][0], twin["curves"][0]
    assert a["hysteresis_width_deg"] == pytest.approx(b["hysteresis_width_deg"], abs=2.0)
    assert a["total_gain"] == pytest.approx(b["total_gain"], abs=0.03)
    # A reversal's stall ends at a sample: on the rig the samples are taken on the wall clock, and one
    # taken late on a loaded host moves that end by a sample, speed / rate = 1.2 deg (seen in CI: 15.08
    # against 17.08 deg; 16.3-16.4 in quiet runs). Within two samples.
    assert a["reversal_width_deg"] == pytest.approx(b["reversal_width_deg"], abs=2 * speed / rate)
