"""The feature tracker on what real endoscopy shows: pale glossy tissue, exposure steps, glints,
instruments slowly covering the target, dropped frames (issue 14)."""
import numpy as np
import pytest

from targetlock.vision import FeatureTracker, PlanarTarget, Renderer, RenderSettings, TrackerSettings
from targetlock.vision.texture import mucosa_texture

P_SEL = (0.021, -0.013)
WINDOW = 80


def _pale_texture(paleness: float) -> np.ndarray:
    """Mucosa bleached towards white: pale (grey ~200-230 on screen) but still textured."""
    tex = mucosa_texture(3, 1024).copy()
    bgr = tex[..., :3].astype(np.float32)
    grey = bgr.mean(axis=2, keepdims=True)
    tex[..., :3] = np.clip(255 - (255 - (0.6 * grey + 0.4 * bgr)) * paleness, 0, 255).astype(np.uint8)
    return tex


@pytest.fixture(scope="module")
def pale(cam):
    return Renderer(cam, RenderSettings(), PlanarTarget((0.2, 0.2), _pale_texture(0.4), (0.0, 0.0)), seed=1)


@pytest.fixture(scope="module")
def bright(cam):
    return Renderer(cam, RenderSettings(), PlanarTarget((0.2, 0.2), _pale_texture(0.7), (0.0, 0.0)), seed=2)


def _err(r, f) -> float:
    return float(np.hypot(*(r.position_px - f.truth_px))) if r.valid else float("inf")


def _drift(renderer, sel_pose, n, step=(0.0003, 0.0001), start=(-0.004, -0.001), **kw):
    return [renderer.render(np.eye(4), sel_pose((start[0] + step[0] * i, start[1] + step[1] * i, 0.05), P_SEL,
                                                (0.1, -0.05, 0.3)), point_m=P_SEL,
                            **{k: (v(i) if callable(v) else v) for k, v in kw.items()}) for i in range(n)]


def _run(tracker, frames, times=None):
    assert tracker.select(frames[0].image, frames[0].truth_px, WINDOW), tracker.failure
    if times is None:
        return [tracker.update(f.image) for f in frames[1:]]
    return [tracker.update(f.image, t) for f, t in zip(frames[1:], times[1:])]


def test_pale_textured_target_is_selected_and_tracked(pale, sel_pose):
    frames = _drift(pale, sel_pose, 20, step=(0.0004, 0.0001))
    grey = frames[0].image[..., 1].astype(float)   # the tissue is bright: most of it above the old level
    x, y = np.round(frames[0].truth_px).astype(int)
    assert np.median(grey[y - 40:y + 40, x - 40:x + 40]) > 190
    res = _run(FeatureTracker(), frames)
    errs = np.array([_err(r, f) for r, f in zip(res, frames[1:])])
    assert np.all(errs < 2.0), errs.round(2)


def test_highlight_mask_keeps_glints_but_not_pale_tissue(cam, sel_pose):
    matte = Renderer(cam, RenderSettings(specular_strength=0.0), PlanarTarget((0.2, 0.2), _pale_texture(0.4)))
    f = matte.render(np.eye(4), sel_pose((0.0, 0.0, 0.05), P_SEL, (0.1, -0.05, 0.3)), point_m=P_SEL)
    img = f.image.copy()
    x, y = np.round(f.truth_px).astype(int)
    glint = (x + 20, y - 15)
    import cv2
    cv2.circle(img, glint, 5, (255, 255, 255), -1)
    tr = FeatureTracker()
    assert tr.select(img, f.truth_px, WINDOW)
    view = tr._crop(img, f.truth_px)
    ox, oy = view.to_frame[:2, 2].astype(int)
    assert view.sat[glint[1] - oy, glint[0] - ox]                                    # the glint is masked
    win = (slice(y - 40, y + 40), slice(x - 40, x + 40))
    white = (img[win].min(axis=2) >= 190).mean()  # bright in every channel: "highlight" by level alone
    assert white > 0.6
    assert view.sat[y - oy - 40:y - oy + 40, x - ox - 40:x - ox + 40].mean() < 0.05  # the pale tissue is not


def test_a_sliding_glint_is_not_tracked(renderer, sel_pose):
    """A saturated white blob slides across the target of a still scene: the tracker stays on the
    tissue, it does not follow the glint."""
    import cv2
    still = renderer.render(np.eye(4), sel_pose((0.0, 0.0, 0.05), P_SEL, (0.1, -0.05, 0.3)), point_m=P_SEL)
    x, y = still.truth_px
    frames = []
    for i in range(16):
        img = still.image.copy()
        cv2.circle(img, (int(x - 30 + 4 * i), int(y + 3)), 7, (250, 252, 253), -1, cv2.LINE_AA)
        frames.append(img)
    tr = FeatureTracker()
    assert tr.select(frames[0], still.truth_px, WINDOW)
    res = [tr.update(im) for im in frames[1:]]
    assert all(r.valid for r in res)
    errs = [float(np.hypot(*(r.position_px - still.truth_px))) for r in res]
    assert max(errs) < 0.5, np.round(errs, 2)


def test_dropped_frames_with_capture_times_do_not_trip_the_jump_rejection(renderer, sel_pose):
    """~13 px per frame interval (~290 px/s), 3 frames dropped at a time (~55 px between received
    frames): the real interval scales the prediction and the jump limit, so nothing is rejected."""
    fps = 22.0
    renderer.reseed(7)
    all_frames = _drift(renderer, sel_pose, 25, step=(0.0025, 0.0004), start=(-0.03, -0.003))
    keep = [0, 1, 2, 3, 7, 8, 12, 13, 17, 18, 19, 23, 24]
    frames = [all_frames[i] for i in keep]
    times = [i / fps for i in keep]
    tr = FeatureTracker()
    res = _run(tr, frames, times)
    assert tr.stats["false_jumps"] == 0
    errs = np.array([_err(r, f) for r, f in zip(res, frames[1:])])
    assert np.all(errs < 2.0), errs.round(2)
    blind = FeatureTracker()       # the same frames without capture times: the jumps look false
    assert not all(r.valid for r in _run(blind, frames))


def test_selection_falls_back_to_a_larger_window(renderer, sel_pose):
    f = renderer.render(np.eye(4), sel_pose((0.0, 0.0, 0.05), P_SEL, (0.1, -0.05, 0.3)), point_m=P_SEL)
    img = f.image.copy()
    x, y = np.round(f.truth_px).astype(int)
    patch = img[y - 45:y + 46, x - 45:x + 46]
    patch[:] = patch.reshape(-1, 3).mean(axis=0).astype(np.uint8)  # no texture in the 80 px window
    tr = FeatureTracker()
    assert tr.select(img, f.truth_px, WINDOW), tr.failure
    assert tr.failure is None and tr.selection["window_px"] > WINDOW
    shifted = np.roll(img, (3, 4), axis=(0, 1))   # the same view moved by (4, 3) px
    r = tr.update(shifted)
    assert r.valid and np.hypot(*(r.position_px - f.truth_px - (4, 3))) < 1.0


def test_selection_failure_says_why(cam):
    tr = FeatureTracker()
    dark = np.zeros((cam.height, cam.width, 3), np.uint8)
    assert not tr.select(dark, (360, 288), WINDOW) and "dark" in tr.failure
    flat = np.full((cam.height, cam.width, 3), 120, np.uint8)
    assert not tr.select(flat, (360, 288), WINDOW) and "featureless" in tr.failure
    assert not tr.select(flat, (900, 288), WINDOW) and "outside" in tr.failure
    r = tr.update(flat)
    assert r.lost and not r.valid


def test_a_slowly_covering_bar_makes_no_keyframe_and_lowers_the_confidence(renderer, sel_pose):
    """An instrument's tip creeps over the target (5 px per frame): while it covers part of the
    target's own patch no keyframe is made from the covered view, the confidence falls, and once
    the target is covered the tracker stops reporting it (or reports it where it is)."""
    from targetlock.vision.evaluate import instrument_polygon
    renderer.reseed(3)
    pose = sel_pose((0.0, 0.0, 0.05), P_SEL, (0.1, -0.05, 0.3))
    tgt = renderer.render(np.eye(4), pose, point_m=P_SEL).truth_px
    frames, gap = [], []
    for i in range(28):
        tip = tgt + np.array([120.0 - 5.0 * i, 0.0])     # 60 px wide bar from the right
        gap.append(120.0 - 5.0 * i - 30.0)                # its edge's distance from the target (px)
        frames.append(renderer.render(np.eye(4), pose, point_m=P_SEL,
                                      occluders=[instrument_polygon(tip, (1.0, 0.15), 60.0)]))
    tr = FeatureTracker()
    assert tr.select(frames[0].image, frames[0].truth_px, WINDOW)
    patch_half = 0.2 * WINDOW
    conf, new_kf = {}, {}
    for i, f in enumerate(frames[1:], 1):
        k0 = tr.stats["keyframes"]
        r = tr.update(f.image)
        conf[i] = r.confidence if r.valid else 0.0
        new_kf[i] = tr.stats["keyframes"] > k0
        assert not (r.valid and _err(r, f) > 3.0), f"frame {i}: false position"
    covering = [i for i in conf if gap[i] < patch_half]
    assert covering and not any(new_kf[i] for i in covering)
    clear = [conf[i] for i in conf if gap[i] > 2 * patch_half + 40]
    partly = [conf[i] for i in covering if 0 < gap[i] <= 0.6 * patch_half]  # over a third of the patch covered
    assert min(clear) > 0.9 and max(partly) < 0.6, (clear, partly)
    assert all(conf[i] == 0.0 for i in conf if gap[i] < -15)   # target well under the bar: not reported


@pytest.mark.parametrize("gain", [1.5, 0.5])
def test_an_exposure_step_on_bright_tissue_keeps_the_lock(bright, sel_pose, gain):
    """The light gain steps at frame 10 on bright tissue: a x1.5 step used to turn half the window
    into "highlight" and lose the target for good."""
    bright.reseed(4)
    frames = _drift(bright, sel_pose, 24, light_gain=lambda i: 1.0 if i < 10 else gain)
    res = _run(FeatureTracker(), frames)
    errs = np.array([_err(r, f) for r, f in zip(res, frames[1:])])
    assert np.all(errs < 2.0), errs.round(2)


@pytest.fixture(scope="module")
def coffee(cam):
    from targetlock.vision.texture import photo_texture
    return Renderer(cam, RenderSettings(), PlanarTarget((0.2, 0.2), photo_texture("coffee"), (0.0, 0.0)), seed=1)


@pytest.mark.parametrize("content", ["renderer", "coffee"])
@pytest.mark.parametrize("gain", [0.6, 1.5])
def test_an_exposure_step_keeps_the_lock(request, sel_pose, content, gain):
    """The exposure steps by x0.6 or x1.5 at frame 10 with the target in view, on the rendered mucosa
    and on a real photograph (where the x1.5 step clips the cup's white rim in the region, which
    changes the region's normalisation: the flow failed on every feature and the target was lost
    for the rest of the sequence). At most 2 frames without a position, and it stays accurate."""
    scene = request.getfixturevalue(content)
    scene.reseed(5)
    frames = _drift(scene, sel_pose, 24, light_gain=lambda i: 1.0 if i < 10 else gain)
    tr = FeatureTracker()
    res = _run(tr, frames)
    assert not any(r.lost for r in res)
    assert sum(not r.valid for r in res) <= 2
    errs = np.array([_err(r, f) for r, f in zip(res, frames[1:])])
    assert np.all(errs[np.isfinite(errs)] < 2.0), errs.round(2)


def test_the_exposure_retry_does_not_overrule_a_strong_chain(cam):
    """vision-eval's `folds` sequence (deforming, non-planar surface) on the coffee photograph, seed 14,
    selected at 80 px and grown to 120 px (20 corners there, fewer than ``selection_margin`` = 3 x 8):
    on frame 7 the chain (27 inliers, 0.3 px from the target) was rightly disputed by a weak keyframe
    match 4.8 px off. The exposure retry then fitted the chain again on local-mean-free images, agreed
    with that match 5 px off, and the frame was accepted: a keyframe made there held the target 5-10 px
    off for the rest of the sequence (13 false frames). A retry may only repair flow that the exposure
    broke: no estimate is ever reported wrong."""
    from targetlock.vision.evaluate import EvalSettings, render_sequence
    from targetlock.vision.texture import photo_texture
    target = PlanarTarget((0.2, 0.2), photo_texture("coffee"), (0.0, 0.0))
    frames = render_sequence("folds", EvalSettings(), seed=14, cam=cam, target=target)
    tr = FeatureTracker(TrackerSettings(selection_margin=3.0))
    assert tr.select(frames[0].image, frames[0].truth_px, WINDOW), tr.failure
    assert tr.selection["window_px"] == 120.0, tr.selection
    res = [tr.update(f.image, i / cam.fps) for i, f in enumerate(frames[1:], 1)]
    errs = np.array([_err(r, f) for r, f in zip(res, frames[1:])])
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(2)  # vision-eval's threshold
    assert np.mean(np.isfinite(errs)) >= 0.75, errs.round(2)


def test_a_target_at_the_edge_of_the_view_is_tracked_then_reported_lost(renderer, sel_pose, cam):
    """The target slides out through the round field of view's edge (280 px radius): with its window
    partly outside, it is still tracked on the features inside, to within a few px of the edge, with
    the confidence falling with the window's missing share; once out it is not reported (no false
    position) and soon declared lost."""
    renderer.reseed(6)
    frames = [renderer.render(np.eye(4), sel_pose((0.03 + 0.0015 * i, 0.003, 0.05), P_SEL, (0.1, -0.05, 0.3)),
                              point_m=P_SEL) for i in range(36)]
    edge = np.array([280.0 - np.hypot(*(f.truth_px - (cam.cx, cam.cy))) for f in frames[1:]])  # px inside
    tr = FeatureTracker()
    res = _run(tr, frames)
    errs = np.array([_err(r, f) for r, f in zip(res, frames[1:])])
    conf = np.array([r.confidence for r in res])
    near = edge >= 4.0
    assert edge.min() < -40 and near.sum() > 15
    assert np.all(errs[near] < 3.0), errs.round(2)                      # tracked up to ~4 px from the edge
    assert conf[(edge < 15) & near].max() < 0.5 * conf[edge > 60].min()  # less confident with half a window
    assert not any(r.valid for r, e in zip(res, edge) if e < 0)          # out: no position reported
    assert all(r.lost for r, e in zip(res, edge) if e < -25)


def test_a_weakly_textured_real_photo_target_keeps_the_lock_under_fast_motion(cam):
    """vision-eval's `fast` sequence on the fundus photograph (scikit-image's retina, CC0): the target
    window is nearly uniform (faint vessels, noise-level corners) and moves up to ~16 px per frame
    with motion blur. Too few corners follow the keyframe, so the dense keyframe match and the
    coasting prediction carry it (it used to be lost from frame 4 on, for good)."""
    from targetlock.vision.evaluate import EvalSettings, render_sequence
    from targetlock.vision.texture import photo_texture
    target = PlanarTarget((0.2, 0.2), photo_texture("retina"), (0.0, 0.0))
    # the loop's renderer settings (sensor noise from the precomputed bank, as when this was found)
    frames = render_sequence("fast", EvalSettings(), seed=0, cam=cam, target=target,
                             render_settings=RenderSettings())[:30]
    tr = FeatureTracker()
    res = _run(tr, frames, [i / cam.fps for i in range(len(frames))])
    errs = np.array([_err(r, f) for r, f in zip(res, frames[1:])])
    assert np.sum(~np.isfinite(errs)) <= 2 and not any(r.lost for r in res), errs.round(2)
    assert np.all(errs[np.isfinite(errs)] < 4.0), errs.round(2)
    assert tr.stats["dense"] > 0


def test_strong_sensor_noise_on_a_weakly_textured_photo_keeps_the_lock(cam):
    """Sensor noise of 8 levels (per channel, fresh every frame) on the fundus photograph, whose
    vessels are faint: in the target's band-passed patch the noise is about as strong as the
    texture, so the patch of a correctly tracked frame correlated ~0.3-0.5 with its keyframe's and
    read as another texture (covered): no keyframe could be made, the tracker drifted out of its
    keyframe's reach and lost the target for good. The patch check takes the noise (estimated per
    region) out of both patches' energies: the target is never lost, and no wrong position is
    reported. (Since the regions of a noisy sensor are smoothed before the flow, issue 14's noise
    follow-up, about a third of this scene's frames from frame 15 on are rejected as covered
    instead of tracked at 2-4 px: on 12 such scenes, 6 per photograph, smoothing keeps the lock on
    more frames, 5.0 vs 4.0 scenes' worth on the fundus, equal on the coffee photograph.)"""
    from targetlock.vision.texture import photo_texture
    r = Renderer(cam, RenderSettings(fresh_noise=True, noise_sigma=8.0),
                 PlanarTarget((0.2, 0.2), photo_texture("retina"), (0.0, 0.0)), seed=5)
    p_sel = (0.01, -0.02)

    def pose(point_cam):
        from targetlock.vision import make_pose
        p = make_pose((0, 0, 0), (0.1, -0.05, 0.3))
        p[:3, 3] = np.asarray(point_cam, float) - p[:3, :3] @ np.array([p_sel[0], p_sel[1], 0.0])
        return p

    frames = [r.render(np.eye(4), pose((-0.004 + 0.0004 * i, 0.0015 * np.sin(i / 5), 0.05)), point_m=p_sel)
              for i in range(40)]
    tr = FeatureTracker()
    res = _run(tr, frames, [i / cam.fps for i in range(len(frames))])
    errs = np.array([_err(r_, f) for r_, f in zip(res, frames[1:])])
    assert not any(r_.lost for r_ in res)
    assert np.mean(errs < 8.0) >= 0.6, errs.round(1)
    assert np.all(errs[np.isfinite(errs)] < 6.0), errs.round(1)
    assert tr.stats["keyframes"] >= 2


def test_a_dark_smooth_target_with_barely_enough_corners_is_selected_with_a_margin_and_held(cam):
    """vision-eval's `fast` sequence on the coffee photograph, seed 1: the selected point lies on a
    dark, smooth part of the cup whose 80 px window holds only 9 corners (8 are needed). Selected
    there, the tracker lost the target on the first frame (motion blur at ~17 px per frame left too
    few of them) and never found it again. With fewer than ``selection_margin`` (3) x min_inliers
    corners, selection takes the larger window that has that margin (or half of it): the target is
    tracked from the first frame on, never lost, and never reported wrong."""
    from targetlock.vision.evaluate import EvalSettings, render_sequence
    from targetlock.vision.texture import photo_texture
    target = PlanarTarget((0.2, 0.2), photo_texture("coffee"), (0.0, 0.0))
    frames = render_sequence("fast", EvalSettings(), seed=1, cam=cam, target=target)[:25]
    tr = FeatureTracker()
    res = _run(tr, frames, [i / cam.fps for i in range(len(frames))])
    assert tr.selection["window_px"] > WINDOW and tr.selection["features"] >= 12, tr.selection
    errs = np.array([_err(r, f) for r, f in zip(res, frames[1:])])
    assert not any(r.lost for r in res) and np.sum(~np.isfinite(errs)) <= 2, errs.round(2)
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(2)  # vision-eval's threshold


def test_a_target_on_plain_glaze_with_few_corners_is_selected_in_a_window_with_the_margin(cam):
    """vision-eval's `slow` sequence on the coffee photograph, seed 11: the point lies on the cup's plain
    glaze under a sliding glint, and its 80 px window holds 19 corners (more than the 8 needed, fewer
    than 3 x 8). Selected there it was tracked on none of its 65 frames; the 160 px window (40 corners)
    held it on all of them. Selection takes the larger window: tracked on most frames, never wrong."""
    from targetlock.vision.evaluate import EvalSettings, render_sequence
    from targetlock.vision.texture import photo_texture
    target = PlanarTarget((0.2, 0.2), photo_texture("coffee"), (0.0, 0.0))
    frames = render_sequence("slow", EvalSettings(), seed=11, cam=cam, target=target)
    tr = FeatureTracker()
    res = _run(tr, frames, [i / cam.fps for i in range(len(frames))])
    assert tr.selection["window_px"] > WINDOW and tr.selection["features"] >= 24, tr.selection
    errs = np.array([_err(r, f) for r, f in zip(res, frames[1:])])
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(2)  # vision-eval's threshold
    assert np.mean(errs < 8.0) >= 0.9, errs.round(2)
    old = FeatureTracker(TrackerSettings(selection_margin=1.5))
    old_res = _run(old, frames, [i / cam.fps for i in range(len(frames))])
    assert old.selection["window_px"] == WINDOW
    assert np.mean([_err(r, f) < 8.0 for r, f in zip(old_res, frames[1:])]) < 0.5


def test_a_window_with_enough_corners_keeps_its_size(renderer, sel_pose):
    """The margin rule only grows a window that has barely enough corners: on textured mucosa the
    requested window is kept."""
    f = renderer.render(np.eye(4), sel_pose((0.0, 0.0, 0.05), P_SEL, (0.1, -0.05, 0.3)), point_m=P_SEL)
    tr = FeatureTracker()
    assert tr.select(f.image, f.truth_px, WINDOW), tr.failure
    assert tr.selection["window_px"] == WINDOW and tr.selection["features"] >= 12


@pytest.mark.parametrize("photo, name, seed, n", [("coffee", "tip", 0, 60), ("retina", "fast", 0, 45)])
def test_a_poorly_determined_scale_or_rotation_does_not_lose_the_target(cam, photo, name, seed, n):
    """vision-eval sequences on real photographs where the features that carry the target lie along
    one edge (the coffee cup's rim as the tip bends) or are few and faint (the fundus under fast,
    blurred motion): single frames' features gave the view a wrong scale/rotation step (20 % and
    -14 deg in one frame on `coffee/tip`). Taken into the view's similarity it misaligned every
    later keyframe warp, the keyframe flow found nothing and the target was lost for good (frame 52
    of `coffee/tip`, frame 27 of `retina/fast`) while the frame-to-frame flow still followed it. The
    view now changes scale and rotation by at most a plausible step from such evidence: never lost,
    never a wrong position."""
    from targetlock.vision.evaluate import EvalSettings, render_sequence
    from targetlock.vision.texture import photo_texture
    target = PlanarTarget((0.2, 0.2), photo_texture(photo), (0.0, 0.0))
    frames = render_sequence(name, EvalSettings(), seed=seed, cam=cam, target=target)[:n]
    # The rule in the 80 px window it was found on, and the defaults (which widen the rim's window for
    # context, so the rule may not be needed there).
    for settings, rule in ((TrackerSettings(context_isotropy=0.0), True), (TrackerSettings(), False)):
        tr = FeatureTracker(settings)
        res = _run(tr, frames, [i / cam.fps for i in range(len(frames))])
        errs = np.array([_err(r, f) for r, f in zip(res, frames[1:])])
        assert not any(r.lost for r in res) and np.sum(~np.isfinite(errs)) <= 3, errs.round(2)
        assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(2)  # vision-eval's threshold
        if rule:
            assert tr.stats["similarity_dropped"] + tr.stats["similarity_limited"] > 0


def test_an_implausible_view_step_keeps_the_position_but_not_the_scale_or_rotation(renderer, sel_pose):
    """The frame-to-frame motion's similarity is believed up to max_view_scale_step /
    max_view_rotation_step_deg per frame interval (scaled by the interval): a 20 % / 14 deg step
    keeps only the target's displacement and marks the chain suspect; a small step is kept whole; a few keyframe features
    change the view's scale and rotation by at most the plausible step (a real correction then
    takes a few frames) while the position is theirs."""
    from targetlock.vision.tracker import _apply, _scale_angle
    f = renderer.render(np.eye(4), sel_pose((0.0, 0.0, 0.05), P_SEL, (0.1, -0.05, 0.3)), point_m=P_SEL)
    tr = FeatureTracker()
    assert tr.select(f.image, f.truth_px, WINDOW)
    pos = tr._pos.copy()

    def sim(scale, deg, shift):
        a = np.radians(deg)
        m = np.eye(3)
        m[:2, :2] = scale * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        m[:2, 2] = pos + shift - m[:2, :2] @ pos  # about the target, then shifted
        return m

    big = sim(0.8, -14.0, (5.0, -3.0))
    chain, suspect = tr._steady((big, big, None, 20), 1.0)
    assert suspect and _scale_angle(chain[1]) == pytest.approx((1.0, 0.0))
    assert _apply(chain[1], pos) == pytest.approx(pos + (5.0, -3.0))
    chain, suspect = tr._steady((big, big, None, 20), 5.0)  # five intervals (dropped frames): plausible
    assert chain[1] is big and not suspect
    small = sim(1.03, 2.0, (5.0, -3.0))
    chain, suspect = tr._steady((small, small, None, 20), 1.0)
    assert chain[1] is small and not suspect
    est = pos + (5.0, -3.0)
    lim = tr._limited(big @ tr._from_anchor, 1.0, est)
    sc, ang = _scale_angle(lim @ np.linalg.inv(tr._from_anchor))
    s = tr.settings
    assert np.log(sc) == pytest.approx(-s.max_view_scale_step) and np.degrees(ang) == pytest.approx(-s.max_view_rotation_step_deg)
    assert _apply(lim, tr._anchor.target) == pytest.approx(est)


def test_a_motion_blurred_target_is_not_taken_for_covered(cam):
    """vision-eval's `blur` sequence (fast, 40 ms exposure: ~10-15 px of smear) on the coffee
    photograph, seed 0: the smear wipes the band-passed texture across the motion out of the
    target's own patch, which then decorrelated from the keyframe's (0.1-0.2) as a covered patch
    does, and frames on which chain and keyframe agreed were rejected as covered (frames 4 and
    45-48). The patch is now also compared with the keyframe's smeared along this frame's motion
    (accepted, no keyframe made from it): at most 2 frames are rejected."""
    from targetlock.vision.evaluate import EvalSettings, render_sequence
    from targetlock.vision.texture import photo_texture
    target = PlanarTarget((0.2, 0.2), photo_texture("coffee"), (0.0, 0.0))
    frames = render_sequence("blur", EvalSettings(), seed=0, cam=cam, target=target)[:50]
    tr = FeatureTracker()
    res = _run(tr, frames, [i / cam.fps for i in range(len(frames))])
    errs = np.array([_err(r, f) for r, f in zip(res, frames[1:])])
    assert not any(r.lost for r in res) and np.sum(~np.isfinite(errs)) <= 2, errs.round(2)
    assert np.all(errs[np.isfinite(errs)] < 2.0), errs.round(2)


def test_an_instrument_covering_a_fast_blurred_target_is_not_reported(cam):
    """The same fast, long-exposure motion with an instrument over the target for 15 frames: the
    smeared-keyframe comparison does not let the instrument pass for the target (no covered frame
    reported, no wrong position), and the target is found again after it."""
    from targetlock.vision.evaluate import EvalSettings, _Scene, instrument_polygon
    from targetlock.vision.texture import photo_texture
    cfg = EvalSettings()
    r = Renderer(cam, RenderSettings(fresh_noise=True), PlanarTarget((0.2, 0.2), photo_texture("coffee"), (0.0, 0.0)),
                 seed=0)
    scene = _Scene("blur", cfg, cam, np.random.default_rng([0, 3]), cfg.frames / cam.fps)
    frames, covered = [], []
    for i in range(40):
        t = i / cam.fps
        cp0, tp0, _, _ = scene.at(t)
        cp1, tp1, _, _ = scene.at(t + 0.04)
        truth = r.render(cp0, tp0, point_m=scene.p_sel).truth_px
        occ = [instrument_polygon(truth + (0.0, -10.0), (0.3, 1.0), 90.0)] if 15 <= i < 30 else []
        frames.append(r.render(cp0, tp0, camera_pose_end=cp1, target_pose_end=tp1, point_m=scene.p_sel,
                               occluders=occ, time_s=t + 0.02))
        covered.append(bool(occ))
    tr = FeatureTracker()
    res = _run(tr, frames, [i / cam.fps for i in range(len(frames))])
    errs = np.array([_err(r_, f) for r_, f in zip(res, frames[1:])])
    assert not any(r_.valid for r_, c in zip(res, covered[1:]) if c)
    assert np.all((errs < 8.0) | ~np.isfinite(errs)), errs.round(2)
    assert np.all(errs[:14] < 2.0) and np.all(errs[-3:] < 2.0), errs.round(2)


def test_a_suspect_chain_does_not_corroborate_a_dense_match(cam):
    """vision-eval's `specular` sequence on the coffee photograph, seed 2 (glints sliding over a
    weakly textured target): the frame-to-frame chain, whose own scale/rotation step was
    implausible, and the keyframe's ECC match agreed within 3 px frame after frame while both
    drifted 6 -> 19 px off the target, reported as valid. A suspect chain no longer corroborates a
    dense match: no wrong position is reported."""
    from targetlock.vision.evaluate import EvalSettings, render_sequence
    from targetlock.vision.texture import photo_texture
    target = PlanarTarget((0.2, 0.2), photo_texture("coffee"), (0.0, 0.0))
    frames = render_sequence("specular", EvalSettings(), seed=2, cam=cam, target=target)[:34]
    tr = FeatureTracker()
    res = _run(tr, frames, [i / cam.fps for i in range(len(frames))])
    errs = np.array([_err(r, f) for r, f in zip(res, frames[1:])])
    assert np.all((errs < 8.0) | ~np.isfinite(errs)), errs.round(2)
    assert np.all(errs[:4] < 3.0), errs.round(2)  # tracked while the evidence holds


def _eval_frames(name: str, photo: str, seed: int, n: int, cam) -> list:
    """The first ``n`` frames of vision-eval's sequence ``name`` on ``photo`` (as
    ``evaluate.render_sequence`` renders them, without rendering the rest)."""
    from targetlock.vision.evaluate import SEQUENCES, EvalSettings, _Scene
    from targetlock.vision.texture import photo_texture
    cfg = EvalSettings()
    r = Renderer(cam, RenderSettings(fresh_noise=True), PlanarTarget((0.2, 0.2), photo_texture(photo), (0.0, 0.0)),
                 seed=seed)
    scene = _Scene(name, cfg, cam, np.random.default_rng([seed, SEQUENCES.index(name)]), cfg.frames / cam.fps)
    r.reseed([seed, SEQUENCES.index(name), 1])
    frames = []
    for i in range(n):
        t = i / cam.fps
        cp0, tp0, gain, occ = scene.at(t)
        cp1, tp1, _, _ = scene.at(t + cfg.exposure_s)
        frames.append(r.render(cp0, tp0, camera_pose_end=cp1, target_pose_end=tp1, light_gain=gain, occluders=occ,
                               point_m=scene.p_sel, time_s=t + cfg.exposure_s / 2))
    return frames


def test_a_target_under_glare_does_not_hand_on_drift(cam):
    """vision-eval's `rotation` sequence on the coffee photograph, seed 2: the target sits under a
    glint while the tissue turns, so its own patch cannot be compared with the keyframe's (mostly
    glare). Keyframes made from such frames one after another (frames 3, 5 and 8) each handed the
    surroundings' error on, and then a dense match of the glared window agreed with the chain: the
    estimate slid 1 -> 13 px off the target over 16 frames, reported valid with confidence up to
    0.8. At most two unverified keyframes are made in a row, and a dense match of a glared window
    against the second carries no frame: no wrong position is reported, the target is tracked
    while it can be."""
    frames = _eval_frames("rotation", "coffee", 2, 18, cam)
    tr = FeatureTracker()
    assert tr.select(frames[0].image, frames[0].truth_px, WINDOW), tr.failure
    res = [tr.update(f.image, i / cam.fps) for i, f in enumerate(frames[1:], 1)]
    errs = np.array([_err(r, f) for r, f in zip(res, frames[1:])])
    assert np.all((errs < 8.0) | ~np.isfinite(errs)), errs.round(2)
    assert np.all(errs[:3] < 2.0), errs.round(2)        # tracked while the target itself is seen
    assert np.sum(errs < 8.0) >= 8, errs.round(2)        # and on its surroundings for a while
    assert tr.stats["keyframes"] <= 3, tr.stats           # the selection's and two unverified
