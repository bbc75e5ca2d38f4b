"""Bending angles of the endoscope tip from motion capture (base and tip rigid bodies).

Motive reports each rigid body's orientation in its own world frame; the rigid bodies' local axes
are wherever the markers were when the body was defined, not the model's base and camera frames.
:class:`MocapBendingSensor` holds the two constant corrections (base body → base frame, tip body →
camera frame) and turns a :class:`~.natnet.MocapSample` into the two bending angles (rad) with
:func:`targetlock.model.kinematics.bending_angles_from_poses`. :meth:`MocapBendingSensor.calibrate_straight`
sets the tip correction from one sample taken with the bending section straight (both angles 0).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model.kinematics import bending_angles_from_poses
from .natnet import MocapSample, RigidBody

__all__ = ["quaternion_to_rotation", "rotation_to_quaternion", "pose_from_rigid_body", "bending_angles_from_sample",
           "MocapBendingSensor", "BendingMeasurement"]


def quaternion_to_rotation(q: tuple[float, float, float, float] | np.ndarray) -> np.ndarray:
    """3x3 rotation of a quaternion (qx, qy, qz, qw) (normalised here)."""
    x, y, z, w = (float(v) for v in q)
    n = x * x + y * y + z * z + w * w
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError(f"quaternion {tuple(q)} has no direction")
    s = 2.0 / n
    return np.array([
        [1.0 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)],
        [s * (x * y + z * w), 1.0 - s * (x * x + z * z), s * (y * z - x * w)],
        [s * (x * z - y * w), s * (y * z + x * w), 1.0 - s * (x * x + y * y)],
    ])


def rotation_to_quaternion(r: np.ndarray) -> np.ndarray:
    """Quaternion (qx, qy, qz, qw), qw >= 0, of a 3x3 (or the rotation part of a 4x4) matrix."""
    m = np.asarray(r, dtype=float)[:3, :3]
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0.0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array([(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s])
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = np.array([0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s])
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = np.array([(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = np.array([(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s])
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def pose_from_rigid_body(body: RigidBody) -> np.ndarray:
    """4x4 pose (m) of a rigid body in Motive's world frame."""
    out = np.eye(4)
    out[:3, :3] = quaternion_to_rotation(body.orientation)
    out[:3, 3] = body.position
    return out


@dataclass(frozen=True)
class BendingMeasurement:
    """Bending angles measured by motion capture."""
    angles: np.ndarray
    """(phi_x, phi_y) in rad."""
    capture_time: float
    """Estimated mid-exposure time on the local monotonic clock (s)."""
    frame_number: int


def bending_angles_from_sample(sample: MocapSample, base_id: int, tip_id: int,
                               base_correction: np.ndarray | None = None,
                               tip_correction: np.ndarray | None = None) -> np.ndarray | None:
    """The two bending angles (rad) from a sample's base and tip rigid bodies, or None.

    None when either body is missing, not tracked, or has a non-finite or non-unit quaternion.
    ``base_correction`` / ``tip_correction`` (3x3) rotate the rigid bodies' frames into the model's
    base and camera frames (R_frame = R_body @ correction); identity when omitted.
    """
    base, tip = sample.rigid_body(base_id), sample.rigid_body(tip_id)
    if base is None or tip is None or not base.usable or not tip.usable:
        return None
    rb = quaternion_to_rotation(base.orientation)
    rt = quaternion_to_rotation(tip.orientation)
    if base_correction is not None:
        rb = rb @ base_correction
    if tip_correction is not None:
        rt = rt @ tip_correction
    return bending_angles_from_poses(rb, rt)


class MocapBendingSensor:
    """Bending angles of the tip from a NatNet client's newest sample.

    ``source`` is anything with ``get(max_age=None) -> MocapSample | None`` (a
    :class:`~.natnet.NatNetClient`); corrections are 3x3 rotations as in
    :func:`bending_angles_from_sample`.
    """

    def __init__(self, source, base_id: int, tip_id: int, *, base_correction: np.ndarray | None = None,
                 tip_correction: np.ndarray | None = None) -> None:
        self.source = source
        self.base_id = base_id
        self.tip_id = tip_id
        self.base_correction = np.eye(3) if base_correction is None else np.asarray(base_correction, dtype=float)
        self.tip_correction = np.eye(3) if tip_correction is None else np.asarray(tip_correction, dtype=float)

    def calibrate_straight(self, sample: MocapSample, max_angle: float | None = None) -> None:
        """Set the tip correction so that ``sample`` (bending section straight) reads (0, 0).

        ``max_angle`` (rad): refuse (ValueError) when the tip reads further than this from straight
        before the calibration — the section is bent, or the wrong bodies are configured.
        """
        base, tip = sample.rigid_body(self.base_id), sample.rigid_body(self.tip_id)
        if base is None or tip is None or not base.usable or not tip.usable:
            raise ValueError("calibration sample lacks a tracked base or tip rigid body")
        rb = quaternion_to_rotation(base.orientation) @ self.base_correction
        rt = quaternion_to_rotation(tip.orientation)
        if max_angle is not None:
            z = (rb.T @ rt)[:, 2]                    # tip optical axis in the base frame
            off = float(np.arccos(np.clip(z[2], -1.0, 1.0)))
            if off > max_angle:
                raise ValueError(f"the tip's axis is {np.degrees(off):.1f} deg from the base's (at most "
                                 f"{np.degrees(max_angle):.1f} allowed): straighten the bending section")
        self.tip_correction = rt.T @ rb

    def angles(self, sample: MocapSample) -> np.ndarray | None:
        return bending_angles_from_sample(sample, self.base_id, self.tip_id, self.base_correction, self.tip_correction)

    def read(self, max_age: float | None = None) -> BendingMeasurement | None:
        """Newest measurement, or None without a fresh sample with both bodies tracked."""
        sample = self.source.get(max_age)
        if sample is None:
            return None
        a = self.angles(sample)
        if a is None:
            return None
        return BendingMeasurement(a, sample.capture_time, sample.frame.frame_number)
