import math

import numpy as np
import pytest

from targetlock.config import ConfigError, validate
from targetlock.model.drives import DriveParams, drive_step


def run(theta, setpoint, seconds, p, dt=1e-4):
    out = [theta]
    for _ in range(int(round(seconds / dt))):
        theta = drive_step(theta, setpoint, dt, p.time_constant, p.max_velocity)
        out.append(theta)
    return np.array(out)


def test_small_step_is_first_order_with_the_time_constant():
    p = DriveParams()
    traj = run(0.0, 0.01, p.time_constant, p)  # small: the rate limit is not reached
    assert traj[-1] == pytest.approx(0.01 * (1 - math.exp(-1)), rel=1e-3)


def test_large_step_is_rate_limited():
    p = DriveParams()
    dt = 1e-4
    traj = run(0.0, 1.5, 0.5, p, dt)
    assert np.max(np.diff(traj)) / dt <= p.max_velocity * (1 + 1e-9)
    assert p.max_velocity == pytest.approx(1.6)  # 100000 tick/s x 1.6e-5 rad/tick


def test_inverted_range_is_refused():
    with pytest.raises(ConfigError, match="min_angle"):
        validate(DriveParams(min_angle=0.0, max_angle=0.0))
