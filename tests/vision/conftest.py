"""Shared fixtures for the vision tests (renderers are costly to build: share them per module)."""
import numpy as np
import pytest

from targetlock.vision import PlanarTarget, Renderer, RenderSettings, endoscope_camera


@pytest.fixture(scope="session")
def cam():
    return endoscope_camera()


@pytest.fixture(scope="session")
def mucosa_target():
    return PlanarTarget.mucosa(seed=3)


@pytest.fixture(scope="session")
def renderer(cam, mucosa_target):
    return Renderer(cam, RenderSettings(), mucosa_target, seed=11)


@pytest.fixture(scope="session")
def clean_settings():
    """No noise, glints or optical blur: for exact geometry checks."""
    return RenderSettings(noise_sigma=0.0, specular_strength=0.0, optical_blur_px=0.0)


def _sel_pose(point_cam, p_sel, rotvec=(0.0, 0.0, 0.0)):
    """Target pose that puts plane point ``p_sel`` at ``point_cam`` (camera at the world origin)."""
    from targetlock.vision import make_pose
    pose = make_pose((0, 0, 0), rotvec)
    pose[:3, 3] = np.asarray(point_cam, float) - pose[:3, :3] @ np.array([p_sel[0], p_sel[1], 0.0])
    return pose


@pytest.fixture(scope="session")
def sel_pose():
    return _sel_pose
