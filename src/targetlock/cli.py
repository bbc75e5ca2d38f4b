"""Command line: ``targetlock COMMAND [options]``; ``targetlock COMMAND --help`` for each.

Options that set a configuration value are derived from the typed config (:func:`config_flag`):
their help shows the field's unit, range and default, and their values are validated exactly like
a config file's. ``--set SECTION.FIELD=VALUE`` sets any other field. Every expected failure ends
in one line on stderr and a non-zero exit (see :mod:`targetlock.errors`); ``-v`` adds the
traceback. Only the chosen command's options are built, so ``targetlock --help`` stays cheap.
"""
from __future__ import annotations

import argparse
import logging
import sys
import tomllib
from typing import Any, Callable

from .config import ConfigError, field_info, from_dict, nest
from .errors import EXIT_INTERRUPTED, as_user_error
from .presets import PRESETS

__all__ = ["main", "command", "config_flag", "cli_overrides", "option_values"]

log = logging.getLogger("targetlock")

COMMANDS: dict[str, tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]] = {}

_SET = "set:"      # dest prefix of flags that set a run-config field (dest "set:twin.camera.fps")
_OPT = "opt:"      # dest prefix of flags that set a field of a command's own options dataclass
_PLAIN: dict[str, str] = {}   # dest of a config flag -> its plain attribute name (``--i-gain``: ``i_gain``)


def command(name: str, help_text: str):
    """Register ``fn(args) -> exit code`` as a subcommand, with an options builder."""
    def wrap(options: Callable[[argparse.ArgumentParser], None]):
        def register(fn):
            COMMANDS[name] = (help_text, options, fn)
            return fn
        return register
    return wrap


def _range_help(meta: dict, default: Any) -> str:
    from .config import _range_text
    shown = default if not isinstance(default, tuple) else " ".join(f"{v:g}" if isinstance(v, float) else str(v)
                                                                    for v in default)
    parts = [meta.get("doc", "")]
    if meta.get("lo") is not None or meta.get("hi") is not None:
        parts.append(f"allowed {_range_text(meta)}")
    parts.append(f"default {shown}")
    return "; ".join(p for p in parts if p)


def config_flag(p: argparse.ArgumentParser, flag: str, cls: type, dotted: str, *, options: bool = False,
                metavar: str | None = None, help: str | None = None) -> None:
    """Add ``flag`` setting field ``dotted`` of config class ``cls``: type, choices, help (unit, range,
    default) come from the field's ``param``. ``options=True``: a field of the command's own options
    (read with :func:`option_values`) instead of the run config (read with :func:`cli_overrides`)."""
    tp, meta, default = field_info(cls, dotted)
    dest = (_OPT if options else _SET) + dotted
    _PLAIN[dest] = flag.lstrip("-").replace("-", "_")
    text = help or _range_help(meta, default)
    if tp is bool:
        p.add_argument(flag, dest=dest, action="store_const", const=True, default=None, help=text)
        return
    kw: dict[str, Any] = {"dest": dest, "help": text, "default": None}
    args = getattr(tp, "__args__", ())
    scalar = args[0] if args and getattr(tp, "__origin__", None) in (tuple, list) else tp
    if scalar is not tp:
        kw["nargs"] = "+" if (not args or args[-1] is Ellipsis) else len(args)
    if meta.get("choices"):
        kw["choices"] = meta["choices"]
    kw["type"] = scalar if scalar in (int, float, str) else str
    unit = meta.get("unit")
    if not meta.get("choices"):
        kw["metavar"] = metavar or (unit.upper() if unit else flag.lstrip("-").upper())
    p.add_argument(flag, **kw)


def _parse_set(item: str) -> tuple[str, Any]:
    key, sep, text = item.partition("=")
    if not sep or not key.strip():
        raise ConfigError(f"--set {item!r}: expected SECTION.FIELD=VALUE, e.g. --set twin.camera.fps=30")
    try:   # TOML syntax for the value: 30, 0.4, true, [1, 2], "text"; anything else is text
        value = tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        value = text
    return key.strip(), value


def cli_overrides(args: argparse.Namespace) -> dict:
    """Nested config overrides from the config-derived flags and ``--set`` (later wins)."""
    from .model.twin import merge
    out: dict = {}
    for dest, value in vars(args).items():
        if dest.startswith(_SET) and value is not None:
            out = merge(out, nest(dest[len(_SET):], list(value) if isinstance(value, list) else value))
    for item in getattr(args, "set", None) or []:
        out = merge(out, nest(*_parse_set(item)))
    return out


def option_values(cls: type, args: argparse.Namespace, where: str) -> Any:
    """The command's own options (fields of ``cls`` added with ``config_flag(..., options=True)``), validated."""
    data = {dest[len(_OPT):]: value for dest, value in vars(args).items() if dest.startswith(_OPT) and value is not None}
    try:
        return from_dict(cls, data)
    except ConfigError as exc:
        raise ConfigError(errors=exc.errors, where=where) from None


def _common(p: argparse.ArgumentParser, *, preset: bool = True) -> None:
    p.add_argument("--config", metavar="FILE", help="TOML config (e.g. a run folder's config.toml)")
    if preset:
        p.add_argument("--preset", choices=PRESETS, help="endoscope preset (default: calibrated)")
    p.add_argument("--set", action="append", metavar="SECTION.FIELD=VALUE",
                   help="set any config field (repeatable), e.g. --set twin.camera.fps=30 --set loop.rate=100; "
                        "values in TOML syntax; see docs/parameters.md")
    _out_options(p)


def _out_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", metavar="DIR", help="run folder (default: runs/<command>-<time>)")
    p.add_argument("--overwrite", action="store_true", help="allow --out to replace an earlier run folder")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object on the last line")


def _verbosity(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                   help="debug messages, and a traceback with every error")
    g.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS, help="warnings and errors only")


# --------------------------------------------------------------------------------------------- hysteresis
def _hysteresis_options(p: argparse.ArgumentParser) -> None:
    from .experiments.hysteresis import HysteresisConfig
    _common(p)
    p.add_argument("--axis", choices=("x", "y"), help="swept axis (default x)")
    config_flag(p, "--held", HysteresisConfig, "held_angles_deg", metavar="DEG")
    config_flag(p, "--amplitudes", HysteresisConfig, "amplitudes_deg", metavar="DEG")
    config_flag(p, "--speed", HysteresisConfig, "sweep_speed_deg_s", metavar="DEG/S")
    config_flag(p, "--sample-rate", HysteresisConfig, "sample_rate", metavar="HZ")
    p.add_argument("--rig", metavar="FILE", help="sweep a rig's drives and measure the tip by motion capture, in "
                                                 "real time (default: simulate the twin)")


@command("hysteresis", "hysteresis and deadband sweep of one axis (report §3.1, Fig. 3.2)")(_hysteresis_options)
def _hysteresis(args: argparse.Namespace) -> int:
    from .experiments.common import build_config, print_json_last
    from .experiments.hysteresis import HysteresisConfig, plot, run_sweep
    from .experiments.runfolder import RunFolder
    from .model.twin import merge
    import numpy as np

    over = cli_overrides(args)
    if args.axis:
        over = merge(over, {"axis": "xy".index(args.axis)})
    cfg = build_config(HysteresisConfig, config_file=args.config, preset=args.preset, overrides=over)
    hw = None
    if args.rig:
        from .interfaces.rigfile import load_rig_file
        hw = load_rig_file(args.rig)
    with RunFolder("hysteresis", cfg, args.out, overwrite=args.overwrite) as run:
        if hw is not None:
            from .experiments.hysteresis import run_sweep_on_rig
            from .rig.hardware import HardwareRig
            with HardwareRig(hw, cfg.twin.camera) as rig:
                res = run_sweep_on_rig(cfg, rig, progress=True)
        else:
            res = run_sweep(cfg)
        with run.timeseries(["t", "curve", "second_angle_deg", "handle_deg", "tip_deg", "held_tip_deg", "cycle",
                             "held_handle_deg"]) as ts:
            for c, held in enumerate(cfg.held_angles_deg):
                n = res.time.size
                ts.write_many(np.column_stack([res.time, np.full(n, c), np.full(n, held), np.degrees(res.handle[:, c]),
                                               np.degrees(res.tip[:, c]), np.degrees(res.held_tip[:, c]), res.phase,
                                               np.degrees(res.held_handle[:, c])]))
        plot(res, cfg, run.file("hysteresis.png"))
        summary = {"source": "rig (motion capture)" if hw is not None else "twin", "preset": cfg.twin.preset,
                   "total_gain": res.total_gain, "curves": res.curves, "run_folder": str(run.path)}
        run.write_summary(summary)
    print(f"hysteresis sweep, preset {cfg.twin.preset!r}: total gain {res.total_gain:.3f} (report: 90/110 = 0.818)")
    print(f"{'held (deg)':>10} {'width (deg)':>12} {'deadband (deg)':>15} {'stop angle (deg)':>17}")
    for curve in res.curves:
        print(f"{curve['second_angle_deg']:>10.0f} {curve['hysteresis_width_deg']:>12.1f} {curve['deadband_deg']:>15.1f} "
              f"{curve['stop_angle_deg']:>17.1f}")
    print(f"run folder: {run.path}  (plot: {run.file('hysteresis.png')})")
    if args.json:
        print_json_last(summary)
    return 0


# --------------------------------------------------------------------------------------------- identify
def _identify_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_folder", metavar="RUN_FOLDER", help="run folder of 'targetlock hysteresis' (twin or --rig)")
    _common(p)
    p.add_argument("--seed", type=int, help="seed of the multi-start (default 0)")


@command("identify", "fit the endoscope model to a recorded hysteresis sweep")(_identify_options)
def _identify(args: argparse.Namespace) -> int:
    from .experiments.common import build_config, print_json_last
    from .experiments.identify import IdentifyConfig, print_summary, run_identify
    over = cli_overrides(args)
    if args.seed is not None:
        over["seed"] = args.seed
    cfg = build_config(IdentifyConfig, config_file=args.config, preset=args.preset, overrides=over)
    summary = run_identify(args.run_folder, cfg, args.out, overwrite=args.overwrite)
    print_summary(summary)
    if args.json:
        print_json_last(summary)
    return 0


# --------------------------------------------------------------------------------------------- bench
def _bench_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("what", choices=("model", "loop", "vision", "robustness", "gym"), help="what to measure")
    p.add_argument("--json", action="store_true", help="print the figures as one JSON object on the last line")
    p.add_argument("--cases", type=int, default=60, help="robustness: number of random cases (default 60)")
    p.add_argument("--seed", default="0", metavar="SEED[,SEED...]",
                   help="robustness: seed of the random set, or a comma-separated list of seeds: several sets, pooled, "
                        "with each set's median and a breakdown by distance and motion (default 0)")
    p.add_argument("--out", metavar="DIR", help="robustness: also write a run folder (config, cases.csv as runs "
                                                "finish, each case's config and waypoints, summary.json)")
    p.add_argument("--overwrite", action="store_true", help="allow --out to replace an earlier run folder")
    p.add_argument("--workers", type=int, metavar="N", help="robustness: run the cases on a local Dask cluster of N "
                                                            "worker processes (default: in this process)")
    p.add_argument("--controllers", metavar="LIST", help="robustness: comma-separated controllers to run (default: all); "
                                                         "kind[+source][@N], e.g. adaptive,adaptive+oracle,adaptive+oracle-endoscope; "
                                                         "@N scores the N-th engagement of the same controller on each "
                                                         "case (adaptive@2: engaged again, it keeps the scope it found)")
    p.add_argument("--vision", action="store_true", help="robustness: every case through the rendered view and the "
                                                         "feature tracker instead of the ideal projection (~3x slower)")


@command("bench", "benchmarks: model, loop, vision, robustness, gym")(_bench_options)
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
        print(f"loop: real-time factor {res['realtime_factor']:.0f}; step of ik {res['ik_step_ms']:.4f} ms, of adaptive {res['adaptive_step_ms']:.4f} ms")
    elif args.what == "robustness":
        from .experiments.robustness import BENCH_CONTROLLERS, bench_robustness, parse_controllers, parse_seeds
        controllers = parse_controllers(args.controllers) if args.controllers is not None else BENCH_CONTROLLERS
        res = bench_robustness(args.cases, parse_seeds(args.seed), workers=args.workers, controllers=controllers,
                               out=args.out, overwrite=args.overwrite, vision=args.vision)
    elif args.what == "gym":
        from .bench import bench_gym
        res = bench_gym()
        print(f"gym: single env {res['single_steps_per_s']:.0f} steps/s")
        for n in res["sizes"]:
            print(f"  N = {n:3d}: SyncVectorEnv {res[f'sync_{n}_env_steps_per_s']:8.0f} env-steps/s, batch vector env "
                  f"{res[f'batch_{n}_env_steps_per_s']:8.0f} env-steps/s ({res[f'batch_{n}_steps_per_s']:.0f} vector steps/s; "
                  f"reset {res[f'batch_{n}_reset_s']:.2f} s vs {res[f'sync_{n}_reset_s']:.2f} s)")
    else:
        from .bench import bench_vision
        res = bench_vision()
        print(f"vision: render {res['render_ms']:.2f} ms/frame in the loop, tracker {res['tracker_fps']:.0f} fps; "
              f"closed loop with vision {res['loop_realtime_factor']:.1f}x real time (median of "
              f"{len(res['loop_realtime_factors'])} runs, {min(res['loop_realtime_factors']):.1f}-"
              f"{max(res['loop_realtime_factors']):.1f}x)")
    if args.json:
        print_json_last(res)
    return 0


def _load_extra_commands() -> None:
    """Commands of the closed loop, vision and hardware live beside their code."""
    from . import commands  # noqa: F401  (registers its commands on import)
    from .console import command as _console  # noqa: F401  (targetlock console)


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time (main() may be called in-process, e.g. by tests)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


def _setup_logging(verbose: bool, quiet: bool) -> None:
    from .experiments.runfolder import LOG_FORMAT
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    root = logging.getLogger()
    root.setLevel(logging.DEBUG if verbose else logging.INFO)   # run.log records this; the console ``level`` and up
    console = _StderrHandler()
    console.setLevel(level)
    console.setFormatter(logging.Formatter(LOG_FORMAT, datefmt="%H:%M:%S"))
    console.set_name("targetlock-console")
    for h in [h for h in root.handlers if h.get_name() == "targetlock-console"]:
        root.removeHandler(h)
    root.addHandler(console)
    for noisy in ("matplotlib", "numba", "PIL", "can", "canopen"):
        logging.getLogger(noisy).setLevel(logging.WARNING)


def _user_error(exc: BaseException):
    """The user-facing error of ``exc`` or of an exception it was raised from (``raise ... from``)."""
    seen: BaseException | None = exc
    while seen is not None:
        err = as_user_error(seen)
        if err is not None:
            return err
        seen = seen.__cause__
    return None


def _chosen_command(argv: list[str]) -> str | None:
    for a in argv:
        if not a.startswith("-"):
            return a
    return None


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    _load_extra_commands()
    top = argparse.ArgumentParser(add_help=False)
    _verbosity(top)
    parser = argparse.ArgumentParser(prog="targetlock", description="Target lock for flexible endoscopes.",
                                     parents=[top])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    chosen = _chosen_command(argv)
    for name, (help_text, options, _) in COMMANDS.items():
        sp = sub.add_parser(name, help=help_text, description=help_text, parents=[top])
        if name == chosen:      # only the chosen command's options: their choices may import heavy modules
            options(sp)
    args = parser.parse_args(argv)
    for dest, plain in _PLAIN.items():     # also as args.i_gain etc., for code that reads flags directly
        if dest in vars(args) and plain not in vars(args):
            setattr(args, plain, getattr(args, dest))
    verbose, quiet = getattr(args, "verbose", False), getattr(args, "quiet", False)
    _setup_logging(verbose, quiet)
    if not args.command:
        parser.print_help()
        return 2
    from .experiments.runfolder import RunFolder
    from .loop.signals import StopSignal, stop_on_signals
    RunFolder.latest = None
    try:
        with stop_on_signals():       # SIGTERM and SIGHUP end a command like Ctrl-C
            return COMMANDS[args.command][2](args)
    except StopSignal as exc:
        kept = f"; data and summary kept in {RunFolder.latest}" if RunFolder.latest is not None else ""
        print(f"targetlock {args.command}: stopped by {exc.signal_name}{kept}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"targetlock {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as exc:
        err = _user_error(exc)
        if err is None:
            raise          # a bug: keep the traceback
        kept = f" (run folder kept: {RunFolder.latest})" if RunFolder.latest is not None else ""
        print(f"targetlock {args.command}: {err}{kept}", file=sys.stderr)
        if verbose:
            import traceback
            traceback.print_exception(exc, file=sys.stderr)
        return err.exit_code


if __name__ == "__main__":
    sys.exit(main())
