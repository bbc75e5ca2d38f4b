"""N target-lock episodes stepped together on the model's batch kernel (a Gymnasium ``VectorEnv``).

Each sub-environment means what :class:`~targetlock.gym.env.TargetLockEnv` means — the same
observation vector, action, reward, domain randomisation (sub-env ``i`` of ``reset(seed=s)`` is the
single environment's ``reset(seed=s + i)``) and the same safety rules (set-point range and rate
limit, a NaN action holds the handle, set-points clipped to the drive range before the integer cast)
— but nothing is routed through N Python control loops:

- **physics**: one call of the numba kernel per tick advances all N endoscopes by the tick's model
  steps and returns the intermediate states (:func:`~targetlock.model.endoscope.simulate`);
- **frames**: each sub-env captures at its own frame rate on the model's time grid (the state at
  the model step nearest the capture time, as the twin does); the camera projection of all captures
  of a tick is one numpy call;
- **latency line**: a table of each sub-env's captured frames, stamped as the twin stamps them (arrival
  minus the latency the controller assumes); a frame arrives ``latency`` s after
  capture (each sub-env its own latency) and passes the loop's plausibility gate;
- **reward**: the true image error of all sub-envs in one projection.

Not supported (a clear error when asked for): rendered-image observations and ``render_mode``
(use ``vectorization_mode="sync"``), and per-episode settings that must be shared by all
sub-environments (model step, loop rate, episode length, rate limit, drives, camera intrinsics,
tip geometry, the tracker's imperfections; all are the base config's unless ``options["config"]``
changes them for all). Tracker imperfections (noise, drops, outliers) draw from each sub-env's own
generator in the single environment's order, so they cost a Python loop over the sub-envs that
captured a frame in a tick; the default ideal tracker has none.

Autoreset: ``autoreset_mode`` (default :attr:`AutoresetMode.NEXT_STEP`, Gymnasium's default) as in
Gymnasium's own vector environments; ``options={"reset_mask": mask}`` resets some sub-envs.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from ..config import from_dict
from ..controllers.knowledge import resolve_knowledge
from ..experiments.target_lock import RunConfig
from ..model.camera import project
from ..model.endoscope import advance, handle_for_tip, initial_state, pack_params, simulate
from ..model.kinematics import tip_pose, tip_poses
from ..model.scene import Scene
from .env import MAX_AGE, env_spaces, episode_settings

__all__ = ["TargetLockVectorEnv"]

TICK_WINDOW = 256
"""ticks of the target's path evaluated at once per sub-env."""

SETTLE_SECONDS = 4.0
"""s: the tip is bent to the scene's start angles before t = 0, as :class:`SimulatedRig` does."""

# settings every sub-environment must share, as (name, getter)
_SHARED = (
    ("twin.model_dt", lambda c: c.twin.model_dt), ("loop.rate", lambda c: c.loop.rate),
    ("loop.seconds", lambda c: c.loop.seconds), ("loop.gate", lambda c: c.loop.gate),
    ("controller.max_rate", lambda c: c.controller.max_rate), ("twin.drive", lambda c: c.twin.drive),
    ("twin.camera (other than fps, latency)", lambda c: (c.twin.camera.width, c.twin.camera.height, c.twin.camera.fx,
                                                          c.twin.camera.fy, c.twin.camera.cx, c.twin.camera.cy,
                                                          c.twin.camera.k1, c.twin.camera.k2)),
    ("twin.camera.latency_jitter", lambda c: c.twin.camera.latency_jitter),
    ("twin.endoscope.tip_length", lambda c: c.twin.endoscope.tip_length),
    ("twin.endoscope.n_elements", lambda c: c.twin.endoscope.n_elements),
    ("tracker (other than seed)", lambda c: (c.tracker.noise_px, c.tracker.drop_probability,
                                             c.tracker.outlier_probability, c.tracker.outlier_px)),
    ("vision", lambda c: c.vision),
)


class TargetLockVectorEnv(VectorEnv):
    """``num_envs`` target-lock episodes on the batch kernel; other arguments as
    :class:`~targetlock.gym.env.TargetLockEnv` (``observation="image"`` and ``render_mode`` are not
    supported). See the module doc."""

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}

    def __init__(self, num_envs: int = 1, config: RunConfig | None = None, *, randomize: bool = True,
                 reward: str = "truth", reward_scale_px: float = 100.0, out_of_view_penalty: float = 5.0,
                 observation: str = "ideal", render_mode: str | None = None,
                 autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP) -> None:
        if observation == "image":
            raise ValueError("observation = 'image' (rendered endoscope frames) is not supported by the batch vector "
                             "environment; use gymnasium.make_vec(..., vectorization_mode='sync') for image observations")
        if observation != "ideal":
            raise ValueError(f"observation = {observation!r}; allowed: 'ideal'")
        if render_mode is not None:
            raise ValueError(f"render_mode = {render_mode!r}: the batch vector environment renders nothing; "
                             "allowed: None (use vectorization_mode='sync' for rendered frames)")
        if reward not in ("truth", "observed"):
            raise ValueError(f"reward = {reward!r}; allowed: 'truth', 'observed'")
        if not (isinstance(num_envs, int) and num_envs >= 1):
            raise ValueError(f"num_envs = {num_envs!r}; allowed: an integer >= 1")
        self.num_envs = num_envs
        self.base = config or RunConfig()
        self.randomize, self.reward_kind = randomize, reward
        self.reward_scale, self.penalty = float(reward_scale_px), float(out_of_view_penalty)
        self.autoreset_mode = AutoresetMode(autoreset_mode)
        self.metadata = {**self.metadata, "autoreset_mode": self.autoreset_mode}
        self.render_mode = None
        action_space, self.single_observation_space = env_spaces(self.base)
        self.single_action_space = action_space
        self.action_low, self.action_high = action_space.low, action_space.high   # rad per tick (float32)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.observation_space = batch_space(self.single_observation_space, num_envs)

        b = self.base
        self.dt = b.twin.model_dt
        self.period = 1.0 / b.loop.rate
        self.n_sub = int(round(self.period / self.dt))        # model steps per tick, the same for all
        if abs(self.period / self.dt - self.n_sub) > 1e-6 or self.n_sub < 1:
            raise ValueError(f"loop.rate = {b.loop.rate:g} Hz and twin.model_dt = {self.dt:g} s: the vector environment "
                             "needs a whole number of model steps per tick (1 / (rate · model_dt) an integer)")
        self.n_ticks = int(round(b.loop.seconds * b.loop.rate))
        self.rate_step = b.controller.max_rate * self.period     # rad per tick, the controllers' rate limit
        self.rpt = b.twin.drive.rad_per_tick
        self.lo_ticks, self.hi_ticks = float(b.twin.drive.min_ticks), float(b.twin.drive.max_ticks)
        self.lower, self.upper = b.twin.drive.min_ticks * self.rpt, b.twin.drive.max_ticks * self.rpt
        cam = b.twin.camera
        self.cam = cam
        m = b.loop.gate.margin_px
        self.x_range, self.y_range = (-cam.cx - m, cam.width - cam.cx + m), (-cam.cy - m, cam.height - cam.cy + m)
        self.noisy = bool(b.tracker.noise_px or b.tracker.drop_probability or b.tracker.outlier_probability)

        n = num_envs
        self.cfgs: list[RunConfig | None] = [None] * n
        self._rngs: list[np.random.Generator | None] = [None] * n       # domain randomisation, per sub-env
        self._trackers: list[np.random.Generator | None] = [None] * n   # tracker imperfections, per sub-env
        self.params = np.zeros((n, 14))
        self.state = initial_state(n)
        self.setpoint_rad = np.zeros((n, 2))      # what the drives were sent (rad)
        self.setpoint = np.zeros((n, 2))          # the agent controller's set-point (rad)
        self.latency, self.fps, self.distance = np.zeros(n), np.zeros(n), np.zeros(n)   # s, 1/s, m
        self.stamp_latency = np.zeros(n)          # s
        self.preset, self.path = np.full(n, "", dtype=object), np.full(n, "", dtype=object)
        self.k = np.zeros(n, dtype=np.int64)      # ticks observed
        self.steps = np.zeros(n, dtype=np.int64)  # actions taken this episode
        self.vec = np.zeros((n, 7))               # the observation vector + the time it was made
        self.truth = np.zeros((n, 2))
        self.last = _Arrival(n)
        self._autoreset = np.zeros(n, dtype=bool)
        self._started = False
        self.scenes: dict[int, Scene] = {}           # per sub-env, anchored at its episode's start pose
        # The target's path is evaluated ahead in windows (memory does not grow with the episode):
        # TICK_WINDOW ticks from tick0, and a window of frames from f0 (captured, in flight, to come).
        self.tick0 = np.zeros(n, dtype=np.int64)
        self.target_tick = np.zeros((n, TICK_WINDOW, 3))       # target (world m) at tick times
        self.f0 = np.zeros(n, dtype=np.int64)                  # frame number of the window's first column
        self.next_frame = np.zeros(n, dtype=np.int64)          # next frame to capture
        self.head = np.zeros(n, dtype=np.int64)                # next frame to arrive
        self.frames = self._frame_tables(0)

    # ------------------------------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None):
        """Reset all sub-envs (or ``options["reset_mask"]``'s); ``seed`` s gives sub-env i seed s + i (a
        list: one seed per sub-env). Returns the batched observation and an info dict of arrays."""
        options = dict(options or {})
        mask = options.pop("reset_mask", None)
        if mask is None:
            mask = np.ones(self.num_envs, dtype=bool)
        mask = np.asarray(mask)
        if mask.shape != (self.num_envs,) or mask.dtype != np.bool_ or not mask.any():
            raise ValueError(f"options['reset_mask'] must be a bool array of shape ({self.num_envs},) with a True value")
        if seed is None:
            seeds: list[int | None] = [None] * self.num_envs
        elif isinstance(seed, (int, np.integer)):
            seeds = [int(seed) + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"seed: {len(seeds)} seeds for {self.num_envs} sub-environments")
        if not self._started and not mask.all():
            raise ValueError("options['reset_mask']: the first reset must reset every sub-environment")
        self._reset_envs(np.flatnonzero(mask), seeds, options)
        self._autoreset[mask] = False
        self._started = True
        return self._observation(), self._info()

    def step(self, actions):
        if not self._started:
            raise RuntimeError("step() before reset()")
        a = np.asarray(actions, dtype=float)
        if a.shape != (self.num_envs, 2):
            raise ValueError(f"actions have shape {a.shape}; allowed: ({self.num_envs}, 2) rad")
        rewards = np.zeros(self.num_envs)
        truncated = np.zeros(self.num_envs, dtype=bool)
        done = self._autoreset.copy()
        if done.any():
            if self.autoreset_mode == AutoresetMode.DISABLED:
                raise RuntimeError(f"sub-environments {np.flatnonzero(done).tolist()} ended: reset them first "
                                   "(autoreset_mode = DISABLED)")
            self._reset_envs(np.flatnonzero(done), [None] * self.num_envs, {})   # NEXT_STEP: the action is ignored
        idx = np.flatnonzero(~done)
        if idx.size:
            self._act(idx, a[idx])
            self.steps[idx] += 1
            truncated[idx] = self.steps[idx] >= self.n_ticks
            self._observe(idx)
            rewards[idx] = self._reward(idx)
        info = self._info()
        self._autoreset = truncated.copy()
        if self.autoreset_mode == AutoresetMode.SAME_STEP and truncated.any():
            ended = np.flatnonzero(truncated)
            info["final_obs"] = np.where(truncated[:, None], self._observation(), 0.0).astype(np.float32)
            info["_final_obs"] = truncated.copy()
            info["final_info"] = {k: v for k, v in info.items() if not k.startswith(("final", "_final"))}
            info["_final_info"] = truncated.copy()
            self._reset_envs(ended, [None] * self.num_envs, {})
            self._autoreset[:] = False
            fresh = self._info()
            for key, value in fresh.items():       # the new episodes' infos where they were reset
                if not key.startswith("_"):
                    info[key] = np.where(truncated.reshape((-1,) + (1,) * (value.ndim - 1)), value, info[key])
        return self._observation(), rewards, np.zeros(self.num_envs, dtype=bool), truncated, info

    def close_extras(self, **kwargs: Any) -> None:
        self._started = False

    # ------------------------------------------------------------------------------------------ episodes
    def _reset_envs(self, idx: np.ndarray, seeds: list[int | None], options: dict) -> None:
        """New episodes in sub-envs ``idx``: settings, settled tip, scene, frame schedule, first tick."""
        m = idx.size
        cfgs = []
        for i in idx:
            if seeds[i] is not None or self._rngs[i] is None:
                self._rngs[i], _ = seeding.np_random(seeds[i])
            cfg = from_dict(RunConfig, episode_settings(self.base, self._rngs[i], seeds[i], options, self.randomize))
            for name, get in _SHARED:
                if get(cfg) != get(self.base):
                    raise ValueError(f"{name} = {get(cfg)!r} in an episode's settings; the vector environment needs the "
                                     f"base config's {get(self.base)!r} in every sub-environment")
            self.cfgs[i] = cfg
            self._trackers[i] = np.random.default_rng(cfg.tracker.seed)
            cfgs.append(cfg)
        self.params[idx] = pack_params([c.twin.endoscope for c in cfgs], self.base.twin.drive)
        self.latency[idx] = [c.twin.camera.latency for c in cfgs]
        # Frames are stamped as the twin (a rig) stamps them: arrival minus the latency the controller assumes.
        self.stamp_latency[idx] = [resolve_knowledge(c.knowledge, c.twin).latency for c in cfgs]
        self.preset[idx] = [c.twin.preset for c in cfgs]
        self.path[idx] = [c.twin.scene.path for c in cfgs]
        self.distance[idx] = [c.twin.scene.distance for c in cfgs]
        self.fps[idx] = [c.twin.camera.fps for c in cfgs]

        # settle: the twin's ramp to the start angles, all sub-envs in one kernel call per stage
        state, params = initial_state(m), self.params[idx]
        goal = np.array([[handle_for_tip(c.twin.endoscope, math.radians(a)) for a in c.twin.scene.start_tip_deg]
                         for c in cfgs])
        n_ramp = int(round(0.75 * SETTLE_SECONDS / self.dt))
        for k in range(0, n_ramp, 10):
            advance(state, params, goal * (k + 10) / n_ramp, self.dt, 10)
        advance(state, params, goal, self.dt, int(round(0.25 * SETTLE_SECONDS / self.dt)))
        state[:, 4:6] = 0.0
        self.state[idx] = state
        self.setpoint_rad[idx] = state[:, 0:2]

        # the scene anchored at each start pose, its path evaluated for the first windows
        width = max(64, max(int(math.ceil((lat + 2 * self.period) * fps)) + 16 for lat, fps in zip(self.latency, self.fps)))
        if width > self.frames["time"].shape[1]:     # more frames in flight than before: wider windows
            old, self.frames = self.frames, self._frame_tables(width)
            for key, value in old.items():
                self.frames[key][:, :value.shape[1]] = value
            for i in np.flatnonzero(self.k > 0):    # sub-envs in mid-episode: their windows' new columns
                if i not in idx:
                    self._fill_frames(int(i), int(self.head[i]))
        e = self.base.twin.endoscope
        for j, (i, c) in enumerate(zip(idx, cfgs)):
            start_pose = tip_pose(state[j, 2], state[j, 3], e.tip_length, e.n_elements)
            self.scenes[int(i)] = Scene(c.twin.scene, c.twin.camera, start_pose)
            self._fill_ticks(int(i), 1)
            self.next_frame[i] = self.head[i] = self.f0[i] = 0
            self._fill_frames(int(i), 0)

        # the loop's begin(): the agent engages at the measured motors, then the first tick
        self.setpoint[idx] = np.clip(self._motor(idx), self.lower, self.upper)
        self.k[idx] = 0
        self.steps[idx] = 0
        self.vec[idx] = 0.0
        self.vec[idx, 6] = -1.0
        self._observe(idx)

    def _frame_tables(self, width: int) -> dict[str, np.ndarray]:
        """Per sub-env, ``width`` frames: capture time (s), target (world m), model step, and what the
        tracker saw (offset px, valid, present: not dropped)."""
        n = self.num_envs
        return {"time": np.full((n, width), np.inf), "target": np.zeros((n, width, 3)),
                "step": np.zeros((n, width), dtype=np.int64), "offset": np.full((n, width, 2), np.nan),
                "valid": np.zeros((n, width), dtype=bool), "present": np.zeros((n, width), dtype=bool)}

    def _fill_ticks(self, i: int, k0: int) -> None:
        """Sub-env ``i``'s target at ticks ``k0`` on (the loop's times k · period)."""
        self.tick0[i] = k0
        self.target_tick[i] = self.scenes[i].target_position(np.arange(k0, k0 + TICK_WINDOW) * self.period)

    def _fill_frames(self, i: int, start: int) -> None:
        """Sub-env ``i``'s frame window from frame ``start`` (all before it have arrived): the frames in flight
        keep what the tracker saw; capture times as the twin's (index · (1 / fps)) and the target there."""
        fr, w, shift = self.frames, self.frames["time"].shape[1], start - self.f0[i]
        flying = self.next_frame[i] - start
        for key in ("offset", "valid", "present"):
            fr[key][i, :flying] = fr[key][i, shift:shift + flying].copy()
        t = np.arange(start, start + w) * (1.0 / self.fps[i])
        fr["time"][i] = t
        fr["target"][i] = self.scenes[i].target_position(t)
        fr["step"][i] = np.rint(t / self.dt)
        self.f0[i] = start

    # ------------------------------------------------------------------------------------------ one tick
    def _motor(self, idx: np.ndarray) -> np.ndarray:
        """Measured handle angles (rad): the encoders' whole ticks."""
        return np.rint(self.state[idx, 0:2] / self.rpt) * self.rpt

    def _act(self, idx: np.ndarray, actions: np.ndarray) -> None:
        """The agent controller's set-point and the loop's send, as ``ControlLoop.act`` with ``_Agent``."""
        a = np.clip(actions, self.action_low, self.action_high)
        a = np.where(np.isfinite(a), a, 0.0)                       # a NaN action holds the handle
        sp = self.setpoint[idx]
        command = np.clip(sp + a, self.lower, self.upper)          # the controller's range ...
        new = np.clip(np.clip(command, sp - self.rate_step, sp + self.rate_step), self.lower, self.upper)  # ... and rate
        self.setpoint[idx] = new
        held = np.clip(new / self.rpt, self.lo_ticks, self.hi_ticks)   # clipped before the integer cast
        self.setpoint_rad[idx] = np.clip(np.rint(held), self.lo_ticks, self.hi_ticks) * self.rpt

    def _observe(self, idx: np.ndarray) -> None:
        """The next tick of sub-envs ``idx``: physics, frames captured, frames arrived, observation vector."""
        k = self.k[idx] + 1
        t = k * self.period
        start = self.state[idx]
        state = start.copy()
        traj = simulate(state, self.params[idx], np.broadcast_to(self.setpoint_rad[idx], (self.n_sub, idx.size, 2)),
                        self.dt, 1)                                  # (n_sub, M, 6): one kernel call
        self.state[idx] = state
        steps0 = (k - 1) * self.n_sub
        self._capture(idx, t, steps0, start, traj)
        self._arrive(idx, t)
        self.k[idx] = k
        for i in idx[k - self.tick0[idx] >= TICK_WINDOW]:     # windows used up: the path's next ticks
            self._fill_ticks(int(i), int(self.k[i]))
        self.truth[idx] = self._offsets(self.state[idx, 2:4], self.target_tick[idx, k - self.tick0[idx]])
        self._update_vector(idx, t)

    def _capture(self, idx, t, steps0, start, traj) -> None:
        """Frames captured during this tick: the tip at the nearest model step, the ideal tracker."""
        fr, width = self.frames, self.frames["time"].shape[1]
        while True:
            for i in idx[self.next_frame[idx] - self.f0[idx] >= width]:    # window used up: move it on
                self._fill_frames(int(i), int(self.head[i]))
            f = self.next_frame[idx]
            tf = fr["time"][idx, f - self.f0[idx]]
            cap = tf <= t + 1e-12
            if not cap.any():
                return
            ii, fi = idx[cap], f[cap] - self.f0[idx[cap]]
            j = np.clip(fr["step"][ii, fi] - steps0[cap], 0, self.n_sub)
            cols = np.flatnonzero(cap)
            phis = np.where((j == 0)[:, None], start[cols, 2:4], traj[np.maximum(j - 1, 0), cols, 2:4])
            offset = self._offsets(phis, fr["target"][ii, fi])
            visible = np.all(np.isfinite(offset), axis=1)
            present = np.ones(ii.size, dtype=bool)
            if self.noisy:
                offset, present = self._imperfect(ii, offset, visible)
            fr["offset"][ii, fi] = np.where(visible[:, None], offset, np.nan)
            fr["valid"][ii, fi] = visible
            fr["present"][ii, fi] = present
            self.next_frame[ii] += 1

    def _imperfect(self, ii, offset, visible):
        """The ideal tracker's imperfections, drawn in the twin's order from each sub-env's generator."""
        nz = self.base.tracker
        offset = offset.copy()
        present = np.ones(ii.size, dtype=bool)
        for n, i in enumerate(ii):
            rng = self._trackers[i]
            if nz.drop_probability and rng.random() < nz.drop_probability:
                present[n] = False
                continue
            if visible[n] and nz.noise_px:
                offset[n] = offset[n] + rng.normal(0.0, nz.noise_px, 2)
            if visible[n] and nz.outlier_probability and rng.random() < nz.outlier_probability:
                angle = rng.uniform(0, 2 * np.pi)
                offset[n] = offset[n] + nz.outlier_px * np.array([np.cos(angle), np.sin(angle)])
        return offset, present

    def _arrive(self, idx, t) -> None:
        """Frames whose latency has passed by ``t``, through the loop's plausibility gate; the newest kept."""
        fr = self.frames
        self.last.reset(idx)
        max_age = self.stamp_latency[idx] + self.base.loop.gate.max_extra_age
        while True:
            h = self.head[idx]
            cap_t = fr["time"][idx, h - self.f0[idx]]
            arrived = (h < self.next_frame[idx]) & (cap_t + self.latency[idx] <= t + 1e-9)
            if not arrived.any():
                return
            ii = idx[arrived]
            s = h[arrived] - self.f0[ii]
            off, valid = fr["offset"][ii, s], fr["valid"][ii, s]
            inside = ((off[:, 0] >= self.x_range[0]) & (off[:, 0] <= self.x_range[1])
                      & (off[:, 1] >= self.y_range[0]) & (off[:, 1] <= self.y_range[1]))
            stamp = cap_t[arrived] + self.latency[ii] - self.stamp_latency[ii]
            admit = fr["present"][ii, s] & (t[arrived] - stamp <= max_age[arrived]) & (~valid | inside)
            self.last.take(ii[admit], stamp[admit], off[admit], valid[admit])
            self.head[ii] += 1

    def _offsets(self, phis: np.ndarray, targets: np.ndarray) -> np.ndarray:
        """Where targets (M, 3, world m) appear in the images of tips bent ``phis`` (M, 2 rad): px from the
        image centre, NaN outside the image."""
        e, cam = self.base.twin.endoscope, self.cam
        poses = tip_poses(np.ascontiguousarray(phis), e.tip_length, e.n_elements)
        in_cam = np.einsum("mi,mij->mj", targets - poses[:, :3, 3], poses[:, :3, :3])
        px = project(in_cam, cam)
        inside = (px[:, 0] >= 0.0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0.0) & (px[:, 1] < cam.height)
        return np.where(inside[:, None], px - (cam.cx, cam.cy), np.nan)

    def _update_vector(self, idx, t) -> None:
        """:func:`~targetlock.gym.env.observation_vector` for all of ``idx`` at once."""
        vec = self.vec[idx]
        got = self.last.got[idx]
        off, valid = self.last.offset[idx], self.last.valid[idx]
        ok = got & valid & np.all(np.isfinite(off), axis=1)
        vec[got, 0:2] = np.where(ok[got, None], off[got], 0.0)
        vec[got, 2] = ok[got]
        vec[got, 3] = t[got] - self.last.capture_time[idx][got]
        old = ~got
        vec[old, 3] = np.minimum(vec[old, 3] + np.where(vec[old, 6] >= 0, t[old] - vec[old, 6], 0.0), MAX_AGE)
        vec[:, 4:6] = self._motor(idx)
        vec[:, 6] = t
        self.vec[idx] = vec

    def _reward(self, idx) -> np.ndarray:
        if self.reward_kind == "truth":
            err = np.hypot(self.truth[idx, 0], self.truth[idx, 1])
        else:
            v = self.vec[idx]
            err = np.where(v[:, 2] > 0, np.hypot(v[:, 0], v[:, 1]), np.nan)
        return np.where(np.isfinite(err), -err / self.reward_scale, -self.penalty)

    def _observation(self) -> np.ndarray:
        return self.vec[:, :6].astype(np.float32)

    def _info(self) -> dict[str, Any]:
        """As the single env's info, one array per key (and Gymnasium's ``_key`` masks): the episode's draw,
        the tick's time (s), true offset (px), motors (rad) and the raw observation that arrived this tick
        (``obs_new``; its ``obs_capture_time`` s, ``obs_offset`` px, ``obs_valid``)."""
        info = {"time": self.k * self.period, "preset": self.preset.copy(), "latency": self.latency.copy(),
                "fps": self.fps.copy(), "distance": self.distance.copy(), "path": self.path.copy(),
                "true_offset": self.truth.copy(), "motor": self.vec[:, 4:6].copy(),
                "obs_new": self.last.got.copy(), "obs_capture_time": self.last.capture_time.copy(),
                "obs_offset": self.last.offset.copy(), "obs_valid": self.last.valid.copy()}
        every = np.ones(self.num_envs, dtype=bool)
        info.update({f"_{key}": every for key in list(info)})
        return info


class _Arrival:
    """The newest admitted observation of this tick, per sub-env."""

    def __init__(self, n: int) -> None:
        self.got = np.zeros(n, dtype=bool)
        self.capture_time = np.full(n, np.nan)
        self.offset = np.full((n, 2), np.nan)
        self.valid = np.zeros(n, dtype=bool)

    def reset(self, idx: np.ndarray) -> None:
        self.got[idx] = False
        self.capture_time[idx] = np.nan
        self.offset[idx] = np.nan
        self.valid[idx] = False

    def take(self, idx: np.ndarray, capture_time: np.ndarray, offset: np.ndarray, valid: np.ndarray) -> None:
        self.got[idx] = True
        self.capture_time[idx] = capture_time
        self.offset[idx] = offset
        self.valid[idx] = valid
