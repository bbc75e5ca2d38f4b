"""The fault matrix (issue 11): hostile or careless inputs and faults, as a new user produces them.

Every expected failure must end in one clear line on stderr naming the field / file / port and what
is allowed or what to do, a non-zero exit code of its class (2 config, 3 file, 4 device), no
traceback (``-v`` adds it), no run folder when refused up front, and the run folder and its data
kept when the failure happens mid-run.
"""
from __future__ import annotations

import errno
import importlib.util
import os
import signal
import socket
import time
from pathlib import Path

import pytest

from targetlock.cli import main
from targetlock.errors import ConfigError, DeviceError, InputFileError, OutputError, as_user_error


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)       # default run folders land in tmp_path/runs


def fail(argv: list[str], capsys, code: int) -> str:
    """Run the CLI expecting exit ``code``; return its one-line (or listed) error message."""
    assert main(argv) == code
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("targetlock ")]
    assert len(lines) == 1, err
    return err[err.index(lines[0]):]


# ------------------------------------------------------------------------------------------ option values
@pytest.mark.parametrize("argv, names", [
    (["step-response", "--i-values", "-5"], ["controller.i_gain = -5.0", "allowed: [-1.0, 100000.0]"]),
    (["step-response", "--i-values", "0"], ["controller.i_gain and controller.p_gain are both 0"]),
    (["step-response", "--i-values", "1e9"], ["controller.i_gain = 1000000000.0", "allowed"]),
    (["hysteresis", "--speed", "0"], ["sweep_speed_deg_s = 0.0", "[0.1, 90.0] deg/s"]),
    (["hysteresis", "--sample-rate", "0"], ["sample_rate = 0.0", "[10.0, 10000.0] Hz"]),
    (["compare", "--latencies", "-1"], ["twin.camera.latency = -1.0", "[0.0, 5.0] s"]),
    (["latency", "--inject-frame", "100000"], ["inject_frame = 100000", "[1, 1000]"]),
    (["sim-rig", "--duration", "-1"], ["duration = -1.0", "allowed"]),
    (["vision-eval", "--seed", "-1"], ["seed[0] = -1", "[0, 4294967295]"]),
    (["run", "--tracker", "marker"], ["--tracker marker needs vision"]),
    (["run", "--seconds", "1"], ["loop.metrics_after = 2 s", "loop.seconds = 1 s"]),
    (["run", "--set", "twin.camera.cx=5000"], ["twin.camera.cx = 5000", "outside the image"]),
    (["run", "--set", "twin.scene.start_tip_deg=[1, 2, 3]"], ["start_tip_deg = [1, 2, 3] needs exactly 2 values"]),
    (["run", "--set", "twin.scene.start_tip_deg=[]"], ["start_tip_deg = [] needs exactly 2 values"]),
    (["run", "--set", "twin.scene.step_offset_px=[5.0]"], ["step_offset_px = [5.0] needs exactly 2 values"]),
    (["run", "--set", "twin.scene.ellipse_size=[0.1]"], ["ellipse_size = [0.1] needs exactly 2 values"]),
    (["run", "--set", "twin=5"], ["twin must be a table"]),
    (["run", "--set", "loop.rat=50"], ["unknown setting loop.rat"]),
    (["run", "--set", "loop.rate"], ["expected SECTION.FIELD=VALUE"]),
    (["run", "--fps", "0", "--latency", "-1"], ["twin.camera.fps = 0.0", "twin.camera.latency = -1.0"]),
])
def test_bad_option_values_get_the_config_error(argv, names, capsys, tmp_path):
    msg = fail(argv, capsys, 2)
    for n in names:
        assert n in msg
    assert not (tmp_path / "runs").exists(), "a refused command must not leave a run folder"


def test_every_config_field_is_settable_from_the_command_line(capsys, tmp_path):
    assert main(["run", "--seconds", "3", "--set", "loop.metrics_after=0.5", "--set", "twin.camera.fps=30",
                 "--out", "r", "-q"]) == 0
    text = (tmp_path / "r" / "config.toml").read_text()
    assert "fps = 30.0" in text and "metrics_after = 0.5" in text


# ------------------------------------------------------------------------------------------ config files
def test_a_config_file_reports_all_its_problems_at_once(capsys, tmp_path):
    (tmp_path / "bad.toml").write_text('twin = 5\n[loop]\nseconds = "x"\nrate = 0\nbogus = 1\n')
    msg = fail(["run", "--config", "bad.toml"], capsys, 2)
    assert "--config bad.toml: 4 problems" in msg
    for part in ("twin must be a table", "loop.seconds must be a number", "loop.rate = 0.0", "unknown setting loop.bogus"):
        assert part in msg


@pytest.mark.parametrize("make, expect", [
    (lambda p: None, "no such file"),
    (lambda p: p.mkdir(), "is a folder"),
    (lambda p: p.write_bytes(b"\xff\xfe[loop]\n"), "not UTF-8"),
    (lambda p: p.write_text("[loop\n"), "not valid TOML"),
])
@pytest.mark.parametrize("flag", ["--config", "--rig"])
def test_unreadable_config_and_rig_files_name_the_file(make, expect, flag, capsys, tmp_path):
    make(tmp_path / "f.toml")
    code = 2 if expect == "not valid TOML" else 3
    msg = fail(["run", flag, "f.toml"], capsys, code)
    assert "f.toml" in msg and expect in msg
    assert not (tmp_path / "runs").exists()


# ------------------------------------------------------------------------------------------ outputs
def test_out_on_an_earlier_run_is_refused_unless_overwrite(capsys, tmp_path):
    argv = ["run", "--seconds", "3", "--set", "loop.metrics_after=0", "--out", "r", "-q"]
    assert main(argv) == 0
    before = (tmp_path / "r" / "timeseries.csv").read_bytes()
    msg = fail(argv, capsys, 3)
    assert "--out r: holds an earlier run" in msg and "--overwrite" in msg
    assert (tmp_path / "r" / "timeseries.csv").read_bytes() == before      # the earlier run is intact
    assert main([*argv, "--overwrite"]) == 0


@pytest.mark.parametrize("out, expect", [("afile", "is a file"), ("afile/sub", "cannot create the run folder"),
                                         ("notrun", "not a run folder")])
def test_out_that_cannot_be_a_run_folder_is_refused(out, expect, capsys, tmp_path):
    (tmp_path / "afile").write_text("x")
    (tmp_path / "notrun").mkdir()
    (tmp_path / "notrun" / "thesis.tex").write_text("precious")
    msg = fail(["run", "--seconds", "3", "--out", out], capsys, 3)
    assert expect in msg
    assert (tmp_path / "notrun" / "thesis.tex").read_text() == "precious"


def test_unwritable_video_is_refused_before_any_work(capsys, tmp_path):
    t0 = time.perf_counter()
    msg = fail(["run", "--vision", "--video", "no/such/dir/v.mp4", "--seconds", "3"], capsys, 3)
    assert "--video no/such/dir/v.mp4" in msg and "does not exist" in msg
    assert time.perf_counter() - t0 < 5.0 and not (tmp_path / "runs").exists()


# ------------------------------------------------------------------------------------------ waypoint CSVs
def _csv(path: Path, text: str, bom: bool = False) -> Path:
    path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode())
    return path


@pytest.mark.parametrize("t1", ["nan", "inf", "-inf"])
def test_non_finite_waypoint_time_is_refused_and_leaves_no_run_folder(t1, capsys, tmp_path):
    _csv(tmp_path / "w.csv", f"t,x,y,z\n0,0,0,0\n{t1},0.01,0,0\n")
    msg = fail(["run", "--path", "w.csv", "--out", "r"], capsys, 2)
    assert "waypoints_file" in msg and "not finite" in msg and "row 3" in msg
    assert not (tmp_path / "r").exists()


def test_waypoint_csv_with_bom_is_copied_and_a_rerun_of_the_folder_gives_the_same_result(capsys, tmp_path):
    src = _csv(tmp_path / "w.csv", "t,x,y,z\n0,0,0,0\n2,0.02,0,0\n4,0.0,0.01,0\n", bom=True)
    common = ["--seconds", "5", "--json", "-q"]
    assert main(["run", "--path", "w.csv", "--out", "a", *common]) == 0
    first = capsys.readouterr().out.splitlines()[-1]
    copy = tmp_path / "a" / "inputs" / "w.csv"
    assert copy.read_bytes() == src.read_bytes()
    assert str(copy.resolve()) in (tmp_path / "a" / "config.toml").read_text()
    src.write_text("t,x,y,z\n0,0,0,0\n1,0.05,0.05,0\n")       # the original changes afterwards
    assert main(["run", "--config", "a/config.toml", "--out", "b", *common]) == 0
    second = capsys.readouterr().out.splitlines()[-1]
    strip = lambda line: {k: v for k, v in __import__("json").loads(line).items()
                          if k not in ("wall_seconds", "realtime_factor", "run_folder", "timing_ms")}
    assert strip(first) == strip(second)


# ------------------------------------------------------------------------------------------ devices
def _twin_process_helpers():
    spec = importlib.util.spec_from_file_location("twin_process_helpers",
                                                  Path(__file__).parent / "rig" / "test_twin_process.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_no_natnet_server_is_one_line_and_keeps_the_run_folder(capsys, tmp_path):
    rig = _twin_process_helpers().rig_file(tmp_path / "rig.toml")
    msg = fail(["run", "--rig", str(rig), "--seconds", "3", "--out", "r"], capsys, 4)
    assert "no NAT_SERVERINFO from 127.0.0.1" in msg and "run folder kept: r" in msg
    assert (tmp_path / "r" / "config.toml").exists() and (tmp_path / "r" / "run.log").exists()


def test_port_in_use_names_the_ports(capsys, tmp_path):
    rig = _twin_process_helpers().rig_file(tmp_path / "rig.toml")
    text = rig.read_text()
    port = int(text.split("command_port = ")[1].split()[0])
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", port))
        msg = fail(["sim-rig", "--rig", str(rig), "--duration", "5"], capsys, 4)
    assert "port in use" in msg and str(port) in msg


def test_sim_rig_dying_mid_run_is_one_line_with_the_data_kept(capsys, tmp_path):
    helpers = _twin_process_helpers()
    rig = helpers.rig_file(tmp_path / "rig.toml")
    with helpers.sim_rig("--rig", str(rig), "--duration", "60") as proc:
        import threading
        threading.Timer(4.0, lambda: os.kill(proc.pid, signal.SIGKILL)).start()
        msg = fail(["run", "--rig", str(rig), "--seconds", "30", "--out", "r"], capsys, 4)
    assert msg.count("\n") <= 1 and "drives:" in msg and "run folder kept: r" in msg
    rows = (tmp_path / "r" / "timeseries.csv").read_text().splitlines()
    assert len(rows) > 50          # what was recorded before the peer died is on disk
    assert "ERROR" in (tmp_path / "r" / "run.log").read_text()


def test_verbose_shows_the_traceback(capsys, tmp_path):
    assert main(["run", "-v", "--config", "missing.toml"]) == 3
    err = capsys.readouterr().err
    assert "missing.toml: no such file" in err and "Traceback" in err


@pytest.mark.parametrize("exc, cls, text", [
    (OSError(errno.EADDRINUSE, "Address already in use"), DeviceError, "port already in use"),
    (OSError(errno.ENODEV, "No such device"), DeviceError, "no such device"),
    (OSError(errno.EADDRNOTAVAIL, "Cannot assign requested address"), DeviceError, "local_ip"),
    (ConnectionError("no answer from 10.0.0.1:1510"), DeviceError, "10.0.0.1:1510"),
    (FileNotFoundError(errno.ENOENT, "No such file", "x.csv"), InputFileError, "x.csv"),
    (PermissionError(errno.EACCES, "Permission denied", "/root/x"), OutputError, "/root/x"),
    (b"\xff".decode("utf-8", "replace") and UnicodeDecodeError("utf-8", b"\xff", 0, 1, "invalid start byte"),
     InputFileError, "not UTF-8"),
])
def test_library_exceptions_map_to_one_clear_line(exc, cls, text):
    err = as_user_error(exc)
    assert isinstance(err, cls) and text in str(err) and "\n" not in str(err)


def test_bus_and_drive_exceptions_map_to_device_errors():
    import can
    from canopen.sdo.exceptions import SdoAbortedError

    from targetlock.interfaces.natnet import NatNetParseError
    from targetlock.rig.base import DriveFault
    for exc in (can.CanOperationError("bus off"), SdoAbortedError(0x06090030), DriveFault("node 1: NMT stopped"),
                NatNetParseError("server speaks NatNet 2.10; 3.x or 4.x supported")):
        assert isinstance(as_user_error(exc), DeviceError), exc


def test_a_bug_is_not_hidden():
    assert as_user_error(ZeroDivisionError("x")) is None
    assert as_user_error(KeyError("x")) is None
    assert isinstance(as_user_error(ConfigError("a = 1 is out of range")), ConfigError)


# ------------------------------------------------------------------------------------------ logging
def test_run_log_and_quiet(capsys, tmp_path):
    assert main(["run", "--seconds", "3", "--set", "loop.metrics_after=0", "--out", "r", "-q"]) == 0
    assert " INFO " not in capsys.readouterr().err
    log = (tmp_path / "r" / "run.log").read_text()
    assert " INFO targetlock" in log and "run finished" in log


def test_sim_rig_without_rig_serves_the_loopback_rig_of_the_example():
    """`sim-rig` with no --rig must serve what its help promises (udp_loopback, NatNet on 127.0.0.1),
    which is what `run --rig examples/twin_rig.toml` connects to, not socketcan can0."""
    from targetlock.commands import LOOPBACK_RIG
    from targetlock.config import from_dict
    from targetlock.interfaces.rigfile import HardwareRigConfig, load_rig_file
    default = from_dict(HardwareRigConfig, LOOPBACK_RIG)
    assert default.can.bus.interface == "udp_loopback" and default.natnet.server_ip == "127.0.0.1"
    assert default == load_rig_file(Path(__file__).parent.parent / "examples" / "twin_rig.toml")
