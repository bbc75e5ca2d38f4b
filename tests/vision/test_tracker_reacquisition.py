"""Re-acquisition of a lost target on weakly textured real photographs (issue 14): the dense search
that stands in where ORB finds no keypoints, and what it must never lock onto."""
from dataclasses import replace

import cv2
import numpy as np
import pytest

from targetlock.vision import FeatureTracker, PlanarTarget, Renderer, RenderSettings, make_pose
from targetlock.vision.evaluate import instrument_polygon
from targetlock.vision.texture import photo_texture
from targetlock.vision.tracker import TrackerSettings

P_SEL = (0.01, -0.02)
NO_ORB = TrackerSettings(reacquire_every=1000)  # no ORB search within a test: the dense search alone


@pytest.fixture(scope="module")
def retina(cam):
    return Renderer(cam, RenderSettings(fresh_noise=True), PlanarTarget((0.2, 0.2), photo_texture("retina"), (0.0, 0.0)),
                    seed=5)


def _pose(point_cam, rotvec=(0.1, -0.05, 0.3)):
    p = make_pose((0, 0, 0), rotvec)
    p[:3, 3] = np.asarray(point_cam, float) - p[:3, :3] @ np.array([P_SEL[0], P_SEL[1], 0.0])
    return p


def _cover(frame_px):
    """An instrument over the target and its whole window."""
    return [instrument_polygon(frame_px, (0.8, 0.6), 260.0)]


def _run(tracker, frames):
    assert tracker.select(frames[0].image, frames[0].truth_px, 80), tracker.failure
    return [tracker.update(f.image, i / 22.0) for i, f in enumerate(frames[1:], 1)]


@pytest.mark.parametrize("uncovered", [12, 13])
def test_a_target_that_returns_elsewhere_is_reacquired_densely(retina, cam, uncovered):
    """The fundus photograph (faint vessels: ORB finds no keypoints to match) is covered by an
    instrument until the target is lost; meanwhile the view moved ~60 px, beyond the local flow's
    reach. When the instrument is gone, the dense search finds the target within 3 frames (one to
    find it, one to confirm it moved with the tissue), to within 2 px, and nothing wrong is reported.
    The searches take turns while lost (the dense search on every 2nd frame, the local re-lock on
    every 4th), so the instrument leaves on a frame with (12) and without (13) a scheduled dense
    search: the re-lock is as quick either way."""
    here, there = (0.0, 0.0, 0.05), (0.010, 0.003, 0.05)
    c0 = retina.render(np.eye(4), _pose(here), point_m=P_SEL).truth_px
    frames = [retina.render(np.eye(4), _pose(here if i < 4 else there), point_m=P_SEL,
                            occluders=_cover(c0) if 2 <= i < uncovered else ()) for i in range(uncovered + 8)]
    assert np.hypot(*(frames[-1].truth_px - frames[0].truth_px)) > 50
    tr = FeatureTracker(NO_ORB)
    res = _run(tr, frames)
    assert any(r.lost for r in res[:uncovered - 1])                      # lost under the instrument
    errs = np.array([np.hypot(*(r.position_px - f.truth_px)) if r.valid else np.inf for r, f in zip(res, frames[1:])])
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(1)          # never a wrong position
    back = np.flatnonzero(np.isfinite(errs[uncovered - 1:]))              # uncovered from here on
    assert len(back) and back[0] <= 2, errs.round(1)
    assert np.all(errs[uncovered - 1 + back[0]:] < 2.0), errs.round(1)
    assert tr.stats["dense_reacquisitions"] >= 1
    lost = tr.stats["lost_frames"]
    assert lost >= 6
    assert tr.stats["dense_searches"] <= lost // 2 + 2                     # every 2nd frame, + confirmations
    assert tr.stats["local_searches"] <= lost // 4 + 2


def _with_glint(image: np.ndarray, centre_px) -> np.ndarray:
    """``image`` with a saturated white glint (radius ~15 px, soft halo) painted at ``centre_px``."""
    blob = np.zeros(image.shape[:2], np.float32)
    cv2.circle(blob, tuple(int(round(v)) for v in centre_px), 14, 1.0, -1)
    blob = np.clip(cv2.GaussianBlur(blob, (0, 0), 5.0) * 1.6, 0.0, 1.0)[..., None]
    return (image * (1.0 - blob) + 255.0 * blob).astype(np.uint8)


def test_a_glint_that_stays_put_is_not_locked_onto(cam):
    """Glossy tissue (the coffee photograph) with a glint that stays put in the image (as a
    specular spot does while the tissue slides under it) inside the selected target's window. The
    target then slides out of the view, the glint stays: nothing may be reported there, and the
    tracker, searching the whole frame densely and by ORB, stays lost."""
    r = Renderer(cam, RenderSettings(fresh_noise=True), PlanarTarget((0.2, 0.2), photo_texture("coffee"), (0.0, 0.0)),
                 seed=7)
    frames = [r.render(np.eye(4), _pose((0.0015 + 0.0035 * max(0, i - 3), 0.0, 0.035), (0.0, 0.0, 0.0)), point_m=P_SEL)
              for i in range(30)]
    glint = frames[0].truth_px + (12.0, -10.0)
    frames = [replace(f, image=_with_glint(f.image, glint)) for f in frames]
    assert sum(not f.visible for f in frames) >= 10 and not frames[-1].visible
    tr = FeatureTracker()
    res = _run(tr, frames)
    for res_i, f in zip(res, frames[1:]):
        if res_i.valid:
            assert np.hypot(*(res_i.position_px - f.truth_px)) < 8.0
    assert not any(r_.valid for r_, f in zip(res, frames[1:]) if not f.visible)
    assert all(r_.lost for r_ in res[-10:])


def test_a_target_that_returns_near_the_edge_of_the_round_view_is_reacquired_there(cam):
    """The whole-frame searches look only at the round field of view's bounding box (the black
    corners of the frame hold nothing to find): a textured target that was covered and returns
    ~200 px up and left, towards the edge of the view, is re-acquired by ORB within a few frames of
    being uncovered, at its true place in frame coordinates, and nothing wrong is reported."""
    r = Renderer(cam, RenderSettings(fresh_noise=True), PlanarTarget.mucosa(seed=3), seed=5)
    here, there = (0.0, 0.0, 0.05), (-0.025, -0.025, 0.05)
    c0 = r.render(np.eye(4), _pose(here), point_m=P_SEL).truth_px
    frames = [r.render(np.eye(4), _pose(here if i < 4 else there), point_m=P_SEL,
                       occluders=_cover(c0) if 2 <= i < 12 else ()) for i in range(20)]
    assert np.hypot(*(frames[-1].truth_px - frames[0].truth_px)) > 150 and frames[-1].visible
    tr = FeatureTracker()
    res = _run(tr, frames)
    assert any(r_.lost for r_ in res[:10])
    errs = np.array([np.hypot(*(r_.position_px - f.truth_px)) if r_.valid else np.inf for r_, f in zip(res, frames[1:])])
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(1)
    assert np.all(errs[-4:] < 2.0), errs.round(1)
    assert tr.stats["reacquisitions"] >= 1


def test_the_quarter_resolution_presearch_changes_no_decision(retina, cam):
    """While lost, a template is searched densely at half resolution only where it stands out at
    quarter resolution; the half-resolution search alone decides. Under the instrument (nothing
    stands out) the half-resolution searches are skipped, and the tracker reports exactly what it
    reports without the pre-search: the same frames lost, the same re-acquisition, the same positions."""
    here, there = (0.0, 0.0, 0.05), (0.010, 0.003, 0.05)
    c0 = retina.render(np.eye(4), _pose(here), point_m=P_SEL).truth_px
    frames = [retina.render(np.eye(4), _pose(here if i < 4 else there), point_m=P_SEL,
                            occluders=_cover(c0) if 2 <= i < 12 else ()) for i in range(20)]
    with_pre, without = FeatureTracker(NO_ORB), FeatureTracker(replace(NO_ORB, dense_presearch=False))
    res, ref = _run(with_pre, frames), _run(without, frames)
    assert with_pre.stats["dense_reacquisitions"] >= 1 and with_pre.stats["dense_searches"] >= 3
    assert with_pre.stats["dense_presearch_skips"] >= 2 and without.stats["dense_presearch_skips"] == 0
    assert [(r.valid, r.lost) for r in res] == [(r.valid, r.lost) for r in ref]
    got = np.array([r.position_px for r in res if r.valid])
    assert len(got) >= 6 and np.allclose(got, [r.position_px for r in ref if r.valid], atol=1e-9)


def _leave_or_cover(name: str, photo: str, seed: int, settings: TrackerSettings):
    """Errors (px; inf where invalid) and visibility of the tracker on ``vision-eval``'s sequence
    ``name`` on ``photo``."""
    from targetlock.vision.evaluate import render_sequence
    frames = render_sequence(name, seed=seed, target=PlanarTarget((0.2, 0.2), photo_texture(photo), (0.0, 0.0)))
    res = _run(FeatureTracker(settings), frames)
    errs = np.array([np.hypot(*(r_.position_px - f.truth_px)) if r_.valid else np.inf for r_, f in zip(res, frames[1:])])
    return errs, np.array([f.visible for f in frames[1:]])


def test_a_target_returning_with_a_weak_lead_is_reacquired_after_a_streak():
    """``vision-eval``'s retina `leave` (seed 0): the target comes back through the dim, distorted
    edge of the round view, blurred by its motion; the dense search finds it as the best place on
    frames 48-54 but leading the second best by only 1.3-1.7, strongly (1.7) on one frame only, and
    ORB re-locks it only at frame 64. Found again where the tissue went on four consecutive frames,
    it is re-acquired ~10 frames earlier; no wrong position is ever reported. (Searched for at the
    central scale too, the default, it leads strongly there: tested at the edge's scale alone.)"""
    edge = TrackerSettings(dense_central_radius=1.0)  # searched at the edge's scale only (as in this case)
    errs, vis = _leave_or_cover("leave", "retina", 0, edge)
    # the two-strong-frames rule alone (a weak lead never counts)
    ref, _ = _leave_or_cover("leave", "retina", 0, replace(edge, dense_streak_lead=1.7))
    back = np.flatnonzero(vis[:-1] & ~vis[1:])[-1] + 1   # the target re-enters the view after this index
    assert np.all(errs[np.isfinite(errs)] < 8.0) and np.all(ref[np.isfinite(ref)] < 8.0)
    assert np.sum(errs[back:] < 8.0) >= np.sum(ref[back:] < 8.0) + 8, (errs[back:].round(1), ref[back:].round(1))


def test_an_instruments_edge_in_a_later_keyframe_is_not_reacquired_on_a_weak_lead():
    """``vision-eval``'s coffee `occlusion` (seed 2): a keyframe made while the instrument came over
    holds its edge, whose template leads a little (0.55, 1.4) on six consecutive frames where the
    instrument goes, ~185 px from the target. A weak lead counts only for the selection's own
    template or where that one peaks too (the selection's template does not stand out there):
    without that rule this streak is accepted, a false lock."""
    errs, _ = _leave_or_cover("occlusion", "coffee", 2, TrackerSettings())
    bad, _ = _leave_or_cover("occlusion", "coffee", 2, TrackerSettings(dense_streak_any_keyframe=True))
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(1)
    assert np.any(np.isfinite(bad) & (bad > 100.0)), bad.round(1)


def test_a_target_lost_at_the_edge_is_searched_for_at_its_central_scale_too():
    """``vision-eval``'s retina `leave` (seed 2): towards the edge of the round view the lens
    distortion compresses the target, and the tracked scale shrinks to 0.56 before it is lost; the
    target comes back at its central scale (~1). Searched for at both scales, it is re-acquired on
    many more frames than at the edge's scale alone (``dense_central_radius=1``: the central scale is
    the last tracked one); no wrong position is ever reported."""
    errs, vis = _leave_or_cover("leave", "retina", 2, TrackerSettings())
    ref, _ = _leave_or_cover("leave", "retina", 2, TrackerSettings(dense_central_radius=1.0))
    back = np.flatnonzero(vis[:-1] & ~vis[1:])[-1] + 1
    assert np.all(errs[np.isfinite(errs)] < 8.0) and np.all(ref[np.isfinite(ref)] < 8.0)
    assert np.sum(errs[back:] < 8.0) >= np.sum(ref[back:] < 8.0) + 8, (errs[back:].round(1), ref[back:].round(1))


def test_a_target_that_left_the_view_is_relocked_where_the_scene_brings_it_back(cam):
    """The view pans until the target has left the round field of view (8.5 cm sideways at 5 cm) and
    pans back along a line 2 cm lower: the target comes back ~100 px from where it was last seen,
    beyond the local re-lock's reach (without following the scene it is still lost 16 frames after
    it is back). While lost the tracker carries the target's predicted place on by the motion of
    the tissue around it, and re-locks there within two frames of the target being back in view,
    never reporting a wrong place."""
    r = Renderer(cam, RenderSettings(), PlanarTarget.mucosa(seed=3), seed=11)
    n = 50
    frames = [r.render(np.eye(4), _pose((0.085 * np.sin(np.pi * i / (n - 1)) ** 2,
                                         0.02 * np.clip((i / (n - 1) - 0.3) / 0.3, 0.0, 1.0), 0.05), (0.0, 0.0, 0.0)),
                       point_m=P_SEL) for i in range(n)]
    visible = np.array([f.visible for f in frames])
    back = int(np.flatnonzero(~visible)[-1]) + 1                          # the first frame back in view
    assert (~visible).sum() >= 10 and visible[back:].all()
    assert np.hypot(*(frames[back].truth_px - frames[int(np.flatnonzero(~visible)[0]) - 1].truth_px)) > 60
    tr = FeatureTracker()
    res = _run(tr, frames)
    errs = np.array([np.hypot(*(r_.position_px - f.truth_px)) if r_.valid else np.inf for r_, f in zip(res, frames[1:])])
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(1)            # never a wrong place
    assert not any(r_.valid for r_, f in zip(res, frames[1:]) if not f.visible)
    assert np.all(np.isfinite(errs[back - 1 + 2:])), errs[back - 1:].round(1)   # re-locked within 2 frames
    assert np.all(errs[-8:] < 2.0), errs.round(1)
    assert tr.stats["scene_relocks"] >= 1
