"""The batch vector environment: Gymnasium's vector API, each sub-env the single environment's meaning."""
from __future__ import annotations

import dataclasses
import math

import gymnasium
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode, SyncVectorEnv
from gymnasium.vector.utils import batch_space

import targetlock.gym  # noqa: F401  (registers the environments)
from targetlock.controllers import ControllerConfig, make_controller
from targetlock.controllers.knowledge import resolve_knowledge
from targetlock.experiments.target_lock import RunConfig, run_target_lock
from targetlock.gym import ENV_ID, TargetLockEnv, TargetLockVectorEnv
from targetlock.loop.runner import LoopConfig
from targetlock.rig.base import Observation
from targetlock.rig.simulated import ObservationNoise

SHORT = RunConfig(loop=LoopConfig(seconds=0.6, metrics_after=0.1))     # 30 ticks an episode


def test_make_vec_gives_the_batch_env_with_the_single_envs_spaces():
    envs = gymnasium.make_vec(ENV_ID, num_envs=3, config=SHORT)
    single = TargetLockEnv(SHORT)
    assert isinstance(envs, TargetLockVectorEnv) and envs.num_envs == 3
    assert envs.single_observation_space == single.observation_space
    assert envs.single_action_space == single.action_space
    assert envs.observation_space == batch_space(single.observation_space, 3)
    assert envs.action_space == batch_space(single.action_space, 3)
    assert envs.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    obs, info = envs.reset(seed=4)
    assert envs.observation_space.contains(obs)
    assert all(np.shape(v)[0] == 3 for v in info.values()) and info["_latency"].all()
    envs.action_space.seed(0)
    obs, reward, terminated, truncated, info = envs.step(envs.action_space.sample())
    assert envs.observation_space.contains(obs)
    assert reward.shape == (3,) and reward.dtype == np.float64 and np.all(reward <= 0.0)
    assert terminated.dtype == truncated.dtype == np.bool_ and not terminated.any() and not truncated.any()


def _actions(rng: np.random.Generator, n: int, step: float) -> np.ndarray:
    """Random actions, some beyond the rate limit and some NaN."""
    a = rng.uniform(-2.0 * step, 2.0 * step, (n, 2))
    a[rng.random((n, 2)) < 0.05] = np.nan
    return a


def test_each_sub_env_is_the_single_env_through_autoresets():
    # Gymnasium's reference vectoriser over N single environments (N Python control loops) against the
    # batch kernel: same seeds, same actions, 2 autoresets, a noisy tracker that drops frames.
    cfg = dataclasses.replace(SHORT, tracker=ObservationNoise(noise_px=1.0, drop_probability=0.2))
    n = 3
    reference = SyncVectorEnv([lambda: TargetLockEnv(cfg) for _ in range(n)])
    batch = TargetLockVectorEnv(n, cfg)
    obs_r, info_r = reference.reset(seed=11)
    obs_b, info_b = batch.reset(seed=11)
    np.testing.assert_array_equal(info_b["latency"], info_r["latency"])
    rng = np.random.default_rng(3)
    step = float(batch.single_action_space.high[0])
    ends = 0
    for _ in range(75):
        # The batch projection sums in another order than the single env's matmul (float ulps), so
        # observations are compared to 1e-6 px/rad/s; in practice they agree bit for bit.
        np.testing.assert_allclose(obs_b, obs_r, rtol=0, atol=1e-6)
        np.testing.assert_allclose(info_b["true_offset"], info_r["true_offset"], rtol=0, atol=1e-6)
        a = _actions(rng, n, step)
        obs_r, rew_r, term_r, trunc_r, info_r = reference.step(a)
        obs_b, rew_b, term_b, trunc_b, info_b = batch.step(a)
        np.testing.assert_allclose(rew_b, rew_r, rtol=0, atol=1e-8)
        np.testing.assert_array_equal(trunc_b, trunc_r)
        np.testing.assert_array_equal(term_b, term_r)
        ends += int(trunc_b.all())
    assert ends == 2


def _pi(cfg: RunConfig, batch: TargetLockVectorEnv):
    rpt = batch.rpt
    lo, hi = cfg.twin.drive.min_ticks, cfg.twin.drive.max_ticks
    return make_controller(cfg.controller, rad_per_tick=rpt, lower=np.array([lo, lo]) * rpt,
                           upper=np.array([hi, hi]) * rpt, control_dt=1.0 / cfg.loop.rate,
                           knowledge=resolve_knowledge(cfg.knowledge, cfg.twin))


def test_a_pi_policy_in_every_sub_env_reproduces_targetlock_run():
    cfg = RunConfig(controller=ControllerConfig(kind="pi"), loop=LoopConfig(seconds=8.0, metrics_after=2.0))
    cfg = dataclasses.replace(cfg, tracker=dataclasses.replace(cfg.tracker, noise_px=0.5))
    seeds = [5, 6]
    batch = TargetLockVectorEnv(len(seeds), cfg, randomize=False)
    obs, info = batch.reset(seed=seeds)
    pis = [_pi(cfg, batch) for _ in seeds]
    for i, pi in enumerate(pis):
        pi.reset(info["motor"][i], 0.0)
    previous = np.array([pi.setpoint.copy() for pi in pis])
    errors: list[list[float]] = [[] for _ in seeds]
    truncated = np.zeros(len(seeds), dtype=bool)
    while not truncated.all():
        setpoints = np.empty_like(previous)
        for i, pi in enumerate(pis):
            if info["time"][i] >= cfg.loop.metrics_after and np.all(np.isfinite(info["true_offset"][i])):
                errors[i].append(math.hypot(*info["true_offset"][i]))
            seen = None
            if info["obs_new"][i]:
                seen = Observation(capture_time=float(info["obs_capture_time"][i]), offset=info["obs_offset"][i].copy(),
                                   valid=bool(info["obs_valid"][i]))
            setpoints[i] = pi.step(seen, info["motor"][i], info["time"][i])
        obs, reward, terminated, truncated, info = batch.step(setpoints - previous)
        previous = setpoints
    for i, seed in enumerate(seeds):
        expected = run_target_lock(dataclasses.replace(cfg, seed=seed,
                                                       tracker=dataclasses.replace(cfg.tracker, seed=seed)))
        assert math.sqrt(np.mean(np.square(errors[i]))) == pytest.approx(expected["rms_px"], rel=1e-6)
        assert max(errors[i]) == pytest.approx(expected["peak_px"], rel=1e-6)


def test_sub_envs_randomise_differently_and_as_the_single_env_does():
    envs = TargetLockVectorEnv(8, SHORT)
    _, info = envs.reset(seed=0)
    single = TargetLockEnv(SHORT)
    for i in range(8):
        _, one = single.reset(seed=i)
        assert [info[k][i] for k in ("preset", "latency", "distance", "path")] == \
               [one[k] for k in ("preset", "latency", "distance", "path")]
    assert len(set(info["latency"])) == 8 and len(set(info["fps"])) == 8 and len(set(info["path"])) > 1
    assert not np.allclose(envs.params[0], envs.params[1])          # each its own scope on the kernel
    _, again = envs.reset(seed=0)
    np.testing.assert_array_equal(again["distance"], info["distance"])


def test_actions_beyond_the_rate_limit_and_nan_are_limited():
    envs = TargetLockVectorEnv(2, SHORT, randomize=False)
    _, info = envs.reset(seed=0)
    step = float(envs.single_action_space.high[0])
    start = info["motor"].copy()
    for _ in range(10):
        _, _, _, _, info = envs.step(np.array([[1e6, np.nan], [-np.inf, 0.0]]))
    moved = info["motor"] - start
    assert 0.0 < moved[0, 0] <= 10 * step + 1e-9      # followed, no faster than the rate limit
    assert moved[0, 1] == 0.0                          # a NaN action holds the handle
    assert -10 * step - 1e-9 <= moved[1, 0] < 0.0      # -inf is the rate limit's other side
    assert moved[1, 1] == 0.0


def test_autoreset_next_step_and_same_step():
    envs = TargetLockVectorEnv(2, dataclasses.replace(SHORT, loop=LoopConfig(seconds=0.2, metrics_after=0.1)))
    _, first = envs.reset(seed=1)
    zero = np.zeros((2, 2))
    for k in range(10):
        obs, reward, _, truncated, info = envs.step(zero)
        assert truncated.all() == (k == 9)
    assert info["time"] == pytest.approx([0.22, 0.22])
    obs, reward, _, truncated, info = envs.step(np.full((2, 2), np.nan))     # the reset step: action ignored
    assert not truncated.any() and np.all(reward == 0.0)
    assert info["time"] == pytest.approx([0.02, 0.02]) and np.all(obs[:, 2] == 0.0)
    assert not np.any(info["latency"] == first["latency"])                    # new episodes, new draws

    same = TargetLockVectorEnv(2, dataclasses.replace(SHORT, loop=LoopConfig(seconds=0.2, metrics_after=0.1)),
                               autoreset_mode=AutoresetMode.SAME_STEP)
    same.reset(seed=1)
    for k in range(10):
        obs, reward, _, truncated, info = same.step(zero)
    assert truncated.all() and info["_final_obs"].all()
    assert info["final_info"]["time"] == pytest.approx([0.22, 0.22]) and info["time"] == pytest.approx([0.02, 0.02])
    assert same.observation_space.contains(info["final_obs"]) and np.all(reward < 0.0)

    off = TargetLockVectorEnv(1, dataclasses.replace(SHORT, loop=LoopConfig(seconds=0.2, metrics_after=0.1)),
                              autoreset_mode=AutoresetMode.DISABLED)
    off.reset(seed=1)
    for _ in range(10):
        off.step(np.zeros((1, 2)))
    with pytest.raises(RuntimeError, match="reset them first"):
        off.step(np.zeros((1, 2)))


def test_reset_mask_resets_only_the_masked_sub_envs():
    cfg = dataclasses.replace(SHORT, loop=LoopConfig(seconds=3.0, metrics_after=0.5))
    envs, single = TargetLockVectorEnv(2, cfg), TargetLockEnv(cfg)
    obs, _ = envs.reset(seed=3)
    one, _ = single.reset(seed=3)
    a = np.full((2, 2), 0.01)
    for _ in range(5):
        obs, *_ = envs.step(a)
        one, *_ = single.step(a[0])
    # sub-env 1 anew with a 3 s latency: more frames in flight, so wider frame tables while sub-env 0 runs on
    _, info = envs.reset(seed=[None, 9], options={"reset_mask": np.array([False, True]),
                                                  "config": {"twin": {"camera": {"latency": 3.0, "fps": 25.0}}}})
    assert info["time"] == pytest.approx([0.12, 0.02]) and info["latency"][1] == 3.0
    arrived = np.zeros(2, dtype=int)
    for _ in range(140):            # sub-env 0 is still the single env's episode (it sees its frames)
        obs, *_, info = envs.step(a)
        one, *_ = single.step(a[0])
        np.testing.assert_allclose(obs[0], one, rtol=0, atol=1e-6)
        arrived += info["obs_new"]
    assert arrived[0] > 40 and arrived[1] == 0         # sub-env 1's first frame is still 3 s away


def test_unsupported_features_are_refused_by_name():
    with pytest.raises(ValueError, match="observation = 'image'.*not supported"):
        gymnasium.make_vec(ENV_ID, num_envs=2, observation="image")
    envs = TargetLockVectorEnv(2, SHORT)
    with pytest.raises(ValueError, match="loop.rate"):
        envs.reset(seed=0, options={"config": {"loop": {"rate": 100.0}}})


def test_gymnasiums_vector_wrappers_see_the_episodes():
    envs = gymnasium.wrappers.vector.RecordEpisodeStatistics(
        gymnasium.make_vec(ENV_ID, num_envs=3, config=dataclasses.replace(SHORT, loop=LoopConfig(seconds=0.2,
                                                                                               metrics_after=0.1))))
    envs.reset(seed=0)
    total = np.zeros(3)
    for _ in range(10):
        _, reward, _, truncated, info = envs.step(np.zeros((3, 2)))
        total += reward
    assert truncated.all() and np.all(info["episode"]["l"] == 10)
    np.testing.assert_allclose(info["episode"]["r"], total, rtol=1e-5)
