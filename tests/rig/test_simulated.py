import math

import numpy as np
import pytest

from targetlock.model.twin import TwinConfig
from targetlock.rig.simulated import ObservationNoise, SimulatedRig


def test_tip_starts_at_the_scene_start_angles_with_the_target_centred():
    rig = SimulatedRig(TwinConfig())
    assert math.degrees(rig.tip_angles()[0]) == pytest.approx(-10.0, abs=0.5)
    np.testing.assert_allclose(rig.truth_offset(0.0), [0.0, 0.0], atol=1e-9)


def test_frames_are_captured_at_the_frame_rate():
    rig = SimulatedRig(TwinConfig())
    rig.drives.home()
    rig.advance(2.0)
    times = np.array([o.capture_time for o in rig.observations.poll(10.0)])
    np.testing.assert_allclose(np.diff(times), 1 / 22, atol=1e-12)
    assert len(times) == int(2.0 * 22) + 1
    log = rig.frame_log
    assert (log.frames, log.valid, log.first, log.last) == (len(times), len(times), 0.0, times[-1])


def test_drives_clamp_setpoints_and_report_positions_in_ticks():
    rig = SimulatedRig(TwinConfig())
    rig.drives.home()
    lo, hi = rig.drives.limits
    rig.drives.send_setpoints(np.array([10 ** 9, -(10 ** 9)]))
    np.testing.assert_array_equal(rig.drives.last_ticks, [hi[0], lo[1]])
    rig.advance(5.0)
    pos = rig.drives.positions()
    assert abs(pos[0] - hi[0]) <= 1 and abs(pos[1] - lo[1]) <= 1


def test_noise_is_seeded_and_dropped_frames_yield_nothing():
    def observed(seed):
        rig = SimulatedRig(TwinConfig(), ObservationNoise(noise_px=3.0, drop_probability=0.3, seed=seed))
        rig.drives.home()
        rig.advance(3.0)
        return [(round(o.capture_time, 6), tuple(o.offset - o.truth)) for o in rig.observations.poll(10.0)]
    a, b, c = observed(1), observed(1), observed(2)
    assert a == b and a != c
    assert 0.5 * 67 < len(a) < 0.9 * 67
    assert np.std([o[1][0] for o in a]) == pytest.approx(3.0, rel=0.4)


def test_target_out_of_view_gives_invalid_observations():
    import dataclasses
    twin = TwinConfig()
    twin = dataclasses.replace(twin, scene=dataclasses.replace(twin.scene, path="step", step_offset_px=(-500.0, 0.0)))
    rig = SimulatedRig(twin)
    rig.drives.home()
    rig.advance(1.0)
    obs = rig.observations.poll(10.0)
    assert obs and not any(o.valid for o in obs) and all(np.isnan(o.offset).all() for o in obs)


def test_frames_are_stamped_with_the_latency_the_rig_was_told_not_the_true_one():
    """A rig knows only when a frame arrived; it stamps arrival minus the latency it was given."""
    import dataclasses
    twin = TwinConfig()
    twin = dataclasses.replace(twin, camera=dataclasses.replace(twin.camera, latency=0.25))
    rig = SimulatedRig(twin, stamp_latency=0.4)
    assert rig.camera.latency == 0.4          # the camera as the rig knows it
    rig.drives.home()
    rig.advance(2.0)
    obs = rig.observations.poll(10.0)
    true_capture = np.arange(len(obs)) / 22
    np.testing.assert_allclose([o.arrival_time for o in obs], true_capture + 0.25, atol=1e-9)
    np.testing.assert_allclose([o.capture_time for o in obs], true_capture + 0.25 - 0.4, atol=1e-9)
    # The offsets are still those of the true capture instants.
    np.testing.assert_allclose([o.offset for o in obs], [rig.truth_offset(t) for t in true_capture], atol=1e-9)


def test_latency_jitter_delays_frames_within_its_bound_and_keeps_them_in_order():
    import dataclasses
    twin = TwinConfig()
    twin = dataclasses.replace(twin, camera=dataclasses.replace(twin.camera, latency=0.3, latency_jitter=0.05))
    rig = SimulatedRig(twin, ObservationNoise(seed=4))
    rig.drives.home()
    rig.advance(5.0)
    obs = rig.observations.poll(1e9)
    true_capture = np.arange(len(obs)) / 22
    delay = np.array([o.arrival_time for o in obs]) - true_capture
    assert delay.min() >= 0.3 - 1e-9 and delay.max() <= 0.35 + 1e-9
    assert np.std(delay) > 0.01                      # it does jitter
    assert np.all(np.diff([o.arrival_time for o in obs]) >= 0.0)
    # Frames are stamped from their arrival, so the stamps carry the jitter (as on a real rig).
    np.testing.assert_allclose([o.capture_time for o in obs], [o.arrival_time - 0.3 for o in obs], atol=1e-12)
