"""Benchmarks (``targetlock bench NAME``): performance goals are measured here, not in timed tests."""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from .model.endoscope import EndoscopeParams, initial_state, pack_params, simulate
from .model.twin import TwinConfig

__all__ = ["bench_model", "bench_loop", "bench_frame_to_setpoint", "bench_vision", "bench_gym"]


def _randomised(base: EndoscopeParams, rng: np.random.Generator, n: int) -> list[EndoscopeParams]:
    """Endoscopes with parameters spread +-30 % (slack -0.5..1.5 mm) around ``base``."""
    out = []
    for _ in range(n):
        f = lambda: float(rng.uniform(0.7, 1.3))  # noqa: E731
        out.append(dataclasses.replace(
            base, cable_stiffness=base.cable_stiffness * f(), tip_stiffness=base.tip_stiffness * f(),
            mu_n=base.mu_n * f(), mu_f=base.mu_f * f(), friction_offset=base.friction_offset * f(),
            cable_slack=float(rng.uniform(-0.0005, 0.0015))))
    return out


def bench_model(seconds: float = 200.0, batch_size: int = 1000, batch_seconds_sim: float = 20.0, seed: int = 0) -> dict:
    """Real-time factor of one endoscope at the internal step, and a randomised batch on one core."""
    twin = TwinConfig()
    dt = twin.model_dt
    p1 = pack_params(twin.endoscope, twin.drive)

    def sweep(t: np.ndarray) -> np.ndarray:
        sp = np.zeros((t.size, 1, 2))
        sp[:, 0, 0] = math.radians(110) * np.sin(2 * np.pi * t / 20.0) * np.minimum(t / 20.0, 1.0)
        sp[:, 0, 1] = math.radians(60) * np.sin(2 * np.pi * t / 13.0)
        return sp

    simulate(initial_state(1), p1, sweep(np.arange(0, 1.0, dt)), dt)  # compile / load cache
    t = np.arange(0.0, seconds, dt)
    sp = sweep(t)
    t0 = time.perf_counter()
    simulate(initial_state(1), p1, sp, dt)
    wall_single = time.perf_counter() - t0

    rng = np.random.default_rng(seed)
    pb = pack_params(_randomised(twin.endoscope, rng, batch_size), twin.drive)
    record_dt = 0.01
    substeps = int(round(record_dt / dt))
    tb = np.arange(0.0, batch_seconds_sim, record_dt)
    spb = np.repeat(sweep(tb), batch_size, axis=1) * rng.uniform(0.5, 1.0, size=(1, batch_size, 1))
    t0 = time.perf_counter()
    out = simulate(initial_state(batch_size), pb, spb, dt, substeps)
    wall_batch = time.perf_counter() - t0
    return {
        "realtime_factor": seconds / wall_single,
        "single_sim_seconds": seconds,
        "single_wall_seconds": wall_single,
        "model_dt": dt,
        "batch_size": batch_size,
        "batch_sim_seconds": batch_seconds_sim,
        "batch_seconds": wall_batch,
        "batch_finite": bool(np.all(np.isfinite(out))),
        "threads": 1,
    }


def bench_loop(seconds: float = 40.0, repeats: int = 3) -> dict:
    """Closed loop (PI + compensation, ideal tracker, linear path) real-time factor on one core, and
    the mean time of one ``ik`` and one ``adaptive`` controller step that processes a new observation
    (adaptive: estimators and its online endoscope model)."""
    from .controllers import ControllerConfig
    from .experiments.target_lock import RunConfig, build_controller, build_rig, run_target_lock
    from .loop.runner import LoopConfig
    from .rig.base import Observation

    cfg = RunConfig(controller=ControllerConfig(kind="pi-hc"), loop=LoopConfig(seconds=seconds))
    run_target_lock(dataclasses.replace(cfg, loop=LoopConfig(seconds=1.0)))  # compile / warm caches
    walls = []
    for _ in range(repeats):
        walls.append(run_target_lock(cfg)["wall_seconds"])
    wall = min(walls)

    def step_ms(kind: str, n: int = 2000) -> float:
        """Mean time (ms) of one controller step that processes a new observation."""
        kind_cfg = dataclasses.replace(cfg, controller=ControllerConfig(kind=kind))
        ctrl = build_controller(kind_cfg, build_rig(kind_cfg))
        motor = np.array([-0.2, 0.05])
        ctrl.reset(motor, 0.0)
        rng = np.random.default_rng(0)
        obs = [Observation(capture_time=0.02 * k, offset=rng.uniform(-150, 150, 2), valid=True) for k in range(n + 50)]
        for k in range(50):
            ctrl.step(obs[k], motor, 0.02 * (k + 1))
        t0 = time.perf_counter()
        for k in range(50, 50 + n):
            ctrl.step(obs[k], motor, 0.02 * (k + 1))
        return (time.perf_counter() - t0) / n * 1e3

    n = 2000
    ik_ms = step_ms("ik", n)
    adaptive_ms = step_ms("adaptive", n)
    return {"realtime_factor": seconds / wall, "sim_seconds": seconds, "wall_seconds": wall,
            "controller": "pi-hc", "ik_step_ms": ik_ms, "adaptive_step_ms": adaptive_ms, "ik_steps": n, **bench_frame_to_setpoint()}


def bench_frame_to_setpoint(seconds: float = 10.0, fps: float = 24.3, rate: float = 50.0) -> dict:
    """Frame arrival -> set-point sent (ms) on the wall-clock loop with a live source: a thread
    delivers observations at ``fps`` (not locked to the loop's ``rate``, so arrivals fall at every
    phase of the period), the twin's drives take the set-points; PI controller. Measured with the
    loop's early ticks on (the default) and off (a frame waits for the next tick)."""
    import threading

    from .controllers import ControllerConfig
    from .experiments.target_lock import RunConfig, build_controller, build_rig
    from .loop.clock import WallClock
    from .loop.runner import ControlLoop
    from .rig.base import HandoffSource, Observation, Rig

    class PacedSource(HandoffSource):
        def __init__(self) -> None:
            super().__init__()
            self.t0 = time.monotonic()
            self.stop = threading.Event()
            self.thread = threading.Thread(target=self._run, daemon=True)

        def start(self) -> None:
            """Frames from loop time zero on (all arrival times on the loop's clock)."""
            self.t0 = time.monotonic()
            self.thread.start()

        def _run(self) -> None:
            k, w0 = 0, time.monotonic()
            while not self.stop.wait(max(0.0, w0 + k / fps - time.monotonic())):
                now = time.monotonic() - self.t0
                self.deliver(Observation(capture_time=now - 0.1, offset=np.array([5.0, -3.0]), valid=True,
                                         frame_index=k, arrival_time=now))
                k += 1

        def close(self) -> None:
            self.stop.set()
            if self.thread.is_alive():
                self.thread.join()

    class LiveRig(Rig):
        def __init__(self, sim) -> None:
            self.sim, self.drives, self.camera = sim, sim.drives, sim.camera
            self.observations: PacedSource = PacedSource()

        def start_clock(self) -> None:
            self.observations.start()

        def advance(self, until: float) -> None:
            self.sim.advance(until)
            self.sim.observations.poll(until)   # the twin's own frames are not used here

    out = {}
    cfg = RunConfig(controller=ControllerConfig(kind="pi"))
    for label, early in (("", True), ("_tick_only", False)):
        with LiveRig(build_rig(cfg)) as rig:
            ms: list[float] = []
            loop = ControlLoop(rig, build_controller(cfg, rig), rate=rate, clock=WallClock(), step_on_arrival=early)
            def note(tk) -> None:
                if tk.observation is not None:
                    ms.append(1e3 * (tk.sent - tk.observation.arrival_time))
            try:
                loop.run(seconds, note)
            finally:
                rig.observations.close()
        out[f"frame_to_setpoint_p50_ms{label}"] = float(np.percentile(ms, 50))
        out[f"frame_to_setpoint_p99_ms{label}"] = float(np.percentile(ms, 99))
    out["frame_to_setpoint_frames"] = len(ms)
    return out


def bench_vision(seconds: float = 20.0, seed: int = 0, repeats: int = 3) -> dict:
    """Renderer ms per frame, tracker fps (evaluation sequences, one core) and the closed loop with
    vision (render + track every frame, PI + compensation, linear path) as a real-time factor: the
    median of ``repeats`` runs (a shared machine's load moves one run's figure by 10-15 %), with
    every run's in ``loop_realtime_factors``."""
    import cv2

    from .controllers import ControllerConfig
    from .experiments.target_lock import RunConfig, run_target_lock
    from .loop.runner import LoopConfig
    from .vision.evaluate import EvalSettings, evaluate

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        # The procedural mucosa only: the speed of our tracker, not of the reference trackers.
        ev = evaluate(EvalSettings(sequences=("slow", "fast", "tip", "specular"), photos=(), references=()), seed=seed)
        # PI + compensation, as this figure has always been measured (the run default is adaptive,
        # whose estimators and online model add ~0.5 ms per frame).
        cfg = RunConfig(controller=ControllerConfig(kind="pi-hc"), loop=LoopConfig(seconds=seconds), vision=True, seed=seed)
        run_target_lock(dataclasses.replace(cfg, loop=LoopConfig(seconds=1.0)))  # warm caches
        runs = sorted((run_target_lock(cfg) for _ in range(max(1, repeats))), key=lambda r: r["realtime_factor"])
    finally:
        cv2.setNumThreads(threads)
    s = runs[len(runs) // 2]   # the median run (the same frames every time: only the timing differs)
    return {"render_ms": s["vision"]["render_ms"], "track_ms": s["vision"]["track_ms"],
            "tracker_fps": ev["overall"]["fps"], "eval_median_px": ev["overall"]["median_px"],
            "loop_realtime_factor": s["realtime_factor"],
            "loop_realtime_factors": [r["realtime_factor"] for r in runs], "loop_sim_seconds": seconds,
            "loop_rms_px": s["rms_px"], "loop_tracker_median_px": s["vision"]["tracker_median_px"], "threads": 1}


def bench_gym(sizes: tuple[int, ...] = (1, 16, 256), env_steps: int = 4000, seed: int = 0) -> dict:
    """Steps per second of the Gymnasium environments (randomised episodes, ideal tracker, random
    actions within the rate limit): the single env, Gymnasium's SyncVectorEnv of N single envs and the
    batch vector env for each N in ``sizes`` (env-steps/s = N x vector steps/s; about ``env_steps``
    env-steps each, at least 40 vector steps, all within one episode). Resets are timed apart (``*_reset_s``: one reset of all N);
    ``batch_*_episode_env_steps_per_s`` is derived for whole episodes of ``loop.seconds`` including
    their reset. One core."""
    import gymnasium

    from .experiments.target_lock import RunConfig
    from .gym import ENV_ID

    def timed(env, n: int, steps: int) -> tuple[float, float]:
        t0 = time.perf_counter()
        env.reset(seed=seed)
        reset = time.perf_counter() - t0
        space = env.action_space
        space.seed(seed)
        actions = [space.sample() for _ in range(steps + 10)]
        for a in actions[:10]:                 # warm caches
            env.step(a)
        t0 = time.perf_counter()
        for a in actions[10:]:
            env.step(a)
        return steps / (time.perf_counter() - t0), reset

    single = gymnasium.make(ENV_ID)
    loop = RunConfig().loop                          # the environments' default base config
    ticks = int(round(loop.seconds * loop.rate))    # steps per episode; timed steps stay within one
    rate, reset = timed(single, 1, min(env_steps, ticks - 10))
    out: dict = {"single_steps_per_s": rate, "single_reset_s": reset, "sizes": list(sizes), "threads": 1}
    for n in sizes:
        steps = min(max(40, env_steps // n), ticks - 10)
        for label, mode in (("sync", "sync"), ("batch", "vector_entry_point")):
            envs = gymnasium.make_vec(ENV_ID, num_envs=n, vectorization_mode=mode)
            rate, reset = timed(envs, n, steps)
            envs.close()
            out[f"{label}_{n}_steps_per_s"] = rate
            out[f"{label}_{n}_env_steps_per_s"] = n * rate
            out[f"{label}_{n}_reset_s"] = reset
        out[f"batch_{n}_episode_env_steps_per_s"] = n * ticks / (ticks / out[f"batch_{n}_steps_per_s"]
                                                                 + out[f"batch_{n}_reset_s"])
    return out
