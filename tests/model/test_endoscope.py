import dataclasses
import math

import numpy as np
import pytest

from targetlock.model.drives import DriveParams
from targetlock.model.endoscope import (EndoscopeParams, advance, calibrate_handle_radius, dead_travel, initial_state,
                                        pack_params, simulate, static_gain)
from targetlock.model.twin import PRESETS, twin_config

DT = 1e-3


def hold(e: EndoscopeParams, handle: tuple[float, float], seconds: float = 3.0, state=None):
    s = initial_state(1) if state is None else state
    advance(s, pack_params(e, DriveParams()), np.array([handle]), DT, int(seconds / DT))
    return s[0]


def ramp(e, target, seconds=4.0, dt=DT, start=(0.0, 0.0), state=None):
    """Move the handle setpoint linearly from ``start`` to ``target`` (rad), then hold 1 s."""
    n = int(seconds / dt)
    sp = np.linspace(start, target, n)[:, None, :]
    sp = np.concatenate([sp, np.repeat(sp[-1:], int(1.0 / dt), axis=0)])
    s = initial_state(1) if state is None else state
    return simulate(s, pack_params(e, DriveParams()), sp, dt)[:, 0, :]


def test_frictionless_equilibrium_is_the_static_gain():
    e = EndoscopeParams(mu_n=0.0, cable_slack=0.0)
    s = hold(e, (0.8, -0.5), seconds=5.0)
    np.testing.assert_allclose(s[2:4], static_gain(e) * np.array([0.8, -0.5]), rtol=1e-6)
    np.testing.assert_allclose(s[4:6], 0.0, atol=1e-9)


def test_calibrated_total_gain_is_90_over_110_degrees():
    e = twin_config("calibrated").endoscope
    traj = ramp(e, (math.radians(110), 0.0))
    assert math.degrees(traj[-1, 2]) == pytest.approx(90.0, abs=1.0)


@pytest.mark.parametrize("preset", PRESETS)
def test_preset_handle_radius_is_the_documented_calibration(preset):
    base = twin_config("calibrated").endoscope
    assert base.handle_radius == pytest.approx(calibrate_handle_radius(base), rel=0.002)


def test_slack_gives_a_deadband_around_the_centre():
    e = dataclasses.replace(EndoscopeParams(), cable_slack=0.0015)
    deadband = e.cable_slack / e.handle_radius  # handle angle that only takes up slack
    inside = hold(e, (0.8 * deadband, 0.0))
    outside = hold(e, (3.0 * deadband, 0.0))
    assert inside[2] == 0.0
    assert outside[2] > 0.0


def test_tip_sticks_when_the_handle_turns_back_a_little():
    """Hysteresis: after bending out, a small handle reversal does not move the tip."""
    e = EndoscopeParams()
    traj = ramp(e, (1.2, 0.0))
    bent = traj[-1].copy()
    back = ramp(e, (1.15, 0.0), seconds=1.0, start=(1.2, 0.0), state=bent[None, :].copy())
    assert back[-1, 2] == pytest.approx(bent[2], abs=1e-9)
    further = ramp(e, (0.7, 0.0), seconds=2.0, start=(1.2, 0.0), state=bent[None, :].copy())
    assert further[-1, 2] < bent[2] - 0.1


def test_friction_of_the_other_axis_widens_the_stall():
    """Eq. 3.29: friction grows with |phi_x| + |phi_y|, so the bent other axis holds the tip longer."""
    e = EndoscopeParams()

    def stall_width(other):
        s = initial_state(1)
        ramp(e, (1.2, other), state=s)
        theta = np.linspace(1.2, 0.6, 601)
        out = simulate(s, pack_params(e, DriveParams()), np.column_stack([theta, np.full_like(theta, other)])[:, None, :],
                       DT, substeps=20)[:, 0]
        moved = np.flatnonzero(out[:, 2] < out[0, 2] - 1e-4)
        return 1.2 - theta[moved[0]]

    assert stall_width(1.0) > stall_width(0.0) * 1.1


def _sweep_error(dt, ref):
    t = np.arange(0.0, 12.0, 0.01)
    theta = np.column_stack([1.6 * np.sin(2 * np.pi * t / 6.0), 0.6 * np.sin(2 * np.pi * t / 4.0)])
    sub = int(round(0.01 / dt))
    out = simulate(initial_state(1), pack_params(EndoscopeParams(), DriveParams()), theta[:, None, :], 0.01 / sub, sub)
    return out[:, 0, 2:4] if ref is None else np.abs(out[:, 0, 2:4] - ref).max()


def test_integrator_converges_with_step_size():
    ref = _sweep_error(1e-5, None)
    errs = [_sweep_error(dt, ref) for dt in (4e-3, 2e-3, 1e-3, 5e-4, 2.5e-4)]
    assert all(b < a for a, b in zip(errs, errs[1:]))
    assert errs[2] < math.radians(0.5)            # the default 1 ms step is within half a degree
    order = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.median(order) > 0.7                 # first-order scheme


def test_quasi_static_limit_agrees_with_the_inertial_model():
    e = EndoscopeParams()
    q = dataclasses.replace(e, tip_inertia=0.0)
    a = ramp(e, (1.5, 0.7), seconds=6.0)
    b = ramp(q, (1.5, 0.7), seconds=6.0)
    assert np.abs(a[:, 2:4] - b[:, 2:4]).max() < math.radians(0.2)


def test_batch_is_deterministic_and_equals_single_runs():
    es = [EndoscopeParams(), dataclasses.replace(EndoscopeParams(), cable_slack=0.001),
          dataclasses.replace(EndoscopeParams(), friction_model="own-angle")]
    sp = np.repeat(np.array([[[1.0, -0.4]]]), 500, axis=0)
    batch = simulate(initial_state(3), pack_params(es, DriveParams()), np.repeat(sp, 3, axis=1), DT)
    for i, e in enumerate(es):
        single = simulate(initial_state(1), pack_params(e, DriveParams()), sp, DT)
        np.testing.assert_array_equal(batch[:, i], single[:, 0])


def test_non_finite_setpoint_never_moves_the_handle():
    s = initial_state(1)
    p = pack_params(EndoscopeParams(), DriveParams())
    advance(s, p, np.array([[0.5, 0.0]]), DT, 2000)
    before = s.copy()
    advance(s, p, np.array([[np.nan, np.inf]]), DT, 1000)
    assert s[0, 0] == before[0, 0]
    assert np.all(np.isfinite(s))


def test_handle_never_leaves_the_drive_range():
    d = DriveParams(min_angle=-1.0, max_angle=1.0)
    s = initial_state(1)
    advance(s, pack_params(EndoscopeParams(), d), np.array([[5.0, -5.0]]), DT, 5000)
    assert s[0, 0] == pytest.approx(1.0) and s[0, 1] == pytest.approx(-1.0)


def test_own_angle_friction_model_has_no_stall_at_the_centre():
    """Eq. 3.39: friction vanishes with the bend, so nothing holds the tip away from the centre."""
    e = dataclasses.replace(EndoscopeParams(), friction_model="own-angle", cable_slack=0.0015)
    s = initial_state(1)
    ramp(e, (1.0, 0.0), state=s)
    ramp(e, (0.0, 0.0), start=(1.0, 0.0), state=s)
    assert abs(s[0, 2]) < math.radians(0.5)


@pytest.mark.parametrize("slack", [0.0004, 0.0012, -0.0003])
def test_dead_travel_is_where_the_simulated_tip_starts_to_move(slack):
    """Bend an axis out quasi-statically, then turn the handle back slowly: the tip first stands still
    (slack, then the friction band), and starts back where dead_travel said."""
    e = dataclasses.replace(EndoscopeParams(), cable_slack=slack)
    drive = DriveParams(time_constant=0.0, max_velocity_ticks=1e9, min_angle=-6.3, max_angle=6.3)
    params = pack_params(e, drive)
    state = initial_state(1)
    out = np.linspace(0.0, 0.8, 400)
    simulate(state, params, np.column_stack([out, 0.3 * out])[:, None, :], 0.002, 10)
    advance(state, params, np.array([[0.8, 0.24]]), 0.002, 500)
    handle, tip = state[0, 0:2].copy(), state[0, 2:4].copy()
    # Further out, the tip moves at once; back, only after the dead travel.
    assert dead_travel(e, handle, tip, np.array([1.0, 0.0]))[0] == pytest.approx(0.0, abs=0.01)
    back = dead_travel(e, handle, tip, np.array([-1.0, 0.0]))[0]
    assert back < -0.05
    ramp = handle[0] - np.linspace(0.0, 0.6, 1200)
    tips = simulate(state, params, np.column_stack([ramp, np.full_like(ramp, handle[1])])[:, None, :], 0.002, 5)
    start = ramp[np.argmax(tip[0] - tips[:, 0, 2] > 1e-4)] - handle[0]
    assert back == pytest.approx(start, rel=0.1), (back, start)
