"""The target-lock experiment: the closed loop on the twin (or a rig), recorded and scored.

Metrics use the *true* target projection at each control tick (what a person watching the
endoscope would see), never the tracker's estimate: total error sqrt(x² + y²) in px over the period
after ``loop.metrics_after`` seconds while the target is in view.
"""
from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from ..config import param
from ..controllers import ControllerConfig, KnowledgeConfig, make_controller, resolve_knowledge
from ..loop.clock import SimClock, WallClock
from ..loop.runner import ControlLoop, LoopConfig, Tick
from ..model.twin import TwinConfig
from ..rig.simulated import ObservationNoise, SimulatedRig
from .runfolder import RunFolder

__all__ = ["RunConfig", "build_rig", "run_target_lock", "metrics", "plot_run", "COLUMNS"]

COLUMNS = ["t", "err_x", "err_y", "err", "obs_x", "obs_y", "obs_valid", "obs_age", "motor_x_deg", "motor_y_deg",
           "setpoint_x_deg", "setpoint_y_deg", "tip_x_deg", "tip_y_deg", "sig_x", "sig_y"]


@dataclass(frozen=True)
class RunConfig:
    """A complete, reproducible target-lock run."""
    twin: TwinConfig = field(default_factory=TwinConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    knowledge: KnowledgeConfig = field(default_factory=KnowledgeConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    tracker: ObservationNoise = field(default_factory=ObservationNoise)
    vision: bool = param(False, doc="render frames and track them instead of the ideal projection")
    vision_tracker: str = param("feature", choices=("feature", "marker"), doc="tracker used with vision = true")
    realtime: bool = param(False, doc="run on the wall clock instead of as fast as possible")
    seed: int = param(0, lo=0, hi=2**63 - 1, doc="seed of everything random in the run")


def build_rig(cfg: RunConfig, frame_hook=None) -> SimulatedRig:
    return SimulatedRig(cfg.twin, cfg.tracker, frame_hook=frame_hook)


def build_controller(cfg: RunConfig, rig):
    """The configured controller with the rig's drive limits and ``cfg.knowledge`` — the nominal
    assumptions, never the simulated plant's truth unless ``knowledge.source = "oracle"``."""
    drives = rig.drives
    lo, hi = drives.limits
    rpt = drives.rad_per_tick
    return make_controller(cfg.controller, rad_per_tick=rpt, lower=lo * rpt, upper=hi * rpt, control_dt=1.0 / cfg.loop.rate,
                           knowledge=resolve_knowledge(cfg.knowledge, cfg.twin), model_dt=cfg.twin.model_dt)


class _Recorder:
    """Collects one row per tick, streaming to the run folder's CSV as it goes."""

    def __init__(self, rig, controller, writer=None) -> None:
        self.rig, self.ctrl, self.writer = rig, controller, writer
        self.rows: list[list[float]] = []
        self.last_obs = None
        self.lateness: list[float] = []
        self.internal: list[float] = []

    def __call__(self, tick: Tick) -> None:
        rig = self.rig
        truth = rig.truth_offset(tick.time)
        self.lateness.append(tick.lateness)
        if tick.observation is not None:
            self.last_obs = tick.observation
            if math.isfinite(tick.observation.arrival_time):
                self.internal.append(tick.sent - tick.observation.arrival_time)
        o = self.last_obs
        ox, oy = (o.offset[0], o.offset[1]) if o is not None else (math.nan, math.nan)
        sig = list(self.ctrl.signals().values()) + [math.nan, math.nan]
        tip = rig.tip_angles()
        row = [tick.time, truth[0], truth[1], math.hypot(truth[0], truth[1]), ox, oy,
               float(o.valid) if o is not None else 0.0, tick.time - o.capture_time if o is not None else math.nan,
               math.degrees(tick.motor[0]), math.degrees(tick.motor[1]),
               math.degrees(tick.setpoint[0]), math.degrees(tick.setpoint[1]),
               math.degrees(tip[0]), math.degrees(tip[1]), sig[0], sig[1]]
        self.rows.append(row)
        if self.writer is not None:
            self.writer.write(row)


def metrics(data: np.ndarray, frame_log: list[tuple[float, bool]], after: float) -> dict:
    """Error figures (px) from recorded rows (COLUMNS) after ``after`` s, and the lost fraction."""
    t = data[:, 0]
    err = data[:, 3]
    sel = t >= after
    tracked = sel & np.isfinite(err)
    e = err[tracked]
    frames = [v for (tf, v) in frame_log if tf >= after]
    out = {
        "rms_px": float(np.sqrt(np.mean(e ** 2))) if e.size else math.nan,
        "peak_px": float(np.max(e)) if e.size else math.nan,
        "p95_px": float(np.percentile(e, 95)) if e.size else math.nan,
        "mean_px": float(np.mean(e)) if e.size else math.nan,
        "out_of_view_fraction": float(1.0 - tracked.sum() / max(sel.sum(), 1)),
        "lost_fraction": float(1.0 - sum(frames) / len(frames)) if frames else math.nan,
        "frames": len(frames),
    }
    for k, name in ((1, "x"), (2, "y")):
        ex = data[tracked, k]
        out[f"rms_{name}_px"] = float(np.sqrt(np.mean(ex ** 2))) if ex.size else math.nan
        out[f"peak_{name}_px"] = float(np.max(np.abs(ex))) if ex.size else math.nan
    out["tip_range_deg"] = [float(np.min(data[sel, 12])), float(np.max(data[sel, 12]))] if sel.any() else []
    return out


def run_target_lock(cfg: RunConfig, run: RunFolder | None = None, *, progress: bool = False,
                    frame_hook=None, rig=None, video=None) -> dict:
    """Run the closed loop as configured; returns the summary (and fills ``run`` if given).

    ``rig``: a rig to run on instead of the in-process twin (e.g. a :class:`HardwareRig`); it
    then runs on the wall clock and must offer ``truth_offset``, ``tip_angles`` and ``frame_log``."""
    hardware = rig is not None
    vision = None
    if cfg.vision and frame_hook is None and not hardware:
        from ..vision.pipeline import VisionPipeline
        vision = frame_hook = VisionPipeline(cfg.twin, tracker=cfg.vision_tracker, seed=cfg.seed, video=video)
    rig = rig if hardware else build_rig(cfg, frame_hook)
    ctrl = build_controller(cfg, rig)
    realtime = cfg.realtime or hardware
    loop = ControlLoop(rig, ctrl, rate=cfg.loop.rate, clock=WallClock() if realtime else SimClock())
    writer = run.timeseries(COLUMNS) if run is not None else None
    rec = _Recorder(rig, ctrl, writer)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=int(round(cfg.loop.seconds)), unit="sim s", file=sys.stderr, leave=False, disable=None)

    def on_tick(tick: Tick) -> None:
        rec(tick)
        if bar is not None and tick.index % int(cfg.loop.rate) == 0:
            bar.update(1)

    t0 = time.perf_counter()
    try:
        loop.run(cfg.loop.seconds, on_tick)
    finally:
        wall = time.perf_counter() - t0
        if writer is not None:
            writer.close()
        if bar is not None:
            bar.close()
        if vision is not None:
            vision.close()
    data = np.asarray(rec.rows, dtype=float)
    summary = metrics(data, rig.frame_log, cfg.loop.metrics_after)
    summary.update({"rig": "hardware" if hardware else "twin", "controller": cfg.controller.kind, "path": cfg.twin.scene.path, "latency_s": cfg.twin.camera.latency,
                    "fps": cfg.twin.camera.fps, "preset": cfg.twin.preset,
                    "knowledge": ctrl.knowledge.label, "target_losses": ctrl.losses, "sim_seconds": cfg.loop.seconds,
                    "wall_seconds": wall, "realtime_factor": cfg.loop.seconds / wall if wall > 0 else math.inf})
    if vision is not None:
        summary["vision"] = vision.stats()
    if realtime:
        late, internal = np.array(rec.lateness) * 1e3, np.array(rec.internal) * 1e3
        summary["timing_ms"] = {
            "period_jitter_p50": float(np.percentile(late, 50)), "period_jitter_p99": float(np.percentile(late, 99)),
            "period_jitter_max": float(late.max()),
            "frame_to_setpoint_p50": float(np.percentile(internal, 50)) if internal.size else math.nan,
            "frame_to_setpoint_p99": float(np.percentile(internal, 99)) if internal.size else math.nan}
    summary["_data"] = data
    if run is not None:
        plot_run(data, cfg, run.file("tracking.png"))
        summary["run_folder"] = str(run.path)
        run.write_summary({k: v for k, v in summary.items() if not k.startswith("_")})
    return summary


def plot_run(data: np.ndarray, cfg: RunConfig, path) -> None:
    """Tracking error (x, y, total), motor angles and the controller's signal over time."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = data[:, 0]
    has_sig = np.isfinite(data[:, 14]).any()
    fig, axes = plt.subplots(3 if has_sig else 2, 1, figsize=(9, 8 if has_sig else 6), sharex=True, dpi=110)
    ax = axes[0]
    ax.plot(t, data[:, 1], lw=0.9, label="x")
    ax.plot(t, data[:, 2], lw=0.9, label="y")
    ax.plot(t, data[:, 3], lw=1.3, color="k", label="total")
    ax.axvspan(0, cfg.loop.metrics_after, color="0.92")
    ax.set_ylabel("tracking error (px)")
    ax.set_title(f"{cfg.controller.kind} on the {cfg.twin.scene.path} path, latency {cfg.twin.camera.latency:g} s, "
                 f"{cfg.twin.camera.fps:g} fps" + (", vision" if cfg.vision else ""))
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(alpha=0.3)
    ax = axes[1]
    ax.plot(t, data[:, 8], lw=0.9, label="motor x")
    ax.plot(t, data[:, 9], lw=0.9, label="motor y")
    ax.plot(t, data[:, 12], lw=0.9, ls="--", label="tip x")
    ax.plot(t, data[:, 13], lw=0.9, ls="--", label="tip y")
    ax.set_ylabel("angle (deg)")
    ax.legend(loc="upper right", fontsize=8, ncol=2)
    ax.grid(alpha=0.3)
    if has_sig:
        ax = axes[2]
        label = {"ik": "IK goal", "adaptive": "estimated |J| (px/rad)"}.get(cfg.controller.kind, "compensation")
        ax.plot(t, data[:, 14], lw=0.9, label=f"{label} x")
        ax.plot(t, data[:, 15], lw=0.9, label=f"{label} y")
        ax.set_ylabel("px/rad" if cfg.controller.kind == "adaptive" else "deg")
        ax.legend(loc="upper right", fontsize=8)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
