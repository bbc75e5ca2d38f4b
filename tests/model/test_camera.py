import numpy as np
import pytest

from targetlock.model.camera import CameraParams, LatencyLine, project, unproject, world_to_camera


def test_point_on_optical_axis_projects_to_principal_point():
    cam = CameraParams()
    np.testing.assert_allclose(project(np.array([0, 0, 0.12]), cam), [cam.cx, cam.cy])


def test_projection_scales_with_focal_length_over_depth():
    cam = CameraParams()
    px = project(np.array([0.01, -0.02, 0.1]), cam)
    np.testing.assert_allclose(px, [cam.cx + cam.fx * 0.1, cam.cy - cam.fy * 0.2])


@pytest.mark.parametrize("k1,k2", [(0.0, 0.0), (-0.25, 0.05)])
def test_unproject_inverts_project(k1, k2):
    cam = CameraParams(k1=k1, k2=k2)
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(-0.05, 0.05, 50), rng.uniform(-0.04, 0.04, 50), rng.uniform(0.05, 0.2, 50)])
    back = unproject(project(pts, cam), pts[:, 2], cam)
    np.testing.assert_allclose(back, pts, atol=1e-9)


def test_points_behind_the_camera_are_not_in_the_image():
    assert np.all(np.isnan(project(np.array([0.0, 0.0, -0.1]), CameraParams())))


def test_world_to_camera_uses_the_camera_pose():
    pose = np.eye(4)
    pose[:3, 3] = [0.0, 0.0, 0.12]
    np.testing.assert_allclose(world_to_camera(pose, np.array([0.0, 0.0, 0.24])), [0, 0, 0.12])


def test_latency_line_delivers_in_order_at_capture_plus_latency():
    line = LatencyLine(0.4)
    for k in range(10):
        line.push(k / 22, k)
    assert line.pop_ready(0.39) == []
    ready = line.pop_ready(0.4 + 2 / 22)
    assert [item for _, item in ready] == [0, 1, 2]
    assert ready[-1][0] == pytest.approx(2 / 22)
    assert len(line) == 7


def test_latency_must_be_non_negative():
    with pytest.raises(ValueError, match="latency"):
        LatencyLine(-0.1)
