"""``targetlock console``: the control loop with the operator's web page (registered into :mod:`targetlock.cli`)."""
from __future__ import annotations

import argparse
import logging

from ..cli import cli_overrides, command, config_flag
from ..presets import PRESETS


def _options(p: argparse.ArgumentParser) -> None:
    # built only when `console` is the command: heavy imports are fine here
    from ..experiments.target_lock import RunConfig
    from .session import TARGET_PATHS
    p.add_argument("--config", metavar="FILE", help="TOML config (e.g. a run folder's config.toml)")
    p.add_argument("--preset", choices=PRESETS, help="endoscope preset (default: calibrated)")
    p.add_argument("--path", choices=TARGET_PATHS, help="twin: target path at start (default linear)")
    for flag, dotted in (("--controller", "controller.kind"), ("--i-gain", "controller.i_gain"),
                         ("--latency", "twin.camera.latency"), ("--fps", "twin.camera.fps"),
                         ("--tracker", "vision_tracker"), ("--seed", "seed")):
        config_flag(p, flag, RunConfig, dotted)
    p.add_argument("--rig", metavar="FILE", help="run on the rig this file describes instead of the twin")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1; any other needs a token)")
    p.add_argument("--port", type=int, default=8765, help="TCP port (default 8765; 0 = any free port)")
    p.add_argument("--token", help="access token (default: generated and printed when not on loopback)")
    p.add_argument("--runs", default="runs", metavar="DIR", help="where recordings go (default runs/)")
    p.add_argument("--loop-nice", type=int, default=-10, metavar="N",
                   help="scheduling priority of the loop thread (default -10; needs root or CAP_SYS_NICE, else a warning)")
    p.add_argument("--bench", action="store_true", help="instead of serving: measure loop jitter with 0 and 3 headless "
                                                        "Chromium pages, serving CPU and frame-to-screen latency")
    p.add_argument("--screenshot", metavar="FILE.png", help="with --bench: save a screenshot of the page")
    p.add_argument("--json", action="store_true", help="with --bench: figures as one JSON object on the last line")


@command("console", "operator console in the browser: live view, select, engage/release, stop, tune, record")(_options)
def _console(args: argparse.Namespace) -> int:
    from ..config import ConfigError
    from ..experiments.common import build_config
    from ..experiments.target_lock import RunConfig
    from .server import ConsoleServer, is_loopback, new_token
    from .session import ConsoleSession

    if args.bench:
        return _bench(args)
    if not 0 <= args.port <= 65535:
        raise ConfigError(f"--port = {args.port} is out of range; allowed: [0, 65535]")
    from ..model.twin import merge
    over = merge({"vision": True, "realtime": True}, cli_overrides(args))
    if args.path:
        over = merge(over, {"twin": {"scene": {"path": args.path}}})
    cfg = build_config(RunConfig, config_file=args.config, preset=args.preset, overrides=over)
    token = args.token or (None if is_loopback(args.host) else new_token())
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    rig = None
    if args.rig:
        from ..interfaces.rigfile import load_rig_file
        from ..rig.hardware import HardwareRig
        rig = HardwareRig(load_rig_file(args.rig), cfg.twin.camera, tracker_settings=cfg.feature_tracker)
    session = ConsoleSession(cfg, rig=rig, runs_root=args.runs)
    server = ConsoleServer(session, host=args.host, port=args.port, token=token)
    session.start(loop_nice=args.loop_nice)
    print(f"targetlock console on the {'twin' if rig is None else 'rig ' + args.rig}: {server.url()}", flush=True)
    if token and not args.token:
        print(f"access token (needed on every request): {token}", flush=True)
    try:
        server.serve()
    finally:
        session.close()
    return 0


def _bench(args: argparse.Namespace) -> int:
    from ..experiments.common import print_json_last
    from .bench import bench_console

    r = bench_console(screenshot=args.screenshot)
    for key, label in (("no_page", "no page"), ("ws_viewers", f"{r['pages']} plain WebSocket viewers"),
                       ("with_pages", f"{r['pages']} Chromium pages")):
        w = r[key]
        print(f"loop lateness with {label}: p50 {w['lateness_p50_ms']:.2f} ms, p99 {w['lateness_p99_ms']:.2f} ms, "
              f"max {w['lateness_max_ms']:.2f} ms over {w['ticks']} ticks; CPU (% of a core): loop thread "
              f"{w['loop_thread_cpu_percent']:.0f}, other threads {w['other_threads_cpu_percent']:.0f}; "
              f"host load {w['load_average_1min']:.1f}")
    f = r["frame_to_screen_ms"]
    print(f"frame-to-screen latency p50 {f['p50']:.1f} ms, p95 {f['p95']:.1f} ms ({f['samples']} frames); "
          f"JPEG {r['jpeg_encode_ms']:.2f} ms/frame; serving the pages costs {r['serving_cpu_percent']:.0f} % of a core")
    if args.json:
        print_json_last(r)
    return 0
