import math

import numpy as np
import pytest

from targetlock.config import ConfigError, validate
from targetlock.model.camera import CameraParams, project, world_to_camera
from targetlock.model.kinematics import tip_pose
from targetlock.model.scene import Scene, SceneParams

CAM = CameraParams()
START = tip_pose(math.radians(-10), 0.0, 0.12, 30)


def scene(**kw):
    return Scene(SceneParams(**kw), CAM, START)


def test_target_starts_centred_at_the_set_distance():
    s = scene()
    p = world_to_camera(START, s.target_position(0.0))
    np.testing.assert_allclose(p, [0, 0, 0.12], atol=1e-12)


def test_linear_path_is_12cm_out_and_back_at_0p1hz_with_1s_stops():
    s = scene(start_delay=0.0)
    t = np.arange(0.0, 20.0, 0.001)
    off = s.offset(t)
    dist = np.linalg.norm(off, axis=1)
    assert dist.max() == pytest.approx(0.12, abs=1e-9)
    assert np.all(dist[(t >= 4.0) & (t <= 5.0)] == pytest.approx(0.12))      # stop at the far end
    assert np.all(dist[(t >= 9.0) & (t <= 10.0)] < 1e-12)                     # stop back home
    np.testing.assert_allclose(off[t.searchsorted(10.0):], off[: t.size - t.searchsorted(10.0)], atol=1e-9)
    assert np.all(off[:, 0] <= 1e-12)                                          # towards image -x


def test_ellipse_has_the_report_extent_and_two_stops():
    s = scene(path="ellipse", start_delay=0.0)
    t = np.arange(0.0, 20.0, 0.001)
    off = s.offset(t)
    assert np.ptp(off[:, 0]) == pytest.approx(0.13, abs=1e-4)
    assert np.ptp(off[:, 1]) == pytest.approx(0.12, abs=1e-4)
    speed = np.linalg.norm(np.diff(off, axis=0), axis=1) / 0.001
    still = speed < 1e-9
    assert 1.9 < still.sum() * 0.001 < 2.1


def test_step_target_appears_at_minus_180_px():
    s = scene(path="step")
    px = project(world_to_camera(START, s.target_position(0.5)), CAM)
    np.testing.assert_allclose(px - [CAM.cx, CAM.cy], [-180.0, 0.0], atol=1e-9)


def test_waypoints_from_csv_are_interpolated(tmp_path):
    f = tmp_path / "path.csv"
    f.write_text("t,x,y,z\n0,0,0,0\n2,0.02,0,0\n4,0.02,0.04,0\n")
    s = scene(path="waypoints", waypoints_file=str(f))
    np.testing.assert_allclose(s.offset(1.0), [0.01, 0, 0])
    np.testing.assert_allclose(s.offset(9.0), [0.02, 0.04, 0])


def test_bad_waypoints_are_refused_with_the_file_named(tmp_path):
    f = tmp_path / "bad.csv"
    f.write_text("t,x,y\n0,0,0\n")
    with pytest.raises(ConfigError, match="bad.csv"):
        scene(path="waypoints", waypoints_file=str(f))
    with pytest.raises(ConfigError, match="waypoints_file"):
        validate(SceneParams(path="waypoints"))


def test_folds_surface_moves_the_target_along_the_normal_with_breathing_and_peristalsis():
    from targetlock.model.scene import SurfaceParams
    surf = SurfaceParams(kind="folds", breathing_amplitude=0.003, breathing_rate=0.2, peristalsis_amplitude=0.0)
    s = Scene(SceneParams(path="static", surface=surf), CAM, START)
    plain = scene(path="static")
    t = np.linspace(0.0, 10.0, 201)
    d = s.target_position(t) - plain.target_position(t)
    normal = START[:3, 2]                                # the start camera's view axis
    np.testing.assert_allclose(d - np.outer(d @ normal, normal), 0.0, atol=1e-12)   # along the normal only
    w = d @ normal
    assert w.min() > 0.0                                 # the target sits on the lumen's wall, deeper than the plane
    np.testing.assert_allclose(np.ptp(w), 2 * 0.003, rtol=1e-3)                   # breathing, peak to peak
    np.testing.assert_allclose(w[t <= 5.0], w[t >= 5.0], atol=1e-12)              # period 1 / 0.2 Hz
    np.testing.assert_allclose(s.target_pose(3.0), plain.target_pose(3.0))        # the plane's frame stays
    # the height field's slope is what the renderer's Newton steps use
    r = np.linspace(0.0, 0.06, 6001)
    wr, dw = SurfaceParams(kind="folds").profile(r, 1.7)
    np.testing.assert_allclose(np.gradient(wr, r)[1:-1], dw[1:-1], atol=2e-3)
    assert not SurfaceParams(kind="folds", amplitude=0.0).height(0.01, 0.0, 1.0)   # amplitude 0: the plane


def test_a_tilted_tissue_turns_the_plane_but_not_the_target_point():
    flat, tilted = scene(path="ellipse"), scene(path="ellipse", tissue_tilt_deg=(30.0, 0.0))
    t = np.linspace(0.0, 30.0, 7)
    np.testing.assert_allclose(tilted.target_position(t), flat.target_position(t), atol=1e-12)
    np.testing.assert_allclose(tilted.target_pose(5.0)[:3, 3], flat.target_pose(5.0)[:3, 3], atol=1e-12)
    normal_flat, normal = flat.target_pose(0.0)[:3, 2], tilted.target_pose(0.0)[:3, 2]
    assert math.degrees(math.acos(float(normal_flat @ normal))) == pytest.approx(30.0, abs=1e-9)
    axis = START[:3, 0]                                # tilted about the start image's x axis
    assert float(axis @ normal) == pytest.approx(0.0, abs=1e-12)
