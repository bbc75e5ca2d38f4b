"""The live camera source: a tracker thread with a newest-only hand-off, fed from a video file."""
import time

import numpy as np

from targetlock.interfaces.rigfile import ObservationSourceConfig
from targetlock.model.camera import CameraParams
from targetlock.vision.live import CameraObservations
from targetlock.vision.render import PlanarTarget, Renderer, make_pose
from targetlock.vision.sources import write_video

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
