"""Frame sources: video file round trip, the twin's rendered source, capture device errors."""

import numpy as np
import pytest

from targetlock.vision import CaptureSource, RenderedSource, VideoFileSource, make_pose, write_video


def _frames(n=12, h=96, w=128):
    """Smooth, codec-friendly test frames: a bright square moving right by 4 px/frame."""
    out = []
    for i in range(n):
        f = np.full((h, w, 3), 40, np.uint8)
        f[30:60, 10 + 4 * i:40 + 4 * i] = (200, 180, 160)
        out.append(f)
    return out


@pytest.mark.parametrize("name,codec", [("clip.avi", "MJPG"), ("clip.mp4", "mp4v")])
def test_video_file_round_trip(tmp_path, name, codec):
    frames = _frames()
    path = write_video(tmp_path / name, frames, fps=22.0, codec=codec)
    assert path.stat().st_size > 0
    with VideoFileSource(path) as src:
        assert src.fps == pytest.approx(22.0, rel=1e-3)
        got = list(src)
        ok, frame, _ = src.read()
        assert not ok and frame is None                       # end of file
    assert len(got) == len(frames)
    times = np.array([t for _, t in got])
    np.testing.assert_allclose(np.diff(times), 1 / 22.0, rtol=1e-6)
    for (img, _), ref in zip(got, frames):
        assert img.shape == ref.shape and img.dtype == np.uint8
        assert np.abs(img.astype(int) - ref.astype(int)).mean() < 6.0  # lossy codec, same picture
    # the moving square is where it was written (centre of its bright columns)
    cols = [np.flatnonzero(img[45, :, 2] > 120).mean() for img, _ in got]
    np.testing.assert_allclose(cols, [25 + 4 * i for i in range(len(frames))], atol=1.0)


def test_video_file_source_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        VideoFileSource(tmp_path / "missing.mp4")
    bad = tmp_path / "not_a_video.mp4"
    bad.write_text("hello")
    with pytest.raises(RuntimeError):
        VideoFileSource(bad)


def test_rendered_source_follows_the_pose_callback(renderer):
    calls = []

    def poses(t):
        calls.append(t)
        return np.eye(4), make_pose((0.01 * t, 0.0, 0.05))

    src = RenderedSource(renderer, poses, fps=20.0, n_frames=4)
    out = list(src)
    assert [t for _, t in out] == pytest.approx([0.0, 0.05, 0.1, 0.15])
    assert src.last_frame is not None and src.last_frame.image is out[-1][0]
    np.testing.assert_allclose(src.last_frame.truth_px, renderer.truth(np.eye(4), make_pose((0.0015, 0, 0.05))))
    assert calls == pytest.approx([0.0, 0.05, 0.1, 0.15])
    assert src.read()[0] is False


def test_rendered_source_blur_uses_the_pose_at_end_of_exposure(renderer):
    def poses(t):
        return {"camera_pose": np.eye(4), "target_pose": make_pose((0.2 * t, 0.0, 0.05)), "light_gain": 0.8}

    src = RenderedSource(renderer, poses, fps=10.0, exposure_s=0.02)
    src.read()
    ok, img, t = src.read()
    assert ok and t == pytest.approx(0.1)
    assert src.last_frame.subframes > 1                      # 4 mm/s * 0.02 s: motion blur
    mid = renderer.truth(np.eye(4), make_pose((0.2 * 0.11, 0.0, 0.05)))
    np.testing.assert_allclose(src.last_frame.truth_px, mid, atol=1e-6)


def test_capture_source_reports_a_missing_device(tmp_path):
    with pytest.raises(RuntimeError):
        CaptureSource(str(tmp_path / "no_such_device"))
