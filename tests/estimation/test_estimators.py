import math

import numpy as np
import pytest

from targetlock.estimation import (BacklashEstimator, BacklashFitEstimator, DelayEstimator, DelayFitEstimator, DriftEstimator,
                                   JacobianEstimator, prior_jacobian)
from targetlock.model.camera import CameraParams

J_TRUE = np.array([[-620.0, 90.0], [-60.0, -540.0]])     # px per handle rad, with cross coupling
PRIOR = np.array([[-300.0, 0.0], [0.0, -300.0]])


def smooth_motion(t):
    """Handle angles (rad) of an excitation like a lock's own motion: two axes, several frequencies."""
    return np.column_stack([0.2 * np.sin(1.3 * t) + 0.05 * np.sin(4.1 * t),
                            0.15 * np.sin(0.9 * t + 1.0) + 0.05 * np.sin(3.3 * t)])


def feed(est, t, m, x):
    for k in range(1, len(t)):
        est.update(m[k] - m[k - 1], x[k] - x[k - 1], t[k] - t[k - 1])


def test_jacobian_converges_with_a_moving_target_noise_and_outliers():
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 20.0, 0.05)
    m = smooth_motion(t)
    target = np.column_stack([15.0 * t, -8.0 * t])                 # the target drifts in the image
    x = m @ J_TRUE.T + target + rng.normal(0.0, 1.0, (t.size, 2))
    bad = rng.random(t.size) < 0.03
    x[bad] += rng.uniform(-150, 150, (bad.sum(), 2))                # tracker outliers
    keep = rng.random(t.size) > 0.1                                  # dropped frames
    est = JacobianEstimator(PRIOR)
    feed(est, t[keep], m[keep], x[keep])
    assert np.linalg.norm(est.j - J_TRUE) / np.linalg.norm(J_TRUE) < 0.15
    assert est.velocity == pytest.approx([15.0, -8.0], abs=5.0)
    assert est.rejected > 0


def test_jacobian_stays_bounded_and_oriented_under_garbage():
    rng = np.random.default_rng(2)
    est = JacobianEstimator(PRIOR, sv_min=100.0, sv_max=3000.0)
    for _ in range(2000):
        dm = rng.normal(0, 0.05, 2) * rng.choice([1.0, 1e6, np.nan], p=[0.8, 0.1, 0.1])
        dx = rng.normal(0, 1.0, 2) * rng.choice([1.0, 1e300, -1e9, np.inf], p=[0.7, 0.1, 0.1, 0.1])
        est.update(dm, dx, rng.choice([0.05, 0.0, -1.0, np.nan]))
        s = np.linalg.svd(est.j, compute_uv=False)
        assert np.all(np.isfinite(est.j)) and 100.0 - 1e-6 <= s.min() and s.max() <= 3000.0 + 1e-6
        assert np.linalg.det(est.j) > 0 and est.j[0, 0] < 0 and est.j[1, 1] < 0


def test_a_stuck_tip_does_not_shrink_the_jacobian():
    """Motor motion without image motion (deadband, friction) says nothing about J."""
    est = JacobianEstimator(PRIOR)
    for _ in range(200):
        est.update(np.array([0.01, 0.0]), np.zeros(2), 0.05)
    np.testing.assert_allclose(est.j, PRIOR)


def stick_slip(j_true, n=40, every=4):
    """Motor increments (rad) of a slow sweep and the image increments (px) of a tip that sticks and
    catches up at every ``every``-th frame (break-free), 0.3 px noise."""
    rng = np.random.default_rng(0)
    m = np.cumsum(np.tile([[0.004, -0.003]], (n, 1)), axis=0)
    tip = m.copy()
    for k in range(n):
        if k % every != every - 1:
            tip[k] = tip[k - 1] if k else 0.0
    x = tip @ j_true.T + rng.normal(0.0, 0.3, (n, 2))
    return np.diff(m, axis=0), np.diff(x, axis=0)


def test_break_free_jumps_grow_a_too_small_jacobian_within_a_second():
    """Near the target the prior is several times too small; the stick-slip shows the true J only in
    the jumps at break-free, which must count (J grows by up to max_growth on them), not be clipped
    as outliers (J then reached 0.41 of the truth after 12 pairs)."""
    j_true = 3.0 * np.array([[-300.0, 30.0], [-20.0, -300.0]])
    dm, dx = stick_slip(j_true)
    est = JacobianEstimator(PRIOR)
    size = []
    for a, b in zip(dm, dx):
        est.update(a, b, 0.05)
        size.append(np.linalg.norm(est.j) / np.linalg.norm(j_true))
    assert size[11] > 0.9                  # three break-free jumps, 0.6 s at 20 fps
    assert np.all(np.diff(size) >= -1e-9)  # the stuck frames between them never shrink it
    assert est.rejected == 0


def test_a_sideways_jump_does_not_grow_the_jacobian():
    """A jump of the target across our own motion is no evidence of a larger J, even where the image
    also moved twice as far along our motion as J predicts: still an outlier."""
    est = JacobianEstimator(PRIOR)
    for _ in range(20):                    # J about right: the image follows the motor
        est.update(np.array([0.01, 0.0]), PRIOR @ [0.01, 0.0], 0.05)
    before = est.j.copy()
    est.update(np.array([0.01, 0.0]), 2.0 * PRIOR @ [0.01, 0.0] + [0.0, 200.0], 0.05)
    assert est.rejected == 1
    np.testing.assert_allclose(est.j, before)


def test_the_pairs_bound_the_size_of_j_from_above_even_under_stick_slip():
    """size_bound: margin x the largest ratio of seen to predicted image motion of any pair (>= 1 px
    predicted by the prior) x the prior's size, once enough image motion was seen along the prior's
    predictions. A sticking tip's pairs do not lower it and its break-free jumps raise it, so near the
    target (J 3x the prior) it lies above the true J; far away (J about the prior) it stays near it."""
    true_size = 3.0 * 300.0
    est = JacobianEstimator(PRIOR)
    assert est.size_bound(20.0, 1.0) is None                    # nothing seen yet
    for a, b in zip(*stick_slip(3.0 * np.array([[-300.0, 30.0], [-20.0, -300.0]]))):
        est.update(a, b, 0.05)
    assert est.size_bound(20.0, 1.0) > true_size

    rng = np.random.default_rng(3)
    far = JacobianEstimator(PRIOR)
    dm = np.array([0.008, -0.006])                              # 3 px per pair predicted
    for k in range(10):
        far.update(dm, PRIOR @ dm + rng.normal(0.0, 0.3, 2), 0.05)
        if far.seen_along_prior < 20.0:
            assert far.size_bound(20.0, 1.0) is None
    assert 300.0 <= far.size_bound(20.0, 1.0) < 1.5 * 300.0
    assert far.size_bound(20.0, 1.5) == pytest.approx(1.5 * far.size_bound(20.0, 1.0))


def test_the_size_bound_ignores_pairs_without_predicted_or_seen_motion():
    """Pairs the prior predicts less than 1 px for (the motor barely moved: any image motion is the
    target's own) and pairs of a stuck tip (no image motion) give no bound, however many."""
    est = JacobianEstimator(PRIOR)
    for _ in range(100):
        est.update(np.array([0.001, 0.0]), np.array([-5.0, 0.0]), 0.05)   # 0.3 px predicted, 5 px seen
        est.update(np.array([0.01, 0.0]), np.zeros(2), 0.05)              # 3 px predicted, none seen
    assert est.size_bound(20.0, 1.0) is None


def test_prior_is_the_kinematic_jacobian_and_grows_at_short_distance():
    cam = CameraParams()
    near = prior_jacobian(np.zeros(2), camera=cam, depth=0.01, tip_gain=0.8, tip_length=0.12, n_elements=30)
    far = prior_jacobian(np.zeros(2), camera=cam, depth=0.12, tip_gain=0.8, tip_length=0.12, n_elements=30)
    # A bend turns the camera (f px/rad) and moves it sideways by about L/2 per rad: f·(1 + L/2d).
    assert abs(far[0, 0]) == pytest.approx(0.8 * 300 * (1 + 0.06 / 0.12), rel=0.1)
    assert abs(near[0, 0]) > 4 * abs(far[0, 0])
    assert abs(far[0, 1]) < 1e-6 * abs(far[0, 0])


def delayed_image(est, delay, drift, given):
    """Feed ``est`` frames showing the motor's image ``delay`` s late (plus the target's own ``drift(t)``
    px and 1 px noise), handing it the Jacobian ``given``; return it."""
    rng = np.random.default_rng(3)
    t_motor = np.arange(-2.0, 12.0, 0.02)
    m = smooth_motion(t_motor) + np.column_stack([np.cumsum(rng.normal(0, 0.004, t_motor.size))] * 2)
    motor_at = lambda ts: np.column_stack([np.interp(ts, t_motor, m[:, k]) for k in range(2)])  # noqa: E731
    for tc in np.arange(0.0, 12.0, 0.05):
        x = motor_at(np.array([tc - delay]))[0] @ J_TRUE.T + drift(tc) + rng.normal(0, 1.0, 2)
        est.add(tc, x, motor_at, given)
    return est


@pytest.mark.parametrize("delay", [0.0, 0.2, 0.35])
def test_delay_is_found_within_one_frame(delay):
    est = delayed_image(DelayEstimator(initial=0.0), delay, lambda t: 0.0, J_TRUE)
    assert est.delay == pytest.approx(delay, abs=0.05)


@pytest.mark.parametrize("delay", [-0.15, 0.0, 0.2])
def test_delay_fit_within_one_frame_with_a_moving_target_and_the_prior_jacobian(delay):
    """The target drifts on its own; the estimator is handed the prior, not the true J."""
    est = delayed_image(DelayFitEstimator(initial=0.0), delay, lambda t: np.array([30.0 * np.sin(0.4 * t), 12.0 * t]),
                        PRIOR)
    assert est.delay == pytest.approx(delay, abs=0.05)
    assert est.lo <= est.delay <= est.hi


@pytest.mark.parametrize("cls", [DelayEstimator, DelayFitEstimator])
def test_delay_stays_in_bounds_without_motion_or_with_garbage(cls):
    est = cls(initial=0.1, lo=-0.2, hi=0.8)
    rng = np.random.default_rng(4)
    still = lambda ts: np.zeros((np.size(ts), 2))  # noqa: E731
    for k in range(300):
        est.add(0.05 * k, rng.normal(0, 50, 2) if k % 7 else np.array([np.nan, 1e300]), still, J_TRUE)
    assert est.delay == 0.1


def play(m, width):
    """Backlash: the output follows the input only beyond half the width either side."""
    out = np.empty_like(m)
    y = m[0]
    for k, u in enumerate(m):
        y = min(max(y, u - width / 2), u + width / 2)
        out[k] = y
    return out


@pytest.mark.parametrize("width", [0.06, 0.12])
def test_backlash_width_within_20_percent_after_a_few_reversals(width):
    t = np.arange(0.0, 30.0, 0.05)
    m = np.column_stack([0.3 * np.sin(2 * np.pi * t / 6.0), 0.2 * np.sin(2 * np.pi * t / 8.0 + 0.5)])
    j = np.diag([-500.0, -500.0])
    tip = np.column_stack([play(m[:, 0], width), play(m[:, 1], width)])
    x = tip @ j.T + np.random.default_rng(5).normal(0, 0.5, tip.shape)
    est = BacklashEstimator(threshold_px=3.0)
    for k in range(t.size):
        est.add(m[k], x[k], j)
    assert est.reversals >= 4
    assert est.width(0.3) == pytest.approx(width, rel=0.2)


def test_backlash_estimate_is_bounded():
    est = BacklashEstimator(max_width=0.5)
    rng = np.random.default_rng(6)
    for _ in range(2000):
        est.add(rng.normal(0, 1.0, 2), rng.normal(0, 500, 2) * rng.choice([1, np.nan], p=[0.95, 0.05]), np.diag([-300.0, -300.0]))
    for bend in (0.0, 1.0, 3.0):
        assert 0.0 <= est.width(bend) <= 0.5
    assert math.isfinite(est.width(1.0))


@pytest.mark.parametrize("width", [0.06, 0.12, 0.3])
def test_backlash_fit_per_axis_within_20_percent_with_a_moving_target_and_a_wrong_jacobian(width):
    t = np.arange(0.0, 30.0, 0.05)
    m = np.column_stack([0.4 * np.sin(2 * np.pi * t / 6.0), 0.3 * np.sin(2 * np.pi * t / 8.0 + 0.5)])
    j = np.diag([-500.0, -450.0])
    tip = np.column_stack([play(m[:, 0], width), play(m[:, 1], 0.8 * width)])
    drift = np.column_stack([40.0 * np.sin(0.3 * t), 25.0 * np.cos(0.2 * t)])          # the target moves, smoothly
    x = tip @ j.T + drift + np.random.default_rng(5).normal(0, 0.5, tip.shape)
    est = BacklashFitEstimator()
    for k in range(t.size):
        est.add(m[k], x[k], 1.6 * j)                   # the J handed in is 60 % too large
    assert est.reversals >= 4
    assert est.axis_width(0, 0.3) == pytest.approx(width, rel=0.2)
    assert est.axis_width(1, 0.3) == pytest.approx(0.8 * width, rel=0.2)


def feed_drift(est, w, fps=20.0, seconds=4.0, j=np.array([[-400.0, 0.0], [0.0, -380.0]]), seed=0, own=None):
    """Frames of a target at ``w(t)`` (px, in the unbent scope's image) while the tip sits at ``own(t)``
    (equivalent handle rad), with 0.8 px of tracker noise; returns the last velocity."""
    rng = np.random.default_rng(seed)
    for t in np.arange(0.0, seconds, 1.0 / fps):
        e = np.zeros(2) if own is None else own(t)
        v = est.add(t, w(t) + j @ e + rng.normal(0.0, 0.8, 2), e, j)
    return v


def test_drift_estimator_reads_a_steady_drift_through_our_own_motion():
    # The tip follows the target, so the image barely moves: the drift is in image + J·(own motion).
    v = feed_drift(DriftEstimator(), lambda t: np.array([8.0 * t, -5.0 * t]),
                   own=lambda t: np.array([8.0 * t, -5.0 * t]) / 400.0 * 0.9)
    np.testing.assert_allclose(v, [8.0, -5.0], atol=0.8)


@pytest.mark.parametrize("case,w", [
    ("still target", lambda t: np.array([3.0, -2.0])),
    ("a step", lambda t: np.array([40.0, 0.0]) * (t > 3.0)),
    ("a drift that stopped", lambda t: np.array([10.0, 0.0]) * min(t, 2.5)),
    ("a slow wobble", lambda t: np.array([6.0 * np.sin(2.0 * t), 0.0])),
])
def test_drift_estimator_reports_no_drift_where_there_is_none(case, w):
    assert np.all(feed_drift(DriftEstimator(), w) == 0.0), case
