"""Subcommands of the closed loop (run, step-response, compare), registered into :mod:`targetlock.cli`."""
from __future__ import annotations

import argparse
import csv
import errno
import logging
import os
import sys
from dataclasses import dataclass
from pathlib import Path

from .cli import _common, _out_options, cli_overrides, command, config_flag, option_values
from .config import ConfigError, field_info, param, replace_path
from .errors import DeviceError
from .presets import PRESETS

log = logging.getLogger(__name__)

PATH_CHOICES = ("linear", "ellipse", "step", "static")


def _loop_options(p: argparse.ArgumentParser) -> None:
    from .experiments.target_lock import RunConfig
    _common(p)
    p.add_argument("--path", metavar="PATH", help=f"target path: {', '.join(PATH_CHOICES)} or a CSV file (t,x,y,z)")
    for flag, dotted in (("--latency", "twin.camera.latency"), ("--assumed-latency", "knowledge.latency"),
                         ("--fps", "twin.camera.fps"),
                         ("--i-gain", "controller.i_gain"), ("--p-gain", "controller.p_gain"),
                         ("--hc-width", "controller.hc_width"), ("--seconds", "loop.seconds"),
                         ("--noise", "tracker.noise_px"), ("--drop", "tracker.drop_probability"),
                         ("--outliers", "tracker.outlier_probability"), ("--realtime", "realtime"),
                         ("--vision", "vision"), ("--tracker", "vision_tracker")):
        config_flag(p, flag, RunConfig, dotted)
    config_flag(p, "--seed", RunConfig, "seed", help="random seed of the run and of the tracker noise "
                                                     "(seed and tracker.seed)")


def _overrides(args: argparse.Namespace) -> dict:
    """Nested config overrides from the loop flags and --set."""
    from .model.twin import merge
    o = cli_overrides(args)
    if args.path:
        if args.path in PATH_CHOICES:
            o = merge(o, {"twin": {"scene": {"path": args.path}}})
        else:
            o = merge(o, {"twin": {"scene": {"path": "waypoints", "waypoints_file": str(Path(args.path).resolve())}}})
    seed = o.get("seed")
    if seed is not None and "seed" not in o.get("tracker", {}):
        o = merge(o, {"tracker": {"seed": seed}})
    return o


def _loop_config(args: argparse.Namespace, base: dict | None = None):
    """The validated run config of a loop command; ``--tracker`` without vision is refused."""
    from .experiments.common import build_config
    from .experiments.target_lock import RunConfig
    from .model.twin import merge
    cfg = build_config(RunConfig, config_file=args.config, preset=args.preset, overrides=merge(base or {}, _overrides(args)))
    if vars(args).get("set:vision_tracker") is not None and not cfg.vision:
        raise ConfigError(f"--tracker {cfg.vision_tracker} needs vision: add --vision (or vision = true in the config)")
    return cfg


def _each_valid(cfg, dotted: str, values, flag: str) -> list:
    """Validate each value of a list option as config field ``dotted``; one ConfigError lists every bad one."""
    errors = []
    for v in values:
        try:
            replace_path(cfg, dotted, v)
        except ConfigError as exc:
            errors += exc.errors
    if errors:
        raise ConfigError(errors=errors, where=flag)
    return list(values)


def _progress(total: int, unit: str):
    from tqdm import tqdm
    return tqdm(total=total, unit=unit, file=sys.stderr, leave=False, disable=None)


def _print_summary(s: dict) -> None:
    print(f"target lock: {s['controller']} on the {s['path']} path, latency {s['latency_s']:g} s, {s['fps']:g} fps, "
          f"preset {s['preset']!r}")
    print(f"  controller knowledge: {s['knowledge']}")
    if s.get("target_losses"):
        print(f"  target lost {s['target_losses']} time(s): the lock held the motors until it was seen again")
    print(f"  tracking error after warm-up: rms {s['rms_px']:.1f} px, peak {s['peak_px']:.1f} px, "
          f"p95 {s['p95_px']:.1f} px, mean {s['mean_px']:.1f} px")
    if s.get("tip_range_deg"):
        print(f"  tip worked between {s['tip_range_deg'][0]:.0f} and {s['tip_range_deg'][1]:.0f} deg; "
              f"frames lost {100 * s['lost_fraction']:.1f} %")
    print(f"  {s['sim_seconds']:g} s simulated in {s['wall_seconds']:.2f} s ({s['realtime_factor']:.0f}x real time)")


# --------------------------------------------------------------------------------------------- run
def _run_options(p: argparse.ArgumentParser) -> None:
    from .experiments.target_lock import RunConfig
    config_flag(p, "--controller", RunConfig, "controller.kind")
    p.add_argument("--rig", metavar="FILE", help="run on the rig this file describes (CANopen drives, NatNet, "
                                                 "observations) on the wall clock, instead of the in-process twin")
    p.add_argument("--video", metavar="FILE.mp4", help="with --vision: write the endoscope view with the tracked "
                                                       "target, the image centre and the error drawn on it")
    _loop_options(p)


@command("run", "closed-loop target lock on the digital twin: the main job")(_run_options)
def _run(args: argparse.Namespace) -> int:
    from .experiments.common import print_json_last
    from .experiments.runfolder import RunFolder, check_writable
    from .experiments.target_lock import run_target_lock

    cfg = _loop_config(args)
    if args.video and not cfg.vision:
        raise ConfigError("--video needs --vision (frames are rendered only with vision)")
    if args.video:
        check_writable(args.video, "--video")      # before any work, not after the run
    hw = None
    if args.rig:
        from .interfaces.rigfile import load_rig_file
        hw = load_rig_file(args.rig)          # validate before anything moves or a folder is made
    with RunFolder("run", cfg, args.out, overwrite=args.overwrite) as run:
        cfg = run.config                      # input files now point at the run folder's copies
        if hw is not None:
            from .config import save_toml
            from .rig.hardware import HardwareRig
            save_toml(hw, run.file("rig.toml"))
            with HardwareRig(hw, cfg.twin.camera, loop_rate=cfg.loop.rate,
                             tracker_settings=cfg.feature_tracker) as rig:
                s = run_target_lock(cfg, run, progress=True, rig=rig)
        else:
            s = run_target_lock(cfg, run, progress=True, video=args.video)
        log.info("run finished: rms %.1f px, peak %.1f px", s["rms_px"], s["peak_px"])
    _print_summary(s)
    if "vision" in s:
        v = s["vision"]
        print(f"  vision: tracker error median {v['tracker_median_px']:.2f} px, p95 {v['tracker_p95_px']:.2f} px; "
              f"render {v['render_ms']:.1f} ms, track {v['track_ms']:.1f} ms per frame"
              + (f"; video {args.video}" if args.video else ""))
    if "timing_ms" in s:
        tm = s["timing_ms"]
        print(f"  loop period jitter p50 {tm['period_jitter_p50']:.2f} ms, p99 {tm['period_jitter_p99']:.2f} ms, "
              f"max {tm['period_jitter_max']:.2f} ms; frame arrival to setpoint sent p50 "
              f"{tm['frame_to_setpoint_p50']:.2f} ms, p99 {tm['frame_to_setpoint_p99']:.2f} ms")
    print(f"  run folder: {run.path}  (plots: {run.file('tracking.png')})")
    if args.json:
        print_json_last({k: v for k, v in s.items() if not k.startswith("_")})
    return 0


# --------------------------------------------------------------------------------------------- step response
def _step_options(p: argparse.ArgumentParser) -> None:
    from .experiments.target_lock import RunConfig
    config_flag(p, "--controller", RunConfig, "controller.kind", help="controller (default pi)")
    _, meta, _ = field_info(RunConfig, "controller.i_gain")
    p.add_argument("--i-values", type=float, nargs="+", metavar="I", default=[100, 200, 300, 400, 500],
                   help=f"I values to compare ({meta['unit']}), each checked like controller.i_gain; "
                        "default 100 200 300 400 500")
    _loop_options(p)


@command("step-response", "step responses for several I values (report §5.2, Fig. 6.1)")(_step_options)
def _step(args: argparse.Namespace) -> int:
    from .experiments.common import print_json_last
    from .experiments.runfolder import RunFolder
    from .experiments.step_response import plot_step_responses, run_step_responses

    base = {"twin": {"scene": {"path": "step", "start_tip_deg": [0.0, 0.0], "start_delay": 0.0}},
            "controller": {"kind": "pi"}, "loop": {"seconds": 5.0, "metrics_after": 0.0}}
    cfg = _loop_config(args, base)
    i_values = _each_valid(cfg, "controller.i_gain", args.i_values, "--i-values")
    with RunFolder("step-response", cfg, args.out, overwrite=args.overwrite) as run:
        cfg = run.config
        results = []
        with _progress(len(i_values), "response") as bar:
            for i in i_values:
                results += run_step_responses(cfg, [i])
                bar.update(1)
        with run.timeseries(["i_gain", "t", "offset_x_px"]) as ts:
            for r in results:
                for t, x in zip(r["_t"], r["_x"]):
                    ts.write([r["i_gain"], t, x])
        plot_step_responses(results, cfg, run.file("step_response.png"))
        rows = [{k: v for k, v in r.items() if not k.startswith("_")} for r in results]
        summary = {"step_px": cfg.twin.scene.step_offset_px[0], "responses": rows, "run_folder": str(run.path)}
        run.write_summary(summary)
    print(f"step response from {cfg.twin.scene.step_offset_px[0]:g} px, {cfg.controller.kind}, "
          f"latency {cfg.twin.camera.latency:g} s")
    print(f"{'I':>6} {'rise (s)':>9} {'overshoot (px)':>15} {'overshoot (%)':>14} {'settling (s)':>13}")
    for r in rows:
        print(f"{r['i_gain']:>6g} {r['rise_time_s']:>9.2f} {r['overshoot_px']:>15.1f} {r['overshoot_pct']:>14.1f} "
              f"{r['settling_time_s']:>13.2f}")
    print(f"run folder: {run.path}  (plot: {run.file('step_response.png')})")
    if args.json:
        print_json_last(summary)
    return 0


# --------------------------------------------------------------------------------------------- compare
def _compare_options(p: argparse.ArgumentParser) -> None:
    from .controllers.base import CONTROLLERS
    # The report's three (Fig. 6.4) and the run's default, so a comparison shows what `run` uses.
    p.add_argument("--controllers", nargs="+", choices=CONTROLLERS, default=["pi", "pi-hc", "ik", "adaptive"],
                   help="controllers to compare (default pi pi-hc ik adaptive)")
    p.add_argument("--latencies", type=float, nargs="+", metavar="S",
                   help="latencies to compare (s), each checked like twin.camera.latency (default: the config's)")
    _loop_options(p)


@command("compare", "several controllers and/or latencies on the same path: table and overlay plot")(_compare_options)
def _compare(args: argparse.Namespace) -> int:
    from .experiments.common import print_json_last
    from .experiments.compare import compare, plot_compare
    from .experiments.runfolder import RunFolder

    cfg = _loop_config(args)
    latencies = _each_valid(cfg, "twin.camera.latency", args.latencies or [cfg.twin.camera.latency], "--latencies")
    _each_valid(cfg, "controller.kind", args.controllers, "--controllers")   # cross-field rules per controller
    with RunFolder("compare", cfg, args.out, overwrite=args.overwrite) as run:
        cfg = run.config
        rows = []
        with _progress(len(latencies) * len(args.controllers), "case") as bar:
            for lat in latencies:
                for kind in args.controllers:
                    rows += compare(cfg, [kind], [lat])
                    bar.update(1)
        plot_compare(rows, cfg, run.file("compare.png"))
        table = [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows]
        with run.timeseries(["case", "t", "err_x", "err_y", "err"]) as ts:
            for i, r in enumerate(rows):
                for row in r["_data"]:
                    ts.write([i, row[0], row[1], row[2], row[3]])
        summary = {"path": cfg.twin.scene.path, "rows": table, "run_folder": str(run.path)}
        run.write_summary(summary)
    print(f"comparison on the {cfg.twin.scene.path} path ({cfg.loop.seconds:g} s, preset {cfg.twin.preset!r})")
    print(f"{'controller':>10} {'latency (s)':>11} {'rms (px)':>9} {'peak (px)':>10} {'p95 (px)':>9}")
    for r in table:
        print(f"{r['controller']:>10} {r['latency_s']:>11g} {r['rms_px']:>9.1f} {r['peak_px']:>10.1f} {r['p95_px']:>9.1f}")
    print(f"run folder: {run.path}  (plot: {run.file('compare.png')})")
    if args.json:
        print_json_last(summary)
    return 0


# --------------------------------------------------------------------------------------------- latency
@dataclass(frozen=True)
class LatencyOptions:
    """Options of ``targetlock latency``."""
    inject_frame: int = param(20, unit="frame", lo=1, hi=1000,
                              doc="frame at which the programmed offset starts (the run lasts until it is seen)")


def _latency_options(p: argparse.ArgumentParser) -> None:
    from .experiments.target_lock import RunConfig
    _common(p)
    config_flag(p, "--latency", RunConfig, "twin.camera.latency")
    config_flag(p, "--fps", RunConfig, "twin.camera.fps")
    config_flag(p, "--inject-frame", LatencyOptions, "inject_frame", options=True)


@command("latency", "measure the loop latency by counting frames until the handle moves (report §3.4.2)")(_latency_options)
def _latency(args: argparse.Namespace) -> int:
    from .experiments.common import build_config, print_json_last
    from .experiments.latency import measure_latency
    from .experiments.runfolder import RunFolder
    from .experiments.target_lock import RunConfig

    opts = option_values(LatencyOptions, args, "latency options")
    cfg = build_config(RunConfig, config_file=args.config, preset=args.preset, overrides=cli_overrides(args))
    cam = cfg.twin.camera
    # Long enough to see the response to the injected frame: its time, the latency and one second.
    seconds = max(4.0, opts.inject_frame / cam.fps + cam.latency + 1.0)
    with RunFolder("latency", cfg, args.out, overwrite=args.overwrite) as run:
        r = measure_latency(run.config, inject_frame=opts.inject_frame, seconds=seconds)
        r["run_folder"] = str(run.path)
        run.write_summary(r)
    print(f"programmed offset at frame {r['inject_frame']}; the video shows the handle moving at frame "
          f"{r['first_moving_frame']}: {r['frames']} frames at {r['fps']:g} fps = {r['measured_latency_s']:.3f} s "
          f"(configured video latency {r['configured_latency_s']:g} s; resolution one frame, {r['resolution_s']:.3f} s)")
    if args.json:
        print_json_last(r)
    return 0


# --------------------------------------------------------------------------------------------- sim-rig
@dataclass(frozen=True)
class SimRigOptions:
    """Options of ``targetlock sim-rig``."""
    duration: float = param(0.0, unit="s", lo=0.0, hi=31 * 86400.0, doc="stop after this many seconds (0: until Ctrl-C)")


# What ``sim-rig`` serves without --rig (as examples/twin_rig.toml): drives on the udp_loopback bus,
# NatNet unicast on 127.0.0.1; everything stays on this machine.
LOOPBACK_RIG = {
    "can": {"node_ids": [1, 2], "homing_method": 37, "status_timeout": 0.5, "heartbeat_timeout": 0.5,
            "bus": {"interface": "udp_loopback", "channel": "239.255.0.1", "port": 43113}},
    "natnet": {"server_ip": "127.0.0.1", "local_ip": "127.0.0.1", "multicast": False},
}


def _sim_rig_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rig", metavar="FILE", help="rig file whose [can], [natnet] and [observations] the twin serves "
                                                 "(default: udp_loopback bus 239.255.0.1:43113, NatNet on 127.0.0.1, "
                                                 "as examples/twin_rig.toml)")
    p.add_argument("--config", metavar="FILE", help="run config (TOML) whose twin settings to simulate")
    p.add_argument("--preset", choices=PRESETS, help="endoscope preset")
    p.add_argument("--set", action="append", metavar="SECTION.FIELD=VALUE", help="set any run-config field")
    config_flag(p, "--duration", SimRigOptions, "duration", options=True)


@command("sim-rig", "serve the digital twin over CANopen (CiA 402) and NatNet for `run --rig`")(_sim_rig_options)
def _sim_rig(args: argparse.Namespace) -> int:
    import signal
    import threading

    from .config import from_dict
    from .experiments.common import build_config
    from .experiments.target_lock import RunConfig
    from .interfaces.rigfile import HardwareRigConfig, load_rig_file
    from .rig.twin_process import serve_twin_rig

    opts = option_values(SimRigOptions, args, "sim-rig options")
    cfg = build_config(RunConfig, config_file=args.config, preset=args.preset, overrides=cli_overrides(args))
    hw = load_rig_file(args.rig) if args.rig else from_dict(HardwareRigConfig, LOOPBACK_RIG)
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
    if opts.duration > 0:
        timer = threading.Timer(opts.duration, stop.set)
        timer.daemon = True
        timer.start()
    try:
        serve_twin_rig(hw, cfg.twin, stop, on_ready=lambda line: print(line, flush=True))
    except KeyboardInterrupt:
        pass
    except OSError as exc:
        if exc.errno != errno.EADDRINUSE:
            raise
        n, bus = hw.natnet, hw.can.bus
        raise DeviceError(f"port in use: NatNet {n.command_port}/{n.data_port} (UDP) or CAN bus {bus.interface} port "
                          f"{bus.port}; is another sim-rig or Motive running? Stop it or choose other ports "
                          "with --rig FILE") from exc
    finally:
        stop.set()
    return 0


# --------------------------------------------------------------------------------------------- vision-eval
@dataclass(frozen=True)
class VisionEvalOptions:
    """Options of ``targetlock vision-eval`` beside its settings."""
    seed: tuple[int, ...] = param((0,), lo=0, hi=2**32 - 1,
                                  doc="random seed of the rendered sequences; several: each seed's sequences, every "
                                      "figure pooled over them")
    workers: int = param(0, lo=0, hi=512, doc="several seeds: run them on a local Dask cluster of this many worker "
                                              "processes at once (0: one after the other in this process)")

    def check(self, prefix: str = "") -> None:
        if len(set(self.seed)) != len(self.seed):
            raise ConfigError(f"{prefix}seed = {list(self.seed)}: a seed is named twice (its frames would count twice)")


def _vision_eval_options(p: argparse.ArgumentParser) -> None:
    from .vision.evaluate import SEQUENCES, EvalSettings
    config_flag(p, "--tracker", EvalSettings, "tracker")
    p.add_argument("--sequences", nargs="+", metavar="NAME", dest="set:sequences",
                   help=f"sequences to run (default: all): {', '.join(SEQUENCES)}")
    config_flag(p, "--frames", EvalSettings, "frames")
    config_flag(p, "--seed", VisionEvalOptions, "seed", options=True)
    config_flag(p, "--workers", VisionEvalOptions, "workers", options=True, metavar="N")
    p.add_argument("--set", action="append", metavar="FIELD=VALUE", help="set any field of the evaluation settings")
    _out_options(p)


@command("vision-eval", "score the tracker on rendered sequences with known ground truth")(_vision_eval_options)
def _vision_eval(args: argparse.Namespace) -> int:
    from .config import from_dict
    from .experiments.common import print_json_last
    from .experiments.runfolder import RunFolder
    from .vision.evaluate import FRAME_COLUMNS, EvalSettings, evaluate

    opts = option_values(VisionEvalOptions, args, "vision-eval options")
    try:
        settings = from_dict(EvalSettings, cli_overrides(args))
    except ConfigError as exc:
        raise ConfigError(errors=exc.errors, where="vision-eval options") from None
    contents = 1 + (len(settings.photos) if settings.tracker != "marker" else 0)   # mucosa + each photograph
    seed = opts.seed[0] if len(opts.seed) == 1 else list(opts.seed)
    with RunFolder("vision-eval", settings, args.out, overwrite=args.overwrite) as run, \
            run.file("frames.csv").open("w", newline="") as fh:
        table = csv.writer(fh)
        table.writerow(FRAME_COLUMNS)

        def on_frames(rows: list[tuple]) -> None:   # as each sequence is scored: kept if the run is stopped
            table.writerows(rows)
            fh.flush()
        with _progress(len(opts.seed) * contents * len(settings.sequences), "sequence") as bar:
            def progress(line: str) -> None:
                log.info("%s", line)
                bar.update(1)
            if opts.workers and len(opts.seed) > 1:
                from .experiments.sweep import dask_client
                with dask_client(None, opts.workers) as client:
                    res = evaluate(settings, seed=seed, progress=progress, on_frames=on_frames,
                                   executor=client.get_executor())
            else:
                res = evaluate(settings, seed=seed, progress=progress, on_frames=on_frames)
        o = res["overall"]
        summary = {"median_px": o["median_px"], "p95_px": o["p95_px"], "tracked_fraction": o["tracked_fraction"],
                   "tracked_in_view_fraction": o["tracked_in_view_fraction"],
                   "tracked_in_view_unwarned": o["tracked_in_view_unwarned"],
                   "delta_avg": o["delta_avg"], "fps": o["fps"], "render_ms": o["render_ms"],
                   "false_lock_fraction": o["false_lock_fraction"],
                   "tracker": settings.tracker, "seed": seed, "sequences": res["sequences"],
                   "content": res["content"], "references": res["references"],
                   "selection_failures": o["selection_failures"], "selection_warnings": o["selection_warnings"],
                   "run_folder": str(run.path)}
        if "per_seed" in res:
            summary["per_seed"] = res["per_seed"]
        run.write_summary(summary)
    seeds = f"seed {seed}" if len(opts.seed) == 1 else f"{len(opts.seed)} seeds"
    n_seq = len(settings.sequences)
    print(f"vision-eval ({settings.tracker} tracker, {n_seq} sequence{'s' if n_seq != 1 else ''} x {settings.frames} frames, "
          f"{seeds}): "
          f"median {o['median_px']:.2f} px, p95 {o['p95_px']:.2f} px, tracked {o['tracked_fraction']:.3f}, "
          f"delta_avg {o['delta_avg']:.3f}, {o['fps']:.0f} fps (one core)")
    for c, m in res["content"].items():
        print(f"  {c:>9}: tracked {m['tracked_fraction']:.3f} (in view {m['tracked_in_view_fraction']:.3f}; "
              f"{m['tracked_in_view_unwarned']:.3f} where the selection warned of nothing), "
              f"delta_avg {m['delta_avg']:.3f}, false locks {m['false_lock_fraction']:.3f}, "
              f"selection failures {m['selection_failures']}, selections with a warning {m['selection_warnings']}")
    for sd, m in res.get("per_seed", {}).items():
        print(f"  seed {sd}: tracked in view {m['tracked_in_view_fraction']:.3f}, "
              f"false locks {m['false_lock_fraction']:.4f}, median {m['median_px']:.2f} px")
    for who, r in res["references"].items():
        m = r["overall"]
        print(f"  reference {who}: median {m['median_px']:.2f} px, tracked {m['tracked_fraction']:.3f}, "
              f"delta_avg {m['delta_avg']:.3f}, false locks {m['false_lock_fraction']:.3f}, "
              f"{m['fps']:.0f} fps (ours {m['speed_ratio']:.1f}x)")
    print(f"run folder: {run.path} (frames.csv: every scored frame)")
    if args.json:
        print_json_last(summary)
    return 0


# --------------------------------------------------------------------------------------------- sweep
def _sweep_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("spec", metavar="SPEC.toml", help="sweep spec: shared [base] settings, a [grid] and/or a seeded "
                                                     "[random] set (see docs/research.md)")
    p.add_argument("--workers", type=int, metavar="N", help="worker processes of the local Dask cluster "
                                                            "(default: one per core)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="run on an existing Dask scheduler (tcp://host:8786) "
                                                          "instead of a local cluster")
    _out_options(p)


@command("sweep", "run a grid or seeded random set of target-lock runs on Dask; one table of results")(_sweep_options)
def _sweep(args: argparse.Namespace) -> int:
    import time

    from .config import ConfigError
    from .experiments.common import print_json_last
    from .experiments.runfolder import RunFolder
    from .experiments.sweep import (ResultsTable, expand, load_spec, plot_sweep, run_cases, sweep_summary,
                                    varied_names, write_case_configs)

    if args.workers is not None and not 1 <= args.workers <= 512:
        raise ConfigError(f"--workers = {args.workers} is out of range; allowed: [1, 512]")
    spec = load_spec(args.spec)
    cases = expand(spec)
    with RunFolder("sweep", spec, args.out, overwrite=args.overwrite) as run:
        names = write_case_configs(cases, run.file("cases"))
        table = ResultsTable(run.file("results.csv"), varied_names(cases))
        from tqdm import tqdm
        bar = tqdm(total=len(cases), unit="run", disable=None)

        def on_result(case, row):
            table.add(case, row, names[case.index])
            bar.update(1)

        t0 = time.perf_counter()
        try:
            rows = run_cases(cases, scheduler=args.scheduler, workers=args.workers, on_result=on_result)
        finally:
            table.close()
            bar.close()
        wall = time.perf_counter() - t0
        workers = args.scheduler or str(args.workers or os.cpu_count())
        summary = sweep_summary(cases, rows, wall, workers)
        plot_sweep(cases, rows, run.file("sweep.png"))
        summary["run_folder"] = str(run.path)
        run.write_summary(summary)
    print(f"sweep: {len(cases)} runs in {wall:.1f} s on {workers} worker(s), {summary['case_seconds_median']:.2f} s per "
          f"run (median), workers busy {100 * summary['busy_fraction']:.0f} % of the time; {summary['failed']} failed")
    for g in summary["groups"]:
        label = " ".join(f"{k}={v}" for k, v in g.items() if "." in k or k == "preset") or "all"
        print(f"  {label:<32} rms median {g['rms_px_median']:7.1f}  p95 {g['rms_px_p95']:7.1f}  worst "
              f"{g['rms_px_worst']:7.1f} px; peak median {g['peak_px_median']:7.1f} px; left image in "
              f"{g['left_image_cases']}/{g['cases']}")
    print(f"run folder: {run.path}  (table: {run.file('results.csv')}, plot: {run.file('sweep.png')})")
    if args.json:
        print_json_last(summary)
    return 0


# --------------------------------------------------------------------------------------------- export
def _export_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_folder", metavar="RUN_FOLDER", help="a run folder (timeseries.csv + config.toml)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing run.mcap")


@command("export", "write run.mcap (Foxglove) for a run folder recorded before MCAP logging")(_export_options)
def _export(args: argparse.Namespace) -> int:
    from .experiments.export import export_run_folder
    out = export_run_folder(args.run_folder, overwrite=args.overwrite)
    print(f"wrote {out} ({out.stat().st_size / 1024:.0f} kB): open it in Foxglove (docs/research.md)")
    return 0
