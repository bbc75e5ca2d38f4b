"""Command line: ``targetlock COMMAND [options]``; ``targetlock COMMAND --help`` for each."""
from __future__ import annotations

import argparse
import sys
from typing import Callable

from .config import ConfigError
from .model.twin import PRESETS

__all__ = ["main"]

COMMANDS: dict[str, tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]] = {}


def command(name: str, help_text: str):
    """Register ``fn(args) -> exit code`` as a subcommand, with an options builder."""
    def wrap(options: Callable[[argparse.ArgumentParser], None]):
        def register(fn):
            COMMANDS[name] = (help_text, options, fn)
            return fn
        return register
    return wrap


def _common(p: argparse.ArgumentParser, *, preset: bool = True) -> None:
    p.add_argument("--config", metavar="FILE", help="TOML config (e.g. a run folder's config.toml)")
    if preset:
        p.add_argument("--preset", choices=PRESETS, help="endoscope preset (default: calibrated)")
    p.add_argument("--out", metavar="DIR", help="run folder (default: runs/<command>-<time>)")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object on the last line")


# --------------------------------------------------------------------------------------------- hysteresis
def _hysteresis_options(p: argparse.ArgumentParser) -> None:
    _common(p)
    p.add_argument("--axis", choices=("x", "y"), help="swept axis (default x)")
    p.add_argument("--held", type=float, nargs="+", metavar="DEG", help="held tip angles of the other axis (deg)")
    p.add_argument("--amplitudes", type=float, nargs="+", metavar="DEG", help="handle sweep amplitudes (deg)")
    p.add_argument("--speed", type=float, metavar="DEG/S", help="handle speed (deg/s)")
    p.add_argument("--sample-rate", type=float, metavar="HZ", help="samples per second (default 200); on a rig, "
                                                                   "setpoints sent and positions read per second")
    p.add_argument("--rig", metavar="FILE", help="sweep a rig's drives and measure the tip by motion capture, in "
                                                 "real time (default: simulate the twin)")


@command("hysteresis", "hysteresis and deadband sweep of one axis (report §3.1, Fig. 3.2)")(_hysteresis_options)
def _hysteresis(args: argparse.Namespace) -> int:
    from .experiments.common import build_config, print_json_last
    from .experiments.hysteresis import HysteresisConfig, plot, run_sweep
    from .experiments.runfolder import RunFolder
    import numpy as np

    over: dict = {}
    if args.axis:
        over["axis"] = "xy".index(args.axis)
    if args.held:
        over["held_angles_deg"] = args.held
    if args.amplitudes:
        over["amplitudes_deg"] = args.amplitudes
    if args.speed:
        over["sweep_speed_deg_s"] = args.speed
    if args.sample_rate:
        over["sample_rate"] = args.sample_rate
    cfg = build_config(HysteresisConfig, config_file=args.config, preset=args.preset, overrides=over)
    hw = None
    if args.rig:
        from .interfaces.rigfile import load_rig_file
        hw = load_rig_file(args.rig)
    run = RunFolder("hysteresis", cfg, args.out)
    if hw is not None:
        from .experiments.hysteresis import run_sweep_on_rig
        from .rig.hardware import HardwareRig
        with HardwareRig(hw, cfg.twin.camera) as rig:
            res = run_sweep_on_rig(cfg, rig)
    else:
        res = run_sweep(cfg)
    with run.timeseries(["t", "curve", "second_angle_deg", "handle_deg", "tip_deg", "held_tip_deg", "cycle"]) as ts:
        for c, held in enumerate(cfg.held_angles_deg):
            n = res.time.size
            ts.write_many(np.column_stack([res.time, np.full(n, c), np.full(n, held), np.degrees(res.handle[:, c]),
                                           np.degrees(res.tip[:, c]), np.degrees(res.held_tip[:, c]), res.phase]))
    plot(res, cfg, run.file("hysteresis.png"))
    summary = {"source": "rig (motion capture)" if hw is not None else "twin", "preset": cfg.twin.preset,
               "total_gain": res.total_gain, "curves": res.curves, "run_folder": str(run.path)}
    run.write_summary(summary)
    print(f"hysteresis sweep, preset {cfg.twin.preset!r}: total gain {res.total_gain:.3f} (report: 90/110 = 0.818)")
    print(f"{'held (deg)':>10} {'width (deg)':>12} {'deadband (deg)':>15} {'stop angle (deg)':>17}")
    for c in res.curves:
        print(f"{c['second_angle_deg']:>10.0f} {c['hysteresis_width_deg']:>12.1f} {c['deadband_deg']:>15.1f} "
              f"{c['stop_angle_deg']:>17.1f}")
    print(f"run folder: {run.path}  (plot: {run.file('hysteresis.png')})")
    if args.json:
        print_json_last(summary)
    return 0


# --------------------------------------------------------------------------------------------- bench
def _bench_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("what", choices=("model", "loop", "vision"), help="what to measure")
    p.add_argument("--json", action="store_true", help="print the figures as one JSON object on the last line")


@command("bench", "benchmarks: model, loop, vision")(_bench_options)
def _bench(args: argparse.Namespace) -> int:
    from .experiments.common import print_json_last
    if args.what == "model":
        from .bench import bench_model
        res = bench_model()
        print(f"model: real-time factor {res['realtime_factor']:.0f} (one endoscope, dt {res['model_dt'] * 1e3:g} ms); "
              f"{res['batch_size']} endoscopes x {res['batch_sim_seconds']:g} s in {res['batch_seconds']:.2f} s (one core)")
    elif args.what == "loop":
        from .bench import bench_loop
        res = bench_loop()
        print(f"loop: real-time factor {res['realtime_factor']:.0f}; IK step {res['ik_step_ms']:.4f} ms")
    else:
        from .bench import bench_vision
        res = bench_vision()
        print(f"vision: render {res['render_ms']:.2f} ms/frame in the loop, tracker {res['tracker_fps']:.0f} fps; "
              f"closed loop with vision {res['loop_realtime_factor']:.1f}x real time")
    if args.json:
        print_json_last(res)
    return 0


def _load_extra_commands() -> None:
    """Commands of the closed loop, vision and hardware live beside their code."""
    from . import commands  # noqa: F401  (registers its commands on import)
    from .console import command as _console  # noqa: F401  (targetlock console)


def main(argv: list[str] | None = None) -> int:
    _load_extra_commands()
    parser = argparse.ArgumentParser(prog="targetlock", description="Target lock for flexible endoscopes.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (help_text, options, _) in COMMANDS.items():
        options(sub.add_parser(name, help=help_text, description=help_text))
    args = parser.parse_args(argv)
    if not args.command:
        parser.print_help()
        return 2
    try:
        return COMMANDS[args.command][2](args)
    except ConfigError as exc:
        print(f"targetlock {args.command}: invalid configuration: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"targetlock {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
