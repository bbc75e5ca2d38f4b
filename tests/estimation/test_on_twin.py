"""The estimators on the full twin (SimulatedRig), fed as ``controllers/adaptive.py`` feeds them, against
the twin's truth measured from the twin itself (oracle, see twin_harness.py):

* delay truth: true latency − stamped latency (the rig stamps with the nominal 0.4 s) + the tip's lag
  behind the measured handle (first order, μ_f/(c²K_c + K_tip) = 45 ms);
* depth truth: the scene's distance;
* backlash truth: the handle travel between the rising and falling branch of a slow triangle sweep.

Excitation: a lock (an integral controller with the nominal Jacobian, loop gain 0.8/s) tracking a
target on an ellipse as large as its distance (0.1 Hz, with stops), after the 2 s engage probe
(ProbeSignal); and the probe alone on a static target (without it a static target gives nothing).
The Jacobian matrix is judged on the TipJacobianEstimator (``Lock(jacobian="tip")``: a nominal
TipModel run on the measured handle angles), its size also on the play-operator RLS.
"""
import math

import numpy as np
import pytest

from targetlock.estimation import DepthEstimator, ProbeSignal, nominal_width
from targetlock.model.camera import CameraParams
from targetlock.model.endoscope import EndoscopeParams
from targetlock.rig.simulated import ObservationNoise

from twin_harness import NOMINAL_TIP_GAIN, NOMINAL_WIDTH, STAMP_LATENCY, Lock, make_twin, nominal_prior, sweep_truth

J_NEAR = float(np.abs(nominal_prior(np.zeros(2), 0.01)).max())     # px/rad at 1 cm, nominal


def probe():
    return ProbeSignal.for_scope(NOMINAL_WIDTH, J_NEAR, margin_px=100.0)


def delay_truth(twin, lag):
    return twin.camera.latency - STAMP_LATENCY + 0.5 * twin.camera.latency_jitter + lag


@pytest.mark.parametrize("preset", ["calibrated", "looped-shaft"])
def test_nominal_backlash_prior_matches_the_twins_hysteresis_within_20_percent(preset):
    """The prior the controller can compute from its assumed scope is the twin's reversal width
    (friction turned around plus slack), not the slack alone (which is 4× smaller)."""
    twin = make_twin(preset, 0.05, latency=0.4)
    truth = sweep_truth(twin)
    assert nominal_width(twin.endoscope, 0.3) == pytest.approx(truth.width.mean(), rel=0.2)
    assert truth.width.min() > 3 * 2 * max(twin.endoscope.cable_slack, 0) / twin.endoscope.handle_radius


WIDTH_CONFOUND = pytest.mark.xfail(strict=True, reason=(
    "known gap: the delay fit is confounded with the backlash width, not starved by the probe. Its play "
    "operator assumes the nominal width (0.24 rad), this scope's is 0.39-0.41 rad, and the fit moves the delay "
    "to make up for it (measured over 10 s: +130 to +230 ms for -105). Handed the true width (oracle) the same "
    "probe gives -80 ms (test below); a probe that grows on an axis whose image did not move (tried: that "
    "axis' image then moves 17-38 px) does not help. Needs delay and width fitted jointly."))
SLOW_AFTER_PROBE = pytest.mark.xfail(strict=True, reason=(
    "known gap: at 12 cm the probe moves this scope's image only 67 px on x and not at all on y (its y loop is "
    "0.31 rad wide, the probe's amplitude 0.18 rad); the delay estimate swings (+470 to -50 ms) until the "
    "tracking after the probe settles it at ~6 s, to 100 ms for 145 (the same with the true width): at 5 s it "
    "is still -50 ms."))


def test_engage_probe_finds_the_delay_on_the_looped_shaft_once_the_width_is_known():
    """Diagnosis of WIDTH_CONFOUND: with the scope's true reversal width given to the play operator
    (oracle), the nominal-sized probe makes the delay observable (measured: -80 ms for -105 from 6 s on)."""
    twin = make_twin("looped-shaft", 0.05, latency=0.25, path="static")
    truth = sweep_truth(twin)
    lock = Lock(twin, probe=probe(), loop_gain=0.8, scheduled=False, fixed_width=truth.width)   # oracle width
    lock.run(8.0)
    assert lock.delay.delay == pytest.approx(delay_truth(twin, truth.tip_lag), abs=1.0 / twin.camera.fps)


@pytest.mark.parametrize("preset,distance,latency", [("calibrated", 0.05, 0.55), ("calibrated", 0.015, 0.3),
                                                     pytest.param("looped-shaft", 0.05, 0.25, marks=WIDTH_CONFOUND),
                                                     pytest.param("uncalibrated", 0.12, 0.5, marks=SLOW_AFTER_PROBE)])
def test_engage_probe_finds_the_residual_delay_within_one_frame(preset, distance, latency):
    twin = make_twin(preset, distance, latency=latency, path="static")
    truth = delay_truth(twin, sweep_truth(twin).tip_lag)
    with_probe = Lock(twin, probe=probe(), loop_gain=0.8, scheduled=False)
    trace = with_probe.run(5.0)
    assert with_probe.delay.delay == pytest.approx(truth, abs=1.0 / twin.camera.fps)
    assert all(with_probe.delay.lo <= d <= with_probe.delay.hi for d in trace.delay)
    # Without the probe a lock at rest on a static target gives the delay no information: unchanged.
    without = Lock(twin, loop_gain=0.8, scheduled=False)
    without.run(5.0)
    assert without.delay.delay == 0.0 and without.delay.estimates == 0


TRACKING = [("calibrated", 0.05, 0.5, 0.0), ("calibrated", 0.015, 0.3, 0.02), ("calibrated", 0.12, 0.25, 0.0),
            ("looped-shaft", 0.05, 0.3, 0.0)]


def track(preset, distance, latency, jitter, noise=None, truth=None, jacobian="rls", jac_kw=None):
    twin = make_twin(preset, distance, latency=latency, jitter=jitter, size=1.0)
    lock = Lock(twin, noise=noise or ObservationNoise(noise_px=0.2), probe=probe(), loop_gain=0.8, scheduled=False,
                truth=truth, jacobian=jacobian, jac_kw=jac_kw)
    return twin, lock, lock.run(30.0)


@pytest.mark.parametrize("preset,distance,latency,jitter", TRACKING)
def test_tracking_finds_the_delay_within_one_frame(preset, distance, latency, jitter):
    """30 s of tracking after the probe, stamped with 0.4 s while the true latency differs. (Measured
    over 5 noise seeds each: error -15 to -35 ms in all 20 runs.)"""
    twin, lock, trace = track(preset, distance, latency, jitter)
    truth = sweep_truth(twin)
    assert lock.delay.delay == pytest.approx(delay_truth(twin, truth.tip_lag), abs=1.0 / twin.camera.fps)
    assert all(lock.delay.lo <= d <= lock.delay.hi for d in trace.delay)


@pytest.mark.parametrize("preset,distance,latency,jitter", [c for c in TRACKING if c[1] < 0.1])
def test_tracking_finds_the_backlash_within_20_percent_in_most_runs(preset, distance, latency, jitter):
    """Per axis, at the bend of the start, in at least 2 of 3 runs (noise seeds); always within bounds.
    Measured over 5 seeds: calibrated 1.5 cm within 4 % in all; 5 cm within 9 % in 4, one +78 % on y;
    looped shaft within 17 % in 4, one -31 % on x; 12 cm (not asserted) within 12 % in 4, one +29 %.
    With the Jacobian the fit asks for: not grown on break-free jumps (``BacklashFitEstimator``)."""
    truth = sweep_truth(make_twin(preset, distance, latency=latency, jitter=jitter))
    good = 0
    for seed in range(3):
        twin, lock, trace = track(preset, distance, latency, jitter, noise=ObservationNoise(noise_px=0.2, seed=seed),
                                  jac_kw={"growth_ratio": math.inf})
        widths = np.array([lock.backlash.axis_width(a, 0.3) for a in range(2)])
        good += bool(np.all(np.abs(widths / truth.width - 1.0) <= 0.2))
        assert lock.backlash.reversals >= 4
        assert all(0.0 <= w <= lock.backlash.max_width for w in trace.width)
    assert good >= 2


@pytest.mark.parametrize("preset,distance,latency,jitter", TRACKING[:3])
def test_tracking_jacobian_size_within_20_percent(preset, distance, latency, jitter):
    """The size of J (geometric mean of its singular values, ``gain_scale``: what a gain schedule
    divides by), median over 10-30 s of tracking, against the twin's. Measured over 4 noise seeds:
    calibrated 5 cm 0.90-0.93, 1.5 cm 0.84-0.90, 12 cm 1.06-1.08 of the truth (single frames swing
    0.6-1.3); the looped shaft 0.65-0.73 (not asserted)."""
    twin = make_twin(preset, distance, latency=latency, jitter=jitter, size=1.0)
    twin, lock, trace = track(preset, distance, latency, jitter, truth=sweep_truth(twin))
    t = np.array(trace.t)
    size = np.sqrt(np.abs(np.linalg.det(np.array(trace.j)) / np.linalg.det(np.array(trace.j_true))))
    assert np.median(size[t > 10.0]) == pytest.approx(1.0, abs=0.2)


@pytest.mark.parametrize("preset,distance,latency,jitter", TRACKING[:3])
def test_tracking_jacobian_within_15_percent(preset, distance, latency, jitter):
    """The whole matrix (Frobenius, cross terms included), median over 15-30 s, by the
    TipJacobianEstimator on the nominal tip model; and the depth it implies. Measured over 3 noise
    seeds: 5 cm 9-11 %, 1.5 cm 5 %, 12 cm 8-10 %; depth 4.9-5.5, 1.5, 9.5-11 cm (the play-operator
    RLS: 38 %, 23-26 %, 43 %, mostly because J depends on where the target is in the image, 100-200 px
    off centre here, which one constant J cannot follow)."""
    twin = make_twin(preset, distance, latency=latency, jitter=jitter, size=1.0)
    twin, lock, trace = track(preset, distance, latency, jitter, truth=sweep_truth(twin), jacobian="tip")
    err = [np.linalg.norm(j - jt) / np.linalg.norm(jt) for j, jt in zip(trace.j, trace.j_true)]
    assert np.median(err[len(err) // 2:]) < 0.15
    assert lock.tip_jac.depth == pytest.approx(distance, rel=0.35)


@pytest.mark.parametrize("distance", [0.015, 0.10])
def test_depth_from_the_jacobian_after_the_probe_within_35_percent(distance):
    """(a) inherits the Jacobian's error after a 2 s probe (measured: 1.95 cm for 1.5, 8.7 cm for 10)."""
    twin = make_twin("calibrated", distance, latency=0.4, path="static")
    lock = Lock(twin, probe=probe(), loop_gain=0.8, scheduled=False)
    lock.run(5.0)
    depth = DepthEstimator(camera=CameraParams(), tip_gain=NOMINAL_TIP_GAIN, tip_length=0.12, n_elements=30)
    d = depth.from_jacobian(lock.jac.j, lock.rig.handle_angles())
    assert d == pytest.approx(distance, rel=0.35)
    assert depth.observable_j


@pytest.mark.parametrize("distance,observable", [(0.015, True), (0.10, False)])
def test_depth_from_the_scale_with_the_true_tip_angles(distance, observable):
    """Oracle geometry check of (b): fed the twin's true tip angles at the true capture time (what a
    rig measuring the tip would have), the scale fit finds 1.5 cm within 10 % after the probe; at 10 cm
    the camera's motion along its axis is too small, and it says so (NaN). Fed the motor through the
    assumed gain and backlash instead it is not observable yet (reported, not asserted)."""
    twin = make_twin("calibrated", distance, latency=0.4, path="static")
    lock = Lock(twin, noise=ObservationNoise(scale_noise=0.005), probe=probe(), loop_gain=0.8, scheduled=False)
    depth = DepthEstimator(camera=CameraParams(), tip_gain=1.0, tip_length=0.12, n_elements=30, use_scale=True)

    def feed(obs):
        true_capture = obs.arrival_time - twin.camera.latency          # oracle
        depth.add(lock.tip_history.at(true_capture), obs.offset, obs.scale, lock.jac.j)

    lock.frame_hooks.append(feed)
    lock.run(6.0)
    if observable:
        assert depth.depth_scale == pytest.approx(distance, rel=0.1)
        assert depth.depth == depth.depth_scale
    else:
        assert math.isnan(depth.depth_scale)
        assert depth.depth == depth.depth_j


def test_estimates_stay_bounded_and_converge_under_noise_drops_and_outliers():
    """1.5 cm, true latency 0.3 s (stamped 0.4), 20 ms jitter; noise 1.5 px, 10 % drops, 5 % outliers:
    every estimate within its bounds at every frame; after 30 s the delay within one frame and the
    backlash widths within 25 % (noise-free: 20 %)."""
    noise = ObservationNoise(noise_px=1.5, drop_probability=0.1, outlier_probability=0.05, seed=3)
    twin, lock, trace = track("calibrated", 0.015, 0.3, 0.02, noise=noise)
    truth = sweep_truth(twin)
    assert all(lock.delay.lo <= d <= lock.delay.hi for d in trace.delay)
    assert all(0.0 <= w <= lock.backlash.max_width for w in trace.width)
    for j in trace.j:
        s = np.linalg.svd(j, compute_uv=False)
        assert lock.jac.sv_min - 1e-6 <= s.min() and s.max() <= lock.jac.sv_max + 1e-6
    assert lock.delay.delay == pytest.approx(delay_truth(twin, truth.tip_lag), abs=1.0 / twin.camera.fps)
    widths = np.array([lock.backlash.axis_width(a, 0.3) for a in range(2)])
    np.testing.assert_allclose(widths, truth.width, rtol=0.25)


def test_tip_jacobian_stays_bounded_and_converges_under_noise_drops_and_outliers():
    """The same conditions for the TipJacobianEstimator: its J within the bounds at every frame, finite,
    and its whole matrix within 20 % of the truth (median over 15-30 s; measured on seeds 3, 4, 5: 9 %,
    6 %, 13 %; noise-free 5 %); the depth within 35 % (measured 1.3, 1.5, 2.2 cm for 1.5)."""
    noise = ObservationNoise(noise_px=1.5, drop_probability=0.1, outlier_probability=0.05, seed=3)
    twin = make_twin("calibrated", 0.015, latency=0.3, jitter=0.02, size=1.0)
    twin, lock, trace = track("calibrated", 0.015, 0.3, 0.02, noise=noise, truth=sweep_truth(twin), jacobian="tip")
    for j in trace.j:
        s = np.linalg.svd(j, compute_uv=False)
        assert np.all(np.isfinite(j)) and lock.jac.sv_min - 1e-6 <= s.min() and s.max() <= lock.jac.sv_max + 1e-6
    err = [np.linalg.norm(j - jt) / np.linalg.norm(jt) for j, jt in zip(trace.j, trace.j_true)]
    assert np.median(err[len(err) // 2:]) < 0.2
    assert lock.tip_jac.depth == pytest.approx(0.015, rel=0.35)


def test_probe_is_bounded_zero_mean_and_ends_at_zero():
    p = ProbeSignal.for_scope(0.24, 1742.0, margin_px=100.0)
    t = np.arange(-0.5, 3.0, 0.001)
    off = np.array([p.offset(x) for x in t])
    assert np.max(np.abs(off)) <= p.amplitude + 1e-12 and p.amplitude == pytest.approx(0.5 * 0.24 + 100.0 / 1742.0)
    assert p.crosses
    capped = ProbeSignal.for_scope(0.24, 1742.0, margin_px=100.0, max_px=150.0)     # worst case 150 px at J_near
    assert capped.amplitude * 1742.0 == pytest.approx(150.0) and not capped.crosses
    inside = (t >= 0) & (t < p.duration)
    assert np.abs(off[inside].mean(axis=0)).max() < 1e-3 * p.amplitude + 1e-9
    assert np.all(off[~inside] == 0.0) and p.done(2.0) and not p.done(1.9)
    assert np.max(np.abs(np.diff(off, axis=0))) / 0.001 <= 1.6 + 1e-6     # within the drive's rate limit
    with pytest.raises(ValueError, match="duration"):
        ProbeSignal(0.1, duration=3.0)
    with pytest.raises(ValueError, match="rad/s"):
        ProbeSignal(0.9, duration=1.0)


def test_depth_estimator_is_bounded_under_garbage():
    est = DepthEstimator(camera=CameraParams(), tip_gain=NOMINAL_TIP_GAIN, tip_length=0.12, n_elements=30,
                         use_scale=True)
    rng = np.random.default_rng(7)
    for k in range(300):
        j = np.diag([-1.0, -1.0]) * rng.choice([1.0, 1e4, 1e9, np.nan])
        d = est.add(rng.normal(0, 0.5, 2), rng.normal(0, 100, 2), float(rng.choice([1.0, np.nan, 1e9, 0.9])), j)
        assert est.lo <= d <= est.hi and math.isfinite(d)
