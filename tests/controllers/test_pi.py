import math

import numpy as np
import pytest

from targetlock.config import ConfigError, validate
from targetlock.controllers import ControllerConfig, PIController, nominal_knowledge
from targetlock.rig.base import Observation

RPT = 1.6e-5
LO, HI = np.array([-2.0, -2.0]), np.array([2.0, 2.0])


def make(kind="pi", **kw):
    cfg = ControllerConfig(kind=kind, **kw)
    return PIController(cfg, rad_per_tick=RPT, lower=LO, upper=HI, control_dt=0.02, knowledge=nominal_knowledge())


def obs(t, x, y=0.0, valid=True):
    return Observation(capture_time=t, offset=np.array([x, y], dtype=float), valid=valid)


def test_engage_starts_at_the_motor_position():
    c = make()
    motor = np.array([0.3, -0.2])
    c.reset(motor, 0.0)
    np.testing.assert_allclose(c.step(None, motor, 0.02), motor)
    np.testing.assert_allclose(c.step(obs(0.0, 0.0), motor, 0.04), motor)


def test_integral_action_follows_eq_4_2():
    c = make(i_gain=300.0)
    c.reset(np.zeros(2), 0.0)
    c.step(obs(0.0, 50.0), np.zeros(2), 0.02)
    sp = c.step(obs(0.05, 50.0), np.zeros(2), 0.04)
    # first frame integrates one control period, the second its capture interval
    assert sp[0] == pytest.approx(300 * RPT * 50 * (0.02 + 0.05))
    assert sp[1] == 0.0


def test_p_action_adds_the_offset():
    c = make(i_gain=0.0, p_gain=100.0)
    c.reset(np.zeros(2), 0.0)
    assert c.step(obs(0.0, -20.0), np.zeros(2), 0.02)[0] == pytest.approx(-100 * RPT * 20)


@pytest.mark.parametrize("bad", [obs(0.1, 80.0, valid=False), obs(0.1, math.nan), obs(0.1, math.inf, 3.0), None])
def test_holds_without_a_valid_observation(bad):
    c = make()
    c.reset(np.zeros(2), 0.0)
    held = c.step(obs(0.0, 40.0), np.zeros(2), 0.02)
    for k in range(50):
        np.testing.assert_array_equal(c.step(bad, np.zeros(2), 0.04 + 0.02 * k), held)


def test_resumes_after_a_loss_without_a_jump():
    c = make(max_frame_gap=0.1, max_rate=100.0)
    c.reset(np.zeros(2), 0.0)
    before = c.step(obs(0.0, 100.0), np.zeros(2), 0.02)
    for k in range(200):  # four seconds without a valid frame
        c.step(obs(0.05 * k, 100.0, valid=False), np.zeros(2), 0.04 + 0.02 * k)
    after = c.step(obs(10.0, 100.0), np.zeros(2), 4.1)
    assert after[0] - before[0] == pytest.approx(300 * RPT * 100 * 0.1)  # one capped frame, not 10 s


def test_setpoints_respect_range_and_rate_limits():
    c = make(i_gain=1e5, max_rate=1.0)
    c.reset(np.zeros(2), 0.0)
    prev = np.zeros(2)
    for k in range(500):
        sp = c.step(obs(0.045 * k, 5000.0, -5000.0), np.zeros(2), 0.02 * (k + 1))
        assert np.all(np.abs(sp - prev) <= 1.0 * 0.02 + 1e-12)
        assert np.all(sp <= HI) and np.all(sp >= LO)
        prev = sp
    np.testing.assert_allclose(prev, [2.0, -2.0])


def test_both_gains_zero_is_refused():
    with pytest.raises(ConfigError, match="i_gain"):
        validate(ControllerConfig(kind="pi", i_gain=0.0, p_gain=0.0))


def test_compensation_switches_on_towards_the_centre_and_off_outwards():
    c = make("pi-hc", hc_width=0.2)
    m = np.array([0.5, 0.0])  # bent to the positive side
    c.reset(m, 0.0)
    c.step(obs(0.0, 30.0), m, 0.02)                         # moving outwards: off
    assert c.compensation[0] == 0.0
    c.step(obs(0.05, -30.0), m, 0.04)                       # turned towards the centre: on
    assert c.compensation[0] == pytest.approx(-0.2 * 0.5)
    c.step(obs(0.10, 5.0), m, 0.06)                         # within 10 px: no switching
    assert c.compensation[0] == pytest.approx(-0.2 * 0.5)
    c.step(obs(0.15, 25.0), m, 0.08)                        # turned outwards again: off
    assert c.compensation[0] == 0.0


def test_compensation_is_continuous_through_the_centre():
    c = make("pi-hc", hc_width=0.2)
    c.reset(np.array([0.3, 0.0]), 0.0)
    comps = []
    for k, m in enumerate(np.linspace(0.3, -0.3, 61)):      # moving negative all the way
        c.step(obs(0.05 * k, -30.0), np.array([m, 0.0]), 0.02 * (k + 1))
        comps.append(c.compensation[0])
    assert max(abs(a - b) for a, b in zip(comps, comps[1:])) < 0.2 * 0.011
    assert comps[-1] == 0.0                                  # outwards on the other side: off


def test_model_2_width_grows_with_both_bending_angles():
    c = make("pi-hc2", hc2_slope=0.1, hc2_offset_deg=9.0, tip_gain=0.8)
    w0 = c._width(np.array([0.5, 0.0]))
    w1 = c._width(np.array([0.5, 0.8]))
    assert w0[0] == pytest.approx(0.1 * 0.8 * 0.5 + math.radians(9.0))
    assert w1[0] > w0[0]


def test_prediction_subtracts_the_motion_since_capture():
    plain, pred = make("pi-hc2", i_gain=800.0), make("pi-smith")     # the same gain: only the prediction differs
    for c in (plain, pred):
        c.reset(np.zeros(2), 0.0)
        for k in range(20):  # motors swept between frames
            c.step(None, np.array([0.01 * k, 0.0]), 0.02 * k)
    m = np.array([0.2, 0.0])
    a = plain.step(obs(0.0, 50.0), m, 0.4)
    b = pred.step(obs(0.0, 50.0), m, 0.4)
    assert b[0] < a[0]   # the predictor knows the target already moved towards the centre


def test_model_2_compensation_is_continuous_through_the_centre():
    c = make("pi-hc2", hc2_slope=0.1, hc2_offset_deg=9.0)
    c.reset(np.array([0.3, 0.0]), 0.0)
    comps = []
    for k, m in enumerate(np.linspace(0.3, -0.3, 121)):     # moving negative all the way, 0.005 rad a frame
        c.step(obs(0.05 * k, -30.0), np.array([m, 0.0]), 0.02 * (k + 1))
        comps.append(c.compensation[0])
    jumps = np.abs(np.diff(comps))
    assert jumps.max() < math.radians(0.5)                   # no ±9° flip at the zero crossing
    assert comps[0] == pytest.approx(-c._width(np.array([0.3, 0.0]))[0])  # full width towards the centre
    assert comps[-1] == 0.0                                  # outwards on the other side: off


def test_the_default_integral_gain_is_the_controllers_own():
    assert ControllerConfig(kind="pi").integral_gain == 300.0
    assert ControllerConfig(kind="pi-smith").integral_gain == 800.0
    assert ControllerConfig(kind="pi-smith", i_gain=250.0).integral_gain == 250.0
    with pytest.raises(ConfigError, match="i_gain"):
        validate(ControllerConfig(kind="pi", i_gain=-0.5))


def test_a_lost_target_is_held_and_reported():
    c = make(i_gain=300.0, max_rate=100.0)
    c.reset(np.zeros(2), 0.0)
    held = c.step(obs(0.0, 80.0, 20.0), np.zeros(2), 0.02)
    for k in range(100):                                     # two seconds of invalid frames
        sp = c.step(obs(0.05 * (k + 1), math.nan, math.nan, valid=False), held, 0.04 + 0.02 * k)
        np.testing.assert_array_equal(sp, held)
    assert c.losses == 1
    assert c.lost_for(2.02) == pytest.approx(2.0)
    c.step(obs(2.1, 0.0), held, 2.04)                        # seen again: tracked, the loss stays counted
    assert c.lost_for(2.04) == 0.0 and c.losses == 1


def test_the_setpoint_slews_between_frames_at_the_rate_limit():
    """A frame's command is reached at max_rate per second whatever the tick rate (not per frame)."""
    for dt in (0.02, 0.001):
        c = PIController(ControllerConfig(kind="pi", i_gain=1e5, max_rate=1.0), rad_per_tick=RPT, lower=LO,
                         upper=HI, control_dt=dt, knowledge=nominal_knowledge())
        c.reset(np.zeros(2), 0.0)
        c.step(obs(0.0, 1000.0), np.zeros(2), dt)            # command far away
        n = int(round(0.2 / dt))
        for k in range(n - 1):
            sp = c.step(None, np.zeros(2), dt * (k + 2))     # no new frames
        assert sp[0] == pytest.approx(0.2, rel=1e-6)          # 0.2 s at 1 rad/s
