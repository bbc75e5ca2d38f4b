"""The image Jacobian relative to the modelled tip (TipJacobianEstimator) on synthetic frames: the
camera model's geometry, recovery of J and depth while the tip follows a moving target, and bounds."""
import math

import numpy as np
import pytest

from targetlock.estimation import TipJacobianEstimator, image_jacobian_parts, prior_jacobian
from targetlock.model.camera import CameraParams, project, world_to_camera
from targetlock.model.kinematics import tip_pose

CAM = CameraParams()
GEOMETRY = dict(tip_length=0.12, n_elements=30)


def test_parts_are_the_pinhole_geometry():
    """A/Z + R is the image motion per tip rad at depth Z: at the centre it is the prior's (which
    differentiates the kinematics directly); the rotation part grows off centre as f·(1 + x²/f²) and
    gains the cross term x·y/f; the translation part shrinks with depth as 1/Z."""
    motor = np.array([-0.3, 0.2])
    gain = 0.8
    a, r = image_jacobian_parts(np.zeros(2), gain * motor, camera=CAM, **GEOMETRY)
    for depth in (0.015, 0.05, 0.12):
        np.testing.assert_allclose((a / depth + r) * gain, prior_jacobian(motor, camera=CAM, depth=depth, tip_gain=gain,
                                                                           **GEOMETRY), rtol=2e-3, atol=0.5)
    a0, r0 = image_jacobian_parts(np.zeros(2), np.zeros(2), camera=CAM, **GEOMETRY)
    assert r0[0, 0] == pytest.approx(-CAM.fx, rel=1e-3) and r0[1, 1] == pytest.approx(-CAM.fy, rel=1e-3)
    a1, r1 = image_jacobian_parts(np.array([150.0, 100.0]), np.zeros(2), camera=CAM, **GEOMETRY)
    assert r1[0, 0] == pytest.approx(-CAM.fx * (1 + (150 / CAM.fx) ** 2), rel=0.01)
    assert abs(r1[1, 0]) == pytest.approx(150 * 100 / CAM.fx, rel=0.02)
    assert np.all(np.sign(np.diag(a0)) == np.sign(np.diag(r0)))     # both move the image the same way
    # half the bending section's length of sideways travel per tip rad (a constant-curvature arc)
    assert abs(a0[0, 0]) == pytest.approx(CAM.fx * 0.06, rel=0.05)


def frames(depth, seconds=14.0, fps=22.0, noise=0.2, seed=0, step=0.01, lag=4):
    """A tip following a target that moves on a circle (0.4 × depth radius, 0.1 Hz) by a lagging loop
    (``lag`` frames late, 30 % of the offset per frame), in stick-slip: the tip stays until the command
    is ``step`` rad away, then jumps to it. Returns capture times, offsets (px), tip angles (rad) per
    frame and the true J (px per tip rad) per frame."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1.0 / fps)
    start = np.array([-0.2, 0.1])
    pose0 = tip_pose(start[0], start[1], 0.12, 30)
    centre = pose0[:3, :3] @ np.array([0.0, 0.0, depth]) + pose0[:3, 3]
    w = 2 * math.pi * 0.1
    target = centre + 0.4 * depth * np.column_stack([np.cos(w * t) - 1, np.sin(w * t), 0 * t]) @ pose0[:3, :3].T
    x = np.zeros((t.size, 2))
    tip = np.repeat(start[None], t.size, axis=0)
    j = np.empty((t.size, 2, 2))
    command = start.copy()
    for k in range(t.size):
        if k > lag:
            command = command - 0.3 * np.linalg.solve(j[k - lag - 1], x[k - lag - 1])
        tip[k] = tip[k - 1] if k else start
        if np.abs(command - tip[k]).max() > step:
            tip[k] = command
        p = world_to_camera(tip_pose(tip[k, 0], tip[k, 1], 0.12, 30), target[k])
        x[k] = project(p, CAM) - (CAM.cx, CAM.cy)
        a, r = image_jacobian_parts(x[k], tip[k], camera=CAM, **GEOMETRY)
        j[k] = a / p[2] + r
    return t, x + rng.normal(0.0, noise, x.shape), tip, j


def feed(est, t, x, tip):
    out = []
    for k in range(t.size):
        est.add(t[k], x[k], lambda times: np.column_stack([np.interp(times, t, tip[:, a]) for a in range(2)]))
        out.append(est.j.copy())
    return np.array(out)


@pytest.mark.parametrize("depth,model_gain", [(0.015, 1.0), (0.05, 1.0), (0.05, 0.8), (0.12, 1.0)])
def test_recovers_j_and_depth_while_following_a_moving_target(depth, model_gain):
    """From the 12 cm prior, after 6 s J (px per handle rad, the whole matrix) is within 5 % of the
    truth on every frame and the depth within 15 % (measured: 2-4 %, 2-6 %). A model whose tip moves 20 %
    less than the true one (its slope, handle to modelled tip, 20 % lower too) still gives J within
    5 %: what the fit gets per modelled tip radian, the slope gives back per handle radian."""
    t, x, tip, j_true = frames(depth)
    slope = np.array([0.87, 0.83])                  # true tip per handle rad
    est = TipJacobianEstimator(camera=CAM, slope=slope * model_gain, depth=0.12, **GEOMETRY)
    j = feed(est, t, x, tip * model_gain)
    late = t > 6.0
    truth = j_true[late] * slope
    err = np.linalg.norm(j[late] - truth, axis=(1, 2)) / np.linalg.norm(truth, axis=(1, 2))
    assert err.max() < 0.05
    if model_gain == 1.0:
        assert est.depth == pytest.approx(depth, rel=0.15)
        assert est.shift == pytest.approx(0.0, abs=0.011)


def test_a_wrong_delay_is_found_by_the_shift():
    """Tip-model times 40 ms early (a delay estimate off by that much): the chosen shift puts it right."""
    t, x, tip, _ = frames(0.05)
    est = TipJacobianEstimator(camera=CAM, slope=1.0, depth=0.12, **GEOMETRY)
    feed(est, t, x, tip)
    late = TipJacobianEstimator(camera=CAM, slope=1.0, depth=0.12, **GEOMETRY)
    for k in range(t.size):
        late.add(t[k], x[k], lambda times: np.column_stack([np.interp(times, t + 0.04, tip[:, a]) for a in range(2)]))
    assert late.shift == pytest.approx(-0.04, abs=0.011)
    assert late.depth == pytest.approx(est.depth, rel=0.1)


def test_without_tip_motion_it_keeps_the_prior():
    """A tip at rest (the target moving alone) says nothing about J: no update, the prior stays."""
    t, x, tip, _ = frames(0.05)
    est = TipJacobianEstimator(camera=CAM, slope=1.0, depth=0.12, **GEOMETRY)
    feed(est, t, x, np.repeat(tip[:1], t.size, axis=0))
    assert est.updates == 0 and est.depth == pytest.approx(0.12)


def test_stays_bounded_under_garbage():
    rng = np.random.default_rng(5)
    est = TipJacobianEstimator(camera=CAM, slope=0.87, depth=0.12, sv_min=100.0, sv_max=3000.0, **GEOMETRY)
    tip = np.zeros(2)
    for k in range(600):
        tip = tip + rng.normal(0.0, 0.02, 2)
        x = rng.choice([1.0, 50.0, 1e3, 1e9, np.nan]) * rng.normal(0.0, 1.0, 2)
        bad = rng.choice([0.0, 0.3, np.nan])
        est.add(0.05 * k + (bad if k % 7 == 0 else 0.0), x, lambda times, tp=tip.copy(): np.tile(tp, (len(times), 1)),
                delay=float(rng.choice([0.0, 0.1, np.nan])))
        s = np.linalg.svd(est.j, compute_uv=False)
        assert np.all(np.isfinite(est.j)) and 100.0 - 1e-6 <= s.min() and s.max() <= 3000.0 + 1e-6
        assert 0.005 <= est.depth <= 0.5 and np.all((est.gain >= 0.5) & (est.gain <= 2.0))


def test_bad_configuration():
    with pytest.raises(ValueError, match="slope"):
        TipJacobianEstimator(camera=CAM, slope=-1.0, depth=0.12, **GEOMETRY)
    with pytest.raises(ValueError, match="depth"):
        TipJacobianEstimator(camera=CAM, slope=1.0, depth=2.0, **GEOMETRY)
    with pytest.raises(ValueError, match="window"):
        TipJacobianEstimator(camera=CAM, slope=1.0, depth=0.12, window=1.0, **GEOMETRY)
