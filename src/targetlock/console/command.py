"""``targetlock console``: the control loop with the operator's web page (registered into :mod:`targetlock.cli`)."""
from __future__ import annotations

import argparse
import logging
import sys

from ..cli import command
from ..controllers.base import CONTROLLERS
from ..model.twin import PRESETS
from .session import TARGET_PATHS


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="FILE", help="TOML config (e.g. a run folder's config.toml)")
    p.add_argument("--preset", choices=PRESETS, help="endoscope preset (default: calibrated)")
    p.add_argument("--controller", choices=CONTROLLERS, help="controller at start (default pi-hc)")
    p.add_argument("--path", choices=TARGET_PATHS, help="twin: target path at start (default linear)")
    p.add_argument("--i-gain", type=float, metavar="I", help="integral gain I (tick/(px·s), default 300)")
    p.add_argument("--latency", type=float, metavar="S", help="twin: video latency (s, default 0.4)")
    p.add_argument("--fps", type=float, help="twin: camera frame rate (default 22)")
    p.add_argument("--tracker", choices=("feature", "marker"), help="twin: tracker of the rendered frames (default feature)")
    p.add_argument("--seed", type=int, help="random seed of the twin's scene texture")
    p.add_argument("--rig", metavar="FILE", help="run on the rig this file describes instead of the twin")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1; any other needs a token)")
    p.add_argument("--port", type=int, default=8765, help="TCP port (default 8765; 0 = any free port)")
    p.add_argument("--token", help="access token (default: generated and printed when not on loopback)")
    p.add_argument("--runs", default="runs", metavar="DIR", help="where recordings go (default runs/)")


@command("console", "operator console in the browser: live view, select, engage/release, stop, tune, record")(_options)
def _console(args: argparse.Namespace) -> int:
    from ..config import ConfigError
    from ..experiments.common import build_config
    from ..experiments.target_lock import RunConfig
    from .server import ConsoleServer, is_loopback, new_token
    from .session import ConsoleSession

    if not 0 <= args.port <= 65535:
        raise ConfigError(f"--port = {args.port} is out of range; allowed: [0, 65535]")
    over: dict = {"twin": {"camera": {}, "scene": {}}, "controller": {}, "vision": True, "realtime": True}
    if args.controller:
        over["controller"]["kind"] = args.controller
    if args.i_gain is not None:
        over["controller"]["i_gain"] = args.i_gain
    if args.path:
        over["twin"]["scene"]["path"] = args.path
    if args.latency is not None:
        over["twin"]["camera"]["latency"] = args.latency
    if args.fps is not None:
        over["twin"]["camera"]["fps"] = args.fps
    if args.tracker:
        over["vision_tracker"] = args.tracker
    if args.seed is not None:
        over["seed"] = args.seed
    cfg = build_config(RunConfig, config_file=args.config, preset=args.preset, overrides=over)
    token = args.token or (None if is_loopback(args.host) else new_token())
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    rig = None
    if args.rig:
        from ..interfaces.rigfile import load_rig_file
        from ..rig.hardware import HardwareRig
        rig = HardwareRig(load_rig_file(args.rig), cfg.twin.camera)
    session = ConsoleSession(cfg, rig=rig, runs_root=args.runs)
    server = ConsoleServer(session, host=args.host, port=args.port, token=token)
    session.start()
    print(f"targetlock console on the {'twin' if rig is None else 'rig ' + args.rig}: {server.url()}", flush=True)
    if token and not args.token:
        print(f"access token (needed on every request): {token}", flush=True)
    try:
        server.serve()
    finally:
        session.close()
    return 0
