"""Renderer: geometry against model.camera.project, field of view, light, blur, noise, occluders."""
import math
import time

import cv2
import numpy as np
import pytest

from targetlock.config import ConfigError, validate
from targetlock.model.camera import CameraParams, project, world_to_camera
from targetlock.model.scene import SurfaceParams
from targetlock.vision import (PlanarTarget, Renderer, RenderSettings, add_dot, aruco_texture, endoscope_camera,
                               make_pose, mucosa_texture)
from targetlock.vision import render as render_module
from targetlock.vision.render import render_benchmark
from targetlock.vision.texture import with_height

SIZE = (0.2, 0.2)
DOTS = [(0.0, 0.0), (0.012, -0.008), (-0.02, 0.015), (0.03, 0.02), (-0.025, -0.02)]


def _centroid(img: np.ndarray, guess: np.ndarray, half: int = 8) -> np.ndarray:
    """Background-subtracted intensity centroid of a bright dot near ``guess`` (px)."""
    g = img[..., 1].astype(float)
    x0, y0 = int(round(guess[0])) - half, int(round(guess[1])) - half
    w = g[y0:y0 + 2 * half + 1, x0:x0 + 2 * half + 1]
    w = np.clip(w - np.median(w) - 5, 0, None)
    ys, xs = np.mgrid[y0:y0 + 2 * half + 1, x0:x0 + 2 * half + 1]
    return np.array([(w * xs).sum() / w.sum(), (w * ys).sum() / w.sum()])


@pytest.fixture(scope="module")
def dot_renderer(cam, clean_settings):
    tex = with_height(np.full((2048, 2048, 3), 60, np.uint8))
    for p in DOTS:
        tex = add_dot(tex, p, SIZE, 0.0008)
    return Renderer(cam, clean_settings, PlanarTarget(SIZE, tex))


@pytest.mark.parametrize("pose", [
    make_pose((0.0, 0.0, 0.05)),                                  # face-on
    make_pose((0.004, -0.002, 0.045), (0.3, -0.2, 0.5)),          # tilted and turned
    make_pose((0.0, 0.0, 0.12), (0.0, 0.0, -0.7)),                # far: coarser texture pyramid level
    make_pose((0.002, 0.001, 0.03), (0.0, 0.0, 1.0)),             # near
])
def test_rendered_dot_lands_where_project_says(dot_renderer, cam, pose):
    frame = dot_renderer.render(np.eye(4), pose)
    checked = 0
    for p in DOTS:
        truth = project(world_to_camera(np.eye(4), (pose @ [p[0], p[1], 0.0, 1.0])[:3]), cam)
        if math.hypot(truth[0] - cam.cx, truth[1] - cam.cy) > 250:
            continue
        err = np.hypot(*(_centroid(frame.image, truth) - truth))
        assert err < 0.5, f"dot {p} at {truth}: centroid off by {err:.3f} px"
        checked += 1
    assert checked >= 3


def test_truth_is_projection_of_selected_point(renderer, cam):
    target_pose = make_pose((0.003, -0.001, 0.05), (0.1, 0.2, 0.3))
    cam_pose = make_pose((0.001, 0.0, 0.0), (0.0, 0.05, 0.0))
    frame = renderer.render(cam_pose, target_pose, point_m=(0.01, -0.02))
    world = (target_pose @ [0.01, -0.02, 0.0, 1.0])[:3]
    np.testing.assert_allclose(frame.truth_px, project(world_to_camera(cam_pose, world), cam), atol=1e-9)
    assert frame.visible and not frame.occluded
    assert frame.image.shape == (576, 720, 3) and frame.image.dtype == np.uint8


def test_round_field_of_view_is_black_outside(renderer, cam):
    img = renderer.render(np.eye(4), make_pose((0, 0, 0.05))).image
    ys, xs = np.mgrid[0:cam.height, 0:cam.width]
    r = np.hypot(xs - cam.cx, ys - cam.cy)
    rf = renderer.settings.fov_radius_px
    assert img[r > rf + 1.5].max() == 0                 # exactly black outside the circle
    inside = img[r < rf - 40].max(axis=1)
    assert (inside > 20).mean() > 0.99                    # lit tissue inside


def test_light_falls_off_with_distance_and_follows_gain(renderer):
    near = renderer.render(np.eye(4), make_pose((0, 0, 0.04))).image
    far = renderer.render(np.eye(4), make_pose((0, 0, 0.08))).image
    dim = renderer.render(np.eye(4), make_pose((0, 0, 0.04)), light_gain=0.4).image
    c = (slice(250, 330), slice(320, 400))
    assert far[c].mean() < 0.85 * near[c].mean()
    assert dim[c].mean() < 0.8 * near[c].mean()
    # centre brighter than the periphery (cos^3 fall-off at a fixed plane)
    assert near[270:310, 340:380].mean() > near[270:310, 130:170].mean()


def test_motion_blur_integrates_the_exposure(renderer):
    p0 = make_pose((0, 0, 0.05))
    p1 = make_pose((0.004, 0, 0.05))  # ~24 px to the right during the exposure
    sharp = renderer.render(np.eye(4), p0)
    blurred = renderer.render(np.eye(4), p0, target_pose_end=p1)
    assert blurred.subframes > 4 and sharp.subframes == 1
    gx = lambda im: np.abs(cv2.Sobel(cv2.cvtColor(im, cv2.COLOR_BGR2GRAY), cv2.CV_32F, 1, 0))[200:380, 260:460].mean()
    assert gx(blurred.image) < 0.7 * gx(sharp.image)     # horizontal detail smeared out
    mid = renderer.truth(np.eye(4), make_pose((0.002, 0, 0.05)))
    np.testing.assert_allclose(blurred.truth_px, mid, atol=1e-6)  # truth at mid-exposure


def test_noise_is_seeded(cam, mucosa_target):
    a = Renderer(cam, RenderSettings(), mucosa_target, seed=5).render(np.eye(4), make_pose((0, 0, 0.05))).image
    b = Renderer(cam, RenderSettings(), mucosa_target, seed=5).render(np.eye(4), make_pose((0, 0, 0.05))).image
    c = Renderer(cam, RenderSettings(), mucosa_target, seed=6).render(np.eye(4), make_pose((0, 0, 0.05))).image
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    noise = (a.astype(int) - c.astype(int))[200:380, 260:460]
    assert 1.5 < noise.std() < 5.0                       # ~ sqrt(2) * sigma (2 levels)


@pytest.mark.parametrize("fresh", [False, True])
def test_fresh_noise_is_not_a_shifted_copy_of_earlier_noise(cam, mucosa_target, fresh):
    """The bank's noise recurs between frames, shifted (a motion a tracker can follow on weak
    texture); with ``fresh_noise`` no frame's noise matches another's at any shift."""
    r = Renderer(cam, RenderSettings(noise_sigma=8.0, fresh_noise=fresh), mucosa_target, seed=3)
    pose = np.eye(4)
    pose[2, 3] = 0.05
    frames = [r.render(np.eye(4), pose).image.astype(np.float32) for _ in range(7)]
    clean = np.mean(frames, axis=0)  # the same view every frame: the noise is what differs
    noise = [cv2.cvtColor(f - clean, cv2.COLOR_BGR2GRAY)[200:376, 260:460] for f in frames]
    best = max(float(cv2.matchTemplate(b, a[40:136, 40:160], cv2.TM_CCOEFF_NORMED).max())
               for i, a in enumerate(noise) for b in noise[i + 1:])
    assert best < 0.3 if fresh else best > 0.6, best


def test_specular_highlights_saturate(cam, mucosa_target):
    on = Renderer(cam, RenderSettings(), mucosa_target).render(np.eye(4), make_pose((0, 0, 0.035)))
    off = Renderer(cam, RenderSettings(specular_strength=0.0), mucosa_target).render(np.eye(4), make_pose((0, 0, 0.035)))
    white_on = (on.image.min(axis=2) > 230).sum()
    white_off = (off.image.min(axis=2) > 230).sum()
    assert white_on > 100 and white_off == 0


def test_occluder_hides_the_target(renderer, cam):
    poly = np.array([[300, 250], [420, 250], [420, 330], [300, 330]], float)
    f = renderer.render(np.eye(4), make_pose((0, 0, 0.05)), occluders=[poly])
    assert f.occluded and not f.visible
    patch = f.image[270:310, 320:400].astype(float)
    assert patch.std(axis=(0, 1)).max() < 8              # uniform instrument colour
    g = renderer.render(np.eye(4), make_pose((0.07, 0.0, 0.05)))
    assert not g.visible and not g.occluded               # outside the field of view


def test_settings_are_validated():
    with pytest.raises(ConfigError, match="fov_radius_px"):
        validate(RenderSettings(fov_radius_px=-5.0))
    with pytest.raises(ConfigError, match=r"noise_sigma.*\[0.0, 50.0\]"):
        validate(RenderSettings(noise_sigma=80.0))


def test_textures_are_deterministic():
    a = mucosa_texture(7, 256)
    b = mucosa_texture(7, 256)
    c = mucosa_texture(8, 256)
    assert a.shape == (256, 256, 4) and np.array_equal(a, b) and not np.array_equal(a, c)


def test_aruco_target_renders_detectably(cam):
    r = Renderer(cam, RenderSettings(), PlanarTarget.aruco(marker_id=7))
    f = r.render(np.eye(4), make_pose((0.002, -0.001, 0.05), (0.15, -0.1, 0.6)))
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50),
                                  cv2.aruco.DetectorParameters())
    corners, ids, _ = det.detectMarkers(cv2.cvtColor(f.image, cv2.COLOR_BGR2GRAY))
    assert ids is not None and 7 in ids.ravel()
    assert aruco_texture(7)[..., 3].min() == 0  # the printed marker is matte (height 0)


def test_render_is_fast_enough(renderer):
    pose = make_pose((0.002, 0, 0.05), (0.1, 0.1, 0.2))
    renderer.render(np.eye(4), pose)
    t0 = time.perf_counter()
    for _ in range(10):
        renderer.render(np.eye(4), pose)
    ms = (time.perf_counter() - t0) / 10 * 1e3
    assert ms < 40.0, f"{ms:.1f} ms per frame"  # ~2 ms on one core; generous for shared CI machines


def test_camera_in_the_target_plane_gives_a_black_frame(renderer):
    f = renderer.render(make_pose((0, 0, 0.05)), make_pose((0, 0, 0.05)))
    assert not f.visible and f.image.max() == 0


def test_frames_are_reproducible_and_own_their_images(cam, mucosa_target):
    """Same seed -> same frames (still, 2 and 4 sub-poses, occluder); no frame shares memory with another."""
    def sequence(seed):
        r = Renderer(cam, RenderSettings(), mucosa_target, seed=seed)
        p0 = make_pose((0, 0, 0.05))
        frames = [r.render(np.eye(4), p0),
                  r.render(np.eye(4), p0, target_pose_end=make_pose((0.0004, 0, 0.05))),
                  r.render(np.eye(4), p0, target_pose_end=make_pose((0.0012, 0.0004, 0.05))),
                  r.render(np.eye(4), p0, occluders=[np.array([[300, 250], [420, 250], [420, 330]], float)])]
        assert [f.subframes for f in frames] == [1, 2, 4, 1]
        return [f.image for f in frames]
    a, b = sequence(4), sequence(4)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not any(np.shares_memory(x, y) for i, x in enumerate(a) for y in a[i + 1:])


@pytest.mark.parametrize("end", [make_pose((0.0012, 0.0004, 0.05)),              # sliding
                                 make_pose((0.0, 0.0, 0.0485), (0.0, 0.0, 0.02))])  # approaching and rolling
def test_image_space_motion_blur_matches_sampling_the_texture(cam, mucosa_target, monkeypatch, end):
    """3+ sub-poses resample the mid-exposure image per tile; that must look like sampling the texture
    at every sub-pose (the reference path)."""
    calls = []
    blur = render_module._motion_blur
    monkeypatch.setattr(render_module, "_motion_blur", lambda *a: calls.append(1) or blur(*a))
    settings = RenderSettings(noise_sigma=0.0)
    fast, exact = Renderer(cam, settings, mucosa_target), Renderer(cam, settings, mucosa_target)
    exact._IMAGE_BLUR_MIN = 10 ** 9
    p0 = make_pose((0, 0, 0.05))
    a = fast.render(np.eye(4), p0, target_pose_end=end)
    assert calls, "the image-space path was not taken"
    b = exact.render(np.eye(4), p0, target_pose_end=end)
    assert len(calls) == 1 and a.subframes == b.subframes >= 3
    d = np.abs(a.image.astype(int) - b.image.astype(int))
    assert d.mean() < 0.5 and np.percentile(d, 99) <= 3, (d.mean(), np.percentile(d, 99))
    np.testing.assert_array_equal(a.truth_px, b.truth_px)


def test_wide_blur_strong_noise_no_blur_and_a_clipped_field_of_view_render(mucosa_target):
    pose = make_pose((0, 0, 0.05))
    gx = lambda im: np.abs(cv2.Sobel(cv2.cvtColor(im, cv2.COLOR_BGR2GRAY), cv2.CV_32F, 1, 0))[200:380, 260:460].mean()
    sharp = Renderer(endoscope_camera(), RenderSettings(optical_blur_px=0.0, noise_sigma=0.0), mucosa_target)
    wide = Renderer(endoscope_camera(), RenderSettings(optical_blur_px=1.5, noise_sigma=0.0), mucosa_target)
    assert gx(wide.render(np.eye(4), pose).image) < 0.6 * gx(sharp.render(np.eye(4), pose).image)
    loud = [Renderer(endoscope_camera(), RenderSettings(noise_sigma=30.0), mucosa_target, seed=s)
            .render(np.eye(4), pose) for s in (1, 2)]         # noise beyond int8: a 16-bit noise bank
    assert 30 < (loud[0].image.astype(float) - loud[1].image)[250:330, 320:400].std() < 50
    small = CameraParams(width=320, height=240, cx=160.0, cy=120.0, fx=150.0, fy=150.0)
    f = Renderer(small, RenderSettings(fov_radius_px=140.0), mucosa_target).render(np.eye(4), pose)
    assert f.image.shape == (240, 320, 3) and f.image[0, 0].max() == 0 and f.image[110:130, 150:170].mean() > 20
    assert f.visible


def test_render_benchmark_reports_per_frame_times():
    res = render_benchmark(3, subposes=(1, 3), texture_px=512)
    assert res["camera"] == "pinhole" and res["frames"] == 3 and set(res["ms"]) == {1, 3}
    assert all(0.0 < v["median"] <= v["p95"] for v in res["ms"].values())


@pytest.mark.parametrize("camera", ["distorted", "pinhole"])
def test_a_region_renders_the_same_pixels_as_the_whole_frame(mucosa_target, camera):
    """Partial frames (for a tracker that reads only its region) equal the whole frame where drawn,
    glints, blur, noise and motion blur included, also after other regions left their buffers."""
    cam = endoscope_camera() if camera == "distorted" else CameraParams()
    r = Renderer(cam, RenderSettings(specular_strength=6.0), mucosa_target, seed=5)
    for i in range(6):
        pose = make_pose((0.003 * math.sin(i), 0.002 * math.cos(i), 0.05 + 0.01 * i),
                         (0.5 * math.cos(0.7 * i), 0.5 * math.sin(0.7 * i), 0.1 * i))
        end = pose.copy()
        end[0, 3] += 0.0004 * (i % 3)                      # still, 2 and several sub-poses
        kw = {"target_pose_end": end} if i % 3 else {}
        r.reseed(i)
        full = r.render(np.eye(4), pose, **kw).image
        x0, y0 = 60 + 61 * i, 20 + 57 * i
        r.reseed(i)
        part = r.render(np.eye(4), pose, region=(x0, y0, x0 + 150.5, y0 + 130), **kw).image
        inside = np.zeros(part.shape[:2], bool)
        inside[y0:y0 + 130, x0:x0 + 151] = True              # x1 = 150.5 covers column x0 + 150
        drawn = inside | (part.max(axis=2) > 0)
        assert np.array_equal(part[drawn], full[drawn])
        assert drawn.sum() < 0.5 * (full.max(axis=2) > 0).sum()    # the rest is not rendered
    with pytest.raises(ValueError, match="region"):
        r.render(np.eye(4), make_pose((0, 0, 0.05)), region=(0, 0, float("nan"), 10))


# ------------------------------------------------------------------- surfaces that are not flat
def _dots_target():
    tex = with_height(np.full((2048, 2048, 3), 60, np.uint8))
    for p in DOTS:
        tex = add_dot(tex, p, SIZE, 0.0008)
    return PlanarTarget(SIZE, tex)


def test_folds_of_zero_amplitude_render_as_the_plane(cam, mucosa_target):
    """The surface path (ray intersection, texel grids, normal shading, glints on the slope) with a
    vanishing height field gives the plane's image up to rounding."""
    pose = make_pose((0.002, -0.001, 0.06), (0.2, -0.1, 0.3))
    plane = Renderer(cam, RenderSettings(), mucosa_target, seed=2).render(np.eye(4), pose).image
    flat = Renderer(cam, RenderSettings(), mucosa_target, seed=2,
                    surface=SurfaceParams(kind="folds", amplitude=1e-9)).render(np.eye(4), pose, time_s=1.3).image
    d = np.abs(plane.astype(int) - flat.astype(int))
    assert d.mean() < 0.05 and np.percentile(d, 99.9) <= 1 and d.max() <= 12   # (glint weights interpolated)


def test_target_on_deforming_folds_is_drawn_where_its_truth_projects(cam, clean_settings):
    """The selected point moves with the breathing, peristaltic surface; the rendered dot follows
    the projection of that surface point within a pixel."""
    surf = SurfaceParams(kind="folds", lumen_offset=(0.01, 0.005), breathing_amplitude=0.004)
    r = Renderer(cam, clean_settings, _dots_target(), surface=surf)
    pose = make_pose((0.004, -0.002, 0.05), (0.15, -0.1, 0.2))
    truths = []
    for t in (0.0, 0.7, 1.4, 2.1, 2.8):
        for p in DOTS[1:4]:
            frame = r.render(np.eye(4), pose, point_m=p, time_s=t)
            err = np.hypot(*(_centroid(frame.image, frame.truth_px) - frame.truth_px))
            assert err < 1.0, f"dot {p} at t = {t} s: centroid off by {err:.2f} px"
            truths.append(frame.truth_px)
        w = surf.height(DOTS[1][0], DOTS[1][1], t)
        world = (pose @ [DOTS[1][0], DOTS[1][1], w, 1.0])[:3]
        np.testing.assert_allclose(r.truth(np.eye(4), pose, DOTS[1], t), project(world_to_camera(np.eye(4), world), cam))
    moved = np.ptp(np.array(truths[::3]), axis=0)
    assert np.hypot(*moved) > 2.0                        # the deformation moves the target visibly


def test_moving_tip_shows_parallax_over_a_lumen(cam, clean_settings):
    """Sideways tip motion moves near tissue more in the image than the deep lumen behind it."""
    deep, near = DOTS[2], DOTS[3]                        # lumen axis at ``deep``: 30 mm further away
    surf = SurfaceParams(kind="folds", lumen_offset=deep, lumen_depth=0.03, fold_amplitude=0.0,
                         breathing_amplitude=0.0, peristalsis_amplitude=0.0)
    r = Renderer(cam, clean_settings, _dots_target(), surface=surf)
    flat = Renderer(cam, clean_settings, _dots_target())
    pose = make_pose((-0.005, -0.017, 0.05))
    moved = make_pose((0.004, 0.0, 0.0))                 # the tip 4 mm to the right

    def shift(rend, p):
        a, b = (rend.render(c, pose, point_m=p) for c in (np.eye(4), moved))
        for f in (a, b):
            assert np.hypot(*(_centroid(f.image, f.truth_px) - f.truth_px)) < 1.0
        return np.hypot(*(_centroid(b.image, b.truth_px) - _centroid(a.image, a.truth_px)))

    s_near, s_deep = shift(r, near), shift(r, deep)
    assert s_near > 1.3 * s_deep > 10.0
    # on the plane both points are at one depth: no such difference
    assert abs(shift(flat, near) - shift(flat, deep)) < 0.15 * shift(flat, near)


def test_breathing_is_periodic_at_its_rate(cam):
    surf = SurfaceParams(kind="folds", breathing_rate=0.25, peristalsis_amplitude=0.0)
    r = Renderer(cam, RenderSettings(), PlanarTarget.mucosa(seed=1, texture_px=512), seed=4, surface=surf)
    pose = make_pose((0.0, 0.0, 0.05))

    def frame(t):
        r.reseed(0)
        return r.render(np.eye(4), pose, time_s=t, point_m=(0.004, 0.002))

    a, period, half = frame(0.3), frame(0.3 + 4.0), frame(0.3 + 2.0)
    assert np.array_equal(a.image, period.image)
    np.testing.assert_allclose(a.truth_px, period.truth_px, atol=1e-9)
    assert np.abs(a.image.astype(int) - half.image.astype(int)).mean() > 2.0
    assert np.hypot(*(a.truth_px - half.truth_px)) > 0.3


def _sobel_rms(height: np.ndarray) -> float:
    """Reference: the rms of the whole image's 3x3 Sobel gradient / 8, in float64."""
    h = height.astype(np.float64)
    gx = cv2.Sobel(h, cv2.CV_64F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(h, cv2.CV_64F, 0, 1, ksize=3) / 8.0
    return math.sqrt(np.mean(gx * gx + gy * gy))


@pytest.mark.parametrize("shape", [(1, 7), (255, 300), (256, 64), (600, 333)])
def test_relief_slope_scale_is_the_whole_image_sobel_rms(shape):
    """The relief's slope scale (the rms height gradient the glints' normals are scaled by) is summed in
    row strips for speed: it must be the whole image's, strip seams and image borders included, also for
    a strided view (the renderer passes the texture's height channel)."""
    height = np.random.default_rng(shape[0]).integers(0, 256, shape, dtype=np.uint8)
    for view in (height, height[:, ::2]):
        assert render_module._gradient_rms(view, rows=100) == pytest.approx(_sobel_rms(view), rel=1e-6)


def test_a_tilted_tissue_moves_the_glints_off_the_centre(cam, mucosa_target):
    """With the light at the tip, a surface seen face-on mirrors it at the image centre, where the lock
    holds the target; tilted by a, the mirror point is where the plane's normal meets the camera:
    f * tan(a) from the centre (173 px at 30 degrees, f = 300 px)."""
    from targetlock.model.scene import Scene, SceneParams
    renderer = Renderer(cam, RenderSettings(), mucosa_target)

    def glints_from_centre(tilt: tuple[float, float]) -> float:
        pose = Scene(SceneParams(distance=0.035, tissue_tilt_deg=tilt), cam, np.eye(4)).target_pose(0.0)
        ys, xs = np.nonzero(renderer.render(np.eye(4), pose).image.min(axis=2) > 230)
        assert xs.size > 50
        return float(np.hypot(np.median(xs) - cam.cx, np.median(ys) - cam.cy))

    assert glints_from_centre((0.0, 0.0)) < 40.0
    assert glints_from_centre((30.0, 0.0)) == pytest.approx(cam.fy * math.tan(math.radians(30.0)), abs=45.0)
