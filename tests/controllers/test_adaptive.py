import dataclasses

import numpy as np
import pytest

from targetlock.controllers import AdaptiveController, ControllerConfig, KnowledgeConfig, nominal_knowledge
from targetlock.experiments.target_lock import RunConfig, run_target_lock
from targetlock.loop.runner import LoopConfig
from targetlock.model.drives import DriveParams
from targetlock.model.endoscope import EndoscopeParams, initial_state, pack_params, simulate
from targetlock.rig.base import Observation

RPT = 1.6e-5


def make(**kw):
    return AdaptiveController(ControllerConfig(kind="adaptive", **kw), rad_per_tick=RPT, lower=np.full(2, -2.0),
                              upper=np.full(2, 2.0), control_dt=0.02, knowledge=nominal_knowledge())


def drive(c, image, seconds=8.0, frame=0.05, plant=EndoscopeParams()):
    """Step the controller with a motor sweep, and frames 0.3 s late showing ``image(tip)`` of the tip
    (in equivalent handle rad: tip angle / assumed tip gain) of the ``plant`` scope (default: the
    nominal one, the one the controller assumes) driven by that sweep."""
    c.reset(np.zeros(2), 0.0)
    t = 0.02 * np.arange(int(seconds / 0.02))
    m = np.column_stack([0.3 * np.sin(1.5 * t), 0.2 * np.sin(1.1 * t)])
    drives = DriveParams(time_constant=0.0, max_velocity_ticks=1e9, min_angle=-6.3, max_angle=6.3)
    states = simulate(initial_state(1), pack_params(plant, drives), np.repeat(m[:, None, :], 1, axis=1),
                      0.001, substeps=20)
    tip = states[:, 0, 2:4] / c.cfg.tip_gain
    lag = int(round(0.3 / 0.02))
    for k in range(1, t.size):
        obs = None
        if k % int(frame / 0.02) == 0 and k >= lag:
            obs = Observation(capture_time=t[k - lag], offset=image(tip[k - lag], t[k - lag]), valid=True)
        c.step(obs, m[k], t[k])
    return c


def test_supervisor_trusts_a_model_that_predicts_the_image():
    c = make()
    j = np.array([[-500.0, 40.0], [-30.0, -450.0]])
    drive(c, lambda m, t: j @ m)
    assert c.trust > 0.8
    assert np.linalg.norm(c.jacobian.j - j) / np.linalg.norm(j) < 0.2


def test_it_steers_with_a_candidate_scope_nearer_the_real_one():
    # A slacker scope with more friction than assumed (1.3 mm slack, friction x1.6): the image lags the
    # nominal model at every reversal. The bank finds a candidate with a wider loop than nominal.
    plant = dataclasses.replace(EndoscopeParams(), cable_slack=0.0013, mu_n=0.16, friction_offset=2.56)
    c = make()
    j = np.array([[-500.0, 0.0], [0.0, -450.0]])
    drive(c, lambda m, t: j @ m, seconds=14.0, plant=plant)
    chosen = c.tip_model.endoscope
    assert c.selector.switches >= 1
    nominal = EndoscopeParams()
    assert abs(chosen.cable_slack - plant.cable_slack) < abs(nominal.cable_slack - plant.cable_slack)
    assert abs(chosen.mu_n - plant.mu_n) < abs(nominal.mu_n - plant.mu_n)


def test_it_keeps_the_assumed_scope_when_that_is_the_real_one():
    c = make()
    drive(c, lambda m, t: np.array([[-500.0, 0.0], [0.0, -450.0]]) @ m, seconds=14.0)
    assert c.selector.switches == 0 and c.tip_model.member == 0


def test_supervisor_distrusts_an_image_that_contradicts_the_model():
    rng = np.random.default_rng(0)
    c = make()
    drive(c, lambda m, t: rng.normal(0.0, 80.0, 2))     # the image moves, but not with the motors
    assert c.trust == 0.0


def test_a_tracker_jump_lowers_the_trust_and_leaves_the_jacobian_alone():
    c = make()
    j = np.array([[-500.0, 40.0], [-30.0, -450.0]])
    drive(c, lambda m, t: j @ m)
    trust, jac = c.trust, c.jacobian.j.copy()
    assert trust > 0.8
    m = np.array([0.3 * np.sin(1.5 * 7.98), 0.2 * np.sin(1.1 * 7.98)])     # drive()'s last motor, now held
    tip = c.effective.copy()                # the plant is the controller's nominal scope: its tip, at rest
    for k in range(12):         # the target jumps 390 px between two frames and stays there
        t = 8.02 + 0.05 * k
        c.step(Observation(capture_time=t - 0.3, offset=j @ tip + [300.0, -250.0], valid=True), m, t)
    assert c.trust < trust - 0.3
    np.testing.assert_allclose(c.jacobian.j, jac, rtol=0.02, atol=5.0)


def test_the_step_is_the_estimated_jacobian_inverse_of_the_predicted_error():
    """Near (large J) the same offset asks for a smaller handle motion than far (small J)."""
    steps = {}
    for name, j in (("near", np.array([[-1500.0, 0.0], [0.0, -1450.0]])), ("far", np.array([[-300.0, 0.0], [0.0, -290.0]]))):
        c = make()
        drive(c, lambda m, t, j=j: j @ m)
        assert np.linalg.norm(c.jacobian.j - j) / np.linalg.norm(j) < 0.2
        motor = c.effective.copy()
        # A frame that shows 30 px of error and nothing still in flight.
        command = c._servo(np.array([30.0, 0.0]), motor, c.effective.copy(), 8.0)
        steps[name] = abs(command[0] - motor[0])
    assert steps["near"] < 0.35 * steps["far"]


def step_config(distance, kind, knowledge=None, seconds=10.0):
    cfg = RunConfig(controller=ControllerConfig(kind=kind), knowledge=knowledge or KnowledgeConfig(),
                    loop=LoopConfig(seconds=seconds))
    scene = dataclasses.replace(cfg.twin.scene, path="step", distance=distance, step_offset_px=(-150.0, 60.0))
    return dataclasses.replace(cfg, twin=dataclasses.replace(cfg.twin, scene=scene))


def test_at_one_and_a_half_centimetres_it_keeps_the_target_that_pi_loses():
    pi = run_target_lock(step_config(0.015, "pi"))
    ad = run_target_lock(step_config(0.015, "adaptive"))
    assert pi["out_of_view_fraction"] > 0.5
    assert ad["out_of_view_fraction"] == 0.0
    last = ad["_data"][-100:, 3]                      # the last 2 s: settled near the centre, at rest
    assert np.nanmax(last) < 40.0


def test_far_away_it_is_not_slower_than_pi():
    pi = run_target_lock(step_config(0.15, "pi", seconds=6.0))
    ad = run_target_lock(step_config(0.15, "adaptive", seconds=6.0))
    assert ad["out_of_view_fraction"] == 0.0
    assert ad["rms_px"] <= 1.1 * pi["rms_px"]


@pytest.mark.parametrize("knowledge", [
    KnowledgeConfig(preset="uncalibrated", fx=600.0, fy=600.0, depth=0.01, latency=0.6),
    KnowledgeConfig(preset="looped-shaft", fx=150.0, fy=150.0, depth=0.5, latency=0.2)])
def test_a_deliberately_wrong_model_is_not_worse_than_pi(knowledge):
    pi = run_target_lock(step_config(0.04, "pi"))
    ad = run_target_lock(step_config(0.04, "adaptive", knowledge))
    assert ad["out_of_view_fraction"] == 0.0
    assert ad["rms_px"] <= 1.1 * pi["rms_px"]


def test_an_axis_not_yet_learned_takes_the_distance_the_other_axis_found():
    """Both axes look at the same target: y learned at twice the prior's J (the target is nearer than
    assumed) while x has not moved -> x's column is the prior's, doubled; a far target (J below the
    prior) never shrinks the unlearned axis (that would make its steps larger)."""
    c = make()
    c.reset(np.zeros(2), 0.0)
    prior = c.prior.copy()
    learned = prior.copy()
    learned[:, 1] *= 2.0
    c.axis_motion = np.array([0.0, 0.5])
    np.testing.assert_allclose(c._filled(learned)[:, 0], 2.0 * prior[:, 0])
    np.testing.assert_allclose(c._filled(learned)[:, 1], learned[:, 1])
    far = prior.copy()
    far[:, 1] *= 0.5
    np.testing.assert_allclose(c._filled(far), far)
    c.axis_motion = np.array([0.5, 0.5])            # both learned: the estimate as it is
    np.testing.assert_allclose(c._filled(learned), learned)


def drift_config(tmp_path, distance, speed, lead, seconds=12.0):
    """The target drifts steadily (``speed`` × distance per second, i.e. ``speed`` rad/s of view) from 1 s on."""
    path = tmp_path / "drift.csv"
    t = np.arange(0.0, seconds + 0.05, 0.05)
    s = speed * distance * np.maximum(t - 1.0, 0.0)
    np.savetxt(path, np.column_stack([t, 0.8 * s, -0.6 * s, 0.0 * s]), delimiter=",", header="t,x,y,z", comments="")
    cfg = RunConfig(controller=ControllerConfig(kind="adaptive", adaptive_drift_lead=lead), loop=LoopConfig(seconds=seconds))
    scene = dataclasses.replace(cfg.twin.scene, path="waypoints", waypoints_file=str(path), distance=distance)
    return dataclasses.replace(cfg, twin=dataclasses.replace(cfg.twin, scene=scene))


def test_a_steady_drift_is_followed_without_the_servo_lag(tmp_path):
    """A servo that removes only the offset it sees trails a drifting target by v·(latency + interval /
    gain): here ~9 px/s × 0.6 s. Leading the clear drift it estimated removes most of that."""
    settled = {}
    for lead in (0.0, 1.0):
        data = run_target_lock(drift_config(tmp_path, 0.10, 0.03, lead))["_data"]
        settled[lead] = float(np.mean(data[data[:, 0] > 9.0, 3]))
    assert settled[0.0] > 3.0                   # the lag is there without the lead...
    assert settled[1.0] < 0.4 * settled[0.0]    # ...and mostly gone with it


def test_the_dead_travel_is_crossed_at_once_but_never_beyond_the_step_asked_for():
    c = make()
    drive(c, lambda m, t: np.array([[-500.0, 0.0], [0.0, -450.0]]) @ m)
    # drive() ends with both handles turning back towards the centre; reversing them (outwards again)
    # first takes up slack and turns the friction around: the model says how far that is.
    last = np.array([0.3 * 1.5 * np.cos(1.5 * 7.98), 0.2 * 1.1 * np.cos(1.1 * 7.98)])
    reverse = -np.sign(last)
    dead = c.tip_model.dead_travel(reverse)
    assert np.all(np.sign(dead) == reverse) and np.all(np.abs(dead) > 0.02)
    big = c._across_dead_travel(reverse * 1.0)
    np.testing.assert_allclose(big, 0.8 * dead)            # the configured share of it
    small = c._across_dead_travel(reverse * 0.01)
    np.testing.assert_allclose(np.abs(small), 0.01)         # never more than the step itself


def test_engaged_again_it_starts_with_the_scope_and_delay_it_found_and_a_fresh_jacobian():
    # The console engages, releases and engages again on the same scope: the candidate scope and the
    # delay belong to the scope and the video path and carry over; J (the target's distance) does not.
    plant = dataclasses.replace(EndoscopeParams(), cable_slack=0.0013, mu_n=0.16, friction_offset=2.56)
    c = make()
    assert not c.engaged_before
    drive(c, lambda m, t: np.array([[-500.0, 0.0], [0.0, -450.0]]) @ m, seconds=14.0, plant=plant)
    member, delay = c.tip_model.member, c.delay.delay
    assert member != 0 and c.engaged_before
    c.reset(np.array([0.1, -0.05]), 20.0)
    assert c.tip_model.member == c.selector.best == member
    assert c.delay.delay == delay
    assert np.allclose(c.jacobian.j, c.prior) and c.jacobian.updates == 0 and c.trust == 0.0
    fresh = make()
    fresh.reset(np.zeros(2), 0.0)
    assert fresh.tip_model.member == 0 and fresh.delay.delay == 0.0


@pytest.mark.parametrize("preset", ["looped-shaft", "uncalibrated"])
def test_a_second_engagement_on_a_scope_unlike_the_assumed_one_holds_the_target_better(preset):
    """Released and engaged again on a fresh 150 px step (the same scope, 1.5 cm): the second
    engagement starts with the candidate scope the first one found, not the assumed calibrated one
    (measured: rms 51.6 -> 43.0 px on the looped shaft, 51.4 -> 47.5 uncalibrated)."""
    from targetlock.experiments.target_lock import build_controller, build_rig
    from targetlock.loop.clock import SimClock
    from targetlock.loop.gate import ObservationGate
    from targetlock.loop.runner import ControlLoop
    from targetlock.model.twin import twin_config

    twin = twin_config(preset)
    scene = dataclasses.replace(twin.scene, path="step", distance=0.015, step_offset_px=(-150.0, 60.0))
    cfg = RunConfig(twin=dataclasses.replace(twin, scene=scene), controller=ControllerConfig(kind="adaptive"),
                    knowledge=KnowledgeConfig(), loop=LoopConfig(seconds=10.0))

    def engage(c=None):
        rig = build_rig(cfg)
        c = c or build_controller(cfg, rig)
        loop = ControlLoop(rig, c, rate=cfg.loop.rate, clock=SimClock(),
                           gate=ObservationGate.for_camera(cfg.loop.gate, rig.camera))
        err = []
        loop.run(10.0, lambda tick: err.append(float(np.linalg.norm(rig.truth_offset()))))
        return c, float(np.sqrt(np.mean(np.square(err))))

    c, first = engage()
    assert c.tip_model.member != 0                     # it found a scope other than the assumed one
    c, second = engage(c)
    assert second < 0.95 * first


def _robustness_case(tmp_path, seed: int, index: int, hold: float):
    """Robustness benchmark case ``index`` of set ``seed`` for ``adaptive`` with ``adaptive_hunt_hold``."""
    from targetlock.experiments.robustness import case_config, draw_cases, write_waypoints

    case = draw_cases(60, seed)[index]
    path = tmp_path / f"case{seed}-{index}.csv"
    write_waypoints(case, path)
    cfg = case_config(case, "adaptive", path, 12.0, seed)
    return dataclasses.replace(cfg, controller=dataclasses.replace(cfg.controller, adaptive_hunt_hold=hold))


def test_a_hunt_about_a_resting_target_is_stopped_where_it_is(tmp_path):
    """Robustness set 204 case 41: a step, calibrated-family scope at 3 cm. Correcting the last few px
    takes a reversal through the dead band, and the tip's stick-slip then jumps past the target: without
    the hold the target swings about the centre to the end (its last 3 s move 23 px, 23 px rms). With it,
    the image is still over the last 3 s and the offset left is within the hunt's extent (2 px rms).
    (Set 1 case 44, the case this test used before, no longer hunts since break-free jumps grow J.)"""
    from targetlock.experiments.robustness import score_run

    hunting = score_run(_robustness_case(tmp_path, 204, 41, 0.0))
    held = score_run(_robustness_case(tmp_path, 204, 41, 15.0))
    assert hunting["rest_motion_px"] > 4.0
    assert held["rest_motion_px"] < 1.0 and held["rest_rms_px"] < hunting["rest_rms_px"]
    assert held["rms_px"] < hunting["rms_px"]


def test_a_stated_nearest_distance_lets_a_far_step_go_at_pis_pace(tmp_path):
    """Robustness set 405 case 47 again (a 135 px step at 10.6 cm, PI 6.5 px rms): sized for a target
    that may be at 1 cm, the first steps are slow (27 px rms). A lab that states the target is at least
    8 cm away (knowledge.nearest_depth), or an oracle that knows the distance, steps at PI's pace."""
    from targetlock.experiments.robustness import case_config, draw_cases, score_run, write_waypoints

    def rms(controller: str, nearest: float | None = None) -> float:
        case = draw_cases(60, 405)[47]
        path = tmp_path / "case.csv"
        write_waypoints(case, path)
        cfg = case_config(case, controller, path, 12.0, 405)
        if nearest is not None:
            cfg = dataclasses.replace(cfg, knowledge=dataclasses.replace(cfg.knowledge, nearest_depth=nearest))
        return score_run(cfg)["rms_px"]

    pi, unknown, stated = rms("pi"), rms("adaptive"), rms("adaptive", 0.08)
    assert unknown > 2.0 * pi
    assert stated < 1.3 * pi and rms("adaptive+oracle") < 1.3 * pi


def test_a_far_step_is_not_crept_into_once_the_image_has_shown_j(tmp_path, monkeypatch):
    """Robustness set 405 case 47: a target appearing 135 px off centre at 10.6 cm on a looped shaft. The
    caution assumes the nearest distance's J until the fit is trusted, and the slow approach's motion is
    taken up by the target's estimated velocity, so the fit has few pairs: the step crept in over ~5 s
    (PI: 1.2 s). The pairs' own ratio of seen to predicted motion says within a second that J is about
    the prior's (JacobianEstimator.size_bound): within 10 px from 3.5 s on, and not without the bound."""
    import math

    from targetlock.controllers import adaptive

    def settled(evidence_px: float) -> float:
        """s from which the error stays within 10 px"""
        monkeypatch.setattr(adaptive, "CAUTION_EVIDENCE_PX", evidence_px)
        d = run_target_lock(_robustness_case(tmp_path, 405, 47, 15.0))["_data"]
        late = np.nonzero(d[:, 3] >= 10.0)[0]
        return float(d[late[-1] + 1, 0]) if late.size else 0.0

    assert settled(adaptive.CAUTION_EVIDENCE_PX) < 3.5
    assert settled(math.inf) > 4.5
