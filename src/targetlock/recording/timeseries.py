"""Time series of a run as CSV, written as the run goes (optionally mirrored into ``run.mcap``)."""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .mcap_log import McapLog

__all__ = ["TimeSeriesWriter"]


class TimeSeriesWriter:
    """CSV writer that flushes at least every ``flush_seconds`` of wall time, so data survive a crash.

    With ``mcap``, every row also goes to that log on ``topic``, at the time of its ``t`` column
    (s; the row number where there is none)."""

    def __init__(self, path: Path, columns: Sequence[str], *, flush_seconds: float = 0.5, mcap: McapLog | None = None,
                 topic: str = "/timeseries") -> None:
        self.path = Path(path)
        self._mcap, self._topic = mcap, topic
        self._t_col = list(columns).index("t") if "t" in columns else None
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
        self._mirror(row, self.n_rows)
        self.n_rows += 1
        if len(self._rows) >= 4096 or time.monotonic() - self._last_flush > self._flush_seconds:
            self.flush()

    def write_many(self, rows: np.ndarray) -> None:
        for k, r in enumerate(np.asarray(rows)):
            self._rows.append(r)
            self._mirror(r, self.n_rows + k)
        self.n_rows += len(rows)
        self.flush()

    def _mirror(self, row: Sequence[float], index: int) -> None:
        if self._mcap is not None:
            self._mcap.row(self._topic, float(row[self._t_col]) if self._t_col is not None else float(index),
                           self.columns, row)

    def flush(self) -> None:
        if self._rows:
            np.savetxt(self._fh, np.asarray(self._rows, dtype=float), delimiter=",", fmt="%.9g")
            self._rows.clear()
        self._fh.flush()
        if self._mcap is not None:
            self._mcap.flush()
        self._last_flush = time.monotonic()

    def close(self) -> None:
        if not self._fh.closed:
            self.flush()
            self._fh.close()

    def __enter__(self) -> "TimeSeriesWriter":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
