"""The target lock as a Gymnasium environment: a thin adapter over the control loop on the twin.

One environment step is one control tick of :class:`~targetlock.loop.runner.ControlLoop`: the
agent's action replaces the controller's output, everything else — the twin's physics, the video
latency, the observation gate, the drives' range and rate limits — is the loop's own, so a policy
learnt here meets the same plant and the same safety rules as ``targetlock run``.

- **observation** (``float32[6]``): tracker offset x, y (px from the image centre; 0 when lost),
  validity (1/0), age of the observation (s since its frame was captured; the video latency and
  more), measured handle angles x, y (rad). With ``observation="image"`` a dict that adds the
  newest rendered endoscope frame (``uint8[H, W, 3]``).
- **action** (``float32[2]``): handle set-point change for this tick (rad), bounded by the rate
  limit (``controller.max_rate`` / ``loop.rate``).
- **reward**: ``-error / reward_scale_px`` with the true image error (what a person watching the
  screen sees; ``reward="observed"`` uses the tracker's offset instead), and ``-out_of_view_penalty``
  while the target is outside the image.
- **episode**: ``loop.seconds`` of the twin; truncated at the end, never terminated early.
- **domain randomisation**: ``reset(seed=s)`` seeds the run with ``s`` and draws a scope around the presets, a latency, a frame
  rate, a distance and a path from ``s`` (:func:`random_case`); ``options={"config": {...}}`` gives
  nested settings instead (as in ``config.toml``), ``options={"randomize": False}`` the base config.
"""
from __future__ import annotations

import functools
import math
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from ..config import from_dict, to_dict
from ..controllers.base import Controller
from ..controllers.knowledge import resolve_knowledge
from ..experiments.target_lock import RunConfig, build_rig
from ..loop.clock import SimClock
from ..loop.gate import ObservationGate
from ..loop.runner import ControlLoop
from ..model.twin import merge, preset_overrides
from ..rig.base import Observation

__all__ = ["TargetLockEnv", "random_case", "observation_vector", "episode_settings", "env_spaces"]

MAX_AGE = 60.0
"""s: the observation's age is reported up to this (a target unseen for longer is simply old)."""


@functools.lru_cache(maxsize=None)
def _preset_endoscope(preset: str):
    """The endoscope of a named preset (built once: validating a config costs milliseconds)."""
    return from_dict(RunConfig, {"twin": merge(preset_overrides(preset), {"preset": preset})}).twin.endoscope


def random_case(rng: np.random.Generator) -> dict:
    """Nested settings of one randomised episode: a scope drawn around a preset (friction, slack or
    pretension, stiffness ±30 %, handle gain ±15 %), latency 0.25-0.6 s, 15-25 fps, target distance
    1-15 cm with the path scaled to it, and one of the report's paths."""
    preset = str(rng.choice(["calibrated", "uncalibrated", "looped-shaft"]))
    e = _preset_endoscope(preset)

    def scale(v: float, rel: float) -> float:
        return float(v * rng.uniform(1.0 - rel, 1.0 + rel))

    distance = float(math.exp(rng.uniform(math.log(0.01), math.log(0.15))))
    return {
        "twin": merge(preset_overrides(preset), {
            "preset": preset,
            "endoscope": {"mu_n": scale(e.mu_n, 0.3), "mu_f": scale(e.mu_f, 0.3),
                          "friction_offset": scale(e.friction_offset, 0.3),
                          "tip_stiffness": scale(e.tip_stiffness, 0.3),
                          "cable_stiffness": scale(e.cable_stiffness, 0.3),
                          "cable_slack": float(e.cable_slack + rng.uniform(-0.0004, 0.0004)),
                          "handle_radius": scale(e.handle_radius, 0.15)},
            "camera": {"latency": float(rng.uniform(0.25, 0.6)), "fps": float(rng.uniform(15.0, 25.0))},
            "scene": {"path": str(rng.choice(["linear", "ellipse", "step", "static"])), "distance": distance,
                      # paths scaled to the distance: the same angles in view at 1 cm and at 12 cm
                      "linear_length": distance, "ellipse_size": [1.08 * distance, distance]},
        }),
    }


def env_spaces(base: RunConfig) -> tuple[spaces.Box, spaces.Box]:
    """The action space (handle set-point change per tick, rad, within the rate limit) and the
    observation vector's space of an environment on ``base``."""
    step = base.controller.max_rate / base.loop.rate
    action = spaces.Box(-step, step, shape=(2,), dtype=np.float32)
    cam = base.twin.camera
    # offsets within the image (the loop's gate rejects the rest), age capped, handle within the drive range
    lo, hi = base.twin.drive.min_angle, base.twin.drive.max_angle   # rad; randomisation keeps them
    vec = spaces.Box(np.array([-cam.width, -cam.height, 0.0, 0.0, lo, lo], np.float32),
                     np.array([cam.width, cam.height, 1.0, MAX_AGE, hi, hi], np.float32), dtype=np.float32)
    return action, vec


def episode_settings(base: RunConfig, rng: np.random.Generator, seed: int | None, options: dict | None,
                     randomize: bool) -> dict:
    """Nested settings of one episode (see the module doc): ``options["config"]``, else a
    :func:`random_case` drawn from ``rng`` when randomising, else ``base``; seeded with ``seed``."""
    options = options or {}
    data = to_dict(base)
    if "config" in options:
        data = merge(data, options["config"])
    elif options.get("randomize", randomize):
        data = merge(data, random_case(rng))
    # the run's own seed: the reset seed when given (so reset(seed=s) on a fixed config is
    # `targetlock run --seed s`), else the next draw of the environment's generator
    episode_seed = int(seed) if seed is not None else int(rng.integers(2**31))
    return merge(data, {"seed": episode_seed, "tracker": {"seed": episode_seed}})


def observation_vector(obs: Observation | None, motor: np.ndarray, t: float, last: np.ndarray) -> np.ndarray:
    """The environment's observation from the loop's newest observation (or the previous vector's
    offset and validity when no frame arrived this tick; the age keeps growing)."""
    out = last.copy()
    if obs is not None:
        ok = obs.valid and bool(np.all(np.isfinite(obs.offset)))
        out[0:2] = obs.offset if ok else 0.0
        out[2] = 1.0 if ok else 0.0
        out[3] = t - obs.capture_time
    else:
        out[3] = min(out[3] + (t - out[6] if out[6] >= 0 else 0.0), MAX_AGE)
    out[4:6] = motor
    out[6] = t
    return out


class _Agent(Controller):
    """The agent's action as the loop's controller: the base class applies range and rate limits."""

    action = np.zeros(2)

    def _reset(self, motor: np.ndarray, t: float) -> None:
        self.action = np.zeros(2)

    def _update(self, obs: Observation | None, motor: np.ndarray, t: float) -> np.ndarray:
        return self.setpoint + self.action


class TargetLockEnv(gym.Env):
    """See the module doc. ``config``: the base :class:`RunConfig` (default: ``targetlock run``'s);
    ``randomize``: draw each episode with :func:`random_case` (default True)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 22}

    def __init__(self, config: RunConfig | None = None, *, randomize: bool = True, reward: str = "truth",
                 reward_scale_px: float = 100.0, out_of_view_penalty: float = 5.0, observation: str = "ideal",
                 render_mode: str | None = None) -> None:
        if reward not in ("truth", "observed"):
            raise ValueError(f"reward = {reward!r}; allowed: 'truth', 'observed'")
        if observation not in ("ideal", "image"):
            raise ValueError(f"observation = {observation!r}; allowed: 'ideal', 'image'")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode = {render_mode!r}; allowed: None, 'rgb_array'")
        self.base = config or RunConfig()
        self.randomize, self.reward_kind = randomize, reward
        self.reward_scale, self.penalty = float(reward_scale_px), float(out_of_view_penalty)
        self.observation_kind, self.render_mode = observation, render_mode
        self.cfg = self.base
        self.action_space, vec = env_spaces(self.base)
        cam = self.base.twin.camera
        if observation == "image":
            self.observation_space = spaces.Dict({
                "state": vec, "image": spaces.Box(0, 255, shape=(cam.height, cam.width, 3), dtype=np.uint8)})
        else:
            self.observation_space = vec
        self._loop: ControlLoop | None = None
        self._frame: np.ndarray | None = None

    # ------------------------------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        data = episode_settings(self.base, self.np_random, seed, options, self.randomize)
        if self.observation_kind == "image" or self.render_mode == "rgb_array":
            data["vision"] = True
        self.cfg = from_dict(RunConfig, data)
        self._close_loop()
        self._frame = None
        hook = None
        if self.cfg.vision:
            from ..vision.pipeline import VisionPipeline
            hook = VisionPipeline(self.cfg.twin, tracker=self.cfg.vision_tracker, seed=self.cfg.seed,
                                  on_frame=self._keep_frame, tracker_settings=self.cfg.feature_tracker)
        self.rig = build_rig(self.cfg, hook)
        lo, hi = self.rig.drives.limits
        rpt = self.rig.drives.rad_per_tick
        # the agent knows only the controller's nominal knowledge, as every controller (never the truth)
        self.agent = _Agent(self.cfg.controller, rad_per_tick=rpt, lower=lo * rpt, upper=hi * rpt,
                            control_dt=1.0 / self.cfg.loop.rate,
                            knowledge=resolve_knowledge(self.cfg.knowledge, self.cfg.twin))
        self._loop = ControlLoop(self.rig, self.agent, rate=self.cfg.loop.rate, clock=SimClock(),
                                 gate=ObservationGate.for_camera(self.cfg.loop.gate, self.rig.camera))
        self._loop.begin()
        self._k = 0
        self._n = int(round(self.cfg.loop.seconds * self.cfg.loop.rate))
        self._vec = np.zeros(7)
        self._vec[6] = -1.0
        tick = self._loop.observe()          # the first tick's observation; the action acts on it
        return self._observe(tick)[0], self._info(tick)

    def step(self, action):
        if self._loop is None:
            raise RuntimeError("step() before reset(), or after the episode was truncated")
        a = np.clip(np.asarray(action, dtype=float).reshape(2), self.action_space.low, self.action_space.high)
        self.agent.action = np.where(np.isfinite(a), a, 0.0)     # a NaN action holds the handle
        self._loop.act()                     # this tick's set-point: the loop's limits apply
        self._k += 1
        truncated = self._k >= self._n
        tick = self._loop.observe()          # the next tick: what the action led to
        obs, err = self._observe(tick)
        reward = -self.penalty if not math.isfinite(err) else -err / self.reward_scale
        info = self._info(tick)
        if truncated:
            self._close_loop()
        return obs, float(reward), False, truncated, info

    def _observe(self, tick) -> tuple[Any, float]:
        """The observation of a tick and the error the reward is computed from (px; NaN out of view)."""
        self._vec = observation_vector(tick.observation, tick.motor, tick.time, self._vec)
        self._truth = self.rig.truth_offset(tick.time)
        if self.reward_kind == "truth":
            err = math.hypot(self._truth[0], self._truth[1])
        else:
            err = math.hypot(self._vec[0], self._vec[1]) if self._vec[2] else math.nan
        return self._observation(), err

    def render(self):
        if self.render_mode == "rgb_array":
            return self._frame
        return None

    def close(self) -> None:
        self._close_loop()

    # ------------------------------------------------------------------------------------------ helpers
    def _keep_frame(self, t: float, image: np.ndarray, result) -> None:
        self._frame = image if image.ndim == 3 else np.repeat(image[..., None], 3, axis=2)

    def _observation(self):
        state = self._vec[:6].astype(np.float32)
        if self.observation_kind == "image":
            cam = self.cfg.twin.camera
            img = self._frame.copy() if self._frame is not None else np.zeros((cam.height, cam.width, 3), np.uint8)
            return {"state": state, "image": img}
        return state

    def _info(self, tick) -> dict[str, Any]:
        """The episode's draw, the tick's time (s), true offset (px), motors (rad) and raw observation."""
        return {"time": tick.time, "preset": self.cfg.twin.preset, "latency": self.cfg.twin.camera.latency,
                "distance": self.cfg.twin.scene.distance, "path": self.cfg.twin.scene.path,
                "true_offset": self._truth, "motor": tick.motor.copy(), "observation": tick.observation}

    def _close_loop(self) -> None:
        self._loop = None          # the twin holds nothing open; a new episode builds a new rig
