"""Run folders: every experiment writes its resolved config, time series, plots and summary.

Layout of a run folder::

    config.toml        the full resolved configuration (re-run with --config config.toml)
    timeseries.csv     one row per sample, written as the run goes (a crash keeps what was recorded)
    summary.json       the figures the command printed
    *.png              plots
"""
from __future__ import annotations

import json
import math
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..config import save_toml

__all__ = ["RunFolder", "TimeSeriesWriter"]


class TimeSeriesWriter:
    """CSV writer that flushes at least every ``flush_seconds`` of wall time, so data survive a crash."""

    def __init__(self, path: Path, columns: Sequence[str], *, flush_seconds: float = 0.5) -> None:
        self.path = Path(path)
        self.columns = list(columns)
        self._fh = self.path.open("w", buffering=1 << 16)
        self._fh.write(",".join(self.columns) + "\n")
        self._fh.flush()
        self._rows: list[Sequence[float]] = []
        self._flush_seconds = flush_seconds
        self._last_flush = time.monotonic()
        self.n_rows = 0

    def write(self, row: Sequence[float]) -> None:
        if len(row) != len(self.columns):
            raise ValueError(f"row has {len(row)} values for {len(self.columns)} columns")
        self._rows.append(row)
        self.n_rows += 1
        if len(self._rows) >= 4096 or time.monotonic() - self._last_flush > self._flush_seconds:
            self.flush()

    def write_many(self, rows: np.ndarray) -> None:
        for r in np.asarray(rows):
            self._rows.append(r)
        self.n_rows += len(rows)
        self.flush()

    def flush(self) -> None:
        if self._rows:
            np.savetxt(self._fh, np.asarray(self._rows, dtype=float), delimiter=",", fmt="%.9g")
            self._rows.clear()
        self._fh.flush()
        self._last_flush = time.monotonic()

    def close(self) -> None:
        if not self._fh.closed:
            self.flush()
            self._fh.close()

    def __enter__(self) -> "TimeSeriesWriter":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class RunFolder:
    """A folder for one experiment run; created at construction, config written immediately."""

    def __init__(self, kind: str, config: Any, out: str | Path | None = None, root: str | Path = "runs") -> None:
        if out is None:
            stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S-%f")
            out = Path(root) / f"{kind}-{stamp}"
        self.path = Path(out)
        self.path.mkdir(parents=True, exist_ok=True)
        self.kind = kind
        self.config = config
        save_toml(config, self.path / "config.toml")

    def file(self, name: str) -> Path:
        return self.path / name

    def timeseries(self, columns: Sequence[str], name: str = "timeseries.csv") -> TimeSeriesWriter:
        return TimeSeriesWriter(self.file(name), columns)

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
