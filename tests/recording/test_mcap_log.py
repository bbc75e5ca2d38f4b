"""run.mcap read back with the mcap reader: schemas, counts, monotonic times, values equal to the CSV,
poses consistent with the recorded image error, and a killed writer keeps what it flushed."""
from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from mcap.reader import NonSeekingReader, make_reader

from targetlock.cli import main
from targetlock.model.camera import CameraParams, project
from targetlock.model.kinematics import tip_pose


def _messages(path, topic):
    with open(path, "rb") as fh:
        return [(m.log_time, json.loads(m.data)) for _, _, m in make_reader(fh).iter_messages(topics=[topic])]


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    run = tmp_path_factory.mktemp("run") / "r"
    assert main(["run", "--seconds", "4", "--path", "ellipse", "--out", str(run)]) == 0
    live = run / "live.mcap"
    (run / "run.mcap").rename(live)          # as a run folder from before MCAP recording
    assert main(["export", str(run)]) == 0
    return run


def test_a_run_writes_its_rows_to_run_mcap_as_it_goes(exported):
    csv = np.loadtxt(exported / "timeseries.csv", delimiter=",", skiprows=1)
    live = _messages(exported / "live.mcap", "/timeseries")
    exp = _messages(exported / "run.mcap", "/timeseries")
    assert len(live) == len(csv) == len(exp)
    live_tf, exp_tf = _messages(exported / "live.mcap", "/tf"), _messages(exported / "run.mcap", "/tf")
    assert len(live_tf) == len(exp_tf) == 2 * len(csv)     # the run writes the scene of every row too
    for (t_live, m_live), (t_exp, m_exp) in zip(live, exp):
        assert t_live == t_exp
        for c, v in m_live.items():       # the CSV (and so the export) keeps 9 significant digits
            assert (v is None and m_exp[c] is None) or v == pytest.approx(m_exp[c], rel=1e-8, abs=1e-12)


def test_export_has_foxglove_schemas_and_one_message_per_row(exported):
    csv = np.loadtxt(exported / "timeseries.csv", delimiter=",", skiprows=1)
    with open(exported / "run.mcap", "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        schemas = {s.name for s in summary.schemas.values()}
        counts = {c.topic: summary.statistics.channel_message_counts[i] for i, c in summary.channels.items()}
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert {"foxglove.FrameTransform", "foxglove.CameraCalibration", "targetlock.timeseries"} <= schemas
    assert counts["/timeseries"] == len(csv)
    assert counts["/tf"] == 2 * len(csv)                     # base → tip and base → target each tick
    assert meta["config"]["config.toml"] == (exported / "config.toml").read_text()


def test_rows_equal_the_csv_with_monotonic_times(exported):
    header = (exported / "timeseries.csv").read_text().splitlines()[0].split(",")
    csv = np.loadtxt(exported / "timeseries.csv", delimiter=",", skiprows=1)
    msgs = _messages(exported / "run.mcap", "/timeseries")
    times = np.array([t for t, _ in msgs])
    assert np.all(np.diff(times) > 0)
    np.testing.assert_allclose(times / 1e9, csv[:, 0], atol=1e-9)
    for (_, m), row in zip(msgs, csv):
        for c, v in zip(header, row):
            assert (m[c] is None and not math.isfinite(v)) or m[c] == pytest.approx(v, rel=1e-12, abs=1e-12)


def test_poses_reproduce_the_recorded_image_error(exported):
    """Projecting the target through the recorded base→tip and base→target poses gives the error the
    CSV recorded: the 3D scene in Foxglove shows what the camera saw."""
    header = (exported / "timeseries.csv").read_text().splitlines()[0].split(",")
    csv = np.loadtxt(exported / "timeseries.csv", delimiter=",", skiprows=1)
    tf = _messages(exported / "run.mcap", "/tf")
    tips = {t: m for t, m in tf if m["child_frame_id"] == "tip"}
    targets = {t: m for t, m in tf if m["child_frame_id"] == "target"}
    cam = CameraParams()
    from scipy.spatial.transform import Rotation
    checked = 0
    for row in csv[::25]:
        ns = int(round(row[0] * 1e9))
        tip, target = tips[ns], targets[ns]
        q = tip["rotation"]
        r = Rotation.from_quat([q["x"], q["y"], q["z"], q["w"]]).as_matrix()
        p = np.array([target["translation"][k] for k in "xyz"]) - np.array([tip["translation"][k] for k in "xyz"])
        px = project(r.T @ p, cam) - [cam.cx, cam.cy]
        err = row[[header.index("err_x"), header.index("err_y")]]
        if np.all(np.isfinite(err)):
            np.testing.assert_allclose(px, err, atol=0.05)
            checked += 1
        # and base → tip is the chained kinematics of the recorded tip angles
        pose = tip_pose(math.radians(row[header.index("tip_x_deg")]), math.radians(row[header.index("tip_y_deg")]),
                        0.12, 30)
        np.testing.assert_allclose(r, pose[:3, :3], atol=1e-9)
    assert checked > 5


def test_export_refuses_to_overwrite_and_non_run_folders(exported, tmp_path, capsys):
    before = (exported / "run.mcap").read_bytes()
    assert main(["export", str(exported)]) == 2
    assert "exists already" in capsys.readouterr().err
    assert (exported / "run.mcap").read_bytes() == before
    assert main(["export", str(tmp_path)]) == 2
    assert "not a run folder" in capsys.readouterr().err


def test_a_killed_writer_keeps_what_it_flushed(tmp_path):
    path = tmp_path / "killed.mcap"
    script = textwrap.dedent(f"""
        import sys, time
        from targetlock.recording import McapLog
        log = McapLog({str(path)!r}, flush_seconds=0.05)
        for k in range(200):
            log.row("/timeseries", k * 0.02, ["t", "err"], [k * 0.02, float(k)])
        log.flush()
        print("flushed", flush=True)
        time.sleep(60)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "flushed"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        proc.kill()
    got = []
    with open(path, "rb") as fh:
        try:
            for _, _, m in NonSeekingReader(fh).iter_messages(log_time_order=False):
                got.append(json.loads(m.data)["err"])
        except Exception:           # the file ends where the process died: no footer
            pass
    assert got == [float(k) for k in range(200)]


def test_a_vision_run_records_its_frames_with_annotations(tmp_path):
    run = tmp_path / "v"
    assert main(["run", "--vision", "--seconds", "3", "--out", str(run)]) == 0
    images = _messages(run / "run.mcap", "/camera/image")
    notes = _messages(run / "run.mcap", "/camera/annotations")
    summary = json.loads((run / "summary.json").read_text())
    assert len(images) == len(notes) == summary["vision"]["frames"] > 30
    import base64
    import cv2
    img = cv2.imdecode(np.frombuffer(base64.b64decode(images[-1][1]["data"]), np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (576, 720, 3) and images[-1][1]["format"] == "jpeg"
    assert notes[-1][1]["circles"], "the tracked target is drawn on the last frame"


def test_quaternions_match_scipy_for_rotations_of_every_kind():
    from scipy.spatial.transform import Rotation

    from targetlock.recording.mcap_log import quaternion
    rots = Rotation.random(200, random_state=4)
    extra = Rotation.from_rotvec([[np.pi, 0, 0], [0, np.pi, 0], [0, 0, np.pi], [0, 0, 0]])   # trace <= 0 branches
    for r in list(rots) + list(extra):
        q = np.array(quaternion(r.as_matrix()))
        ref = r.as_quat()
        assert min(np.abs(q - ref).max(), np.abs(q + ref).max()) < 1e-9
