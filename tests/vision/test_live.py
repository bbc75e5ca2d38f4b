"""The live camera source: a tracker thread with a newest-only hand-off, fed from a video file."""
import dataclasses
import time

import numpy as np
import pytest

from targetlock.interfaces.rigfile import ObservationSourceConfig
from targetlock.model.camera import CameraParams
from targetlock.vision.live import CameraObservations
from targetlock.vision.render import PlanarTarget, Renderer, make_pose
from targetlock.vision.sources import CaptureSource, write_video

CAM = CameraParams()


def test_camera_source_tracks_a_recorded_video_and_hands_over_only_the_newest(tmp_path):
    target = PlanarTarget.mucosa(size_m=(0.3, 0.3), seed=2, texture_px=1024)
    r = Renderer(CAM, target=target, seed=2)
    cam_pose = np.eye(4)
    frames, truths = [], []
    for k in range(40):  # the target slides 2 mm per frame to the right, 12 cm away
        pose = make_pose((0.002 * k - 0.04, 0.0, 0.12))
        f = r.render(cam_pose, pose, point_m=(0.04, 0.0))
        frames.append(f.image)
        truths.append(f.truth_offset(CAM))
    video = write_video(tmp_path / "v.avi", frames, fps=22, codec="MJPG")
    src = CameraObservations(ObservationSourceConfig(kind="camera", device=str(video), window_px=80), CAM)
    try:
        deadline = time.monotonic() + 20
        while src.frames < 40 and time.monotonic() < deadline:
            time.sleep(0.01)
        got = src.poll(1e9)
    finally:
        src.close()
    assert src.frames == 40
    assert len(got) == 1 and got[0].frame_index == 39           # newest only, no backlog
    assert got[0].valid
    assert np.hypot(*(got[0].offset - truths[-1])) < 3.0       # MJPG compression costs a little accuracy
    assert src.poll(1e9) == []                                  # handed over once


def tracked_video(tmp_path, n=30, fps=15.0):
    target = PlanarTarget.mucosa(size_m=(0.3, 0.3), seed=2, texture_px=512)
    r = Renderer(CAM, target=target, seed=2)
    frames = [r.render(np.eye(4), make_pose((0.001 * k - 0.02, 0.0, 0.12)), point_m=(0.02, 0.0)).image
              for k in range(n)]
    return write_video(tmp_path / "v.avi", frames, fps=fps, codec="MJPG")


def collect(src, until, last_index):
    """What a loop polling on each arrival gets, up to frame ``last_index`` (or time ``until``)."""
    got = []
    while time.monotonic() < until and (not got or got[-1].frame_index < last_index):
        if src.wait_arrival(0.05):
            got.extend(src.poll(0.0))
    return got


def test_a_video_file_is_paced_at_its_frame_rate_and_stamped_on_the_loop_clock(tmp_path):
    video = tracked_video(tmp_path, n=20, fps=20.0)
    cam = dataclasses.replace(CAM, latency=0.3)
    src = CameraObservations(ObservationSourceConfig(kind="camera", device=str(video), window_px=80), cam)
    t0 = time.monotonic()
    src.start_clock(t0)                                     # loop time zero
    try:
        got = collect(src, t0 + 20, 19)
    finally:
        src.close()
    assert src.frames == 20 and got[-1].frame_index == 19
    idx = np.array([o.frame_index for o in got])
    cap = np.array([o.capture_time for o in got])
    arr = np.array([o.arrival_time for o in got])
    assert arr[-1] >= 19 / 20.0 - 0.05                      # paced: ~1 s of video takes ~1 s
    np.testing.assert_allclose(np.diff(cap), np.diff(idx) / 20.0, atol=1e-9)   # capture times at the file's rate
    age = arr - cap                                          # latency plus the tracking time
    assert np.all(age >= 0.3) and np.all(age < 0.3 + 0.5)
    assert -0.3 - 0.5 < cap[0] < 0.0                         # on the loop's clock, not thousands of s off
    c0 = cap[0] - idx[0] / 20.0                              # frame 0's capture time
    assert src.frame_log.frames == sum(c0 + k / 20.0 >= 0.0 for k in range(20))   # counted from loop time zero


class FakeDevice(CaptureSource):
    """A capture device: frames grabbed now, stamped with the monotonic clock (as OpenCV's is)."""

    def __init__(self, image, fps):
        self.image, self.fps, self.k, self._cap = image, fps, 0, None
        self.w0 = time.monotonic()
        self.grabs: list[float] = []          # the stamp of each frame handed out (monotonic s)

    def read(self):
        self.k += 1
        time.sleep(max(0.0, self.w0 + self.k / self.fps - time.monotonic()))
        if self.k > 10:
            return False, None, time.monotonic()
        self.grabs.append(time.monotonic())
        return True, self.image, self.grabs[-1]


def test_a_capture_device_frame_carries_its_grab_time_minus_the_video_latency(tmp_path):
    r = Renderer(CAM, target=PlanarTarget.mucosa(size_m=(0.3, 0.3), seed=2, texture_px=512), seed=2)
    image = r.render(np.eye(4), make_pose((0.0, 0.0, 0.12))).image
    cam = dataclasses.replace(CAM, latency=0.25)
    t0 = time.monotonic()
    device = FakeDevice(image, fps=20.0)
    src = CameraObservations(ObservationSourceConfig(kind="camera", device="0", window_px=80), cam, source=device)
    src.start_clock(t0)
    try:
        got = collect(src, t0 + 5, 9)
    finally:
        src.close()
    assert got and src.live
    for o in got:
        # the device's own stamp of that frame, on the loop clock, minus the latency (not when the thread got to
        # it: on a loaded host the device's reads wake late, which moves the stamps, not this relation)
        grab = device.grabs[o.frame_index] - t0
        assert o.capture_time == pytest.approx(grab - 0.25, abs=1e-9)
        assert 0.0 <= o.arrival_time - grab < 0.3             # tracked right after the grab
