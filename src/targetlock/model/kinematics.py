"""Chained constant-curvature forward kinematics of the two-DOF endoscope tip (report §3.2.3).

Frames: the **base frame** sits where the bending section starts, z along the straight tip, x and
y matching the camera's image x (right) and y (down). The **camera frame** sits at the tip end:
z is the optical axis, x and y are the image axes.

Bending angles (rad), named after the image axis they steer:

* ``phi_x`` turns the view towards image +x: a rotation about the y axis by +phi_x.
* ``phi_y`` turns the view towards image +y (down): a rotation about the x axis by -phi_y.

So a positive pixel offset on an axis asks for a positive bend on that axis, for both axes.

Each element transform is derived from the twist (Eq. 3.6-3.13): a rotation R about an axis
through q = r·n (r = l/phi, n the in-plane normal towards the centre of curvature) gives the
translation (I - R) q. This corrects Eq. 3.15 of the report, which puts the translation of a
bend about x on the x axis; a rotation about x displaces the element end in y and z. The
phi -> 0 limit uses l·sin(phi)/phi = l·sinc(phi) and l·(1-cos phi)/phi = l·sin(phi/2)·sinc(phi/2),
so no division by zero occurs.

The chain (Eq. 3.17-3.20) has n pairs; each pair is an x-bend element then a y-bend element, each
of length L/(2n) and bending phi/n.
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["tip_pose", "tip_poses", "planar_arc_pose", "bending_angles_from_poses"]


@njit(cache=True, inline="always")
def _sinc(u: float) -> float:
    if abs(u) < 1e-4:
        return 1.0 - u * u / 6.0
    return np.sin(u) / u


@njit(cache=True)
def _element_pair(phi_x: float, phi_y: float, length: float) -> np.ndarray:
    """Transform of one (x-bend, y-bend) element pair; each element has length ``length`` (m)."""
    # x-bend: rotation about +y by a, end at (l(1-cos a)/a, 0, l sin a / a)
    a = phi_x
    ca, sa = np.cos(a), np.sin(a)
    tx = length * np.sin(0.5 * a) * _sinc(0.5 * a)
    tz = length * _sinc(a)
    hx = np.array([[ca, 0.0, sa, tx],
                   [0.0, 1.0, 0.0, 0.0],
                   [-sa, 0.0, ca, tz],
                   [0.0, 0.0, 0.0, 1.0]])
    # y-bend: rotation about +x by b = -phi_y; end at (0, -l(1-cos b)/b, l sin b / b)
    b = -phi_y
    cb, sb = np.cos(b), np.sin(b)
    ty = -length * np.sin(0.5 * b) * _sinc(0.5 * b)
    tz2 = length * _sinc(b)
    hy = np.array([[1.0, 0.0, 0.0, 0.0],
                   [0.0, cb, -sb, ty],
                   [0.0, sb, cb, tz2],
                   [0.0, 0.0, 0.0, 1.0]])
    return hx @ hy


@njit(cache=True)
def tip_pose(phi_x: float, phi_y: float, length: float, n_elements: int) -> np.ndarray:
    """Pose (4x4 homogeneous) of the camera frame in the base frame.

    phi_x, phi_y: total bending angles (rad); length: bending-section length (m);
    n_elements: number of (x, y) element pairs in the chain (report: 30).
    """
    pair = _element_pair(phi_x / n_elements, phi_y / n_elements, length / (2.0 * n_elements))
    # pair ** n by repeated squaring: log2(n) products instead of n.
    out = np.eye(4)
    k = n_elements
    while k > 0:
        if k & 1:
            out = out @ pair
        k >>= 1
        if k:
            pair = pair @ pair
    return out


@njit(cache=True)
def tip_poses(phis: np.ndarray, length: float, n_elements: int) -> np.ndarray:
    """Batch of :func:`tip_pose`: ``phis`` is (N, 2) rad, returns (N, 4, 4)."""
    out = np.empty((phis.shape[0], 4, 4))
    for i in range(phis.shape[0]):
        out[i] = tip_pose(phis[i, 0], phis[i, 1], length, n_elements)
    return out


@njit(cache=True)
def planar_arc_pose(phi_x: float, length: float) -> np.ndarray:
    """Closed-form constant-curvature pose for a bend in one plane (Eq. 3.14), rad and m."""
    c, s = np.cos(phi_x), np.sin(phi_x)
    return np.array([[c, 0.0, s, length * np.sin(0.5 * phi_x) * _sinc(0.5 * phi_x)],
                     [0.0, 1.0, 0.0, 0.0],
                     [-s, 0.0, c, length * _sinc(phi_x)],
                     [0.0, 0.0, 0.0, 1.0]])


def bending_angles_from_poses(base: np.ndarray, tip: np.ndarray, length: float = 0.12, n_elements: int = 30) -> np.ndarray:
    """Two bending angles (rad) from base and tip orientations, as motion capture measures them.

    ``base`` and ``tip`` are 3x3 (or 4x4) orientations of the two rigid bodies in any common world
    frame (report §3.1). The angles are those for which the chained model's optical axis points where
    the measured one points: a first guess from the axis' two projections, refined by Gauss-Newton.
    """
    r = np.asarray(base, dtype=float)[:3, :3].T @ np.asarray(tip, dtype=float)[:3, :3]
    z = r[:, 2]
    phi = np.array([np.arctan2(z[0], z[2]), np.arctan2(z[1], z[2])])
    for _ in range(20):
        f = tip_pose(phi[0], phi[1], length, n_elements)[:3, 2] - z
        if np.abs(f).max() < 1e-13:
            break
        jac = np.empty((3, 2))
        for k in range(2):
            d = np.zeros(2)
            d[k] = 1e-7
            jac[:, k] = (tip_pose(phi[0] + d[0], phi[1] + d[1], length, n_elements)[:3, 2] - z - f) / 1e-7
        phi = phi - np.linalg.lstsq(jac, f, rcond=None)[0]
    return phi
