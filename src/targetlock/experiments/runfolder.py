"""Run folders: every experiment writes its resolved config, time series, plots and summary.

Layout of a run folder::

    config.toml        the full resolved configuration (re-run with --config config.toml)
    run.log            every log message of the run, with time and level
    timeseries.csv     one row per sample, written as the run goes (a crash keeps what was recorded)
    run.mcap           the same rows (and, for target-lock runs, poses, frames, logs) for Foxglove
    summary.json       the figures the command printed
    *.png              plots
    inputs/            copies of the input files the config names (e.g. a waypoint CSV); config.toml
                       points at the copies, so re-running the folder gives the same result
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import shutil
import weakref
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..config import replace_path, save_toml
from ..errors import OutputError
from ..recording import McapLog, TimeSeriesWriter

__all__ = ["RunFolder", "TimeSeriesWriter", "check_writable", "input_files"]

log = logging.getLogger(__name__)
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def check_writable(path: str | Path, what: str) -> Path:
    """Refuse (OutputError) an output file that cannot be created: a folder in the way, a missing
    or read-only parent folder. Cheap; call it before expensive work."""
    p = Path(path)
    if p.is_dir():
        raise OutputError(f"{what} {p}: is a folder, a file name is needed")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise OutputError(f"{what} {p}: folder {parent} does not exist; create it or choose another path")
    if not os.access(parent, os.W_OK | os.X_OK) or (p.exists() and not os.access(p, os.W_OK)):
        raise OutputError(f"{what} {p}: not writable; choose a place you may write to")
    return p


def input_files(cfg: Any, prefix: str = "") -> dict[str, str]:
    """Dotted names and values of every non-empty input-file setting (``param(..., file=True)``)."""
    out: dict[str, str] = {}
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            out.update(input_files(value, f"{prefix}{f.name}."))
        elif f.metadata.get("file") and value:
            out[prefix + f.name] = value
    return out


def _detach(handler: logging.Handler) -> None:
    logging.getLogger().removeHandler(handler)
    handler.close()


class RunFolder:
    """A folder for one experiment run; created at construction, config written immediately.

    ``out`` must be new or empty: an earlier run folder is replaced only with ``overwrite=True``
    (anything else in the way is refused). Input files the config names are copied into
    ``inputs/`` and :attr:`config` points at the copies. Log messages go to ``run.log`` until
    :meth:`close` (or the end of a ``with`` block)."""

    latest: Path | None = None   # the most recently created run folder (named in error messages)

    def __init__(self, kind: str, config: Any, out: str | Path | None = None, root: str | Path = "runs", *,
                 overwrite: bool = False) -> None:
        if out is None:
            stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S-%f")
            out = Path(root) / f"{kind}-{stamp}"
        self.path = Path(out)
        # Inputs are read before an old folder is removed: a re-run of a folder may name its own copies.
        inputs = {k: (Path(v).name, Path(v).read_bytes()) for k, v in input_files(config).items()}
        self._prepare(overwrite)
        for dotted, (name, data) in inputs.items():
            copy = self.path / "inputs" / name
            copy.parent.mkdir(exist_ok=True)
            copy.write_bytes(data)
            config = replace_path(config, dotted, str(copy.resolve()))
        self.kind = kind
        self.config = config
        save_toml(config, self.path / "config.toml")
        self._mcap: McapLog | None = None
        self._log_handler = logging.FileHandler(self.path / "run.log", encoding="utf-8")
        self._log_handler.setFormatter(logging.Formatter(LOG_FORMAT))
        logging.getLogger().addHandler(self._log_handler)
        ours = logging.getLogger("targetlock")
        if ours.getEffectiveLevel() > logging.INFO:     # run.log keeps at least targetlock's INFO messages
            ours.setLevel(logging.INFO)
        self._finalizer = weakref.finalize(self, _detach, self._log_handler)
        RunFolder.latest = self.path
        log.info("run folder %s (%s)", self.path, kind)

    def _prepare(self, overwrite: bool) -> None:
        p = self.path
        try:
            if p.exists() and not p.is_dir():
                raise OutputError(f"--out {p}: is a file, not a folder; choose another --out")
            if p.is_dir() and any(p.iterdir()):
                if not (p / "config.toml").is_file():
                    raise OutputError(f"--out {p}: folder is not empty and not a run folder; choose another --out")
                if not overwrite:
                    raise OutputError(f"--out {p}: holds an earlier run; choose another --out or add --overwrite "
                                      "to replace it")
                shutil.rmtree(p)
            p.mkdir(parents=True, exist_ok=True)
            probe = p / ".write-test"
            probe.write_bytes(b"")
            probe.unlink()
        except OutputError:
            raise
        except OSError as exc:
            raise OutputError(f"--out {p}: cannot create the run folder ({exc.strerror or exc}); choose a "
                              "place you may write to") from None

    @property
    def mcap(self) -> McapLog:
        """``run.mcap`` of this run (created on first use; see :mod:`targetlock.recording`)."""
        if self._mcap is None:
            self._mcap = McapLog(self.file("run.mcap"))
            self._mcap.metadata("config", {"config.toml": self.file("config.toml").read_text(encoding="utf-8")})
        return self._mcap

    def close(self) -> None:
        """Finish ``run.mcap`` and stop writing log messages to ``run.log``."""
        if self._mcap is not None:
            self._mcap.close()
        self._finalizer()

    def __enter__(self) -> "RunFolder":
        return self

    def __exit__(self, exc_type: Any, exc: BaseException | None, tb: Any) -> None:
        if exc is not None and self._finalizer.alive:
            # Into run.log only (the console gets the command line's one-line message).
            self._log_handler.handle(logging.LogRecord("targetlock", logging.ERROR, __file__, 0,
                                                       "run ended by %s: %s", (exc_type.__name__, exc),
                                                       (exc_type, exc, tb)))
        self.close()

    def file(self, name: str) -> Path:
        return self.path / name

    def timeseries(self, columns: Sequence[str], name: str = "timeseries.csv") -> TimeSeriesWriter:
        """A CSV ``name`` written as the run goes, mirrored into ``run.mcap`` on topic ``/<stem>``."""
        return TimeSeriesWriter(self.file(name), columns, mcap=self.mcap, topic="/" + Path(name).stem)

    def write_summary(self, summary: dict) -> Path:
        def clean(v: Any) -> Any:
            if isinstance(v, dict):
                return {k: clean(x) for k, x in v.items()}
            if isinstance(v, (list, tuple)):
                return [clean(x) for x in v]
            if isinstance(v, (np.floating, float)):
                return None if not math.isfinite(float(v)) else float(v)
            if isinstance(v, np.integer):
                return int(v)
            return v
        p = self.file("summary.json")
        p.write_text(json.dumps(clean(summary), indent=2) + "\n")
        return p
