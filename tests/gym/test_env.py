"""The Gymnasium environment: API conformance, the loop's behaviour through it, randomisation."""
from __future__ import annotations

import dataclasses
import math

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import targetlock.gym  # noqa: F401  (registers the environment)
from targetlock.controllers import ControllerConfig, make_controller
from targetlock.controllers.knowledge import resolve_knowledge
from targetlock.experiments.target_lock import RunConfig, run_target_lock
from targetlock.gym import ENV_ID, TargetLockEnv
from targetlock.loop.runner import LoopConfig


def test_passes_the_gymnasium_checker():
    env = gymnasium.make(ENV_ID, config=RunConfig(loop=LoopConfig(seconds=3.0, metrics_after=1.0)))
    check_env(env.unwrapped, skip_render_check=True)


def test_a_pi_policy_through_the_environment_reproduces_targetlock_run():
    cfg = RunConfig(controller=ControllerConfig(kind="pi"), loop=LoopConfig(seconds=8.0, metrics_after=2.0), seed=5)
    cfg = dataclasses.replace(cfg, tracker=dataclasses.replace(cfg.tracker, seed=5, noise_px=0.5))
    expected = run_target_lock(cfg)

    env = TargetLockEnv(cfg, randomize=False)
    obs, info = env.reset(seed=5)
    lo, hi = env.rig.drives.limits
    rpt = env.rig.drives.rad_per_tick
    pi = make_controller(cfg.controller, rad_per_tick=rpt, lower=lo * rpt, upper=hi * rpt,
                         control_dt=1.0 / cfg.loop.rate, knowledge=resolve_knowledge(cfg.knowledge, cfg.twin))
    pi.reset(info["motor"], 0.0)
    previous = pi.setpoint.copy()
    errors, truncated = [], False
    while not truncated:
        if info["time"] >= cfg.loop.metrics_after and np.all(np.isfinite(info["true_offset"])):
            errors.append(math.hypot(*info["true_offset"]))
        setpoint = pi.step(info["observation"], info["motor"], info["time"])
        obs, reward, terminated, truncated, info = env.step(setpoint - previous)
        previous = setpoint
        assert not terminated and np.all(np.isfinite(obs))
    assert math.sqrt(np.mean(np.square(errors))) == pytest.approx(expected["rms_px"], rel=1e-6)
    assert max(errors) == pytest.approx(expected["peak_px"], rel=1e-6)


def test_actions_beyond_the_rate_limit_and_nan_are_limited_by_the_loop():
    env = TargetLockEnv(RunConfig(loop=LoopConfig(seconds=2.0, metrics_after=0.5)), randomize=False)
    obs, info = env.reset(seed=0)
    step = env.action_space.high[0]
    start = info["motor"].copy()
    for _ in range(10):
        obs, *_rest, info = env.step(np.array([1e6, np.nan]))
    moved = info["motor"] - start
    assert 0.0 < moved[0] <= 10 * step + 1e-9        # the handle followed, no faster than the rate limit
    assert moved[1] == 0.0                            # a NaN action holds the handle


def test_reset_seed_randomises_scope_latency_distance_and_path_reproducibly():
    env = TargetLockEnv(RunConfig(loop=LoopConfig(seconds=2.0, metrics_after=0.5)))
    seen = [env.reset(seed=s)[1] for s in range(8)]
    again = [env.reset(seed=s)[1] for s in range(8)]
    keys = ("preset", "latency", "distance", "path")
    assert [[i[k] for k in keys] for i in seen] == [[i[k] for k in keys] for i in again]
    assert len({i["latency"] for i in seen}) == 8 and all(0.25 <= i["latency"] <= 0.6 for i in seen)
    assert all(0.01 <= i["distance"] <= 0.15 for i in seen)
    assert len({i["path"] for i in seen}) > 1


def test_image_observations_are_the_rendered_endoscope_frames():
    env = gymnasium.make(ENV_ID, config=RunConfig(loop=LoopConfig(seconds=1.0, metrics_after=0.5)),
                         randomize=False, observation="image")
    obs, info = env.reset(seed=1)
    for _ in range(10):
        obs, *_ = env.step(np.zeros(2))
    assert env.observation_space.contains(obs)
    img = obs["image"]
    assert img.shape == (576, 720, 3) and img.std() > 5.0           # tissue, not a blank frame
    assert obs["state"][2] in (0.0, 1.0)
