"""Score a tracker on rendered sequences with known ground truth.

Each sequence is rendered by :class:`~targetlock.vision.render.Renderer` (distorted endoscope
camera, round field of view, light fall-off, specular glints, motion blur, noise) at the camera's
frame rate; the tracker selects the target on frame 0 at its true position and is then fed the
remaining frames. Default sequences (:data:`SEQUENCES`):

``slow``      target drifts slowly (~3 px/frame) over a slightly tilted plane
``fast``      target swings ~120 px at up to ~17 px/frame (motion blur from the exposure)
``tip``       the camera moves with the bending tip (``model.kinematics.tip_pose``)
``blur``      fast motion with a long exposure: up to ~15 px of motion blur
``specular``  tilted plane whose glints sit on the target and slide over it while it rocks
``lighting``  the light gain steps and swings between 0.35 and 1.6
``noise``     strong sensor noise (sigma 8 levels)
``occlusion`` an instrument sweeps over the target, covers it completely, and withdraws
``leave``     the view pans until the target leaves the field of view, then comes back
``scale``     the tip approaches from 75 mm to 30 mm (target 2.5x larger)
``rotation``  the target turns 180 deg in the image plane
``folds``     not a plane: a lumen with ring folds that breathes and carries a peristaltic wave
              (``model.scene.SurfaceParams``), target on its wall, the tip moving sideways (parallax)

Sensor noise is drawn fresh for every frame (``RenderSettings(fresh_noise=True)`` unless render
settings are given): the loop renderer's noise bank repeats its pattern, shifted, between frames,
which on weak texture under strong noise is a motion a tracker can follow.

Scoring rules (per frame after the selection frame; ``threshold_px`` = 8 px):

* **error**: distance (px) of a *valid* estimate from the true position of the selected point.
* **visible** frames (point in front, inside the round field of view, not covered): correct when
  the estimate is valid and within ``threshold_px``.
* **not visible** frames (occluded by design, or outside the field of view): correct when the
  tracker reports no valid estimate (valid=False) **or** a valid estimate within the threshold (a
  tracker may legitimately infer a covered point from its surroundings); a valid estimate farther
  away is wrong (a false lock).
* ``tracked_fraction``: correct frames / all frames; ``tracked_in_view_fraction``: visible frames
  with a valid estimate within the threshold / visible frames (issue 14's goal). ``median_px``, ``p95_px``: errors of valid
  estimates on visible frames. ``delta_avg``: on visible frames, the fraction of frames with an
  error below 4, 8, 16, 32, 64 px, averaged (TAP-Vid / STIR style; an invalid estimate counts as
  a miss at every threshold). ``false_lock_fraction``: valid estimates farther than the threshold
  / all frames. ``fps``: tracker frames per second on one core, timing only ``update`` calls;
  ``fps_locked``: the same over the frames that arrive while the target is locked (the normal,
  region-of-interest case), leaving out whole-frame re-acquisition while lost; ``fps_lost``: over
  the frames that arrive while it is lost (the whole-frame searches).

:func:`markdown_tables` writes a result as the tables of ``docs/vision.md``
(``scripts/make_docs.py vision``).
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, fields, replace
from concurrent.futures import Executor, as_completed
from typing import Callable, Sequence

import cv2
import numpy as np

from ..config import param, validate
from ..model.camera import CameraParams
from ..model.kinematics import tip_pose
from ..model.scene import SurfaceParams
from .render import Frame, PlanarTarget, Renderer, RenderSettings, endoscope_camera, make_pose
from .reference import make_reference, reference_trackers
from .texture import PHOTOS, photo_texture
from .tracker import FeatureTracker, MarkerSettings, MarkerTracker, Tracker, TrackerSettings

__all__ = ["EvalSettings", "SEQUENCES", "FRAME_COLUMNS", "evaluate", "render_sequence", "score",
           "instrument_polygon", "markdown_tables"]

SEQUENCES = ("slow", "fast", "tip", "blur", "specular", "lighting", "noise", "occlusion", "leave", "scale",
             "rotation", "folds")
THRESHOLDS_PX = (4.0, 8.0, 16.0, 32.0, 64.0)


@dataclass(frozen=True)
class EvalSettings:
    """What :func:`evaluate` renders and how it scores."""
    frames: int = param(66, lo=10, hi=100000, doc="frames per sequence (66 = 3 s at 22 fps)")
    sequences: tuple[str, ...] = param(SEQUENCES, choices=None, doc="sequences to run, from SEQUENCES")
    tracker: str = param("feature", choices=("feature", "marker"), doc="tracker under test")
    window_px: int = param(80, unit="px", lo=8, hi=1024, doc="side of the template window given to select()")
    exposure_s: float = param(0.02, unit="s", lo=0.0, hi=1.0, doc="exposure time (motion blur)")
    threshold_px: float = param(8.0, unit="px", lo=0.1, hi=1000.0, doc="largest error of a frame that counts as tracked")
    distance_m: float = param(0.05, unit="m", lo=0.005, hi=1.0, doc="usual distance of the tissue from the tip")
    photos: tuple[str, ...] = param(("retina", "coffee"), choices=None,
                                    doc="real photographs (scikit-image's bundled data, see texture.PHOTOS) the "
                                        "sequences are also rendered on, besides the procedural mucosa")
    references: tuple[str, ...] = param(("mil", "lk"), choices=None,
                                        doc="OpenCV reference trackers run on the same frames (reference.reference_trackers)")
    feature: TrackerSettings = field(default_factory=TrackerSettings)  # the feature tracker's settings

    def check(self, prefix: str = "") -> None:
        from ..config import ConfigError
        for field, allowed in (("sequences", SEQUENCES), ("photos", tuple(PHOTOS)), ("references", reference_trackers())):
            bad = [s for s in getattr(self, field) if s not in allowed]
            if bad:
                raise ConfigError(f"{prefix}{field}: unknown {', '.join(bad)}; allowed: {', '.join(allowed)}")


# ---------------------------------------------------------------------------------- scenes
def instrument_polygon(tip_px, direction, width_px: float, length_px: float = 900.0) -> np.ndarray:
    """Polygon (N, 2) px of an instrument shaft of ``width_px`` ending in a round tip at ``tip_px``
    and reaching back along ``direction`` (from the tip towards where it enters the view)."""
    d = np.asarray(direction, float)
    d /= np.linalg.norm(d)
    n = np.array([-d[1], d[0]])
    tip = np.asarray(tip_px, float)
    r = width_px / 2
    back = tip + d * length_px
    ang = np.linspace(0, np.pi, 12)
    arc = tip[None] + r * (np.cos(ang)[:, None] * n[None] - np.sin(ang)[:, None] * d[None])
    return np.vstack([back + n * r, arc, back - n * r])


class _Scene:
    """Poses of one sequence as functions of time (s)."""

    def __init__(self, name: str, cfg: EvalSettings, cam: CameraParams, rng: np.random.Generator, duration: float):
        self.name, self.cfg, self.cam, self.T = name, cfg, cam, duration
        d = cfg.distance_m
        self.p_sel = rng.uniform(-0.05, 0.05, 2)              # which tissue is the target
        if cfg.tracker == "marker":
            self.p_sel = np.zeros(2)                          # the marker sits at the plane centre
        self.start = np.array([*rng.uniform(-0.004, 0.004, 2), d])  # target point in the camera frame
        self.tilt = np.array([*rng.uniform(-0.25, 0.25, 2), rng.uniform(-np.pi, np.pi)])
        self.phase = rng.uniform(0, 2 * np.pi, 2)
        self.light_gain = 1.0
        self.occluders: list = []
        self.camera = np.eye(4)
        if name == "specular":  # tilt so the glints (where the normal faces the camera) sit on the target
            self.start = np.array([0.0, 0.0, 0.035])
            self.tilt[:2] = 0.0
        if name == "tip":
            self.length, self.n_el = 0.04, 10
            self.start = np.array([0.0, 0.0, self.length + d])

    def target_pose(self, point_cam: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
        """Target pose that puts the selected plane point at ``point_cam`` (m, camera/world frame)."""
        pose = make_pose((0, 0, 0), rotvec)
        pose[:3, 3] = point_cam - pose[:3, :3] @ np.array([self.p_sel[0], self.p_sel[1], 0.0])
        return pose

    def at(self, t: float):
        """(camera pose, target pose, light gain, occluders) at time t (s)."""
        u = t / self.T                     # 0..1 over the sequence
        w = 2 * np.pi * u
        d = self.cfg.distance_m
        pos = self.start.copy()
        rv = self.tilt.copy()
        cam_pose = self.camera
        gain = 1.0
        occ: list = []
        name = self.name
        if name in ("slow", "lighting", "noise"):
            pos[:2] += 0.006 * np.sin(np.array([w, 2 * w]) + self.phase) * [1.0, 0.7]
            if name == "lighting":
                gain = 1.0 + 0.6 * math.sin(3 * w) if u < 0.5 else (0.35 if u < 0.75 else 1.6)
        elif name in ("fast", "blur"):
            amp = 0.02 if name == "fast" else 0.016
            pos[:2] += amp * np.sin(np.array([1.5 * w, 0.75 * w]) + self.phase * [0, 1]) * [1.0, 0.5]
        elif name == "tip":
            phx = 0.35 * math.sin(w + self.phase[0])
            phy = 0.25 * math.sin(2 * w + self.phase[1])
            cam_pose = tip_pose(phx, phy, self.length, self.n_el)
            pos = self.start.copy()
        elif name == "specular":
            rv = np.array([0.12 * math.sin(w), 0.12 * math.sin(2 * w + 1.0), self.tilt[2]])
            pos[:2] += 0.002 * np.array([math.sin(w), math.cos(w)])
        elif name == "occlusion":
            pos[:2] += 0.002 * np.sin(np.array([w, 2 * w]) + self.phase)
            # instrument from the lower right; its tip passes over the target and comes back
            s = max(0.0, math.sin(np.pi * min(1.0, max(0.0, (u - 0.2) / 0.6))))  # 0 -> 1 -> 0
            direc = np.array([0.8, 0.6])
            tgt = np.array([self.cam.cx, self.cam.cy]) + pos[:2] / d * self.cam.fx
            tip = tgt + direc / np.linalg.norm(direc) * (300.0 - 390.0 * s)
            occ = [instrument_polygon(tip, direc, 130.0)]
        elif name == "leave":
            pos[0] += 0.085 * math.sin(np.pi * u) ** 2
            pos[1] += 0.004 * math.sin(w)
        elif name == "scale":
            pos[2] = 0.075 - 0.045 * (0.5 - 0.5 * math.cos(np.pi * u))
            pos[:2] += 0.002 * np.sin(np.array([w, w]) + self.phase)
        elif name == "rotation":
            rv = self.tilt.copy()
            rv[2] += np.pi * u
            pos[:2] += 0.002 * np.sin(np.array([w, w]) + self.phase)
        elif name == "folds":   # the tissue stays, the tip moves sideways: parallax over the folds
            cam_pose = make_pose((0.008 * math.sin(w + self.phase[0]), 0.005 * math.sin(2 * w + self.phase[1]), 0.0))
        return cam_pose, self.target_pose(pos, rv), gain, occ


def render_sequence(name: str, settings: EvalSettings | None = None, *, seed: int = 0,
                    cam: CameraParams | None = None, render_settings: RenderSettings | None = None,
                    target: PlanarTarget | None = None, renderer: Renderer | None = None) -> list[Frame]:
    """Render sequence ``name`` (one of :data:`SEQUENCES`) with ground truth, deterministic in ``seed``."""
    cfg = validate(settings or EvalSettings())
    if name not in SEQUENCES:
        raise ValueError(f"sequence {name!r}; allowed: {', '.join(SEQUENCES)}")
    cam = cam or endoscope_camera()
    rs = render_settings or RenderSettings(fresh_noise=True)
    if name == "noise":
        rs = replace(rs, noise_sigma=max(rs.noise_sigma, 8.0))
    exposure = cfg.exposure_s * (2.0 if name == "blur" else 1.0)
    rng = np.random.default_rng([seed, SEQUENCES.index(name)])
    scene = _Scene(name, cfg, cam, rng, cfg.frames / cam.fps)
    if renderer is None or name in ("noise", "folds"):
        tgt = target if target is not None else (renderer.target if renderer is not None else None)
        # folds: the lumen beside the target (as in the scene's default), so the target is on its wall
        surface = SurfaceParams(kind="folds", lumen_offset=tuple(scene.p_sel + SurfaceParams().lumen_offset)) \
            if name == "folds" else None
        renderer = Renderer(cam, rs, tgt, seed=seed, surface=surface)
    renderer.reseed([seed, SEQUENCES.index(name), 1])
    frames = []
    for i in range(cfg.frames):
        t = i / cam.fps
        cp0, tp0, gain, occ = scene.at(t)
        if exposure > 0:
            cp1, tp1, _, _ = scene.at(t + exposure)
            frames.append(renderer.render(cp0, tp0, camera_pose_end=cp1, target_pose_end=tp1, light_gain=gain,
                                          occluders=occ, point_m=scene.p_sel, time_s=t + exposure / 2))
        else:
            frames.append(renderer.render(cp0, tp0, light_gain=gain, occluders=occ, point_m=scene.p_sel, time_s=t))
    return frames


# --------------------------------------------------------------------------------- scoring
def _per_frame(frames: list[Frame], results: list, threshold_px: float) -> tuple[np.ndarray, ...]:
    """(error px, inf where invalid; valid; visible; within the threshold; correct) per frame, by the
    rules of the module docstring."""
    n = len(frames)
    err = np.full(n, np.inf)
    valid = np.zeros(n, bool)
    vis = np.array([f.visible for f in frames], dtype=bool)
    for i, (f, r) in enumerate(zip(frames, results)):
        valid[i] = bool(r.valid)
        if r.valid:
            err[i] = float(np.hypot(*(np.asarray(r.position_px) - f.truth_px)))
    close = err <= threshold_px
    correct = np.where(vis, valid & close, ~valid | close)
    return err, valid, vis, close, correct


def score(frames: list[Frame], results: list, threshold_px: float = 8.0) -> dict:
    """Metrics (see module docstring) of tracker ``results`` (TrackResult per frame) against ``frames``."""
    n = len(frames)
    err, valid, vis, close, correct = _per_frame(frames, results, threshold_px)
    ev = err[vis & valid]
    delta = [float(np.mean(err[vis] < t)) if vis.any() else float("nan") for t in THRESHOLDS_PX]
    return {
        "frames": int(n),
        "visible_frames": int(vis.sum()),
        "valid_frames": int(valid.sum()),
        "median_px": float(np.median(ev)) if len(ev) else float("nan"),
        "p95_px": float(np.percentile(ev, 95)) if len(ev) else float("nan"),
        "tracked_fraction": float(np.mean(correct)) if n else float("nan"),
        "tracked_in_view_fraction": float(np.mean((valid & close)[vis])) if vis.any() else float("nan"),
        "delta_avg": float(np.mean(delta)),
        "false_lock_fraction": float(np.mean(valid & ~close)) if n else float("nan"),
    }


FRAME_COLUMNS = ("seed", "content", "sequence", "tracker", "frame", "visible", "occluded", "truth_x_px", "truth_y_px",
                 "valid", "lost", "x_px", "y_px", "error_px", "confidence", "correct", "selection_warned")
"""Columns of a per-frame row (:func:`evaluate`'s ``on_frames``, ``vision-eval``'s ``frames.csv``): the
frame's ground truth (px), what the tracker reported (position px and error px, NaN where it
reported no valid position) and whether the frame counts as correct by the scoring rules; ``sequence``
is the sequence's name, ``tracker`` the tracker under test (``feature``, ``marker``) or a reference;
``selection_warned``: the tracker under test's selection on this sequence failed or came with a
warning."""


def _frame_rows(seed: int, content: str, sequence: str, tracker: str, frames: list[Frame], results: list,
                threshold_px: float, warned: bool) -> list[tuple]:
    """One :data:`FRAME_COLUMNS` row per scored frame (frames after the selection frame)."""
    err, valid, vis, _, correct = _per_frame(frames, results, threshold_px)
    rows = []
    for i, (f, r) in enumerate(zip(frames, results)):
        pos = np.asarray(r.position_px, float)
        px = [round(float(v), 4) if valid[i] else math.nan for v in (pos[0], pos[1], err[i])]
        rows.append((int(seed), content, sequence, tracker, i + 1, int(vis[i]), int(f.occluded),
                     round(float(f.truth_px[0]), 4), round(float(f.truth_px[1]), 4), int(valid[i]), int(bool(r.lost)),
                     *px, round(float(r.confidence), 4), int(correct[i]), int(warned)))
    return rows


_NO_IMAGE = np.zeros((0, 0, 3), np.uint8)


def _truth_only(frames: list[Frame]) -> list[Frame]:
    """The frames' ground truth without their images (what pooled scoring keeps: a run's memory does
    not grow with its frames)."""
    return [replace(f, image=_NO_IMAGE) for f in frames]


def _make(cfg: EvalSettings, tracker_settings, cam: CameraParams) -> Tracker:
    if cfg.tracker == "marker":
        return MarkerTracker(tracker_settings if isinstance(tracker_settings, MarkerSettings) else None, cam)
    return FeatureTracker(cfg.feature)


def _run_tracker(tracker: Tracker, frames: list[Frame], fps: float, window_px: int, threshold_px: float) -> tuple:
    """Select on frame 0, update on the rest (timed). Returns (metrics, results, t_all, t_locked,
    n_locked); the metrics' ``fps_lost`` times the frames that arrive while the target is lost."""
    ok = tracker.select(frames[0].image, frames[0].truth_px, window_px)
    results = []
    dt = dt_lock = 0.0
    n_lock = 0
    for i, f in enumerate(frames[1:], 1):
        locked = not tracker.lost
        t0 = time.perf_counter()
        results.append(tracker.update(f.image, i / fps))
        t1 = time.perf_counter() - t0
        dt += t1
        if locked:
            dt_lock += t1
            n_lock += 1
    m = score(frames[1:], results, threshold_px)
    m["fps"] = (len(results) / dt) if dt > 0 else float("inf")
    m["fps_locked"] = (n_lock / dt_lock) if dt_lock > 0 else float("nan")
    n_lost = len(results) - n_lock
    m["fps_lost"] = n_lost / (dt - dt_lock) if n_lost and dt > dt_lock else float("nan")
    m["selected"] = bool(ok)
    m["selection_failure"] = tracker.failure
    m["selection_warning"] = tracker.warning
    return m, results, dt, dt_lock, n_lock


@dataclass
class _Pool:
    """One tracker's frames on one texture, pooled over sequences (and seeds): what its figures are
    scored from."""
    truth: list[Frame] = field(default_factory=list)       # ground truth (frames without images)
    results: list = field(default_factory=list)
    seconds: float = 0.0                                    # time in ``update``
    seconds_locked: float = 0.0                             # ... on frames that arrived while locked
    locked: int = 0                                         # frames that arrived while locked
    failures: int = 0                                       # selection failures
    warnings: int = 0                                       # selections with a warning
    clear_truth: list[Frame] = field(default_factory=list)  # the sequences whose selection warned of nothing
    clear_results: list = field(default_factory=list)

    def add(self, other: "_Pool") -> None:
        for f in fields(self):
            setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))

    @staticmethod
    def score(pools: list["_Pool"], threshold_px: float) -> dict:
        """:func:`score` of the pools' frames together, with speed and selection counts."""
        whole = _Pool()
        for p in pools:
            whole.add(p)
        m = score(whole.truth, whole.results, threshold_px)
        t, t_lock, n = whole.seconds, whole.seconds_locked, len(whole.truth)
        m["fps"] = n / t if t > 0 else float("inf")
        m["fps_locked"] = whole.locked / t_lock if t_lock > 0 else float("nan")
        n_lost = n - whole.locked
        m["fps_lost"] = n_lost / (t - t_lock) if n_lost and t > t_lock else float("nan")
        m["selection_failures"] = whole.failures
        m["selection_warnings"] = whole.warnings
        # The sequences whose selection (by the tracker evaluated, for the references too) warned of nothing.
        m["tracked_in_view_unwarned"] = score(whole.clear_truth, whole.clear_results,
                                              threshold_px)["tracked_in_view_fraction"]
        return m


@dataclass
class _SeedRun:
    """What one seed's sequences gave (:func:`_run_seed`): merged by :func:`evaluate`."""
    sequences: dict[str, dict]                 # key -> the tracker's metrics
    references: dict[str, dict[str, dict]]     # reference -> key -> metrics
    pooled: dict[tuple[str, str], _Pool]        # (tracker, content) -> its frames
    contents: list[str]
    render_s: float
    rendered: int
    rows: list[tuple]                           # FRAME_COLUMNS rows, when collected for another process


def _run_seed(cfg: EvalSettings, seed: int, keyed: bool, tracker_settings, cam: CameraParams, rs: RenderSettings,
              progress: Callable[[str], None] | None = None,
              on_frames: Callable[[list[tuple]], None] | None = None, collect: bool = False) -> _SeedRun:
    """Render, track and score every sequence of one seed (keys prefixed ``SEED:`` if ``keyed``), on
    one OpenCV thread; ``collect`` (in a worker process): the rows go into the result's ``rows``."""
    out = _SeedRun({}, {who: {} for who in cfg.references}, {}, [], 0.0, 0, [])
    if collect:
        on_frames = out.rows.extend
    if cfg.tracker == "marker":
        contents = [("mucosa", PlanarTarget.aruco(seed=seed, texture_px=rs.texture_px))]
    else:
        contents = [("mucosa", PlanarTarget.mucosa(seed=seed, texture_px=rs.texture_px))]
        contents += [(ph, PlanarTarget((0.2, 0.2), photo_texture(ph), (0.0, 0.0))) for ph in cfg.photos]
    out.contents = [c for c, _ in contents]
    names = ("tracker", *cfg.references)
    threads = cv2.getNumThreads()
    try:
        cv2.setNumThreads(1)
        renderer = Renderer(cam, rs, contents[0][1], seed=seed)
        for content, target in contents:
            renderer.set_target(target)
            for name in cfg.sequences:
                t0 = time.perf_counter()
                frames = render_sequence(name, cfg, seed=seed, cam=cam, render_settings=rs, target=target,
                                         renderer=renderer)
                out.render_s += time.perf_counter() - t0
                out.rendered += len(frames)
                key = (f"{seed}:" if keyed else "") + (name if content == "mucosa" else f"{content}/{name}")
                truth = _truth_only(frames[1:])
                warned = False  # the tracker's selection on this sequence came with a warning (or failed)
                for who in names:
                    tracker = _make(cfg, tracker_settings, cam) if who == "tracker" else make_reference(who)
                    m, results, dt, dt_lock, n_lock = _run_tracker(tracker, frames, cam.fps, cfg.window_px,
                                                                   cfg.threshold_px)
                    if who == "tracker":
                        warned = m["selection_warning"] is not None or not m["selected"]
                    if on_frames is not None:
                        on_frames(_frame_rows(seed, content, name, cfg.tracker if who == "tracker" else who,
                                              frames[1:], results, cfg.threshold_px, warned))
                    out.pooled.setdefault((who, content), _Pool()).add(_Pool(
                        truth=truth, results=results, seconds=dt, seconds_locked=dt_lock, locked=n_lock,
                        failures=int(not m["selected"]), warnings=int(m["selection_warning"] is not None),
                        clear_truth=[] if warned else truth, clear_results=[] if warned else results))
                    if who != "tracker":
                        out.references[who][key] = m
                    else:
                        out.sequences[key] = m
                        if progress:
                            progress(_progress_line(key, m))
                del frames  # before the next sequence is rendered: one sequence's images at a time
    finally:
        cv2.setNumThreads(threads)
    return out


def _progress_line(key: str, m: dict) -> str:
    return f"{key}: median {m['median_px']:.2f} px, tracked {m['tracked_fraction']:.3f}, fps {m['fps']:.0f}"


def evaluate(settings: EvalSettings | None = None, *, seed: int | Sequence[int] = 0, tracker_settings=None,
             render_settings: RenderSettings | None = None, cam: CameraParams | None = None,
             progress: Callable[[str], None] | None = None,
             on_frames: Callable[[list[tuple]], None] | None = None,
             executor: Executor | None = None) -> dict:
    """Render every sequence of ``settings`` (deterministic in ``seed``) on the procedural mucosa
    and on each real photograph of ``settings.photos``, run the tracker and the reference
    trackers on the same frames, score them.

    ``seed``: one seed, or several: each seed's sequences (its own mucosa, target places and motions)
    are run in turn and every figure is pooled over them; the per-sequence keys then start with
    ``SEED:`` (``3:coffee/tip``).
    Returns a JSON-ready dict: ``overall`` (the tracker's metrics pooled over all scored frames,
    plus ``fps``, ``render_ms``, ``selection_failures`` and ``selection_warnings``: selections that
    succeeded with a :attr:`~targetlock.vision.tracker.Tracker.warning`, and ``tracked_in_view_unwarned``:
    the in-view frames tracked on the sequences without one), ``sequences`` (per sequence; keys
    ``name`` on the mucosa, ``photo/name`` on a photograph), ``content`` (pooled per texture:
    ``mucosa`` and each photo), ``references`` (per reference tracker: ``overall`` and
    ``content``, with ``speed_ratio`` = the tracker's fps / the reference's, and ``sequences``, keyed
    like the tracker's), ``settings``, ``seed`` (as given: an int or a list), ``rules``; with several
    seeds also ``per_seed`` (the tracker's metrics over each seed's frames, keyed by the seed as text).
    Trackers are timed on one OpenCV thread (``fps`` counts only ``update`` calls).
    ``tracker_settings``: the tracker's settings (a :class:`TrackerSettings` replaces
    ``settings.feature``, and the result's ``settings`` show it; a :class:`MarkerSettings` is for
    ``tracker = "marker"``).
    ``on_frames``: called after each tracker ran on a sequence with its :data:`FRAME_COLUMNS` rows
    (to write them as the evaluation goes).
    ``executor`` (a :class:`concurrent.futures.Executor` of processes, e.g. a Dask client's
    ``get_executor()``): several seeds run on it at once, each on one OpenCV thread of its worker
    (``fps`` stays a one-core figure while the workers do not outnumber the cores); ``progress`` and
    ``on_frames`` then hear of a seed's sequences when the whole seed is done. The figures are the
    same as in this process.
    """
    cfg = settings or EvalSettings()
    if isinstance(tracker_settings, TrackerSettings):
        cfg = replace(cfg, feature=tracker_settings)
    cfg = validate(cfg)
    one_seed = isinstance(seed, (int, np.integer))
    seeds = (int(seed),) if one_seed else tuple(int(x) for x in seed)
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"seed = {seed!r}: one seed or a list of distinct seeds")
    cam = cam or endoscope_camera()
    rs = render_settings or RenderSettings(fresh_noise=True)
    keyed = len(seeds) > 1
    runs: dict[int, _SeedRun] = {}
    if executor is None or not keyed:
        for sd in seeds:
            runs[sd] = _run_seed(cfg, sd, keyed, tracker_settings, cam, rs, progress, on_frames)
    else:
        collect = on_frames is not None
        jobs = {executor.submit(_run_seed, cfg, sd, keyed, tracker_settings, cam, rs, None, None, collect): sd
                for sd in seeds}
        for fut in as_completed(jobs):
            run = runs[jobs[fut]] = fut.result()
            if on_frames is not None:
                on_frames(run.rows)
            if progress:
                for key, m in run.sequences.items():
                    progress(_progress_line(key, m))
            run.rows = []
    # merged in seed order (the result does not depend on which worker finished first)
    per_seq = {k: m for sd in seeds for k, m in runs[sd].sequences.items()}
    ref_seq = {who: {k: m for sd in seeds for k, m in runs[sd].references[who].items()} for who in cfg.references}
    all_contents = runs[seeds[0]].contents
    t_render = sum(r.render_s for r in runs.values())
    n_render = sum(r.rendered for r in runs.values())

    def pool(who: str, which: list[str], of: tuple[int, ...] = seeds) -> dict:
        """``who``'s figures over the textures ``which`` of the seeds ``of``."""
        return _Pool.score([runs[sd].pooled[(who, c)] for sd in of for c in which], cfg.threshold_px)

    overall = pool("tracker", all_contents)
    overall["render_ms"] = 1e3 * t_render / max(n_render, 1)
    refs = {}
    for who in cfg.references:
        o = pool(who, all_contents)
        o["speed_ratio"] = overall["fps"] / o["fps"] if o["fps"] > 0 else float("nan")
        refs[who] = {"overall": o, "content": {c: pool(who, [c]) for c in all_contents}, "sequences": ref_seq[who]}
    cfg_d = asdict(cfg)
    for k in ("sequences", "photos", "references"):
        cfg_d[k] = list(getattr(cfg, k))
    out = {"overall": overall, "sequences": per_seq, "content": {c: pool("tracker", [c]) for c in all_contents},
           "references": refs, "photo_licences": {c: PHOTOS[c] for c in all_contents if c in PHOTOS},
           "settings": cfg_d, "seed": seeds[0] if one_seed else list(seeds),
           "rules": "visible frame: correct if valid and error <= threshold; not visible (occluded/outside "
                    "the field of view): correct if not valid, or valid and error <= threshold"}
    if keyed:   # how much the figures vary from seed to seed
        out["per_seed"] = {str(sd): pool("tracker", all_contents, (sd,)) for sd in seeds}
    return out


def markdown_tables(result: dict) -> str:
    """The tables of ``docs/vision.md`` from an :func:`evaluate` result: per texture (the tracker and
    each reference; the pooled row), then per sequence with the references' delta_avg (bold: at
    least as high as every reference's on that sequence)."""
    refs = list(result["references"])
    names = {"mil": "MIL", "lk": "plain LK"}

    def fmt(v: float, spec: str) -> str:
        return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)

    def row(label: str, who: str, m: dict, bold: bool = False) -> str:
        b = "**" if bold else ""
        # a reference tracker has no loss-and-search mode: its "lost" frames are not comparable
        lost = fmt(m["fps_lost"], ".0f") if who == "feature" else "-"
        return (f"| {label} | {who} | {b}{fmt(m['median_px'], '.2f')}{b} | {fmt(m['p95_px'], '.2f')} | "
                f"{b}{m['tracked_fraction']:.3f}{b} | {b}{m['delta_avg']:.3f}{b} | {m['false_lock_fraction']:.3f} | "
                f"{fmt(m['fps'], '.0f')} | {lost} |")

    out = ["| texture | tracker | median px | p95 px | tracked | delta_avg | false lock | fps | fps while lost |",
           "|---|---|---|---|---|---|---|---|---|"]
    for c, m in result["content"].items():
        out.append(row(c, "feature", m))
        out += [row(c, names.get(w, w), result["references"][w]["content"][c]) for w in refs]
    out.append(row("all", "feature", result["overall"], bold=True))
    out += [row("all", names.get(w, w), result["references"][w]["overall"]) for w in refs]
    seq = ["", "| sequence | tracked | false lock | median px | delta_avg | "
           + " | ".join(f"{names.get(w, w)} delta_avg" for w in refs) + " | fps | fps while lost |",
           "|---|---|---|---|---|" + "---|" * len(refs) + "---|---|"]
    ahead = 0
    for key, m in result["sequences"].items():
        others = [result["references"][w]["sequences"][key]["delta_avg"] for w in refs]
        lead = all(m["delta_avg"] >= o for o in others)
        ahead += lead
        b = "**" if lead else ""
        seq.append(f"| {key} | {m['tracked_fraction']:.3f} | {m['false_lock_fraction']:.3f} | "
                   f"{fmt(m['median_px'], '.2f')} | {b}{m['delta_avg']:.3f}{b} | "
                   + " | ".join(f"{o:.3f}" for o in others)
                   + f" | {fmt(m['fps'], '.0f')} | {fmt(m['fps_lost'], '.0f')} |")
    seq.append("")
    sd = result["seed"]
    seeds = f"seed {sd}" if isinstance(sd, int) else "seeds " + ", ".join(map(str, sd))
    seq.append(f"delta_avg at least as high as every reference's on {ahead} of {len(result['sequences'])} sequences "
               f"({seeds}).")
    return "\n".join(out + seq) + "\n"
