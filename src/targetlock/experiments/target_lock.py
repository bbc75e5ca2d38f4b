"""The target-lock experiment: the closed loop on the twin (or a rig), recorded and scored.

Metrics use the *true* target projection at each control tick (what a person watching the
endoscope would see), never the tracker's estimate: total error sqrt(x² + y²) in px over the period
after ``loop.metrics_after`` seconds while the target is in view.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config import commented_toml, param, to_dict
from ..controllers import Controller, ControllerConfig, KnowledgeConfig, make_controller, resolve_knowledge
from ..loop.clock import SimClock, WallClock
from ..loop.gate import ObservationGate
from ..loop.runner import ControlLoop, LoopConfig, Tick
from ..loop.signals import StopSignal, stop_on_signals
from ..loop.stats import RunningStats
from ..model.endoscope import EndoscopeParams
from ..model.twin import TwinConfig
from ..rig.base import FrameLog
from ..recording import RunMcap
from ..rig.simulated import ObservationNoise, SimulatedRig
from ..vision.tracker import TrackerSettings
from .runfolder import RunFolder

__all__ = ["RunConfig", "build_rig", "run_target_lock", "run_engagements", "plot_run", "COLUMNS"]

log = logging.getLogger(__name__)

IDENTIFIED_SCOPE_FILE = "identified_scope.toml"
"""The run folder's file with the endoscope an identifying controller (``adaptive``) found."""
IDENTIFIED_WHILE_RUNNING = "identified by the running lock"
"""The knowledge label's endoscope source when the console's tuning carries the lock's scope over."""

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
    feature_tracker: TrackerSettings = field(default_factory=TrackerSettings)  # the feature tracker's settings
    realtime: bool = param(False, doc="run on the wall clock instead of as fast as possible")
    seed: int = param(0, lo=0, hi=2**63 - 1, doc="seed of everything random in the run")


def build_rig(cfg: RunConfig, frame_hook=None) -> SimulatedRig:
    """The twin, stamping frames as a real rig would: arrival time minus the latency the lab knows
    (``cfg.knowledge``; the true latency only with ``knowledge.source = "oracle"``)."""
    return SimulatedRig(cfg.twin, cfg.tracker, frame_hook=frame_hook,
                        stamp_latency=resolve_knowledge(cfg.knowledge, cfg.twin).latency)


def build_controller(cfg: RunConfig, rig, *, identified: EndoscopeParams | None = None):
    """The configured controller with the rig's drive limits and ``cfg.knowledge`` — the nominal
    assumptions, never the simulated plant's truth unless ``knowledge.source = "oracle"``. ``identified``:
    an endoscope a running lock found (:meth:`Controller.learned_endoscope`), assumed instead of the
    knowledge's (the console's tuning replaces the controller on the same scope)."""
    drives = rig.drives
    lo, hi = drives.limits
    rpt = drives.rad_per_tick
    knowledge = resolve_knowledge(cfg.knowledge, cfg.twin)
    if identified is not None and identified != knowledge.endoscope:
        knowledge = dataclasses.replace(knowledge, endoscope=identified, endoscope_from=IDENTIFIED_WHILE_RUNNING)
    return make_controller(cfg.controller, rad_per_tick=rpt, lower=lo * rpt, upper=hi * rpt, control_dt=1.0 / cfg.loop.rate,
                           knowledge=knowledge, model_dt=cfg.twin.model_dt)


class _Thinned:
    """At most ``2 * points`` rows for plots, evenly spaced in time: when full, every other row is
    dropped and only every ``stride``-th new row kept, so memory does not grow with the run."""

    def __init__(self, columns: int, points: int = 10000) -> None:
        self.buf = np.empty((2 * points, columns))
        self.n = 0
        self.stride = 1
        self._seen = 0

    def add(self, row: list[float]) -> None:
        if self._seen % self.stride == 0:
            if self.n == self.buf.shape[0]:
                half = self.buf[0:self.n:2].copy()
                self.n = half.shape[0]
                self.buf[:self.n] = half
                self.stride *= 2
            if self._seen % self.stride == 0:
                self.buf[self.n] = row
                self.n += 1
        self._seen += 1

    def rows(self) -> np.ndarray:
        return self.buf[:self.n].copy()


class RunRecorder:
    """One row per tick (COLUMNS), streamed to the run folder's CSV; the summary's figures are
    accumulated as the run goes (:class:`~targetlock.loop.stats.RunningStats`), so memory does not grow
    with the run's length. All rows are kept in memory only with ``keep_rows``; otherwise a thinned
    copy is kept for the plot.

    Error figures use the true target offset at ticks after ``after`` (s) while the target is in view;
    quantiles to 0.01 px (errors) and 0.01 ms (timing)."""

    def __init__(self, rig, controller, *, after: float, writer=None, keep_rows: bool = False,
                 scene: RunMcap | None = None) -> None:
        self.rig, self.ctrl, self.writer, self.after = rig, controller, writer, after
        self.scene = scene            # run.mcap: poses of each row, target lost/back
        self._valid: bool | None = None
        self.rows: list[list[float]] | None = [] if keep_rows else None
        self.thinned = None if keep_rows else _Thinned(len(COLUMNS))
        self.last_obs = None
        cam = rig.camera
        self.err = RunningStats(hist_hi=math.hypot(cam.width, cam.height), resolution=0.01)
        self.err_x, self.err_y = RunningStats(), RunningStats()   # of |error| per axis (px)
        self.tip_x = RunningStats()                                # deg; a motion-capture gap is NaN
        self.ticks_after = 0
        self.lateness = RunningStats(hist_hi=1.0, resolution=1e-5)   # s
        self.skipped = 0                  # slots a starved wall-clock loop skipped
        self.internal = RunningStats(hist_hi=1.0, resolution=1e-5)   # s, frame arrival -> set-point sent
        self.n_rows = 0

    def __call__(self, tick: Tick) -> None:
        rig = self.rig
        truth = rig.truth_offset(tick.time)
        self.lateness.add(tick.lateness)
        self.skipped += tick.skipped
        if tick.observation is not None:
            self.last_obs = tick.observation
            self.internal.add(tick.sent - tick.observation.arrival_time)
        o = self.last_obs
        ox, oy = (o.offset[0], o.offset[1]) if o is not None else (math.nan, math.nan)
        sig = list(self.ctrl.signals().values()) + [math.nan, math.nan]
        tip = rig.tip_angles()
        err = math.hypot(truth[0], truth[1])
        row = [tick.time, truth[0], truth[1], err, ox, oy,
               float(o.valid) if o is not None else 0.0, tick.time - o.capture_time if o is not None else math.nan,
               math.degrees(tick.motor[0]), math.degrees(tick.motor[1]),
               math.degrees(tick.setpoint[0]), math.degrees(tick.setpoint[1]),
               math.degrees(tip[0]), math.degrees(tip[1]), sig[0], sig[1]]
        if tick.time >= self.after:
            self.ticks_after += 1
            self.tip_x.add(row[12])
            if math.isfinite(err):
                self.err.add(err)
                self.err_x.add(abs(row[1]))
                self.err_y.add(abs(row[2]))
        self.n_rows += 1
        if self.rows is not None:
            self.rows.append(row)
        else:
            self.thinned.add(row)
        if self.writer is not None:
            self.writer.write(row)
        if self.scene is not None:
            self.scene.tick(tick.time, row)
            if o is not None and o.valid != self._valid:
                if self._valid is not None:
                    self.scene.log.log(tick.time, "info" if o.valid else "warning",
                                       "target back" if o.valid else "target lost")
                self._valid = o.valid

    def data(self) -> np.ndarray:
        """All rows (``keep_rows``) or the thinned ones, as an array (COLUMNS)."""
        if self.rows is not None:
            return np.asarray(self.rows, dtype=float).reshape(-1, len(COLUMNS))
        return self.thinned.rows()

    def summary(self, frames: FrameLog) -> dict:
        """Error figures (px) after ``after``, the lost fractions and the tip's range (deg)."""
        e = self.err
        out = {
            "rms_px": e.rms, "peak_px": e.max if e.count else math.nan, "p95_px": e.quantile(0.95),
            "mean_px": e.mean,
            "out_of_view_fraction": 1.0 - e.count / max(self.ticks_after, 1),
            "lost_fraction": frames.lost_fraction, "frames": frames.frames,
        }
        for s, name in ((self.err_x, "x"), (self.err_y, "y")):
            out[f"rms_{name}_px"] = s.rms
            out[f"peak_{name}_px"] = s.max if s.count else math.nan
        out["tip_range_deg"] = self.tip_x.range()
        return out

    def timing_ms(self) -> dict:
        late, internal = self.lateness, self.internal
        return {"period_jitter_p50": 1e3 * late.quantile(0.5), "period_jitter_p99": 1e3 * late.quantile(0.99),
                "period_jitter_max": 1e3 * late.max if late.count else math.nan,
                "frame_to_setpoint_p50": 1e3 * internal.quantile(0.5),
                "frame_to_setpoint_p99": 1e3 * internal.quantile(0.99)}


def run_target_lock(cfg: RunConfig, run: RunFolder | None = None, *, progress: bool = False,
                    frame_hook=None, rig=None, video=None, keep_rows: bool | None = None,
                    controller: Controller | None = None) -> dict:
    """Run the closed loop as configured; returns the summary (and fills ``run`` if given).

    ``controller``: the controller to engage instead of building one from ``cfg`` (it must have been
    built for the same rig's limits, e.g. by :func:`build_controller`). The loop resets it when it starts,
    as an engagement after a release: what it keeps across engagements (``adaptive``: the candidate scope
    and the video delay it found) it keeps here (:func:`run_engagements`).

    ``rig``: a rig to run on instead of the in-process twin (e.g. a :class:`HardwareRig`); it then
    runs on the wall clock. ``keep_rows`` (default: without a run folder) returns every row as
    ``summary["_data"]`` (COLUMNS); with a run folder the rows are only streamed to its CSV, so
    memory stays the same however long the run.

    SIGTERM, SIGHUP and Ctrl-C (see :mod:`targetlock.loop.signals`) stop the run like an error: the
    drives are disabled, the CSV flushed, and the summary of what was recorded written with
    ``"stopped"`` naming the signal, before :class:`~targetlock.loop.signals.StopSignal` is re-raised."""
    with stop_on_signals():
        return _run_target_lock(cfg, run, progress=progress, frame_hook=frame_hook, rig=rig, video=video,
                                keep_rows=run is None if keep_rows is None else keep_rows, controller=controller)


def run_engagements(cfg: RunConfig, n: int) -> list[dict]:
    """``n`` runs of ``cfg`` (each on a fresh twin: the same scope, latency, target path and seed) engaging
    one and the same controller, as the lock is engaged again and again in a procedure on one scope
    (the console's engage after a release). Returns the summaries, first engagement first; rows are kept
    (``summary["_data"]``). The first run is exactly ``run_target_lock(cfg)``'s."""
    if not 1 <= n <= 10:
        raise ValueError(f"run_engagements: n = {n}; allowed: 1 to 10")
    ctrl = build_controller(cfg, build_rig(cfg))
    return [run_target_lock(cfg, controller=ctrl) for _ in range(n)]


def _run_target_lock(cfg: RunConfig, run: RunFolder | None, *, progress: bool, frame_hook, rig, video,
                     keep_rows: bool, controller: Controller | None) -> dict:
    hardware = rig is not None
    vision = None
    if cfg.vision and frame_hook is None and not hardware:
        from ..vision.pipeline import VisionPipeline
        # Partial frames where only the tracker reads them: the pipeline renders whole frames while a
        # video or the run folder's MCAP (its on_frame) takes them.
        vision = frame_hook = VisionPipeline(cfg.twin, tracker=cfg.vision_tracker, seed=cfg.seed, video=video,
                                             regions=True, tracker_settings=cfg.feature_tracker)
    rig = rig if hardware else build_rig(cfg, frame_hook)
    ctrl = build_controller(cfg, rig) if controller is None else controller
    realtime = cfg.realtime or hardware
    gate = ObservationGate.for_camera(cfg.loop.gate, rig.camera)
    loop = ControlLoop(rig, ctrl, rate=cfg.loop.rate, clock=WallClock() if realtime else SimClock(), gate=gate,
                       step_on_arrival=cfg.loop.step_on_arrival)
    rig.frame_log.since = cfg.loop.metrics_after
    writer = run.timeseries(COLUMNS) if run is not None else None
    scene = None
    if run is not None:
        e = cfg.twin.endoscope
        scene = RunMcap(run.mcap, COLUMNS, tip_length=e.tip_length, n_elements=e.n_elements, camera=rig.camera,
                        target_pose=None if hardware else rig.scene.target_pose)
    rec = RunRecorder(rig, ctrl, after=cfg.loop.metrics_after, writer=writer, keep_rows=keep_rows, scene=scene)
    if vision is not None and scene is not None:
        def frame_to_mcap(t: float, image, result) -> None:
            state = "tracked" if result.valid else ("lost" if result.lost else "missed")
            scene.frame(t, image, target_px=result.position_px if result.valid else None,
                        label=f"{state}, confidence {result.confidence:.2f}")
        vision.on_frame = frame_to_mcap
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=int(round(cfg.loop.seconds)), unit="sim s", file=sys.stderr, leave=False, disable=None)

    def on_tick(tick: Tick) -> None:
        rec(tick)
        if bar is not None and tick.index % int(cfg.loop.rate) == 0:
            bar.update(1)

    stopped: BaseException | None = None
    t0 = time.perf_counter()
    try:
        loop.run(cfg.loop.seconds, on_tick)
    except BaseException as exc:  # noqa: BLE001 - the loop has disabled the drives; finish the record, re-raise
        stopped = exc
    finally:
        wall = time.perf_counter() - t0
        if writer is not None:
            writer.close()
        if bar is not None:
            bar.close()
        if vision is not None:
            vision.close()
    try:
        summary = _finish(cfg, rec, rig, gate, run, wall=wall, hardware=hardware, realtime=realtime, vision=vision,
                          keep_rows=keep_rows, stopped=stopped)
    except Exception:
        if stopped is None:
            raise
        log.exception("writing the summary of the stopped run failed")
        raise stopped from None
    if stopped is not None:
        raise stopped
    return summary


def save_identified_scope(run: RunFolder, ctrl: Controller, summary: dict) -> None:
    """If ``ctrl`` identified an endoscope, write it (what it steered with at the end of the run) into the
    run folder as ``identified_scope.toml``, a ``[knowledge.endoscope]`` table for the next run's
    ``knowledge.endoscope_file``, and name the file in ``summary`` (relative to the folder: a re-run's
    summary stays the same). ``targetlock run`` and the console's recordings both do."""
    endoscope = ctrl.learned_endoscope()
    if endoscope is None:
        return
    same = "the same as the assumed one" if endoscope == ctrl.knowledge.endoscope else \
        "found by the lock, unlike the assumed one"
    note = (f"The endoscope the lock steered with at the end of this run ({same}).\n"
            "Use it next time: --set knowledge.endoscope_file='\"PATH_OF_THIS_FILE\"'")
    run.file(IDENTIFIED_SCOPE_FILE).write_text(commented_toml({"knowledge": {"endoscope": to_dict(endoscope)}}, note))
    summary["identified_scope"] = IDENTIFIED_SCOPE_FILE


def _finish(cfg: RunConfig, rec: RunRecorder, rig, gate: ObservationGate, run: RunFolder | None, *, wall: float,
            hardware: bool, realtime: bool, vision, keep_rows: bool, stopped: BaseException | None) -> dict:
    """The summary of what was recorded (also of a run that was stopped), its plot and summary file."""
    data = rec.data()
    summary = rec.summary(rig.frame_log)
    recorded = rec.n_rows / cfg.loop.rate
    summary.update({"rig": "hardware" if hardware else "twin", "controller": cfg.controller.kind, "path": cfg.twin.scene.path, "latency_s": cfg.twin.camera.latency,
                    "fps": cfg.twin.camera.fps, "preset": cfg.twin.preset,
                    "knowledge": rec.ctrl.knowledge.label, "target_losses": rec.ctrl.losses,
                    "sim_seconds": cfg.loop.seconds,
                    "wall_seconds": wall, "realtime_factor": recorded / wall if wall > 0 else math.inf,
                    "rows": rec.n_rows, "rejected_observations": gate.n_rejected,
                    "rejected_by_reason": dict(gate.rejected)})
    if stopped is not None:
        why = stopped.signal_name if isinstance(stopped, StopSignal) else \
            "Ctrl-C" if isinstance(stopped, KeyboardInterrupt) else f"{type(stopped).__name__}: {stopped}"
        summary.update({"stopped": why, "recorded_seconds": recorded, "drives_disabled": rig.drives.is_disabled()})
    if vision is not None:
        summary["vision"] = vision.stats()
    if realtime:
        summary["timing_ms"] = rec.timing_ms()
        period = 1.0 / cfg.loop.rate
        # what the loop achieved on the wall clock: its rate, the ticks that ran a whole period late, and
        # the slots skipped when it fell more than MAX_BEHIND behind
        summary["loop"] = {"rate_hz": rec.n_rows / wall if wall > 0 else math.nan,
                           "overruns": rec.lateness.count_above(period), "skipped": rec.skipped}
    drives = rig.drives.report()
    if drives:
        summary["drives"] = drives
    if keep_rows:
        summary["_data"] = data
    if run is not None:
        summary["run_folder"] = str(run.path)
        save_identified_scope(run, rec.ctrl, summary)
        run.write_summary({k: v for k, v in summary.items() if not k.startswith("_")})
        if data.shape[0]:
            plot_run(data, cfg, run.file("tracking.png"))
    if stopped is not None:
        confirmed = {True: " (confirmed by the drives)", False: " (NOT confirmed: check the drives)", None: ""}
        log.warning("run stopped (%s) after %.1f s: drives disabled%s; %d rows%s", summary["stopped"], recorded,
                    confirmed[summary["drives_disabled"]], rec.n_rows,
                    f" and the summary in {run.path}" if run is not None else " recorded")
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
