"""Subcommands of the closed loop (run, step-response, compare), registered into :mod:`targetlock.cli`."""
from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

from .cli import _common, command
from .controllers.base import CONTROLLERS
from .model.scene import PATHS
from .model.twin import PRESETS as PRESETS_CHOICES

PATH_CHOICES = [p for p in PATHS if p != "waypoints"]


def _loop_options(p: argparse.ArgumentParser) -> None:
    _common(p)
    p.add_argument("--path", metavar="PATH", help=f"target path: {', '.join(PATH_CHOICES)} or a CSV file (t,x,y,z)")
    p.add_argument("--latency", type=float, metavar="S", help="video latency (s, default 0.4)")
    p.add_argument("--fps", type=float, help="camera frame rate (default 22)")
    p.add_argument("--i-gain", type=float, metavar="I", help="integral gain I (tick/(px·s), default 300)")
    p.add_argument("--p-gain", type=float, metavar="P", help="proportional gain P (tick/px, default 0)")
    p.add_argument("--hc-width", type=float, metavar="W", help="compensation width w of model 1 (default 0.2)")
    p.add_argument("--seconds", type=float, help="run length (s, default 40)")
    p.add_argument("--seed", type=int, help="random seed")
    p.add_argument("--noise", type=float, metavar="PX", help="tracker noise (px standard deviation)")
    p.add_argument("--drop", type=float, metavar="P", help="probability of a dropped frame")
    p.add_argument("--outliers", type=float, metavar="P", help="probability of an outlier observation")
    p.add_argument("--realtime", action="store_true", help="run on the wall clock")
    p.add_argument("--vision", action="store_true", help="render endoscope frames and track them (instead of the "
                                                         "ideal projection)")
    p.add_argument("--tracker", choices=("feature", "marker"), help="tracker with --vision (default feature)")


def _overrides(args: argparse.Namespace) -> dict:
    """Nested config overrides from the common loop flags."""
    o: dict = {"twin": {"camera": {}, "scene": {}}, "controller": {}, "loop": {}, "tracker": {}}
    if getattr(args, "controller", None):
        o["controller"]["kind"] = args.controller
    if args.path:
        if args.path in PATH_CHOICES:
            o["twin"]["scene"]["path"] = args.path
        else:
            o["twin"]["scene"].update(path="waypoints", waypoints_file=str(Path(args.path).resolve()))
    for flag, section, key in (("latency", "camera", "latency"), ("fps", "camera", "fps")):
        if getattr(args, flag) is not None:
            o["twin"][section][key] = getattr(args, flag)
    for flag, key in (("i_gain", "i_gain"), ("p_gain", "p_gain"), ("hc_width", "hc_width")):
        if getattr(args, flag, None) is not None:
            o["controller"][key] = getattr(args, flag)
    if args.seconds is not None:
        o["loop"]["seconds"] = args.seconds
    for flag, key in (("noise", "noise_px"), ("drop", "drop_probability"), ("outliers", "outlier_probability")):
        if getattr(args, flag) is not None:
            o["tracker"][key] = getattr(args, flag)
    if args.seed is not None:
        o["seed"] = args.seed
        o["tracker"]["seed"] = args.seed
    if args.realtime:
        o["realtime"] = True
    if args.vision:
        o["vision"] = True
    if args.tracker:
        o["vision_tracker"] = args.tracker
    return o


def _print_summary(s: dict) -> None:
    print(f"target lock: {s['controller']} on the {s['path']} path, latency {s['latency_s']:g} s, {s['fps']:g} fps, "
          f"preset {s['preset']!r}")
    print(f"  tracking error after warm-up: rms {s['rms_px']:.1f} px, peak {s['peak_px']:.1f} px, "
          f"p95 {s['p95_px']:.1f} px, mean {s['mean_px']:.1f} px")
    if s.get("tip_range_deg"):
        print(f"  tip worked between {s['tip_range_deg'][0]:.0f} and {s['tip_range_deg'][1]:.0f} deg; "
              f"frames lost {100 * s['lost_fraction']:.1f} %")
    print(f"  {s['sim_seconds']:g} s simulated in {s['wall_seconds']:.2f} s ({s['realtime_factor']:.0f}x real time)")


# --------------------------------------------------------------------------------------------- run
def _run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--controller", choices=CONTROLLERS, help="controller (default pi-hc)")
    p.add_argument("--rig", metavar="FILE", help="run on the rig this file describes (CANopen drives, NatNet, "
                                                 "observations) on the wall clock, instead of the in-process twin")
    p.add_argument("--video", metavar="FILE.mp4", help="with --vision: write the endoscope view with the tracked "
                                                       "target, the image centre and the error drawn on it")
    _loop_options(p)


@command("run", "closed-loop target lock on the digital twin: the main job")(_run_options)
def _run(args: argparse.Namespace) -> int:
    from .experiments.common import build_config, print_json_last
    from .experiments.runfolder import RunFolder
    from .experiments.target_lock import RunConfig, run_target_lock

    cfg = build_config(RunConfig, config_file=args.config, preset=args.preset, overrides=_overrides(args))
    if args.video and not cfg.vision:
        from .config import ConfigError
        raise ConfigError("--video needs --vision (frames are rendered only with vision)")
    hw = None
    if args.rig:
        from .interfaces.rigfile import load_rig_file
        hw = load_rig_file(args.rig)          # validate before anything moves or a folder is made
    run = RunFolder("run", cfg, args.out)
    if hw is not None:
        from .config import save_toml
        from .rig.hardware import HardwareRig
        save_toml(hw, run.file("rig.toml"))
        with HardwareRig(hw, cfg.twin.camera, loop_rate=cfg.loop.rate) as rig:
            s = run_target_lock(cfg, run, progress=True, rig=rig)
    else:
        s = run_target_lock(cfg, run, progress=True, video=args.video)
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
    p.add_argument("--controller", choices=CONTROLLERS, help="controller (default pi)")
    p.add_argument("--i-values", type=float, nargs="+", metavar="I", default=[100, 200, 300, 400, 500],
                   help="I values to compare (tick/(px·s))")
    _loop_options(p)


@command("step-response", "step responses for several I values (report §5.2, Fig. 6.1)")(_step_options)
def _step(args: argparse.Namespace) -> int:
    from .experiments.common import build_config, print_json_last
    from .experiments.runfolder import RunFolder
    from .experiments.step_response import plot_step_responses, run_step_responses
    from .experiments.target_lock import RunConfig
    from .model.twin import merge

    base = {"twin": {"scene": {"path": "step", "start_tip_deg": [0.0, 0.0], "start_delay": 0.0}},
            "controller": {"kind": "pi"}, "loop": {"seconds": 5.0, "metrics_after": 0.0}}
    cfg = build_config(RunConfig, config_file=args.config, preset=args.preset, overrides=merge(base, _overrides(args)))
    run = RunFolder("step-response", cfg, args.out)
    results = run_step_responses(cfg, args.i_values)
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
    p.add_argument("--controllers", nargs="+", choices=CONTROLLERS, default=["pi", "pi-hc", "ik"],
                   help="controllers to compare")
    p.add_argument("--latencies", type=float, nargs="+", metavar="S", help="latencies to compare (s)")
    _loop_options(p)


@command("compare", "several controllers and/or latencies on the same path: table and overlay plot")(_compare_options)
def _compare(args: argparse.Namespace) -> int:
    from .experiments.common import build_config, print_json_last
    from .experiments.compare import compare, plot_compare
    from .experiments.runfolder import RunFolder
    from .experiments.target_lock import RunConfig

    cfg = build_config(RunConfig, config_file=args.config, preset=args.preset, overrides=_overrides(args))
    run = RunFolder("compare", cfg, args.out)
    latencies = args.latencies or [cfg.twin.camera.latency]
    rows = compare(cfg, args.controllers, latencies)
    plot_compare(rows, cfg, run.file("compare.png"))
    table = [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows]
    with run.timeseries(["case", "t", "err_x", "err_y", "err"]) as ts:
        for i, r in enumerate(rows):
            d = r["_data"]
            for row in d:
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
def _latency_options(p: argparse.ArgumentParser) -> None:
    _common(p)
    p.add_argument("--latency", type=float, metavar="S", help="configured video latency of the twin (s)")
    p.add_argument("--fps", type=float, help="camera frame rate")
    p.add_argument("--inject-frame", type=int, default=20, help="frame at which the programmed offset starts")


@command("latency", "measure the loop latency by counting frames until the handle moves (report §3.4.2)")(_latency_options)
def _latency(args: argparse.Namespace) -> int:
    from .experiments.common import build_config, print_json_last
    from .experiments.latency import measure_latency
    from .experiments.runfolder import RunFolder
    from .experiments.target_lock import RunConfig

    over: dict = {"twin": {"camera": {}}}
    if args.latency is not None:
        over["twin"]["camera"]["latency"] = args.latency
    if args.fps is not None:
        over["twin"]["camera"]["fps"] = args.fps
    cfg = build_config(RunConfig, config_file=args.config, preset=args.preset, overrides=over)
    run = RunFolder("latency", cfg, args.out)
    r = measure_latency(cfg, inject_frame=args.inject_frame)
    r["run_folder"] = str(run.path)
    run.write_summary(r)
    print(f"programmed offset at frame {r['inject_frame']}; the video shows the handle moving at frame "
          f"{r['first_moving_frame']}: {r['frames']} frames at {r['fps']:g} fps = {r['measured_latency_s']:.3f} s "
          f"(configured video latency {r['configured_latency_s']:g} s; resolution one frame, {r['resolution_s']:.3f} s)")
    if args.json:
        print_json_last(r)
    return 0


# --------------------------------------------------------------------------------------------- sim-rig
def _sim_rig_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rig", metavar="FILE", help="rig file whose [can], [natnet] and [observations] the twin serves "
                                                 "(default: udp_loopback bus, NatNet on 127.0.0.1)")
    p.add_argument("--config", metavar="FILE", help="run config (TOML) whose twin settings to simulate")
    p.add_argument("--preset", choices=PRESETS_CHOICES, help="endoscope preset")
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: until Ctrl-C)")


@command("sim-rig", "serve the digital twin over CANopen (CiA 402) and NatNet for `run --rig`")(_sim_rig_options)
def _sim_rig(args: argparse.Namespace) -> int:
    import signal
    import threading

    from .experiments.common import build_config
    from .experiments.target_lock import RunConfig
    from .interfaces.rigfile import HardwareRigConfig, load_rig_file
    from .rig.twin_process import serve_twin_rig

    cfg = build_config(RunConfig, config_file=args.config, preset=args.preset)
    hw = load_rig_file(args.rig) if args.rig else HardwareRigConfig()
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
    if args.duration > 0:
        timer = threading.Timer(args.duration, stop.set)
        timer.daemon = True
        timer.start()
    try:
        serve_twin_rig(hw, cfg.twin, stop, on_ready=lambda line: print(line, flush=True))
    except KeyboardInterrupt:
        pass
    finally:
        stop.set()
    return 0


# --------------------------------------------------------------------------------------------- vision-eval
def _vision_eval_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--tracker", choices=("feature", "marker"), help="tracker under test (default feature)")
    p.add_argument("--sequences", nargs="+", metavar="NAME", help="sequences to run (default: all)")
    p.add_argument("--frames", type=int, help="frames per sequence (default 66)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the rendered sequences")
    p.add_argument("--out", metavar="DIR", help="run folder (default: runs/vision-eval-<time>)")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object on the last line")


@command("vision-eval", "score the tracker on rendered sequences with known ground truth")(_vision_eval_options)
def _vision_eval(args: argparse.Namespace) -> int:
    from .config import from_dict
    from .experiments.common import print_json_last
    from .experiments.runfolder import RunFolder
    from .vision.evaluate import EvalSettings, evaluate

    over = {k: v for k, v in (("tracker", args.tracker), ("sequences", args.sequences), ("frames", args.frames))
            if v is not None}
    settings = from_dict(EvalSettings, over)
    run = RunFolder("vision-eval", settings, args.out)
    res = evaluate(settings, seed=args.seed, progress=lambda line: print("  " + line, flush=True))
    o = res["overall"]
    summary = {"median_px": o["median_px"], "p95_px": o["p95_px"], "tracked_fraction": o["tracked_fraction"],
               "delta_avg": o["delta_avg"], "fps": o["fps"], "render_ms": o["render_ms"], "tracker": settings.tracker,
               "seed": args.seed, "sequences": res["sequences"], "run_folder": str(run.path)}
    run.write_summary(summary)
    print(f"vision-eval ({settings.tracker} tracker, {len(settings.sequences)} sequences x {settings.frames} frames): "
          f"median {o['median_px']:.2f} px, p95 {o['p95_px']:.2f} px, tracked {o['tracked_fraction']:.3f}, "
          f"delta_avg {o['delta_avg']:.3f}, {o['fps']:.0f} fps (one core)")
    print(f"run folder: {run.path}")
    if args.json:
        print_json_last(summary)
    return 0
