"""The scope bank: candidate endoscopes around the assumed one, and the selector that finds the one the
image follows (with an unknown delay) without switching away from a right assumption on noise."""
import numpy as np
import pytest

from targetlock.estimation import ScopeSelector, TipModel, scope_candidates
from targetlock.estimation.play import rough_residuals
from targetlock.model.endoscope import EndoscopeParams

DELAYS = np.arange(-0.16, 0.33, 0.04)
J = np.array([[-900.0, 0.0], [0.0, -800.0]])       # px per tip rad, a near target


def _run(truth: EndoscopeParams, candidates: list[EndoscopeParams], delay: float, seconds: float = 14.0,
         seed: int = 0, switch_times: list[float] | None = None) -> ScopeSelector:
    """Motor reversals on both axes (a lock hunting about the centre); the image follows ``truth``'s tip
    ``delay`` s behind the stamps, with 1 px tracker noise, 20 fps from 0.5 s on. The capture times of
    the frames that made the selector switch are appended to ``switch_times``."""
    rng = np.random.default_rng(seed)
    bank = TipModel(candidates, horizon=3.0)
    plant = TipModel(truth, horizon=3.0)
    start = np.radians([30.0, -20.0])
    bank.reset(0.0, start)
    plant.reset(0.0, start)
    sel = ScopeSelector(len(candidates), DELAYS)
    t, frame_every, next_frame = 0.0, 0.05, 0.5
    while t < seconds:
        t += 0.02
        handle = start + np.radians([12.0 * np.sin(2 * np.pi * 0.35 * t), 9.0 * np.sin(2 * np.pi * 0.23 * t + 1.0)])
        bank.update(t, handle)
        plant.update(t, handle)
        if t >= next_frame + 0.6:           # frames arrive 0.6 s after they are stamped
            c = next_frame
            x = J @ plant.tip_at(c - delay) + rng.normal(0.0, 1.0, 2)
            if sel.add(c, x, bank.all_tips_at(c - DELAYS), J) is not None and switch_times is not None:
                switch_times.append(c)
            next_frame += frame_every
    return sel


def test_candidates_start_with_the_assumed_scope_and_spread_around_it():
    assumed = EndoscopeParams()
    cands = scope_candidates(assumed, 32)
    assert len(cands) == 32 and cands[0] == assumed
    friction = np.array([c.mu_n / assumed.mu_n for c in cands[1:]])
    slack = np.array([c.cable_slack - assumed.cable_slack for c in cands[1:]])
    assert friction.min() < 0.8 and friction.max() > 1.8       # covers lighter and looped-shaft-like friction
    assert slack.min() < -0.0006 and slack.max() > 0.001       # pretensioned to very slack
    assert scope_candidates(assumed, 32) == cands              # deterministic
    with pytest.raises(ValueError, match="n = 0"):
        scope_candidates(assumed, 0)


def test_selector_finds_the_scope_the_image_follows_despite_an_unknown_delay():
    assumed = EndoscopeParams()
    cands = scope_candidates(assumed, 32)
    truth_index = 7
    sel = _run(cands[truth_index], cands, delay=0.12)
    assert sel.switches >= 1
    chosen = cands[sel.best]
    # The chosen candidate is the truth, or one whose loop is as wide (friction within 20 %, slack within 0.3 mm).
    assert abs(chosen.mu_n / cands[truth_index].mu_n - 1.0) < 0.2
    assert abs(chosen.cable_slack - cands[truth_index].cable_slack) < 0.0003


def test_selector_keeps_a_right_assumption_over_noise():
    cands = scope_candidates(EndoscopeParams(), 32)
    for seed in range(3):
        sel = _run(cands[0], cands, delay=0.0, seed=seed)
        assert sel.best == 0 and sel.switches == 0


def test_selector_ignores_garbage_frames():
    sel = ScopeSelector(4, DELAYS)
    motions = np.zeros((DELAYS.size, 4, 2))
    assert sel.add(1.0, np.array([np.nan, 0.0]), motions, J) is None
    assert sel.add(1.0, np.zeros(2), np.zeros((3, 4, 2)), J) is None       # wrong shape
    assert sel.add(float("inf"), np.zeros(2), motions, J) is None
    assert len(sel.frames) == 0 and sel.best == 0


def test_selector_switches_as_soon_as_it_judges_when_the_evidence_is_strong():
    """With a lot of own motion (reversals on both axes every ~1.5 s) the first judgements (from 15
    frames, 0.75 s of frames at 20 fps) already find the scope: the switch comes within 1.5 s of frames
    (about one reversal per axis), not seconds later."""
    cands = scope_candidates(EndoscopeParams(), 32)
    truth = cands[12]
    switched_at: list[float] = []
    sel = _run(truth, cands, delay=0.12, seconds=8.0, switch_times=switched_at)
    first_frame, fps = 0.5, 20.0
    assert switched_at and switched_at[0] <= first_frame + 30 / fps + 1e-9
    assert abs(cands[sel.best].mu_n / truth.mu_n - 1.0) < 0.2
    assert abs(cands[sel.best].cable_slack - truth.cable_slack) < 0.0003


def _closed_loop(preset: str, distance: float, path: str, seconds: float = 10.0):
    """``adaptive`` (nominal knowledge: the calibrated scope) locking on the twin of ``preset``; returns
    the controller, the times (s) and the candidate it steered with at each tick, and each candidate's
    error (deg rms, after the best gain and offset per axis) in explaining the twin's true tip angles."""
    import dataclasses

    from targetlock.controllers import ControllerConfig, KnowledgeConfig
    from targetlock.experiments.target_lock import RunConfig, build_controller, build_rig
    from targetlock.loop.clock import SimClock
    from targetlock.loop.gate import ObservationGate
    from targetlock.loop.runner import ControlLoop, LoopConfig
    from targetlock.model.twin import twin_config

    twin = twin_config(preset)
    twin = dataclasses.replace(twin, scene=dataclasses.replace(twin.scene, path=path, distance=distance))
    cfg = RunConfig(twin=twin, controller=ControllerConfig(kind="adaptive"), knowledge=KnowledgeConfig(),
                    loop=LoopConfig(seconds=seconds))
    rig = build_rig(cfg)
    c = build_controller(cfg, rig)
    loop = ControlLoop(rig, c, rate=cfg.loop.rate, clock=SimClock(),
                       gate=ObservationGate.for_camera(cfg.loop.gate, rig.camera))
    times, handles, tips, member = [], [], [], []

    def on(tick):
        times.append(tick.time)
        handles.append(rig.handle_angles())
        tips.append(rig.tip_angles())
        member.append(c.tip_model.member if c.engaged else 0)

    loop.run(seconds, on)
    times, handles, tips, member = map(np.array, (times, handles, tips, member))
    bank = TipModel(c.tip_model.endoscopes, horizon=seconds + 1.0)
    bank.reset(times[0], handles[0])
    for t, h in zip(times[1:], handles[1:]):
        bank.update(t, h)
    modelled = bank.all_tips_at(times)                   # (n, candidates, 2)
    err = np.zeros(modelled.shape[1])
    for k in range(err.size):
        for a in range(2):
            design = np.column_stack([modelled[:, k, a], np.ones(times.size)])
            coef, *_ = np.linalg.lstsq(design, tips[:, a], rcond=None)
            err[k] += np.mean((design @ coef - tips[:, a]) ** 2)
    return c, times, member, np.degrees(np.sqrt(err))


@pytest.fixture(scope="module")
def looped_shaft_run():
    return _closed_loop("looped-shaft", 0.03, "ellipse", seconds=12.0)


def test_in_the_loop_it_finds_a_looped_shaft(looped_shaft_run):
    """On a looped shaft (friction and slack far from the assumed calibrated scope) at 3 cm, the lock
    steers, within 6 s of engaging and from then on, with a candidate that explains the true tip more
    than 2x better than the assumed one (measured: from 3.1 s, 2.7x; from 7.6 s, 12x; with the paired t-test
    before the likelihood ratio: from 5.8 s, 2.5x)."""
    c, times, member, err = looped_shaft_run
    assert err[0] > 2.0                                   # the assumed scope is far off (deg)
    good = err[member] < 0.5 * err[0]
    assert good.any() and np.all(good[np.argmax(good):])
    assert times[np.argmax(good)] - times[0] < 6.0


@pytest.mark.xfail(strict=True, reason="open goal: the first switch (3.1 s) goes to a candidate only 2.7x better "
                                       "than the assumed one; a 12x better one follows at 7.6 s (with the paired "
                                       "t-test before: first a worse one at 4.5 s)")
def test_in_the_loop_its_first_switch_on_a_looped_shaft_is_to_a_good_candidate_within_5_s(looped_shaft_run):
    c, times, member, err = looped_shaft_run
    switched = member != 0
    assert switched.any() and times[np.argmax(switched)] - times[0] < 5.0
    assert err[member[np.argmax(switched)]] < 0.3 * err[0]


@pytest.mark.parametrize("distance, path", [(0.03, "ellipse"), (0.06, "step"), (0.12, "linear")])
def test_in_the_loop_it_keeps_the_assumed_scope_when_that_is_the_real_one(distance, path):
    """On the report's straight path at 12 cm the paired t-test the selector used before switched at
    4.5 s to a candidate 100x worse (a group of very different candidates tied within 1 %, all
    'significantly' better than the assumed scope); the likelihood ratio keeps the right one."""
    c, times, member, err = _closed_loop("calibrated", distance, path)
    assert c.selector.switches == 0 and np.all(member == 0)


def test_rows_only_the_right_candidate_explains_count_and_rows_none_explains_are_dropped():
    """The selector's criterion (``rough_residuals`` with common outliers): the tip's stick-slip jumps
    are in the image and in the right candidate's modelled motion only; the wrong candidates move
    the same distance smoothly. The jump frames must stay in the judgement (they are what tells the
    scopes apart), a tracker outlier that no candidate explains must be dropped for all of them, and
    the right candidate must come out clearly best."""
    rng = np.random.default_rng(3)
    n, wrong = 120, 9
    t = np.arange(n) * 0.05
    smooth = np.column_stack([0.08 * np.sin(2 * np.pi * 0.3 * t), 0.05 * np.sin(2 * np.pi * 0.2 * t + 1.0)])
    jumps = (20, 50, 80, 105)
    steps = np.zeros((n, 2))
    ramps = np.zeros((n, 2))
    for k in jumps:
        steps[k:, 0] += 0.03                                       # rad, a slip of the tip in one frame
        ramps[k - 5:, 0] += 0.03 * np.clip(np.arange(n - k + 5) / 10.0, 0.0, 1.0)   # the same slip over 10 frames
    p = np.stack([smooth + steps] + [smooth + ramps] * wrong)      # candidate 0 is right
    x = (J @ (smooth + steps).T).T + rng.normal(0.0, 0.5, (n, 2))
    outlier = 66
    x[outlier] += (40.0, -30.0)                                    # a tracker jump for one frame
    _, rn, kept = rough_residuals(x, p, J, common_outliers=True)
    # Row i is the increment into frame i + 1.
    assert np.all(kept[:, np.array(jumps) - 1] == 1)              # the jumps count, for every candidate
    assert np.all(kept[:, [outlier - 1, outlier]] == 0)            # the outlier's two increments do not
    assert np.all(kept == kept[0])                                 # the same rows for all
    cost = np.sum(rn * kept, axis=1)
    assert cost[0] < 0.6 * cost[1:].min()


def _stick_slip_frames(follow_right: bool, seed: int, n: int = 130) -> tuple[ScopeSelector, list[int]]:
    """Two candidates that differ only in 6 frames: the right one (1) slips 0.02 rad in one frame where the
    assumed one (0) moves the same distance smoothly over 10 frames; 1 px tracker noise. The image follows
    candidate 1 or 0. Returns the selector and the frames at which it switched."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.05
    smooth = np.column_stack([0.08 * np.sin(2 * np.pi * 0.3 * t), 0.05 * np.sin(2 * np.pi * 0.2 * t + 1.0)])
    steps, ramps = np.zeros((n, 2)), np.zeros((n, 2))
    for k in (15, 37, 58, 79, 98, 117):
        steps[k:, 0] += 0.02
        ramps[k - 5:, 0] += 0.02 * np.clip(np.arange(n - k + 5) / 10.0, 0.0, 1.0)
    cands = np.stack([smooth + ramps, smooth + steps], axis=1)      # (n, 2 candidates, 2)
    seen = cands[:, 1 if follow_right else 0]
    sel = ScopeSelector(2, np.array([0.0]))
    switched = []
    for i in range(n):
        x = J @ seen[i] + rng.normal(0.0, 1.0, 2)
        if sel.add(t[i], x, cands[i][None], J) is not None:
            switched.append(i)
    return sel, switched


def test_a_few_stick_slip_frames_are_enough_to_switch_and_noise_is_not():
    """What tells two scopes apart is often only their stick-slip: 6 frames of 130 here, each a 18 px
    jump the wrong candidate spreads over 10 frames. The selector switches to the right candidate at
    the first judgement after its second slip (frame 37; within 45 frames); when the image follows the
    assumed candidate it never switches on the noise."""
    for seed in range(4):
        sel, switched = _stick_slip_frames(True, seed)
        assert sel.best == 1 and switched and switched[0] <= 45, (seed, switched)
        sel, switched = _stick_slip_frames(False, seed)
        assert sel.best == 0 and not switched, (seed, switched)


def test_selector_judges_from_min_frames_and_more_often_until_its_window_is_full():
    """The first seconds after engaging are where a wrong model costs most: the first window is judged
    at ``min_frames``, then every ``every_while_filling`` frames until ``window`` frames are in, then
    every ``every`` frames."""
    sel = ScopeSelector(4, DELAYS, window=60, every=10, every_while_filling=5, min_frames=20)
    rng = np.random.default_rng(0)
    judged_at = []
    for i in range(1, 121):
        before = sel.judged
        sel.add(0.05 * i, rng.normal(0.0, 1.0, 2), rng.normal(0.0, 0.01, (DELAYS.size, 4, 2)), J)
        if sel.judged > before:
            judged_at.append(i)
    assert judged_at == [20, 25, 30, 35, 40, 45, 50, 55, 60, 70, 80, 90, 100, 110, 120]


@pytest.mark.parametrize("kw", [{"every": 0}, {"every_while_filling": 0}, {"min_frames": 1},
                                {"min_frames": 121, "window": 120}])
def test_selector_rejects_a_cadence_it_cannot_keep(kw):
    with pytest.raises(ValueError, match="ScopeSelector"):
        ScopeSelector(4, DELAYS, **kw)


def test_selector_rejects_a_threshold_that_is_not_positive():
    with pytest.raises(ValueError, match="min_evidence"):
        ScopeSelector(4, DELAYS, min_evidence=0.0)
