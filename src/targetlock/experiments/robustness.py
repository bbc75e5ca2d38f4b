"""Robustness benchmark (``targetlock bench robustness``): an unknown scope at any working distance.

A seeded random set of cases, each a plant the controllers do NOT know: a scope drawn around one of
the presets (friction, slack or pretension, cable and tip stiffness, handle gain ±15 %, drive speed
and time constant), camera focal length ±10 %, video latency 0.25–0.6 s with 0–40 ms of frame-time jitter
(frames are stamped as a rig stamps them: arrival time minus the nominal 0.4 s), 15–25 fps, target distance
1–15 cm (log-uniform: the report's recommended 1–2 cm is well represented) with the path scaled to the
distance (the same angular motion), tracker noise and dropped frames, a random start bend, and one
of six target motions none of the controllers was tuned on:

* ``smooth``   — a random smooth path (three sines per axis);
* ``stops``    — waypoints with stops;
* ``move``     — a 2 cm move (at 12 cm; scaled) within 1 s, then rest;
* ``drift``    — slow drift;
* ``rotation`` — the shaft rotating ~10° about its axis (the scene turns about the base axis);
* ``step``     — a target appearing 100–180 px off centre, then rest.

Every controller runs with its **nominal** knowledge (preset ``calibrated``, 0.4 s, 12 cm) unless its
name ends in ``+oracle`` (then it gets the plant's truth). Scores per case: the rms and peak of the
true image error, where a sample with the target out of the image counts as the image's half
diagonal (so losing the target is never rewarded), the fraction of time out of view, and the rms of
the error over the last 3 s of the resting cases (``move`` and ``step``), and the target's motion in the
image over those 3 s (rms about its mean position: a sustained oscillation at rest shows there, a
steady offset does not), and the fraction of frames without a valid observation (``lost_fraction``:
out of view, dropped, or missed by the tracker), and with ``vision`` the tracker's own error
(median and p95 over the frames it reported with the target in view: a wrong lock shows there, a lost
target in ``lost_fraction``). Ratios are to PI (I = 300) on the same case.

A controller name ending in ``@N`` (``adaptive@2``) scores its N-th engagement on each case: the case
run N times engaging one and the same controller, each on a fresh twin, as a lock is engaged again and
again on one scope in a procedure (what ``adaptive`` keeps across engagements: the candidate scope and
the video delay it found; :func:`~targetlock.experiments.target_lock.run_engagements`).

``vision=True`` (``--vision``) runs every case through the camera: the twin renders each frame and the
feature tracker measures it (as ``targetlock run --vision``: the target selected where it is on the first
frame) instead of the ideal projection with noise and drops: the whole chain a lab runs, about 3x slower.
Each case's tissue is then seen 0-40 degrees from face-on (``scene.tissue_tilt_deg``, drawn apart from
the case's other draws; the ideal projection does not depend on it): a face-on plane mirrors the tip's
light at the image centre, right where the lock holds the target.
"""
from __future__ import annotations

import csv
import math
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from ..config import param, save_toml
from ..controllers import CONTROLLERS, ControllerConfig, KnowledgeConfig
from ..controllers.knowledge import KNOWLEDGE_SOURCES
from ..loop.runner import LoopConfig
from ..model.kinematics import tip_pose
from ..model.twin import PRESETS, twin_config
from ..rig.simulated import ObservationNoise
from .target_lock import RunConfig, run_engagements, run_target_lock

if TYPE_CHECKING:
    from .runfolder import RunFolder

__all__ = ["MOTIONS", "Case", "draw_cases", "split_name", "case_config", "write_waypoints", "score", "run_robustness", "summarise", "BENCH_CONTROLLERS",
           "CASE_COLUMNS", "DISTANCE_BANDS", "breakdown", "format_table", "format_breakdown", "RobustnessSpec", "check_seeds", "parse_seeds",
           "bench_robustness"]

MOTIONS = ("smooth", "stops", "move", "drift", "rotation", "step")
RESTING = ("move", "step")
BENCH_CONTROLLERS = ("pi", "pi-hc", "pi-hc2", "ik", "pi-smith", "pi-smith+oracle", "adaptive", "adaptive+oracle")
SAMPLE_DT = 0.05       # s, waypoint spacing of the generated paths


@dataclass(frozen=True)
class Case:
    """One random plant + target motion (everything a run needs, nothing the controller gets)."""
    index: int
    preset: str
    endoscope: dict        # overrides of the preset's endoscope parameters
    drive: dict
    camera: dict           # fx, fy, fps, latency
    distance: float        # m
    start_tip_deg: tuple[float, float]
    motion: str
    noise_px: float
    drop_probability: float
    waypoints: np.ndarray  # (n, 4): t, x, y, z offsets in the start camera frame (m)
    tissue_tilt_deg: tuple[float, float] = (0.0, 0.0)   # the rendered tissue's tilt (only seen with vision)

    def describe(self) -> str:
        return (f"case {self.index}: {self.motion}, preset {self.preset}, {100 * self.distance:.1f} cm, "
                f"latency {self.camera['latency']:.2f} s, {self.camera['fps']:.0f} fps")


def _smooth(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * u)


def _motion(kind: str, rng: np.random.Generator, d: float, seconds: float, start_tip: tuple[float, float],
            f_px: float) -> np.ndarray:
    """Target offsets (m, start camera frame) sampled every SAMPLE_DT over ``seconds``, scaled to ``d``."""
    t = np.arange(0.0, seconds + SAMPLE_DT, SAMPLE_DT)
    xyz = np.zeros((t.size, 3))
    start = 1.0
    if kind == "smooth":
        for ax in (0, 1):
            for _ in range(3):
                a = d * rng.uniform(0.05, 0.2)
                f = rng.uniform(0.03, 0.2)
                ph = rng.uniform(0, 2 * np.pi)
                xyz[:, ax] += a * (np.sin(2 * np.pi * f * (t - start) + ph) - np.sin(ph)) * (t >= start)
    elif kind == "stops":
        p = np.zeros(3)
        tk = start
        while tk < seconds:
            q = np.array([*rng.uniform(-0.5, 0.5, 2) * d, 0.0])
            move, stop = rng.uniform(1.0, 2.5), rng.uniform(0.5, 2.0)
            s = _smooth((t - tk) / move)[:, None]
            sel = t >= tk
            xyz[sel] = (p + s * (q - p))[sel]
            p, tk = q, tk + move + stop
    elif kind == "move":
        direction = rng.uniform(0, 2 * np.pi)
        amp = 0.02 * d / 0.12
        xyz[:, 0] = amp * math.cos(direction) * _smooth(t - start)
        xyz[:, 1] = amp * math.sin(direction) * _smooth(t - start)
    elif kind == "drift":
        direction = rng.uniform(0, 2 * np.pi)
        v = d * rng.uniform(0.02, 0.05)   # ≈ 1–3°/s
        xyz[:, 0] = v * math.cos(direction) * np.maximum(t - start, 0.0)
        xyz[:, 1] = v * math.sin(direction) * np.maximum(t - start, 0.0)
    elif kind == "rotation":
        # The endoscope rolls by theta about its base axis = the scene turns by -theta about it.
        theta = math.radians(rng.uniform(8.0, 12.0)) * rng.choice([-1.0, 1.0]) * _smooth((t - start) / rng.uniform(1.0, 3.0))
        pose = tip_pose(math.radians(start_tip[0]), math.radians(start_tip[1]), 0.12, 30)
        rot = pose[:3, :3]
        anchor = pose[:3, 3] + d * rot[:, 2]
        c, s = np.cos(-theta), np.sin(-theta)
        moved = np.stack([c * anchor[0] - s * anchor[1], s * anchor[0] + c * anchor[1], np.full_like(c, anchor[2])], 1)
        xyz = (moved - anchor) @ rot
    elif kind == "step":
        off = rng.uniform(100.0, 180.0)
        direction = rng.uniform(0, 2 * np.pi)
        xyz[:, 0] = off / f_px * d * math.cos(direction)
        xyz[:, 1] = off / f_px * d * math.sin(direction)
    else:
        raise ValueError(f"motion = {kind!r}; allowed: {', '.join(MOTIONS)}")
    return np.column_stack([t, xyz])


def draw_cases(n: int, seed: int, seconds: float = 12.0) -> list[Case]:
    """``n`` random cases from ``seed`` (the motions cycle so each appears equally often)."""
    rng = np.random.default_rng(seed)
    cases = []
    for i in range(n):
        u = lambda lo, hi: float(rng.uniform(lo, hi))  # noqa: E731
        preset = PRESETS[int(rng.integers(len(PRESETS)))]
        base = twin_config(preset).endoscope
        endo = {"mu_n": base.mu_n * u(0.75, 1.3), "friction_offset": base.friction_offset * u(0.75, 1.3),
                "mu_f": base.mu_f * u(0.75, 1.3), "cable_stiffness": base.cable_stiffness * u(0.7, 1.3),
                "tip_stiffness": base.tip_stiffness * u(0.75, 1.3), "cable_slack": base.cable_slack + u(-0.0003, 0.0003),
                "handle_radius": base.handle_radius * u(0.85, 1.15)}
        drive = {"time_constant": u(0.01, 0.04), "max_velocity_ticks": u(70000.0, 100000.0)}
        f_px = 300.0 * u(0.9, 1.1)
        camera = {"fx": f_px, "fy": f_px, "fps": u(15.0, 25.0), "latency": u(0.25, 0.6), "latency_jitter": u(0.0, 0.04)}
        d = float(math.exp(rng.uniform(math.log(0.01), math.log(0.15))))
        start = (u(-35.0, 35.0), u(-25.0, 25.0))
        motion = MOTIONS[i % len(MOTIONS)]
        wp = _motion(motion, rng, d, seconds, start, f_px)
        # The tissue seen at 0-40 degrees from face-on, in any direction: drawn apart from the rest so
        # that adding it left every other draw of a seed as it was.
        tilt_rng = np.random.default_rng([seed, i, 1])
        tilt, about = math.radians(tilt_rng.uniform(0.0, 40.0)), tilt_rng.uniform(0.0, 2.0 * math.pi)
        tilt_deg = (math.degrees(tilt * math.cos(about)), math.degrees(tilt * math.sin(about)))
        cases.append(Case(index=i, preset=preset, endoscope=endo, drive=drive, camera=camera, distance=d,
                          start_tip_deg=start, motion=motion, noise_px=u(0.0, 1.5), drop_probability=u(0.0, 0.08),
                          waypoints=wp, tissue_tilt_deg=tilt_deg))
    return cases


def write_waypoints(case: Case, path: Path) -> None:
    """The case's target path as the waypoints CSV its run config names (t s, x y z m)."""
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "x", "y", "z"])
        w.writerows(case.waypoints.tolist())


def split_name(controller: str) -> tuple[str, str, int]:
    """A benchmark controller name ``kind[+source][@N]`` as (kind, knowledge source or "", engagement N:
    1 without ``@``, 0 when what follows ``@`` is not a whole number; :func:`parse_controllers` checks it)."""
    name, at, n = controller.partition("@")
    kind, _, source = name.partition("+")
    if not at:
        return kind, source, 1
    return kind, source, int(n) if n.isdigit() else 0


def case_config(case: Case, controller: str, waypoints_file: Path, seconds: float, seed: int,
                vision: bool = False) -> RunConfig:
    """The run of ``controller`` on ``case``: a controller kind, with ``+source`` a knowledge source
    (:data:`~targetlock.controllers.knowledge.KNOWLEDGE_SOURCES`, e.g. ``adaptive+oracle`` for the
    plant's truth, ``adaptive+oracle-endoscope`` for its endoscope only); an ``@N`` suffix (the engagement
    scored, :func:`score_run`) does not change the run's config. ``vision``: rendered frames and the feature
    tracker instead of the ideal projection (its noise and drops are then the tracker's)."""
    kind, source, _ = split_name(controller)
    twin = twin_config(case.preset, {"endoscope": case.endoscope, "drive": case.drive, "camera": case.camera,
                                     "scene": {"path": "waypoints", "waypoints_file": str(waypoints_file),
                                               "distance": case.distance, "start_tip_deg": case.start_tip_deg,
                                               "tissue_tilt_deg": case.tissue_tilt_deg}})
    return RunConfig(twin=twin, controller=ControllerConfig(kind=kind),
                     knowledge=KnowledgeConfig(source=source or "nominal"),
                     loop=LoopConfig(seconds=seconds, metrics_after=1.0), vision=vision,
                     tracker=ObservationNoise(noise_px=case.noise_px, drop_probability=case.drop_probability,
                                              seed=seed + case.index),
                     seed=seed + case.index)


def score(data: np.ndarray, width: int, height: int, after: float, rest_window: float = 3.0) -> dict:
    """Per-case scores (px) from recorded rows (target_lock.COLUMNS)."""
    t, err = data[:, 0], data[:, 3]
    sel = t >= after
    out = ~np.isfinite(err)
    lost_px = 0.5 * math.hypot(width, height)
    e = np.where(out, lost_px, err)[sel]
    last = t >= t[-1] - rest_window
    rest = np.where(out, lost_px, err)[last]
    # Oscillation at rest: how much the target still moves in the image (rms about its mean position);
    # a target out of view in the window counts as the half diagonal.
    xy = data[last][:, 1:3]
    motion = lost_px if np.any(out[last]) else float(np.sqrt(np.mean(np.sum((xy - xy.mean(axis=0)) ** 2, axis=1))))
    return {"rms_px": float(np.sqrt(np.mean(e ** 2))), "peak_px": float(np.max(e)),
            "out_of_view": float(np.mean(out[sel])), "rest_rms_px": float(np.sqrt(np.mean(rest ** 2))),
            "rest_motion_px": motion}


def score_run(cfg: RunConfig, engagement: int = 1) -> dict:
    """Run one case's config and score it (:func:`score`, with the run's ``lost_fraction`` and, through
    the camera, the tracker's own error: :data:`SCORES`); a task of its own on a Dask worker.
    ``engagement`` N > 1: the case is run N times engaging the same controller
    (:func:`~targetlock.experiments.target_lock.run_engagements`, the lock engaged again on the same
    scope) and the N-th run is scored."""
    s = run_target_lock(cfg) if engagement == 1 else run_engagements(cfg, engagement)[-1]
    seen = s.get("vision", {})
    return {**score(s["_data"], cfg.twin.camera.width, cfg.twin.camera.height, cfg.loop.metrics_after),
            "lost_fraction": float(s["lost_fraction"]),
            "tracker_median_px": float(seen.get("tracker_median_px", math.nan)),
            "tracker_p95_px": float(seen.get("tracker_p95_px", math.nan))}


SCORES = ("rms_px", "peak_px", "out_of_view", "rest_rms_px", "rest_motion_px", "lost_fraction",
          "tracker_median_px", "tracker_p95_px")   # of :func:`score_run`; the tracker's error only with vision
CASE_COLUMNS = ["seed", "case", "controller", "motion", "preset", "distance_m", "latency_s", "fps", *SCORES]
"""Columns of a per-case row (:func:`run_robustness`'s ``on_result``, ``bench robustness --out``'s ``cases.csv``)."""


def _as_seeds(seed: int | Sequence[int]) -> tuple[int, ...]:
    """One seed or several, as a tuple."""
    return (int(seed),) if isinstance(seed, (int, np.integer)) else tuple(int(s) for s in seed)


def run_robustness(n_cases: int = 60, seed: int | Sequence[int] = 0, controllers: tuple[str, ...] = BENCH_CONTROLLERS,
                   seconds: float = 12.0, progress: bool = False, workers: int | None = None,
                   cases_folder: Path | None = None, on_result: Callable[[dict], None] | None = None,
                   vision: bool = False) -> dict:
    """Run every controller on every case of one random set (``seed``) or several (a sequence of
    seeds, ``n_cases`` each); returns per-case scores and the per-controller summary over all cases
    (:func:`summarise`), with ``sets`` (the summary of each set, by seed) and ``breakdown``
    (:func:`breakdown`) when there are several.

    ``workers``: run the cases on a local Dask cluster of that many single-threaded worker processes
    (the sweep engine, :func:`targetlock.experiments.sweep.dask_client`) instead of in this process.
    ``cases_folder``: keep each case's waypoints there (``seed-S-case-NNN.csv``, else in a temporary
    folder) with its run config for PI (``seed-S-case-NNN.toml``: ``targetlock run --config`` runs the
    case again, ``--controller`` / ``--set knowledge.source=...`` with another controller). ``on_result(row)``
    is called as each run finishes, with a row of :data:`CASE_COLUMNS`. ``vision``: every run through the
    rendered view and the feature tracker (:func:`case_config`)."""
    seeds = _as_seeds(seed)
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"run_robustness: seeds {list(seeds)}; allowed: one or more, each once")
    if "pi" not in controllers:
        controllers = ("pi",) + tuple(controllers)
    sets = [(s, draw_cases(n_cases, s, seconds)) for s in seeds]
    per: dict[str, list[dict]] = {c: [] for c in controllers}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="targetlock-robustness-") as tmp:
        folder = Path(cases_folder) if cases_folder is not None else Path(tmp)
        jobs = []                      # (seed, case, controller, config), in set, case, controller order
        for s, cases in sets:
            for case in cases:
                path = folder / f"seed-{s}-case-{case.index:03d}.csv"
                write_waypoints(case, path)
                if cases_folder is not None:   # kept: a row of the results can be run again
                    save_toml(case_config(case, "pi", path.resolve(), seconds, s, vision), path.with_suffix(".toml"))
                jobs += [(s, case, c, case_config(case, c, path, seconds, s, vision)) for c in controllers]
        engagement = {c: split_name(c)[2] for c in controllers}
        scores: list[dict] = [{} for _ in jobs]     # filled in as the runs finish (any order on Dask)

        def done(k: int, sc: dict) -> None:
            s, case, c, _ = jobs[k]
            sc.update(seed=s, case=case.index, motion=case.motion, distance=case.distance)
            scores[k] = sc
            if on_result is not None:
                on_result({"seed": s, "case": case.index, "controller": c, "motion": case.motion, "preset": case.preset,
                           "distance_m": case.distance, "latency_s": case.camera["latency"], "fps": case.camera["fps"],
                           **{name: sc[name] for name in SCORES}})

        if workers:
            from distributed import as_completed

            from .sweep import dask_client
            with dask_client(None, workers) as client:
                futures = {client.submit(score_run, j[3], engagement[j[2]], pure=False): k for k, j in enumerate(jobs)}
                for fut in as_completed(futures):
                    done(futures[fut], fut.result())
        else:
            for k, j in enumerate(jobs):
                done(k, score_run(j[3], engagement[j[2]]))
        for k, (s, case, c, _) in enumerate(jobs):
            per[c].append(scores[k])
            if progress and c == controllers[-1]:
                row = scores[k - len(controllers) + 1:k + 1]
                print(f"seed {s} " + case.describe() + ": " +
                      ", ".join(f"{name} {r['rms_px']:.0f}" for name, r in zip(controllers, row)), flush=True)
    out = {"seed": seeds[0] if len(seeds) == 1 else list(seeds), "cases": n_cases, "seconds": seconds, "vision": vision,
           "wall_seconds": time.perf_counter() - t0, "workers": workers or 0, "per_case": per, "summary": summarise(per)}
    if len(seeds) > 1:
        out["sets"] = {s: summarise({c: [r for r in rows if r["seed"] == s] for c, rows in per.items()}) for s in seeds}
        out["breakdown"] = breakdown(per)
    return out


def summarise(per: dict[str, list[dict]]) -> dict:
    """Per controller: median / p95 / worst rms and peak, out-of-view cases, ratios to PI on the same case."""
    pi = per["pi"]
    out = {}
    for c, rows in per.items():
        rms = np.array([r["rms_px"] for r in rows])
        peak = np.array([r["peak_px"] for r in rows])
        ratio = rms / np.array([r["rms_px"] for r in pi])
        left = np.array([r["out_of_view"] > 0 for r in rows])
        pi_kept = np.array([r["out_of_view"] == 0 for r in pi])
        near = np.array([r["distance"] <= 0.02 for r in rows])
        in_view_near = 1.0 - np.array([r["out_of_view"] for r in rows])[near]
        rest = np.array([r["rest_rms_px"] for r in rows if r["motion"] in RESTING])
        motion = np.array([r["rest_motion_px"] for r in rows if r["motion"] in RESTING])
        out[c] = {"rms_median": float(np.median(rms)), "rms_p95": float(np.percentile(rms, 95)), "rms_worst": float(rms.max()),
                  "peak_median": float(np.median(peak)), "peak_p95": float(np.percentile(peak, 95)),
                  "peak_worst": float(peak.max()), "left_image_fraction": float(left.mean()),
                  "left_where_pi_kept": int(np.sum(left & pi_kept)),
                  "ratio_to_pi_median": float(np.median(ratio)), "ratio_to_pi_worst": float(ratio.max()),
                  "median_ratio_of_medians": float(np.median(rms) / np.median([r["rms_px"] for r in pi])),
                  "cases_worse_than_pi_by_10pct": int(np.sum(ratio > 1.1)),
                  "in_view_near_median": float(np.median(in_view_near)) if in_view_near.size else math.nan,
                  "rest_rms_worst": float(rest.max()) if rest.size else math.nan,
                  "rest_motion_median": float(np.median(motion)) if motion.size else math.nan,
                  "rest_motion_worst": float(motion.max()) if motion.size else math.nan,
                  "lost_fraction_median": float(np.median([r["lost_fraction"] for r in rows])),
                  "lost_fraction_worst": float(max(r["lost_fraction"] for r in rows))}
    return out


DISTANCE_BANDS = {"1-3 cm": (0.0, 0.03), "3-6 cm": (0.03, 0.06), "6-10 cm": (0.06, 0.10), "10-15 cm": (0.10, math.inf)}
"""Target distance bands (m, [lo, hi)) of :func:`breakdown`: near the target, where J is 4-12x the 12-cm
prior's and the scope's dead travel decides, to the report's 12 cm, where PI's gain was tuned."""


def breakdown(per: dict[str, list[dict]]) -> dict:
    """Per controller, by target distance (:data:`DISTANCE_BANDS`) and by motion (:data:`MOTIONS`): the
    number of cases, the median rms (px), the median per-case ratio to PI and the cases worse than
    1.1x PI. Where a controller loses is rarely spread evenly: near cases and steps are where the
    estimates are still wrong, far drifts where PI's gain is right."""
    pi = np.array([r["rms_px"] for r in per["pi"]])
    dist = np.array([r["distance"] for r in per["pi"]])
    motion = np.array([r["motion"] for r in per["pi"]])
    groups = {**{band: (dist >= lo) & (dist < hi) for band, (lo, hi) in DISTANCE_BANDS.items()},
              **{m: motion == m for m in MOTIONS}}
    out: dict[str, dict] = {}
    for c, rows in per.items():
        rms = np.array([r["rms_px"] for r in rows])
        ratio = rms / pi
        out[c] = {g: {"cases": int(sel.sum()),
                      "rms_median": float(np.median(rms[sel])) if sel.any() else math.nan,
                      "ratio_to_pi_median": float(np.median(ratio[sel])) if sel.any() else math.nan,
                      "cases_worse_than_pi_by_10pct": int(np.sum(ratio[sel] > 1.1))}
                  for g, sel in groups.items()}
    return out


def format_breakdown(by: dict) -> list[str]:
    """:func:`breakdown` as a table: per controller and group, median rms / per-case ratio to PI
    (cases worse than 1.1x PI)."""
    groups = list(next(iter(by.values())))
    w = max([18] + [len(c) for c in by])
    title = "median rms/xPI (>1.1xPI)"
    w = max(w, len(title))
    cells = {c: [f"{v['rms_median']:.1f}/{v['ratio_to_pi_median']:.2f} ({v['cases_worse_than_pi_by_10pct']})"
                 if v["cases"] else "-" for v in g.values()] for c, g in by.items()}
    widths = [max(len(g), *(len(cells[c][k]) for c in by)) for k, g in enumerate(groups)]
    first = next(iter(by.values()))
    lines = [f"{title:<{w}} " + " ".join(f"{g:>{widths[k]}}" for k, g in enumerate(groups)),
             f"{'cases':<{w}} " + " ".join(f"{first[g]['cases']:>{widths[k]}}" for k, g in enumerate(groups))]
    lines += [f"{c:<{w}} " + " ".join(f"{cell:>{widths[k]}}" for k, cell in enumerate(cells[c])) for c in by]
    return lines


def format_table(summary: dict) -> list[str]:
    w = max([18] + [len(c) for c in summary])
    lines = [f"{'controller':<{w}} {'rms med':>7} {'xPI med':>7} {'p95':>6} {'worst':>6} | {'peak med':>8} {'p95':>6} {'worst':>6} | "
             f"{'left img':>8} {'PI kept':>7} {'vs PI med':>9} {'worst':>6} {'>1.1xPI':>7} | {'1-2cm in view':>13} {'rest rms':>8} {'rest motion med/worst':>21} | "
             f"{'unseen med/worst':>16}"]
    for c, s in summary.items():
        lines.append(f"{c:<{w}} {s['rms_median']:>7.1f} {s['median_ratio_of_medians']:>7.2f} {s['rms_p95']:>6.0f} {s['rms_worst']:>6.0f} | "
                     f"{s['peak_median']:>8.0f} {s['peak_p95']:>6.0f} {s['peak_worst']:>6.0f} | "
                     f"{100 * s['left_image_fraction']:>7.0f}% {s['left_where_pi_kept']:>7d} {s['ratio_to_pi_median']:>9.2f} {s['ratio_to_pi_worst']:>6.2f} "
                     f"{s['cases_worse_than_pi_by_10pct']:>7d} | {100 * s['in_view_near_median']:>12.0f}% "
                     f"{s['rest_rms_worst']:>8.1f} {s['rest_motion_median']:>10.1f} / {s['rest_motion_worst']:>8.1f} | "
                     f"{100 * s['lost_fraction_median']:>6.0f}% / {100 * s['lost_fraction_worst']:>6.0f}%")
    return lines


def parse_controllers(names: str) -> tuple[str, ...]:
    """A comma-separated list of benchmark controller names (``kind``, ``kind+source``, either with
    ``@N``: its N-th engagement on the case, 2-10), checked."""
    from ..config import ConfigError
    out = tuple(n.strip() for n in names.split(",") if n.strip())
    if not out:
        raise ConfigError("--controllers is empty; give e.g. pi,adaptive,adaptive+oracle")
    for name in out:
        kind, source, n = split_name(name)
        if kind not in CONTROLLERS or ("+" in name and source not in KNOWLEDGE_SOURCES) or \
                ("@" in name and not 2 <= n <= 10):
            raise ConfigError(f"--controllers: {name!r}; allowed: a controller {', '.join(CONTROLLERS)}, optionally "
                              f"+ a knowledge source {', '.join(s for s in KNOWLEDGE_SOURCES if s != 'nominal')}, "
                              f"optionally @N for its N-th engagement on the case (N 2-10, e.g. adaptive@2)")
    return out


@dataclass(frozen=True)
class RobustnessSpec:
    """What ``targetlock bench robustness`` ran (the run folder's ``config.toml``)."""
    cases: int = param(60, lo=1, hi=10000, doc="random cases per set")
    seeds: tuple[int, ...] = param((0,), doc="seeds of the random sets (each its own set of cases)")
    controllers: tuple[str, ...] = param(BENCH_CONTROLLERS, doc="controllers, kind[+knowledge source][@engagement]; pi always runs")
    seconds: float = param(12.0, unit="s", lo=1.0, hi=3600.0, doc="length of each run")
    workers: int = param(0, lo=0, hi=512, doc="local Dask worker processes (0: in this process)")
    vision: bool = param(False, doc="rendered frames and the feature tracker instead of the ideal projection")


def check_seeds(seeds: tuple[int, ...], text: str | None = None) -> tuple[int, ...]:
    """``seeds`` if there is at least one, each in [0, 2^63) and named once; else a ConfigError naming
    ``--seed`` (as the user wrote it: ``text``)."""
    from ..config import ConfigError
    given = text if text is not None else ",".join(map(str, seeds))
    if not seeds or any(not 0 <= s < 2 ** 63 for s in seeds):
        raise ConfigError(f"--seed = {given!r}; allowed: a whole number in [0, 2^63) or a comma-separated list of them")
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"--seed = {given!r}: a seed is named twice (the same set would count twice)")
    return seeds


def parse_seeds(text: str) -> tuple[int, ...]:
    """``--seed``: one seed or a comma-separated list (``0,23,204``), checked (:func:`check_seeds`)."""
    from ..config import ConfigError
    try:
        seeds = tuple(int(p) for p in str(text).split(",") if p.strip())
    except ValueError:
        raise ConfigError(f"--seed = {text!r}; allowed: a whole number in [0, 2^63) or a comma-separated list of them") from None
    return check_seeds(seeds, text)


def bench_robustness(n_cases: int = 60, seed: int | Sequence[int] = 0, workers: int | None = None,
                     controllers: tuple[str, ...] = BENCH_CONTROLLERS, out: str | Path | None = None,
                     overwrite: bool = False, vision: bool = False) -> dict:
    """``targetlock bench robustness``: print the table; returns the summary (the JSON line).

    Several seeds run several random sets in one go (one Dask cluster): the table is pooled over all
    cases, with each set's median and their mean, and a breakdown by distance and motion. ``out``: a run
    folder with ``config.toml``, ``cases.csv`` (one row per run, :data:`CASE_COLUMNS`, appended as
    runs finish, so a killed benchmark keeps them), each case's waypoints (``cases/``) and
    ``summary.json``. ``vision``: through the rendered view and the feature tracker (:func:`case_config`)."""
    from ..config import ConfigError
    from .runfolder import RunFolder
    seeds = check_seeds(_as_seeds(seed))
    if not 1 <= n_cases <= 10000:
        raise ConfigError(f"--cases = {n_cases}; allowed: [1, 10000]")
    if workers is not None and not 1 <= workers <= 512:
        raise ConfigError(f"--workers = {workers}; allowed: [1, 512]")
    if out is None:
        return _bench(n_cases, seeds, workers, controllers, None, vision)
    spec = RobustnessSpec(cases=n_cases, seeds=seeds, controllers=tuple(controllers), workers=workers or 0,
                          vision=vision)
    with RunFolder("robustness", spec, out, overwrite=overwrite) as folder:
        return _bench(n_cases, seeds, workers, controllers, folder, vision)


def _bench(n_cases: int, seeds: tuple[int, ...], workers: int | None, controllers: tuple[str, ...],
           folder: RunFolder | None, vision: bool) -> dict:
    """:func:`bench_robustness` after its checks, into the run folder ``folder`` (or none)."""
    if folder is None:
        r = run_robustness(n_cases, seeds, controllers=controllers, workers=workers, vision=vision)
    else:
        (folder.path / "cases").mkdir()
        with folder.file("cases.csv").open("w", newline="") as fh:
            table = csv.DictWriter(fh, CASE_COLUMNS)
            table.writeheader()

            def on_result(row: dict) -> None:
                table.writerow(row)
                fh.flush()
            r = run_robustness(n_cases, seeds, controllers=controllers, workers=workers,
                               cases_folder=folder.path / "cases", on_result=on_result, vision=vision)
    print(f"robustness: {n_cases} random cases per set (seed {', '.join(map(str, seeds))}), {r['seconds']:g} s each, "
          f"nominal knowledge unless '+oracle' (+oracle-<item>: that item's truth only); "
          + ("through the rendered view and the feature tracker; " if vision else "")
          + "rms/peak in px (out of view = image half diagonal), ratios to PI (I = 300)")
    print("\n".join(format_table(r["summary"])))
    result = {"seed": r["seed"], "cases": n_cases, "seconds_per_case": r["seconds"], "vision": vision,
              "wall_seconds": r["wall_seconds"],
              "controllers": r["summary"]}
    if len(seeds) > 1:
        sets = r["sets"]
        means = {c: float(np.mean([sets[s][c]["rms_median"] for s in seeds])) for c in r["summary"]}
        w = max([18] + [len(c) for c in means])
        print(f"{'median rms per set':<{w}} " + " ".join(f"{s:>7}" for s in seeds) + f" {'mean':>7}")
        for c, m in means.items():
            print(f"{c:<{w}} " + " ".join(f"{sets[s][c]['rms_median']:>7.1f}" for s in seeds) + f" {m:>7.2f}")
        print("\n".join(format_breakdown(r["breakdown"])))
        result.update(mean_of_set_medians=means, sets={str(s): v for s, v in sets.items()}, breakdown=r["breakdown"])
    print(f"({r['wall_seconds']:.0f} s " + (f"on {workers} Dask workers)" if workers else "on one core)"))
    if folder is not None:
        folder.write_summary(result)
        result["run_folder"] = str(folder.path)
        print(f"run folder: {folder.path}")
    return result
