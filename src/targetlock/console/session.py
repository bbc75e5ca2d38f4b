"""The operator console's session: the control loop in its own thread, and what the web page may do to it.

The loop (:class:`~targetlock.loop.runner.ControlLoop` on the wall clock) is unchanged; the console
reaches it only through small objects it hands the loop:

* :class:`LockSwitch` — a :class:`~targetlock.controllers.base.Controller` around the real one:
  released, it holds the last setpoint (the handle holds still); engaged, it steps the real
  controller. A new controller (kind or gains tuned in the page) is swapped in at the next tick,
  reset at the current setpoint, so the setpoint never jumps.
* :class:`ConsoleDrives` — the drives as the loop sees them, behind the rig's safety supervisor
  (:class:`~targetlock.interfaces.safety.SafeDrives`): after a stop the supervisor refuses every
  set-point and the loop keeps running as a viewer (frames, plots) without commanding anything.
* :class:`TapTracker` — the tracker with a newest-only tap: every tracked frame and its result are
  left in a one-slot hand-off for the web server, and a target picked in the page is selected on
  the next frame.
* :class:`MovableScene` (twin only) — the target path can be changed and the target nudged while
  running, continuously (no jump of the target).

Nothing the server does waits on the loop or makes the loop wait: the loop only writes into slots
and a ring buffer under short locks.
"""
from __future__ import annotations

import collections
import dataclasses
import logging
import math
import os
import sys
import threading
import time
from dataclasses import dataclass
from datetime import datetime, timezone

import numpy as np

from ..config import ConfigError, from_dict, to_dict, validate
from ..controllers.base import CONTROLLERS, Controller
from ..experiments.runfolder import RunFolder
from ..experiments.target_lock import (COLUMNS, RunConfig, RunRecorder, build_controller, build_rig, plot_run,
                                       save_identified_scope)
from ..rig.base import FrameLog
from ..interfaces.safety import SafeDrives, SafetyConfig, SafetyTrip
from ..loop.clock import WallClock
from ..loop.runner import ControlLoop, Tick
from ..model.endoscope import EndoscopeParams
from ..model.scene import Scene, SceneParams
from ..rig.base import Drives, Observation
from ..vision.tracker import Tracker, TrackResult

__all__ = ["ConsoleSession", "LockSwitch", "ConsoleDrives", "TapTracker", "MovableScene", "Frame",
           "TARGET_PATHS", "TUNABLE", "TUNABLE_KNOWLEDGE"]

log = logging.getLogger("targetlock.console")

TARGET_PATHS = ("static", "linear", "ellipse")
"""Paths the target can be switched to on the twin."""

TUNABLE = ("kind", "i_gain", "p_gain", "hc_width", "hc2_slope", "hc2_offset_deg", "hc_threshold_px", "tip_gain",
           "ik_damping", "target_prediction", "max_rate")
"""Controller settings the page may change while running (names of :class:`ControllerConfig` fields)."""
TUNABLE_KNOWLEDGE = ("nearest_depth", "farthest_depth")
"""What the controller assumes that the page may change (``knowledge.<name>`` in a tune request): the range
the target can be in, which a clinician's engineer may know (e.g. "at least 3 cm away") better than the
config did."""

PLOT_COLUMNS = ("t", "err_x", "err_y", "err", "true_err", "motor_x_deg", "motor_y_deg", "tip_x_deg", "tip_y_deg")
"""One plot row per tick: loop time (s), tracked error (px), true error (px, twin), angles (deg)."""


# ------------------------------------------------------------------------------------------ controller
class LockSwitch(Controller):
    """Engage/release and live replacement of the controller, without a setpoint jump.

    Thread use: :meth:`engage`, :meth:`release` and :meth:`replace` may be called from any thread;
    they take effect at the next tick, in the loop's thread."""

    def __init__(self, inner: Controller) -> None:
        super().__init__(inner.cfg, rad_per_tick=inner.rad_per_tick, lower=inner.lower, upper=inner.upper,
                         control_dt=inner.control_dt, knowledge=inner.knowledge)
        self.inner = inner
        self.locked = False
        self._want_locked = False
        self._pending: Controller | None = None
        self._mutex = threading.Lock()

    def engage(self) -> None:
        with self._mutex:
            self._want_locked = True

    def release(self) -> None:
        with self._mutex:
            self._want_locked = False

    def replace(self, controller: Controller) -> None:
        """Use ``controller`` (not yet reset) from the next tick on."""
        with self._mutex:
            self._pending = controller

    def signals(self) -> dict[str, float]:
        return self.inner.signals()

    def learned_endoscope(self) -> EndoscopeParams | None:
        return self.inner.learned_endoscope()

    def _reset(self, motor: np.ndarray, t: float) -> None:
        self.inner.reset(motor, t)

    def _update(self, obs: Observation | None, motor: np.ndarray, t: float) -> np.ndarray:
        with self._mutex:
            pending, self._pending = self._pending, None
            want = self._want_locked
        if pending is not None:
            pending.reset(self.setpoint, t)  # from the current setpoint: no jump
            self.inner, self.cfg, self.knowledge = pending, pending.cfg, pending.knowledge
        if want and not self.locked:
            self.inner.reset(self.setpoint, t)  # engage where the handle is held
        self.locked = want
        if not self.locked:
            return self.setpoint.copy()           # released: the handle holds still
        return self.inner.step(obs, motor, t)


# ------------------------------------------------------------------------------------------ drives
class ConsoleDrives(Drives):
    """The loop's view of the drives: everything goes through the safety supervisor ``safe``; while it
    is tripped (stop, fault) no set-point is sent and the loop keeps running without commanding."""

    def __init__(self, safe: SafeDrives) -> None:
        self.safe = safe
        self.n_axes = safe.n_axes
        self.refused = 0

    @property
    def homed(self) -> bool:
        return self.safe.homed

    def home(self) -> None:
        self.safe.home()

    def send_setpoints(self, ticks: np.ndarray) -> None:
        if self.safe.tripped:
            self.refused += 1
            return
        try:
            self.safe.send_setpoints(ticks)
        except SafetyTrip:
            self.refused += 1  # tripped meanwhile (stop from the page, drive fault): the drives are disabled

    def positions(self) -> np.ndarray:
        return self.safe.positions()

    @property
    def limits(self) -> tuple[np.ndarray, np.ndarray]:
        return self.safe.limits

    @property
    def rad_per_tick(self) -> float:
        return self.safe.rad_per_tick

    def fault(self) -> str | None:
        return self.safe.fault()

    def disable(self) -> None:
        self.safe.disable()

    def enable(self) -> None:
        self.safe.enable()

    def note_observation(self, valid: bool, now: float) -> None:
        """Forwarded to the supervisor's target-lost hold."""
        self.safe.note_observation(valid, now)


# ------------------------------------------------------------------------------------------ frames
@dataclass(frozen=True)
class Frame:
    """A tracked frame for the page (the loop has moved on; this is a copy)."""
    seq: int
    image: np.ndarray          # BGR uint8
    result: TrackResult
    wall_time: float           # time.time() when the frame was tracked (s), for frame-to-screen latency
    window_px: int


class TapTracker(Tracker):
    """Wraps a tracker: newest tracked frame into a one-slot hand-off; selections from the page applied
    on the next frame."""

    def __init__(self, inner: Tracker, window_px: int = 96) -> None:
        self.inner = inner
        self.window_px = window_px
        self._lock = threading.Lock()
        self._slot: Frame | None = None
        self._seq = 0
        self._request: tuple[float, float, int] | None = None
        self.selected_ok: bool | None = None      # a target has been selected (None: none tried yet)
        self.last_selection_ok: bool | None = None  # the newest selection succeeded
        self.last: TrackResult | None = None

    def request_select(self, x: float, y: float, window_px: int | None = None) -> None:
        with self._lock:
            self._request = (float(x), float(y), int(window_px or self.window_px))

    def fresh(self) -> "TapTracker":
        return TapTracker(self.inner.fresh(), self.window_px)

    @property
    def footprint_px(self) -> float | None:
        with self._lock:
            pending = self._request is not None
        return None if pending else self.inner.footprint_px   # a selection reads about the click

    def select(self, frame_bgr: np.ndarray, point_px, window_px: int) -> bool:
        """Select on a fresh tracker and keep it only if the selection succeeds: a click on a spot
        that cannot be tracked says why (``failure``) and the target tracked until then is kept."""
        trial = self.inner.fresh()
        ok = trial.select(frame_bgr, point_px, window_px)
        self.failure, self.warning = trial.failure, trial.warning
        if ok:
            self.inner, self.window_px = trial, int(window_px)
        self.selected_ok = ok or bool(self.selected_ok)
        self.last_selection_ok = ok
        return ok

    @property
    def kept_previous(self) -> bool:
        """The newest selection failed and the target selected before it is still followed."""
        return self.last_selection_ok is False and bool(self.selected_ok)

    def update(self, frame_bgr: np.ndarray, capture_time: float | None = None) -> TrackResult:
        with self._lock:
            req, self._request = self._request, None
        if req is not None:
            self.select(frame_bgr, req[:2], req[2])
        result = self.inner.update(frame_bgr, capture_time)
        self.last = result
        frame = Frame(self._seq + 1, frame_bgr.copy(), result, time.time(), self.window_px)
        with self._lock:
            self._seq += 1
            self._slot = frame
        return result

    def newest(self) -> Frame | None:
        """The newest tracked frame (it stays in the slot; compare ``seq`` to see if it is new)."""
        with self._lock:
            return self._slot


# ------------------------------------------------------------------------------------------ twin target
class MovableScene(Scene):
    """The twin's scene with a path that can be switched, and a target that can be nudged, while running.

    offset(t) = base + path offset(t - t0): switching at t0 keeps the target where it is."""

    def __init__(self, params: SceneParams, camera, start_camera_pose: np.ndarray) -> None:
        super().__init__(params, camera, start_camera_pose)
        self.base = np.zeros(3)
        self.t0 = 0.0
        self._mutex = threading.Lock()
        self._current: Scene = Scene(params, camera, start_camera_pose)

    def offset(self, t):
        with self._mutex:
            base, t0, cur = self.base.copy(), self.t0, self._current
        return base + cur.offset(np.asarray(t) - t0)

    def set_path(self, path: str, t: float) -> None:
        if path not in TARGET_PATHS:
            raise ConfigError(f"target path = {path!r} is not allowed; allowed: {', '.join(map(repr, TARGET_PATHS))}")
        now = self.offset(t)
        params = dataclasses.replace(self.params, path=path, start_delay=0.0)
        new = Scene(params, self.camera, self.start_pose)
        with self._mutex:
            self._current, self.t0 = new, t
            self.base = now - new.offset(0.0)

    def nudge(self, dx_px: float, dy_px: float, t: float) -> None:
        """Move the target by (dx, dy) px as seen from the start camera at the target distance."""
        d = self.params.distance
        with self._mutex:
            self.base = self.base + np.array([dx_px * d / self.camera.fx, dy_px * d / self.camera.fy, 0.0])

    @property
    def path(self) -> str:
        return self._current.params.path


# ------------------------------------------------------------------------------------------ session
AUTOGROUP = "/proc/self/autogroup"


def _raise_priority(nice: int) -> str | None:
    """Scheduling priority ``nice`` for the calling thread and, on Linux with autogroups, for this process's
    scheduling group against other sessions' work (CPU is shared per session first). Needs root or
    CAP_SYS_NICE; without, a warning and the loop runs at normal priority. Returns the group's previous
    nice (to restore with :func:`_restore_group`), or None when it was not changed."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)   # this thread only (Linux)
    except (OSError, AttributeError) as exc:
        log.warning("cannot raise the loop thread's priority to nice %d: %s", nice, exc)
        return None
    try:
        with open(AUTOGROUP) as fh:
            before = fh.read().split()[-1]
        with open(AUTOGROUP, "w") as fh:
            fh.write(str(nice))
        return before
    except (OSError, IndexError) as exc:
        log.warning("cannot raise the console's scheduling group to nice %d: %s", nice, exc)
        return None


def _restore_group(before: str | None) -> None:
    """The group is the whole login session's (the shell too): give it back its nice when the console ends."""
    if before is not None:
        try:
            with open(AUTOGROUP, "w") as fh:
                fh.write(before)
        except OSError as exc:
            log.warning("cannot restore the scheduling group's nice %s: %s", before, exc)


class _Stop(Exception):
    """Raised from the loop's tick callback to end the console's loop."""


class ConsoleSession:
    """Builds the rig (twin with rendered frames and the feature tracker, or a given rig), runs the loop in
    a thread on the wall clock and offers the page's actions. Use :meth:`start` / :meth:`close`."""

    def __init__(self, cfg: RunConfig, *, rig=None, history_seconds: float = 20.0, runs_root: str = "runs") -> None:
        validate(cfg)
        self.cfg = cfg
        self.runs_root = runs_root
        self.twin = rig is None
        self.vision = None
        if self.twin:
            from ..vision.pipeline import VisionPipeline
            self.vision = VisionPipeline(cfg.twin, tracker=cfg.vision_tracker, seed=cfg.seed,
                                         tracker_settings=cfg.feature_tracker)
            self.tap: TapTracker | None = TapTracker(self.vision.tracker, self.vision.window_px)
            self.vision.tracker = self.tap
            rig = build_rig(cfg, self.vision)
            rig.scene = MovableScene(cfg.twin.scene, cfg.twin.camera, rig.start_camera_pose)
            rig.drives = SafeDrives(rig.drives, SafetyConfig(max_rate=cfg.controller.max_rate))
            # Render and track the first frame now: compiling the renderer and tracker takes seconds, which
            # must not happen in the loop's first tick. The loop's own capture at t = 0 sees the same frame.
            self.vision(rig, 0.0, rig.truth_offset(0.0))
            pose, target = rig.camera_pose(), rig.scene.target_pose(0.0)
            moved, target_moved = pose.copy(), target.copy()
            moved[:3, 3] += 1e-3
            target_moved[:3, 3] += 1e-3
            self.vision.renderer.render(pose, target, camera_pose_end=moved, target_pose_end=target_moved)  # motion blur
        else:
            from ..vision.live import CameraObservations
            obs = rig.observations
            self.tap = None
            if isinstance(obs, CameraObservations):   # a camera rig tracks frames; motion capture has none
                self.tap = TapTracker(obs.tracker, obs.window_px)
                obs.tracker = self.tap
        if not isinstance(rig.drives, SafeDrives):
            raise TypeError("the console needs the rig's drives behind a SafeDrives supervisor")
        self.rig = rig
        self.safe: SafeDrives = rig.drives
        self.drives = ConsoleDrives(self.safe)
        rig.drives = self.drives
        self.switch = LockSwitch(build_controller(cfg, rig))
        self._warm_up(self.switch.inner)
        self.loop = ControlLoop(rig, self.switch, rate=cfg.loop.rate, clock=WallClock())
        n = int(round(history_seconds * cfg.loop.rate))
        self._rows: collections.deque = collections.deque(maxlen=n)
        self._sig: collections.deque = collections.deque(maxlen=n)
        self._lateness: collections.deque = collections.deque(maxlen=int(5 * cfg.loop.rate))
        self._busy: collections.deque = collections.deque(maxlen=int(5 * cfg.loop.rate))
        self._latency: collections.deque = collections.deque(maxlen=50)
        self._frame_times: collections.deque = collections.deque(maxlen=60)
        self._data_lock = threading.Lock()
        self._tick_index = 0
        self._time = 0.0
        self._last_obs: Observation | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None
        self.actions: collections.deque = collections.deque(maxlen=200)
        self._record: tuple[RunFolder, RunRecorder, int, int, str] | None = None
        self._record_lock = threading.Lock()
        self.last_record: dict | None = None
        self._mocap_seq: collections.deque = collections.deque(maxlen=20)
        self._group_nice: str | None = None
        self._finishing: str | None = None

    def _warm_up(self, ctrl: Controller) -> None:
        """Step a new controller twice off-line: compiling its model (seconds) must not stall a tick.
        The loop resets it at the current setpoint before its first real step."""
        here = self.switch.setpoint.copy() if hasattr(self, "switch") else np.zeros(2)
        ctrl.reset(here, 0.0)
        obs = Observation(capture_time=0.0, offset=np.array([4.0, -4.0]), valid=True, arrival_time=0.0)
        for k in (1, 2):
            ctrl.step(dataclasses.replace(obs, capture_time=0.05 * k), here, 0.05 * k)

    # ---------------------------------------------------------------- loop thread
    def start(self, loop_nice: int | None = None) -> None:
        """Start the loop thread; ``loop_nice`` (e.g. -10): its scheduling priority, where the OS allows it
        (Linux, root or CAP_SYS_NICE) — a busy host (browsers, other work) then takes CPU from others first."""
        if loop_nice is not None:
            # Server threads run Python too: hand the GIL back to the loop after 0.5 ms, not the default 5 ms.
            sys.setswitchinterval(min(sys.getswitchinterval(), 0.0005))
        self._thread = threading.Thread(target=self._run, args=(loop_nice,), name="targetlock-console-loop", daemon=True)
        self._thread.start()

    def _run(self, loop_nice: int | None) -> None:
        if loop_nice is not None:
            self._group_nice = _raise_priority(loop_nice)
        try:
            self.loop.run(7 * 86400.0, self._on_tick)
        except _Stop:
            pass
        except BaseException as exc:  # noqa: BLE001 - shown on the page; the loop already disabled the drives
            self.error = exc
            log.exception("control loop stopped")

    def _on_tick(self, tick: Tick) -> None:
        if self._stop.is_set():
            raise _Stop()
        obs = tick.observation
        if obs is not None:
            self._last_obs = obs
            if math.isfinite(obs.arrival_time):
                self._latency.append(obs.arrival_time - obs.capture_time)
            self._frame_times.append(tick.time)
        o = self._last_obs
        ox, oy = (o.offset[0], o.offset[1]) if o is not None else (math.nan, math.nan)
        truth = self.rig.truth_offset(tick.time)
        tip = self.rig.tip_angles()
        assert tick.motor is not None
        row = (tick.time, ox, oy, math.hypot(ox, oy), math.hypot(truth[0], truth[1]),
               math.degrees(tick.motor[0]), math.degrees(tick.motor[1]), math.degrees(tip[0]), math.degrees(tip[1]))
        sig = self.switch.signals()
        with self._data_lock:
            self._tick_index = tick.index
            self._time = tick.time
            self._rows.append((tick.index, row))
            self._sig.append((tick.index, tick.time, dict(sig)))
            self._lateness.append(tick.lateness)
            self._busy.append(tick.sent - tick.time - tick.lateness)  # the tick's own work (s)
        if self._record is not None:
            with self._record_lock:   # held elsewhere only to swap the recorder in or out
                if self._record is not None:
                    self._record[1](tick)

    # ---------------------------------------------------------------- actions (any thread)
    def _act(self, who: str, action: str, **details) -> None:
        stamp = datetime.now(timezone.utc).isoformat(timespec="milliseconds")
        entry = {"time": stamp, "who": who, "action": action, **details}
        self.actions.append(entry)
        log.info("console action %s by %s %s", action, who, details if details else "")

    def select(self, x: float, y: float, window_px: int | None = None, who: str = "?") -> None:
        cam = self.cfg.twin.camera
        if not (0.0 <= x < cam.width and 0.0 <= y < cam.height):
            raise ConfigError(f"select point = ({x:g}, {y:g}) px is outside the image; allowed: x in [0, {cam.width}), "
                              f"y in [0, {cam.height}) px")
        if window_px is not None and not 16 <= window_px <= 512:
            raise ConfigError(f"select window = {window_px} px is out of range; allowed: [16, 512] px")
        if self.tap is None:
            raise ConfigError("this rig has no camera tracker: the target cannot be selected in the view")
        self.tap.request_select(x, y, window_px)
        self._act(who, "select", x=round(x, 1), y=round(y, 1), window_px=window_px)

    def engage(self, who: str = "?") -> None:
        if self.safe.tripped:
            raise ConfigError(f"drives are stopped ({self.safe.fault()}): enable them first")
        self.switch.engage()
        self._act(who, "engage")

    def release(self, who: str = "?") -> None:
        self.switch.release()
        self._act(who, "release")

    def stop(self, who: str = "?") -> None:
        """Disable the drives through the safety supervisor now; release the lock."""
        self.safe.emergency_stop("operator stop (console)")
        self.switch.release()
        self._act(who, "stop")

    def enable(self, who: str = "?") -> None:
        """Explicit re-enable after a stop or a cleared fault; the lock stays released."""
        self.switch.release()
        try:
            self.safe.enable()
        except SafetyTrip as exc:
            raise ConfigError(str(exc)) from None
        self._act(who, "enable")

    def tune(self, changes: dict, who: str = "?") -> dict:
        """Change controller settings (names in :data:`TUNABLE`) and what it assumes (``knowledge.<name>``,
        names in :data:`TUNABLE_KNOWLEDGE`); validated like the config; returns the new controller settings."""
        knowledge = {k.removeprefix("knowledge."): v for k, v in changes.items() if k.startswith("knowledge.")}
        controller = {k: v for k, v in changes.items() if not k.startswith("knowledge.")}
        unknown = sorted(set(controller) - set(TUNABLE))
        if unknown:
            raise ConfigError(f"controller.{unknown[0]} cannot be changed while running; allowed: {', '.join(TUNABLE)}")
        unknown = sorted(set(knowledge) - set(TUNABLE_KNOWLEDGE))
        if unknown:
            raise ConfigError(f"knowledge.{unknown[0]} cannot be changed while running; allowed: "
                              f"{', '.join('knowledge.' + k for k in TUNABLE_KNOWLEDGE)}")
        data = to_dict(self.switch.cfg)
        data.update(controller)
        new_cfg = validate(from_dict(type(self.switch.cfg), data, prefix="controller."), prefix="controller.")
        new_knowledge = validate(from_dict(type(self.cfg.knowledge), {**to_dict(self.cfg.knowledge), **knowledge},
                                           prefix="knowledge."), prefix="knowledge.")
        cfg = dataclasses.replace(self.cfg, controller=new_cfg, knowledge=new_knowledge)
        # The new controller assumes the scope the running lock identified, if it did: same scope, new gains.
        ctrl = build_controller(cfg, self.rig, identified=self.switch.learned_endoscope())
        self._warm_up(ctrl)
        self.switch.replace(ctrl)
        self.cfg = cfg
        self._act(who, "tune", **changes)
        return to_dict(new_cfg)

    def set_target_path(self, path: str, who: str = "?") -> None:
        scene = self._scene()
        scene.set_path(path, self.time)
        self._act(who, "target-path", path=path)

    def nudge_target(self, dx: float, dy: float, who: str = "?") -> None:
        if not (math.isfinite(dx) and math.isfinite(dy) and abs(dx) <= 2000 and abs(dy) <= 2000):
            raise ConfigError(f"target move = ({dx}, {dy}) px is out of range; allowed: [-2000, 2000] px per axis")
        self._scene().nudge(dx, dy, self.time)
        self._act(who, "target-move", dx=round(dx, 1), dy=round(dy, 1))

    def _scene(self) -> MovableScene:
        if not self.twin:
            raise ConfigError("the target can be moved only on the twin")
        return self.rig.scene

    # ---------------------------------------------------------------- recording
    def record_start(self, who: str = "?") -> str:
        if self._record is not None:
            raise ConfigError(f"already recording into {self._record[0].path}")
        run = RunFolder("console", self.cfg, root=self.runs_root)      # disk work outside the loop's lock
        rec = RunRecorder(self.rig, self.switch, after=self.time, writer=run.timeseries(COLUMNS))
        started = datetime.now(timezone.utc).isoformat(timespec="milliseconds")
        with self._record_lock:
            if self._record is not None:
                rec.writer.close()
                raise ConfigError(f"already recording into {self._record[0].path}")
            log_ = self.rig.frame_log
            self._record = (run, rec, log_.frames, log_.valid, started)
        self._act(who, "record-start", folder=str(run.path))
        return str(run.path)

    def record_stop(self, who: str = "?") -> dict:
        with self._record_lock:
            if self._record is None:
                raise ConfigError("not recording")
            run, rec, frames0, valid0, started = self._record
            self._record = None
            self._finishing = str(run.path)     # shown as recording until the folder is complete
        rec.writer.close()
        data = rec.data()
        frames = FrameLog()            # the frames of the recording only
        frames.frames, frames.valid = self.rig.frame_log.frames - frames0, self.rig.frame_log.valid - valid0
        summary = rec.summary(frames) if len(data) else {}
        summary.update({"rig": "twin" if self.twin else "hardware", "controller": self.cfg.controller.kind,
                        "seconds": float(data[-1, 0] - data[0, 0]) if len(data) else 0.0,
                        "actions": [a for a in self.actions if a["time"] >= started]})
        if len(data):
            plot_run(data, self.cfg, run.file("tracking.png"))
        summary["run_folder"] = str(run.path)
        save_identified_scope(run, self.switch, summary)
        run.write_summary(summary)
        run.close()
        self.last_record = summary
        self._finishing = None
        self._act(who, "record-stop", folder=str(run.path))
        return summary

    # ---------------------------------------------------------------- views (any thread)
    @property
    def time(self) -> float:
        with self._data_lock:
            return self._time

    def rows_since(self, index: int) -> tuple[int, list[tuple], list[dict]]:
        """Plot rows (:data:`PLOT_COLUMNS`) and controller signals of ticks after ``index``; the newest index."""
        with self._data_lock:
            rows = [r for (i, r) in self._rows if i > index]
            sig = [s for (i, _, s) in self._sig if i > index]
            return self._tick_index, rows, sig

    def status(self) -> dict:
        with self._data_lock:
            late = np.array(self._lateness) * 1e3
            busy = np.array(self._busy) * 1e3
            lat = list(self._latency)
            ft = list(self._frame_times)
            t = self._time
        fps = (len(ft) - 1) / (ft[-1] - ft[0]) if len(ft) > 2 and ft[-1] > ft[0] else 0.0
        tr = self.tap.last if self.tap is not None else None
        mocap = None
        if not self.twin:
            mocap = self._mocap_status()
        rec = self._record
        return {
            "time": t,
            "rig": "twin" if self.twin else "hardware",
            "running": self._thread is not None and self._thread.is_alive(),
            "error": None if self.error is None else f"{type(self.error).__name__}: {self.error}",
            "locked": self.switch.locked,
            "drives": {"enabled": not self.safe.tripped, "homed": self.safe.homed, "fault": self.safe.fault(),
                       "holding": self.safe.holding, "refused": self.drives.refused},
            "mocap": mocap,
            "frame_rate": fps,
            "latency_ms": 1e3 * float(np.median(lat)) if lat else None,
            "loop": {"rate_hz": self.cfg.loop.rate,
                     "jitter_p50_ms": float(np.percentile(late, 50)) if late.size else None,
                     "jitter_p99_ms": float(np.percentile(late, 99)) if late.size else None,
                     "jitter_max_ms": float(late.max()) if late.size else None,
                     "tick_ms_p50": float(np.percentile(busy, 50)) if busy.size else None},
            "tracker": None if tr is None else {"valid": bool(tr.valid), "lost": bool(tr.lost),
                                                "confidence": float(tr.confidence),
                                                "selected": None if self.tap is None else self.tap.selected_ok},
            "selection": self._selection_status(),
            "controller": to_dict(self.switch.cfg),
            "knowledge": {k: getattr(self.cfg.knowledge, k) for k in ("depth", *TUNABLE_KNOWLEDGE)},
            "controllers": list(CONTROLLERS),
            "target_path": self.rig.scene.path if self.twin else None,
            "target_paths": list(TARGET_PATHS) if self.twin else [],
            "recording": self._finishing if rec is None else str(rec[0].path),
            "actions": list(self.actions)[-8:],
        }

    def _selection_status(self) -> dict | None:
        """The newest selection from the page: whether it took, why not, and any warning (None before one)."""
        tap = self.tap
        if tap is None or tap.last_selection_ok is None:
            return None
        return {"ok": tap.last_selection_ok, "failure": tap.failure, "warning": tap.warning,
                "kept_previous": tap.kept_previous}

    def _mocap_status(self) -> dict:
        """Connected (a sample younger than 0.5 s) and sample rate (1/s) of the rig's NatNet client."""
        client = self.rig.client
        seq, _ = client.latest.get_with_sequence()
        now = time.monotonic()
        self._mocap_seq.append((now, seq))
        (t0, s0), (t1, s1) = self._mocap_seq[0], self._mocap_seq[-1]
        return {"connected": client.get(max_age=0.5) is not None,
                "rate_hz": (s1 - s0) / (t1 - t0) if t1 > t0 else None}

    def lateness_ms(self) -> np.ndarray:
        """Loop lateness of the last ~5 s of ticks (ms), for jitter measurements."""
        with self._data_lock:
            return np.array(self._lateness) * 1e3

    def close(self) -> None:
        """End the loop (drives left disabled), finish a recording, release the rig."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        _restore_group(self._group_nice)
        if self._record is not None:
            self.record_stop("shutdown")
        try:
            self.safe.disable()
        finally:
            if self.vision is not None:
                self.vision.close()
            if self.twin:
                self.safe.close()
            else:
                self.rig.close()
