"""The scope bank: candidate endoscopes around the assumed one, and the selector that finds the one the
image follows (with an unknown delay) without switching away from a right assumption on noise."""
import numpy as np
import pytest

from targetlock.estimation import ScopeSelector, TipModel, scope_candidates
from targetlock.model.endoscope import EndoscopeParams

DELAYS = np.arange(-0.16, 0.33, 0.04)
J = np.array([[-900.0, 0.0], [0.0, -800.0]])       # px per tip rad, a near target


def _run(truth: EndoscopeParams, candidates: list[EndoscopeParams], delay: float, seconds: float = 14.0,
         seed: int = 0) -> ScopeSelector:
    """Motor reversals on both axes (a lock hunting about the centre); the image follows ``truth``'s tip
    ``delay`` s behind the stamps, with 1 px tracker noise, 20 fps."""
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
            sel.add(c, x, bank.all_tips_at(c - DELAYS), J)
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
