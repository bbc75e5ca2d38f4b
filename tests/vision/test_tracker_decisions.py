"""The feature tracker's accept / reject decisions on real-photograph sequences of `vision-eval`
(issue 14): frames it used to reject or lose although the target was in view and tracked, and
that it must not report at a wrong position."""
import numpy as np
import pytest

from targetlock.vision import FeatureTracker, PlanarTarget, RenderSettings
from targetlock.vision.evaluate import EvalSettings, render_sequence
from targetlock.vision.texture import photo_texture
from targetlock.vision.tracker import TrackerSettings

WINDOW = 80
# The 80 px windows some rules below were found on: the context widening and the selection margin of 3 x
# min_inliers corners (both on by default) now widen them, which avoids those scenarios; the rules stay
# for windows that are not widened.
SEL_80 = {"selection_margin": 1.5}
EDGE_80 = {"context_isotropy": 0.0, **SEL_80}


def _run(tracker, frames, window=WINDOW):
    """Errors (px; inf when not valid) of frames 1.. and the results."""
    assert tracker.select(frames[0].image, frames[0].truth_px, window), tracker.failure
    errs, res = [], []
    for i, f in enumerate(frames[1:], 1):
        r = tracker.update(f.image, i / 22.0)
        res.append(r)
        errs.append(float(np.hypot(*(r.position_px - f.truth_px))) if r.valid else np.inf)
    return np.array(errs), res


def _assert_found_again_after_the_instrument(target, seed, least, without, base=None):
    """`occlusion` (instrument over the target until frame 44) on ``target``: never at a wrong place,
    tracked within 4 px on at least ``least`` frames after it is back in view with the tracker settings
    ``base`` (default: the defaults), and never found again with ``without`` (the rule off)."""
    frames = render_sequence("occlusion", EvalSettings(photos=()), seed=seed, target=target)
    back = np.array([f.visible for f in frames[1:]]) & (np.arange(1, len(frames)) >= 45)
    errs, _ = _run(FeatureTracker(base), frames)
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(1)      # never a wrong position
    assert np.sum(errs[back] < 4.0) >= least, errs[back].round(1)      # found again after the instrument
    old, _ = _run(FeatureTracker(without), frames)
    assert not np.any(np.isfinite(old[back])), old[back].round(1)      # lost for good before


@pytest.fixture(scope="module")
def retina_lighting():
    """`vision-eval`'s `lighting` sequence on the fundus photograph, seed 0, first 40 frames: the light's
    gain swings between 0.4 and 1.6, then steps to 0.35 at frame 33, while the target drifts up to 5 px
    per frame."""
    target = PlanarTarget((0.2, 0.2), photo_texture("retina"), (0.0, 0.0))
    return render_sequence("lighting", EvalSettings(photos=()), seed=0, target=target)[:40]


def test_a_decorrelated_patch_with_its_surroundings_tracked_is_not_taken_for_covered(retina_lighting):
    """As the gain changes, the target's band-passed patch decorrelates from the keyframe's (ncc -0.05
    to 0.13 on frames 33-35, after the step) although the chain and the keyframe's features around the target agree
    within 1 px (24-26 keyframe inliers): those frames were rejected as covered. With the keyframe's
    features right around the target still following it, they are accepted (low confidence, no
    keyframe); a covered target's surroundings would be covered too."""
    errs, res = _run(FeatureTracker(), retina_lighting)
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(1)     # never a wrong position
    assert np.all(errs[32:35] < 3.0), errs[30:38].round(2)            # frames 33-35
    assert all(0.0 < r.confidence < 0.5 for r in res[32:35])          # low confidence
    # rejected as covered before
    old, _ = _run(FeatureTracker(TrackerSettings(patch_override_px=0.0)), retina_lighting)
    assert not np.any(np.isfinite(old[32:35])), old[30:38].round(2)


def test_a_target_under_strong_noise_is_not_taken_for_covered():
    """`vision-eval`'s `noise` sequence (sensor noise sigma 8) on the fundus photograph, seed 0, first
    34 frames: under the noise the faint target patch decorrelated (0.07-0.2) on frames 21-23 while a
    keyframe's features around the target put it within 1 px; rejected as covered, the target was
    lost on frame 25 and never found again (every place of the noisy fundus correlates alike)."""
    target = PlanarTarget((0.2, 0.2), photo_texture("retina"), (0.0, 0.0))
    frames = render_sequence("noise", EvalSettings(photos=()), seed=0, target=target)[:34]
    errs, res = _run(FeatureTracker(), frames)
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(1)     # never a wrong position
    assert np.all(errs[20:32] < 3.0), errs[18:33].round(2)            # frames 21-32
    old, res_old = _run(FeatureTracker(TrackerSettings(patch_override_px=0.0)), frames)
    assert res_old[24].lost and not np.any(np.isfinite(old[24:])), old[18:].round(2)


def test_a_dense_match_with_its_surroundings_tracked_is_not_taken_for_covered():
    """`vision-eval`'s `tip` sequence on the fundus photograph, seed 1, first 50 frames: on frame 41 too
    few keyframe corners follow (motion blur), the keyframe's window matches densely where the chain
    puts the target and the chain's features around it follow it, but the band-passed patch
    decorrelated: rejected as covered, and the target was lost by frame 50. A dense match counts
    like the keyframe's features (the chain's features right around the target must follow it)."""
    target = PlanarTarget((0.2, 0.2), photo_texture("retina"), (0.0, 0.0))
    frames = render_sequence("tip", EvalSettings(photos=()), seed=1, target=target)[:52]
    errs, res = _run(FeatureTracker(), frames)
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(1)     # never a wrong position
    assert errs[40] < 3.0 and np.all(np.isfinite(errs[40:])), errs[38:].round(2)   # frames 41-51
    old, res_old = _run(FeatureTracker(TrackerSettings(patch_override_px=0.0)), frames)
    assert not np.isfinite(old[40]) and res_old[49].lost, old[38:].round(2)


def test_a_strong_keyframe_match_corrects_the_error_the_chain_inherited():
    """`vision-eval`'s `leave` sequence on the fundus photograph, seed 0: after the target came back
    into view and was re-acquired, the chain (which starts from the last accepted position, 3-5 px
    off) disagreed by 3-7 px with a later keyframe matched on 16-24 features around the target,
    0.4-1 px from it; only the selection keyframe could overrule the chain, so frames 55-60 were
    rejected. A strong, surrounding match of any keyframe now corrects the chain (within
    keyframe_correction_px)."""
    target = PlanarTarget((0.2, 0.2), photo_texture("retina"), (0.0, 0.0))
    frames = render_sequence("leave", EvalSettings(photos=()), seed=0, target=target)
    errs, _ = _run(FeatureTracker(), frames)
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(1)     # never a wrong position
    assert np.all(errs[54:60] < 2.0), errs[50:62].round(2)            # frames 55-60
    old, _ = _run(FeatureTracker(TrackerSettings(keyframe_correction_px=0.0)), frames)
    assert np.sum(np.isfinite(old[54:60])) <= 2, old[50:62].round(2)


def test_under_strong_noise_a_later_keyframe_does_not_overrule_the_chain():
    """`vision-eval`'s `noise` sequence on the coffee photograph, seed 3, first 40 frames: keyframes made
    under sigma-8 noise carry their own error (5-10 px here); letting such a later keyframe overrule
    the chain (as it may on a quiet sensor) drifted the estimate 8-14 px off on frames 32-38.
    Under strong noise only the selection keyframe corrects the chain: no wrong position."""
    target = PlanarTarget((0.2, 0.2), photo_texture("coffee"), (0.0, 0.0))
    frames = render_sequence("noise", EvalSettings(photos=()), seed=3, target=target)[:40]
    errs, _ = _run(FeatureTracker(TrackerSettings(**SEL_80)), frames)
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(1)
    assert np.mean(np.isfinite(errs)) > 0.6, errs.round(1)


def test_under_strong_noise_a_dense_match_renews_the_keyframe():
    """`vision-eval`'s `noise` sequence on the fundus photograph, seed 2, first 36 frames: under
    sigma-8 noise the keyframe made on frame 4 matched 1-9 of its 40 corners from frame 16 on; dense
    matches agreeing with the chain carried frames 16-21 (0.6-1.2 px) but made no keyframe, the stale
    keyframe then failed for good and the target (in view) was lost from frame 24 to 53. Under strong
    noise a dense match that agrees with the chain now renews the keyframe: the target is kept, never
    misplaced."""
    target = PlanarTarget((0.2, 0.2), photo_texture("retina"), (0.0, 0.0))
    frames = render_sequence("noise", EvalSettings(photos=()), seed=2, target=target)[:36]
    tracker = FeatureTracker()
    errs, res = _run(tracker, frames)
    assert all(f.visible for f in frames)
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(1)     # never a wrong position
    assert not any(r.lost for r in res), errs.round(1)                # never lost
    assert np.all(errs[25:35] < 3.0), errs[20:].round(2)              # frames 26-35
    assert tracker.stats["keyframes"] >= 2                            # renewed after frame 4


def test_a_dense_match_that_disagrees_with_a_strong_chain_does_not_reject_the_frame():
    """`vision-eval`'s `tip` sequence on the coffee photograph, seed 0, first 20 frames: weak keyframe
    matches (8-11 of 40 corners, all close to the target) left the view's similarity 15 % off in
    scale, so the keyframe's corners stopped following and the dense (ECC) match, started from that
    warp, converged 17-30 px off on frames 12, 13 and 16, where the chain (20-23 inliers) was within
    2 px: those frames were rejected as inconsistent. Such a frame is now reported from a strong
    chain whose target patch matches the keyframe's (the tracker still goes on from the last
    accepted frame)."""
    target = PlanarTarget((0.2, 0.2), photo_texture("coffee"), (0.0, 0.0))
    frames = render_sequence("tip", EvalSettings(photos=()), seed=0, target=target)[:20]
    tracker = FeatureTracker(TrackerSettings(**EDGE_80))
    errs, _ = _run(tracker, frames)
    assert np.all(np.isfinite(errs)), errs.round(1)                   # every frame tracked
    assert np.all(errs < 3.0), errs.round(2)                          # and within a few px
    assert tracker.stats["inconsistent"] > 0                          # the dense match did disagree


def test_no_keyframe_from_an_edge_window_whose_texture_motion_blur_smeared():
    """`vision-eval`'s `blur` sequence on the coffee photograph, seed 3, first 42 frames: the target
    lies beside the cup's curved rim, a window whose texture is an edge (structure-tensor isotropy
    0.01-0.03) and locates the target only across it. From frame 13 the view speeds up along the rim
    (up to 14 px per frame, long exposure): the chain and the keyframe's features slid along it
    together (the consistency check cannot see that), keyframes made in the smear on frames 15 and
    20 were 2.4 and 10.1 px off, and frames 18-38 were reported 8-17 px off. A keyframe is not made
    from an edge-like window that lost the 2-D texture of the keyframe it was matched against: no
    wrong position."""
    target = PlanarTarget((0.2, 0.2), photo_texture("coffee"), (0.0, 0.0))
    frames = render_sequence("blur", EvalSettings(photos=()), seed=3, target=target)[:42]
    tracker = FeatureTracker(TrackerSettings(**EDGE_80))
    errs, _ = _run(tracker, frames)
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(1)     # never a wrong position
    assert np.mean(np.isfinite(errs)) > 0.9, errs.round(1)            # and still tracked
    assert tracker.stats["edge_smeared"] > 0
    old, _ = _run(FeatureTracker(TrackerSettings(edge_isotropy=0.0, **EDGE_80)), frames)
    assert np.sum(old[np.isfinite(old)] > 8.0) >= 10, old.round(1)     # the false lock before


def test_an_exposure_step_that_clips_an_edge_window_is_not_taken_for_blur():
    """`vision-eval`'s `lighting` sequence on the coffee photograph, seed 4: the light's gain rises and
    clips the cup's white rim beside the target, whose marks were the window's 2-D texture (its
    isotropy 0.24 -> 0.02). Texture lost to clipping is no motion blur (isotropies are compared only
    over pixels clear of highlights in both frames): keyframes are still made, and every frame is
    tracked (without them the target was lost from frame 24 on)."""
    target = PlanarTarget((0.2, 0.2), photo_texture("coffee"), (0.0, 0.0))
    frames = render_sequence("lighting", EvalSettings(photos=()), seed=4, target=target)
    tracker = FeatureTracker()
    errs, _ = _run(tracker, frames)
    assert np.all(errs < 3.0), errs.round(1)                           # every frame, within 3 px
    assert tracker.stats["edge_smeared"] == 0


def test_a_strong_chain_carries_the_frame_after_a_reported_disputed_frame():
    """`vision-eval`'s `specular` sequence on the coffee photograph, seed 0, first 49 frames: sliding
    glare leaves only the selection keyframe, matched densely; on frame 46 the dense match disagreed
    with a strong chain (reported from the chain, its target patch matching the keyframe's), and on
    frame 47 the dense match failed while the chain still followed 21 features within 3 px of the
    target: rejected, because a frame after a miss could not be carried by the chain alone. Misses
    that were all reported that way now do not block the chain (the target is not lost early)."""
    target = PlanarTarget((0.2, 0.2), photo_texture("coffee"), (0.0, 0.0))
    frames = render_sequence("specular", EvalSettings(photos=()), seed=0, target=target)[:49]
    errs, _ = _run(FeatureTracker(), frames)
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(1)     # never a wrong position
    assert np.all(errs[45:47] < 5.0), errs[40:].round(2)              # frames 46, 47
    old, _ = _run(FeatureTracker(TrackerSettings(chain_after_reported=False)), frames)
    assert np.isfinite(old[45]) and not np.isfinite(old[46]), old[40:].round(2)


def test_a_large_window_keeps_its_features_clear_of_the_glints():
    """`vision-eval`'s `specular` sequence on the coffee photograph, seed 2, first 16 frames, selected
    with a 160 px window: the corners near the target sat on the rims of two glints (just outside
    their masks: the halo), which slide over the tissue as it rocks, and moved with them (2-15 px off
    by frame 7), while the true corners lay on the spoon 80-105 px away. The RANSAC affine bent to fit
    both groups, chain and keyframe agreed, and from frame 7 on the target was reported 8-21 px off
    (89 % of the sequence). A large window's features are now kept clear of highlights by the flow
    window's reach: no wrong position, every frame tracked."""
    target = PlanarTarget((0.2, 0.2), photo_texture("coffee"), (0.0, 0.0))
    frames = render_sequence("specular", EvalSettings(photos=()), seed=2, target=target)[:16]
    errs, _ = _run(FeatureTracker(), frames, 160)
    assert np.all(errs < 3.0), errs.round(1)                          # every frame, within 3 px
    old, _ = _run(FeatureTracker(TrackerSettings(highlight_clearance_px=0)), frames, 160)
    assert np.sum(old[np.isfinite(old)] > 8.0) >= 5, old.round(1)      # the false lock before


def test_a_large_window_searches_densely_for_the_target_not_for_its_periphery():
    """`vision-eval`'s `occlusion` sequence on the mucosa, seed 0, first 36 frames, selected with a 160 px
    window: the instrument was already inside the window when the last keyframe was made (frame 20), a
    frame before it covered the target. While the target was covered, the whole-frame dense search with
    that keyframe's 160 px template found the instrument 184 px away (correlation 0.46, leading every
    other place) and reported it on frames 31 and 35. The dense templates are now the central 80 px:
    no wrong position. (The check that the selection looks like a later keyframe's candidate,
    ``dense_anchor_ncc``, catches it too: off for the comparison.)"""
    target = PlanarTarget.mucosa(seed=0, texture_px=RenderSettings().texture_px)
    frames = render_sequence("occlusion", EvalSettings(photos=()), seed=0, target=target)[:36]
    errs, _ = _run(FeatureTracker(), frames, 160)
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(1)     # never a wrong position
    old, _ = _run(FeatureTracker(TrackerSettings(dense_template_max_px=4096.0, dense_anchor_ncc=-1.0)), frames, 160)
    assert np.sum(old[np.isfinite(old)] > 8.0) >= 2, old.round(1)      # the false lock before


def test_a_keyframe_made_on_the_chain_alone_does_not_correct_the_chain():
    """`vision-eval`'s `leave` sequence on the coffee photograph, seed 2, first 23 frames, selected with a
    160 px window: on frame 16, near the edge of the view, the keyframe did not match and the chain
    alone (37 inliers) carried the frame 3.5 px off and made a keyframe. On frame 17 that keyframe's
    features (20 inliers, around the target) put the target 3.4 px from the chain's estimate, and as
    a later keyframe's strong match it "corrected" the chain: 6.8 px off, then 7.9-8.2 px on frames 18-22.
    A keyframe made on the chain alone holds the chain's own error: it no longer corrects it, and
    the target is followed 1.4-3.3 px off through frame 22."""
    target = PlanarTarget((0.2, 0.2), photo_texture("coffee"), (0.0, 0.0))
    frames = render_sequence("leave", EvalSettings(photos=()), seed=2, target=target)[:23]
    errs, _ = _run(FeatureTracker(), frames, 160)
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(1)     # never a wrong position
    assert np.sum(errs[16:] < 4.0) >= 4, errs.round(1)                # frames 17-22 still tracked
    old, _ = _run(FeatureTracker(TrackerSettings(chain_keyframe_corrects=True)), frames, 160)
    assert np.sum(old[np.isfinite(old)] > 8.0) >= 3, old.round(1)     # the false lock before


def test_a_target_that_moved_while_covered_is_relocked_where_the_dense_search_finds_it():
    """`vision-eval`'s `occlusion` sequence on the coffee photograph, seed 0: an instrument covers the
    target from frame 22 to 44 while the tissue carries it 25 px from where it was last seen, beyond the
    optical flow's reach from there. The whole-frame dense search's best place (a weak template, 0.4-0.6,
    not leading enough to be accepted on its own) now seeds the local re-lock, which still needs the
    selection keyframe's corners around it: the target is found again, never at a wrong place."""
    target = PlanarTarget((0.2, 0.2), photo_texture("coffee"), (0.0, 0.0))
    _assert_found_again_after_the_instrument(target, 0, 4, TrackerSettings(seeded_relock_px=0.0, **SEL_80),
                                             TrackerSettings(**SEL_80))


def test_a_target_coming_back_at_the_edge_of_the_view_is_not_relocked_there_from_a_seed():
    """`vision-eval`'s `leave` sequence on the mucosa, seed 6, selected with a 160 px window: the target
    leaves the view at frame 22 and comes back through its edge from frame 44. A seeded local re-lock
    there (the selection keyframe, made near the centre, against the lens distortion at the edge) put it
    6.7 px off, then 8.3 px. Seeds at the edge are left to the re-lock further in: found again, never at
    a wrong place."""
    target = PlanarTarget.mucosa(seed=6, texture_px=RenderSettings().texture_px)
    frames = render_sequence("leave", EvalSettings(photos=()), seed=6, target=target)
    errs, _ = _run(FeatureTracker(), frames, 160)
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(1)     # never a wrong position
    assert np.sum(errs[50:] < 4.0) >= 8, errs[50:].round(1)           # found again further in


def test_fast_motion_that_blurs_every_corner_is_carried_by_the_phase_correlation_and_a_dense_match():
    """`vision-eval`'s `fast` sequence on the coffee photograph, seed 4, first 21 frames: the target
    moves 17 px per frame from the first frame on, and motion blur leaves none of the window's 12
    corners to follow, so the tracker used to miss every frame and lose the target for the whole
    sequence. The region's phase correlation measures the motion (16.4 px against 17); the keyframe's
    window aligned densely there and agreeing with it carries the frame: tracked, never at a wrong place."""
    target = PlanarTarget((0.2, 0.2), photo_texture("coffee"), (0.0, 0.0))
    frames = render_sequence("fast", EvalSettings(photos=()), seed=4, target=target)[:21]
    errs, _ = _run(FeatureTracker(TrackerSettings(**EDGE_80)), frames)
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(1)     # never a wrong position
    assert np.sum(errs < 4.0) >= 15, errs.round(1)                    # most frames tracked
    old, _ = _run(FeatureTracker(TrackerSettings(phase_dense=False, **EDGE_80)), frames)
    assert not np.any(np.isfinite(old)), old.round(1)                 # lost from the first frame before


def test_a_chain_alone_that_jumps_away_from_the_targets_motion_is_not_believed():
    """`vision-eval`'s `occlusion` sequence on the fundus photograph, seed 8, first 30 frames: on frame 21
    the instrument's round tip reaches the target; its patch decorrelates (0.05), but the selection
    keyframe's corners around it still follow, so the frame is accepted and tops its corners up with new
    ones, some on the instrument's outline. On frame 22 the keyframe no longer matched and the chain
    alone, following those corners, jumped 24 px with the instrument while the target drifted 0.5 px per
    frame: reported 24, 47 and 68 px off. A chain alone must stay near the target's motion: never at a
    wrong place."""
    target = PlanarTarget((0.2, 0.2), photo_texture("retina"), (0.0, 0.0))
    frames = render_sequence("occlusion", EvalSettings(photos=()), seed=8, target=target)[:30]
    errs, _ = _run(FeatureTracker(), frames)
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(1)     # never a wrong position
    old, _ = _run(FeatureTracker(TrackerSettings(chain_only_jump_px=1000.0)), frames)
    assert np.sum(old[np.isfinite(old)] > 8.0) >= 2, old.round(1)      # the false lock before


def test_a_target_strewn_with_glints_is_relocked_where_its_window_correlates_around_the_last_place():
    """`vision-eval`'s `occlusion` sequence on the mucosa, seed 5: the target window is strewn with small
    glints, so the whole-frame dense search has no template (nothing is left beyond the glints' whole
    band-pass halo), and the target, 13-22 px from where it was last seen, was never found again in the 21
    frames it was back in view. The local re-lock is now also seeded where the selection's window
    (glints left out with a few px of halo) correlates best around the last position: found again,
    never at a wrong place. (Following the scene's motion while lost finds it too: it is off for the
    comparison.)"""
    target = PlanarTarget.mucosa(seed=5, texture_px=RenderSettings().texture_px)
    _assert_found_again_after_the_instrument(target, 5, 12, TrackerSettings(local_seed_px=0.0, scene_relock=False))


def test_an_edge_like_window_is_widened_for_context():
    """`vision-eval`'s `tip` sequence on the coffee photograph, seed 6, first 25 frames: the target lies
    on the cup's plain white rim, and the 80 px window's texture is the rim's two edges and a glint
    (structure-tensor isotropy 0.06): it locates the target across the rim only. As the tip moves the
    view 13-23 px per frame, its 12 corners stopped following on frame 3 and the target was lost for
    the rest of the sequence (and of all 65 frames). With ``context_isotropy`` (0.15 by default, see
    docs/vision.md), selection widens such a window, here to 160 px (isotropy 0.13), where the
    surroundings hold corners in other directions: tracked within 3 px on most frames, never at a
    wrong position."""
    target = PlanarTarget((0.2, 0.2), photo_texture("coffee"), (0.0, 0.0))
    frames = render_sequence("tip", EvalSettings(photos=()), seed=6, target=target)[:25]
    tracker = FeatureTracker()
    errs, _ = _run(tracker, frames)
    assert tracker.selection["window_px"] > WINDOW and tracker.selection["isotropy"] >= 0.1, tracker.selection
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(1)      # never a wrong position
    assert np.sum(errs < 3.0) >= 18, errs.round(1)                    # tracked on most frames
    old, _ = _run(FeatureTracker(TrackerSettings(**EDGE_80)), frames)
    assert np.sum(np.isfinite(old)) <= 4, old.round(1)                # lost from frame 3 without it


def test_a_window_still_edge_like_after_widening_is_not_carried_by_its_dense_match():
    """`vision-eval`'s `fast` sequence on the coffee photograph, seed 17 (not tuned on), first 30 frames:
    the target is on a plain rim; widened for context to 160 px the window is still edge-like (isotropy
    0.07). Under the fast blurred motion its corners stop matching the keyframe, and the dense alignment
    of the keyframe window, which locates the target across the rim only, carried the frames while it
    and the chain slid along the rim together: 8.6-11.6 px off on 12 frames. Such a window's dense match
    is a miss: the target is reported lost instead."""
    target = PlanarTarget((0.2, 0.2), photo_texture("coffee"), (0.0, 0.0))
    frames = render_sequence("fast", EvalSettings(photos=()), seed=17, target=target)[:30]
    tracker = FeatureTracker()
    errs, _ = _run(tracker, frames)
    assert tracker.selection["window_px"] > WINDOW and tracker.selection["isotropy"] < 0.15, tracker.selection
    assert tracker.stats["edge_like_dense"] > 0
    assert np.all(errs[np.isfinite(errs)] < 8.5), errs.round(1)      # no frame reported on the slide
    slid, _ = _run(FeatureTracker(TrackerSettings(edge_like_dense=True)), frames)
    assert np.sum(slid[np.isfinite(slid)] > 8.5) >= 8, slid.round(1)  # before: carried along the rim


def test_a_later_keyframe_that_holds_the_instrument_does_not_relock_on_it():
    """`vision-eval`'s `occlusion` sequence on the fundus photograph, seed 15 (a seed the rules were
    not tuned on): the keyframe made on frame 20, as the instrument's round tip entered the window,
    holds the tip's outline. Once the target was covered and lost, that keyframe's dense template
    found the instrument 146 px away (correlation 0.94, leading 1.74) and the tracker re-locked on it:
    reported 54-192 px off on 34 frames. The selection's own window correlates 0.05 there: a later
    keyframe's candidate that the selection does not look like is dropped. Then, on the frame after the
    correct re-lock, the phase correlation followed the receding instrument and that keyframe's dense
    match agreed (27 px off, then 140-148 px on the instrument): the phase-placed dense match is now
    made against the selection keyframe only."""
    target = PlanarTarget((0.2, 0.2), photo_texture("retina"), (0.0, 0.0))
    frames = render_sequence("occlusion", EvalSettings(photos=()), seed=15, target=target)
    tracker = FeatureTracker()
    errs, _ = _run(tracker, frames)
    assert np.all(errs[np.isfinite(errs)] < 8.0), errs.round(1)      # never a wrong position
    assert tracker.stats["dense_anchor_disagrees"] > 0
    assert np.sum(errs < 4.0) >= 40, errs.round(1)                    # and tracked while visible
    old, _ = _run(FeatureTracker(TrackerSettings(dense_anchor_ncc=-1.0)), frames)
    assert np.sum(old[np.isfinite(old)] > 50.0) >= 20, old.round(1)    # on the instrument before


def test_a_target_moving_fast_from_the_first_frame_is_followed_by_the_corners_that_passed():
    """`vision-eval`'s `fast` sequence on the fundus photograph, seed 5: the target moves 17 px per
    frame from the first frame on, under ~7 px of motion blur. With no velocity yet to predict from,
    the phase correlation found no peak (0.01) and 35 of the 40 corners failed the forward-backward
    check; the 5 that passed moved within 3 px of the true motion. Seeded by their motion the chain
    carries the frame; without it the target was lost on frame 5 and found again only on frame 27."""
    target = PlanarTarget((0.2, 0.2), photo_texture("retina"), (0.0, 0.0))
    frames = render_sequence("fast", EvalSettings(photos=()), seed=5, target=target)[:30]
    tracker = FeatureTracker()
    errs, _ = _run(tracker, frames)
    assert np.all(errs < 4.0), errs.round(1)                        # every frame, within 4 px
    assert tracker.stats["survivor_seeds"] >= 1
    old, res = _run(FeatureTracker(TrackerSettings(survivor_seed=False)), frames)
    assert res[4].lost and not np.any(np.isfinite(old[:26])), old.round(1)


def test_the_keyframe_flow_on_local_mean_free_regions_does_not_drift_as_the_tip_approaches():
    """`vision-eval`'s `scale` sequence on the fundus photograph, seed 12: the tip approaches from 75 to
    30 mm (the target 2.5x larger) while it swings ±15 px. The light across the window changes as the tip
    comes nearer, and the faint vessels' flow follows it: the selection keyframe's corners came out
    0.9 px off their true places on average at 1.2x (frame 20), the chain agreed, and keyframes renewed on
    the way handed it on, 9.7 px off at frame 64 with full confidence. With the keyframe flow on the
    regions less their local mean (``key_flow_local``) the same corners are 0.05 px off and the target
    stays within ~1 px. Not yet the default: the tracker's other decisions (the tests above) were made
    with the plain flow."""
    target = PlanarTarget((0.2, 0.2), photo_texture("retina"), (0.0, 0.0))
    frames = render_sequence("scale", EvalSettings(photos=()), seed=12, target=target)
    errs, _ = _run(FeatureTracker(TrackerSettings(key_flow_local=True)), frames)
    assert np.all(errs < 2.5), errs.round(1)
    old, _ = _run(FeatureTracker(), frames)
    assert np.all(np.isfinite(old)) and old[-1] > 8.0, old.round(1)     # reported, 8+ px off


def test_a_target_lost_at_the_edge_of_the_view_is_relocked_at_the_scale_it_had_near_the_centre():
    """`vision-eval`'s `leave` on the fundus photograph, seed 5: the target runs out of the round view and
    comes back. Near the edge the lens distortion had shrunk the tracked scale (to ~0.66), and the local
    re-lock predicted the keyframe's corners at that scale where the target, coming back towards the
    centre, has its central scale again: none of the corners followed (seed 1: 0-1 of 40 with the place
    right to 0.5 px), and it re-locked late or not at all. Trying first the scale the distortion gives
    where the re-lock searches (``relock_central``: between the central one and the loss's) finds 8-12
    of them: re-locked 6 frames after it is back in view, where it took 11 and was lost again without."""
    target = PlanarTarget((0.2, 0.2), photo_texture("retina"), (0.0, 0.0))
    frames = render_sequence("leave", EvalSettings(photos=()), seed=5, target=target)
    visible = np.array([f.visible for f in frames[1:]])
    out = int(np.argmax(~visible))
    back = out + int(np.argmax(visible[out:]))        # the first frame back in view
    errs, _ = _run(FeatureTracker(), frames)
    assert np.all(errs[back + 6:] < 8.0), errs.round(1)
    old, _ = _run(FeatureTracker(TrackerSettings(relock_central=False)), frames)
    assert np.count_nonzero(~(old[back:] < 8.0)) >= 12, old.round(1)
