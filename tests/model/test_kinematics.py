import math

import numpy as np
import pytest

from targetlock.model.kinematics import bending_angles_from_poses, planar_arc_pose, tip_pose, tip_poses

L = 0.12


def test_straight_tip_is_a_translation_along_z():
    h = tip_pose(0.0, 0.0, L, 30)
    np.testing.assert_allclose(h[:3, :3], np.eye(3), atol=1e-15)
    np.testing.assert_allclose(h[:3, 3], [0, 0, L], atol=1e-15)


def test_zero_limit_is_continuous_and_finite():
    for eps in (1e-15, 1e-9, 1e-6):
        h = tip_pose(eps, -eps, L, 30)
        assert np.all(np.isfinite(h))
        np.testing.assert_allclose(h[:3, 3], [0, 0, L], atol=1e-6)


def test_chain_matches_closed_form_within_2mm_and_orientation_exact():
    """Report §3.2.3: 12 cm tip, 30 elements, -135..135 deg: < 2 mm, orientation exact."""
    worst_pos, worst_rot = 0.0, 0.0
    for deg in np.linspace(-135, 135, 55):
        a = math.radians(deg)
        chain, closed = tip_pose(a, 0.0, L, 30), planar_arc_pose(a, L)
        worst_pos = max(worst_pos, np.linalg.norm(chain[:3, 3] - closed[:3, 3]))
        worst_rot = max(worst_rot, np.abs(chain[:3, :3] - closed[:3, :3]).max())
    assert worst_pos < 0.002
    assert worst_rot < 1e-12


def test_chain_converges_to_closed_form_with_more_elements():
    a = math.radians(120)
    errs = [np.linalg.norm(tip_pose(a, 0.0, L, n)[:3, 3] - planar_arc_pose(a, L)[:3, 3]) for n in (5, 10, 20, 40, 80)]
    assert all(e2 < e1 for e1, e2 in zip(errs, errs[1:]))
    assert errs[-1] < errs[0] / 10


def test_bend_about_x_displaces_the_tip_in_y_and_z_only():
    """The trap of Eq. 3.15: a rotation about x must not move the tip along x."""
    h = tip_pose(0.0, math.radians(60), L, 30)
    assert abs(h[0, 3]) < 1e-12
    assert h[1, 3] > 0.02  # view turned towards image +y, the tip went that way
    assert 0 < h[2, 3] < L
    # optical axis tilted by the bend towards +y
    assert math.isclose(math.atan2(h[1, 2], h[2, 2]), math.radians(60), abs_tol=1e-12)


@pytest.mark.parametrize("deg", [-135, -60, 30, 135])
def test_pure_y_bend_matches_the_closed_form_seen_rotated(deg):
    """Both axes are the same physics: a y bend is the closed-form arc with x and y swapped."""
    a = math.radians(deg)
    hy, closed = tip_pose(0.0, a, L, 30), planar_arc_pose(a, L)
    assert np.linalg.norm(hy[:3, 3] - [closed[1, 3], closed[0, 3], closed[2, 3]]) < 0.002
    assert math.isclose(math.atan2(hy[1, 2], hy[2, 2]), a, abs_tol=1e-12)


def test_batch_equals_single():
    phis = np.array([[0.1, -0.3], [1.0, 0.5], [-2.0, 0.0]])
    hs = tip_poses(phis, L, 30)
    for p, h in zip(phis, hs):
        np.testing.assert_array_equal(h, tip_pose(p[0], p[1], L, 30))


@pytest.mark.parametrize("phis", [(0.4, 0.0), (0.0, -0.7), (0.5, 0.6), (-1.0, 0.8)])
def test_bending_angles_recovered_from_base_and_tip_orientations(phis):
    h = tip_pose(phis[0], phis[1], L, 30)
    base = np.eye(3)
    world = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]], dtype=float)  # any common world frame
    got = bending_angles_from_poses(world @ base, world @ h[:3, :3])
    np.testing.assert_allclose(got, phis, atol=1e-6)
