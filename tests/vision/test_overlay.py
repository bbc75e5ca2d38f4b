"""Overlay: draws centre cross, target, error line and text without touching the input."""
import numpy as np

from targetlock.vision import TrackResult, draw_overlay


def test_overlay_draws_state_and_keeps_the_input():
    img = np.full((576, 720, 3), 50, np.uint8)
    before = img.copy()
    res = TrackResult(np.array([500.0, 200.0]), 0.8, True, False)
    out = draw_overlay(img, res, centre_px=(360, 288), truth_px=(502.0, 201.0), lines=["t = 1.00 s"])
    assert np.array_equal(img, before)
    changed = np.any(out != before, axis=2)
    assert changed[288, 350:371].any() and changed[278:299, 360].any()       # centre cross
    assert changed[190:211, 490:511].any()                                  # target marker
    assert changed[244, 420:440].any()                                      # line centre -> target
    assert changed[540:576, 0:300].any()                                    # text at the bottom left
    assert tuple(out[200, 490]) != (50, 50, 50) and out[200, 490][1] > 150  # green when valid


def test_overlay_marks_lost_and_rejected_frames():
    img = np.zeros((200, 300, 3), np.uint8)
    lost = draw_overlay(img, TrackResult(np.full(2, np.nan), 0.0, False, True))
    assert (lost[:40] > 0).any()                                            # "LOST" banner
    held = draw_overlay(img, TrackResult(np.array([100.0, 100.0]), 0.0, False, False))
    b, g, r = held[100, 90].astype(int)
    assert r > 200 and g > 100 and b < 80                                   # orange: held position
