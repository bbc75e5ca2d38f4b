"""Parameter sweeps: a grid and/or a seeded random set of target-lock runs on a Dask cluster.

A sweep spec (TOML) names the settings every run shares and the ones that vary::

    preset = "calibrated"                 # optional: endoscope preset of the twin
    seed = 7                              # seeds the random draws and every run
    [base]                                # any `targetlock run` settings (as in config.toml)
    loop = { seconds = 20.0 }
    [grid]                                # dotted setting = list of values: the Cartesian product
    "controller.kind" = ["pi", "pi-hc"]
    [random]                              # n seeded draws; each draw is run for every grid point
    n = 10
    "twin.camera.latency" = { uniform = [0.25, 0.6] }
    "twin.endoscope.mu_f" = { loguniform = [0.05, 0.2] }
    "twin.scene.path" = { choice = ["linear", "ellipse"] }

Every case is a complete, validated run config; all are built (and refused with the field name)
before anything is submitted. Each case's config is written to ``cases/case-NNNN.toml`` in the run
folder, so ``targetlock run --config cases/case-NNNN.toml`` reproduces its row. Grid points of the
same draw share the draw's seed, so controllers are compared on identical scopes and noise.

Runs execute on Dask distributed: a :class:`distributed.LocalCluster` of single-threaded worker
processes by default, or an existing scheduler (``--scheduler tcp://host:8786``). Results are
appended to ``results.csv`` as they arrive (a crash keeps the finished rows).
"""
from __future__ import annotations

import contextlib
import csv
import itertools
import logging
import math
import os
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import numpy as np

from ..config import ConfigError, param, save_toml
from ..model.twin import PRESETS, merge, preset_overrides
from .target_lock import RunConfig

__all__ = ["SweepSpec", "Case", "load_spec", "expand", "run_case", "run_cases", "dask_client", "METRICS"]

METRICS = ("rms_px", "peak_px", "p95_px", "mean_px", "rms_x_px", "rms_y_px", "out_of_view_fraction",
           "lost_fraction", "wall_seconds", "realtime_factor")
DISTRIBUTIONS = ("uniform", "loguniform", "choice", "integers")


@dataclass(frozen=True)
class SweepSpec:
    """What a sweep runs: shared settings, a grid and a seeded random set (see the module doc)."""
    preset: str = param("calibrated", choices=PRESETS, doc="endoscope preset of the twin in every case")
    seed: int = param(0, lo=0, hi=2**32 - 1, doc="seed of the random draws; case seeds derive from it")
    base: dict = field(default_factory=dict)
    grid: dict = field(default_factory=dict)
    random: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Case:
    """One run of a sweep: its index, the varied values and the nested overrides of RunConfig."""
    index: int
    draw: int
    varied: dict[str, Any]
    overrides: dict[str, Any]


def load_spec(path: str | Path) -> SweepSpec:
    """Read and check a sweep spec; errors name the file and the setting."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8-sig"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such sweep spec") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    known = {"preset", "seed", "base", "grid", "random"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ConfigError(f"{path}: unknown sweep setting(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    for table in ("base", "grid", "random"):
        if not isinstance(data.get(table, {}), dict):
            raise ConfigError(f"{path}: [{table}] must be a table")
    spec = SweepSpec(preset=data.get("preset", "calibrated"), seed=data.get("seed", 0), base=data.get("base", {}),
                     grid=data.get("grid", {}), random=data.get("random", {}))
    from ..config import validate
    try:
        validate(spec)
        expand(spec)          # builds and validates every case: a bad value is refused before any run
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    return spec


def _nested(dotted: str, value: Any) -> dict:
    out: Any = value
    for part in reversed(dotted.split(".")):
        out = {part: out}
    return out


def _draw(rng: np.random.Generator, name: str, dist: Any) -> Any:
    if not isinstance(dist, dict) or len(dist) != 1 or next(iter(dist)) not in DISTRIBUTIONS:
        raise ConfigError(f"random.{name} must be one of {{ {' | '.join(f'{d} = [...]' for d in DISTRIBUTIONS)} }}, "
                          f"got {dist!r}")
    kind, args = next(iter(dist.items()))
    if kind == "choice":
        if not isinstance(args, list) or not args:
            raise ConfigError(f"random.{name}.choice must be a non-empty list")
        return args[int(rng.integers(len(args)))]
    if not (isinstance(args, list) and len(args) == 2 and all(isinstance(a, (int, float)) for a in args)
            and args[0] <= args[1]):
        raise ConfigError(f"random.{name}.{kind} must be [low, high] with low <= high, got {args!r}")
    lo, hi = args
    if kind == "uniform":
        return float(rng.uniform(lo, hi))
    if kind == "integers":
        return int(rng.integers(int(lo), int(hi) + 1))
    if lo <= 0:
        raise ConfigError(f"random.{name}.loguniform needs low > 0, got {lo!r}")
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def expand(spec: SweepSpec) -> list[Case]:
    """Every case of the sweep (random draws × grid points), each validated as a RunConfig."""
    for name, values in spec.grid.items():
        if not isinstance(values, list) or not values:
            raise ConfigError(f"grid.{name} must be a non-empty list of values, got {values!r}")
    dists = {k: v for k, v in spec.random.items() if k != "n"}
    n_draws = spec.random.get("n", 1 if not dists else None)
    if not isinstance(n_draws, int) or isinstance(n_draws, bool) or not 1 <= n_draws <= 100_000:
        raise ConfigError(f"random.n = {n_draws!r} must be a whole number in [1, 100000]"
                          + (" (needed with random settings)" if n_draws is None else ""))
    rng = np.random.default_rng(spec.seed)
    draws = [{k: _draw(rng, k, d) for k, d in dists.items()} for _ in range(n_draws)]
    grid_names = list(spec.grid)
    points = [dict(zip(grid_names, combo)) for combo in itertools.product(*(spec.grid[k] for k in grid_names))]
    cases: list[Case] = []
    for d, drawn in enumerate(draws):
        case_seed = (spec.seed * 1_000_003 + d) % 2**63
        for point in points:
            varied = {**drawn, **point}
            preset = varied.get("preset", spec.preset)
            data = merge(spec.base, {"twin": merge(preset_overrides(preset), {"preset": preset})})
            data = merge(data, {"seed": case_seed, "tracker": {"seed": case_seed}})
            for name, value in varied.items():
                if name != "preset":
                    data = merge(data, _nested(name, value))
            _config(data, f"case {len(cases)} ({', '.join(f'{k}={v!r}' for k, v in varied.items())})")
            cases.append(Case(index=len(cases), draw=d, varied=varied, overrides=data))
    return cases


def _config(data: dict, where: str) -> RunConfig:
    from ..config import from_dict
    try:
        return from_dict(RunConfig, data)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def run_case(overrides: dict) -> dict:
    """Run one case (in a worker process); returns its flat figures, or ``error`` with the reason."""
    from .target_lock import run_target_lock
    t0 = time.perf_counter()
    try:
        summary = run_target_lock(_config(overrides, "case"))
    except Exception as exc:  # one broken case is a row with its reason, not a lost sweep
        return {"error": f"{type(exc).__name__}: {exc}", "case_seconds": time.perf_counter() - t0}
    row = {k: summary.get(k, math.nan) for k in METRICS}
    tip = summary.get("tip_range_deg") or [math.nan, math.nan]
    row.update(tip_min_deg=tip[0], tip_max_deg=tip[1], case_seconds=time.perf_counter() - t0, error="")
    return row


@contextlib.contextmanager
def dask_client(scheduler: str | None, workers: int | None) -> Iterator[Any]:
    """A Dask client, closed (with its cluster) on leaving: to ``scheduler`` if given, else to a
    LocalCluster of ``workers`` (default: one per core) single-threaded processes."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise ConfigError("--workers and sweeps run on Dask: install it with `pip install 'targetlock[sweep]'`") from None
    # Importing distributed sets its loggers to INFO (dask's logging config), and its scheduler, client and
    # nannies log in this process: ~40 lines around every run, burying the results table. Warnings only,
    # unless debug messages were asked for (-v).
    if logging.getLogger().getEffectiveLevel() > logging.DEBUG:
        logging.getLogger("distributed").setLevel(logging.WARNING)
    cluster = None
    if scheduler:
        try:
            client = Client(scheduler, timeout="10s")
        except OSError as exc:
            raise ConfigError(f"--scheduler {scheduler}: no Dask scheduler answers there ({exc})") from None
    else:
        cluster = LocalCluster(n_workers=workers or os.cpu_count() or 1, threads_per_worker=1, processes=True,
                               host="127.0.0.1", dashboard_address=None, silence_logs=logging.ERROR)
        client = Client(cluster)
    try:
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def run_cases(cases: list[Case], *, scheduler: str | None = None, workers: int | None = None,
              on_result: Callable[[Case, dict], None] | None = None) -> list[dict]:
    """Run ``cases`` on Dask; ``on_result(case, row)`` is called as each finishes. Rows in case order."""
    with dask_client(scheduler, workers) as client:
        from distributed import as_completed
        futures = {client.submit(run_case, c.overrides, key=f"targetlock-case-{c.index}-{id(cases)}", pure=False): c
                   for c in cases}
        rows: dict[int, dict] = {}
        for fut in as_completed(futures):
            case = futures[fut]
            rows[case.index] = fut.result()
            if on_result is not None:
                on_result(case, rows[case.index])
        return [rows[c.index] for c in cases]


class ResultsTable:
    """``results.csv``: one row per finished case, appended and flushed as results arrive."""

    def __init__(self, path: Path, varied: Iterable[str]) -> None:
        self.columns = ["case", "draw", "seed", *varied, *METRICS, "tip_min_deg", "tip_max_deg", "case_seconds",
                        "error", "config"]
        self._fh = Path(path).open("w", newline="")
        self._w = csv.DictWriter(self._fh, self.columns, extrasaction="ignore")
        self._w.writeheader()
        self._fh.flush()

    def add(self, case: Case, row: dict, config_file: str) -> None:
        self._w.writerow({"case": case.index, "draw": case.draw, "seed": case.overrides["seed"], **case.varied,
                          **row, "config": config_file})
        self._fh.flush()

    def close(self) -> None:
        self._fh.close()


def group_stats(cases: list[Case], rows: list[dict], by: list[str]) -> list[dict]:
    """Median, p95 and worst rms/peak per combination of the categorical settings ``by``."""
    groups: dict[tuple, list[dict]] = {}
    for c, r in zip(cases, rows):
        groups.setdefault(tuple(c.varied.get(k) for k in by), []).append(r)
    out = []
    for key, rs in groups.items():
        ok = [r for r in rs if not r.get("error")]
        entry: dict[str, Any] = dict(zip(by, key))
        entry.update(cases=len(rs), failed=len(rs) - len(ok))
        for m in ("rms_px", "peak_px"):
            v = np.array([r[m] for r in ok], dtype=float)
            v = v[np.isfinite(v)]
            entry[f"{m}_median"] = float(np.median(v)) if v.size else math.nan
            entry[f"{m}_p95"] = float(np.percentile(v, 95)) if v.size else math.nan
            entry[f"{m}_worst"] = float(v.max()) if v.size else math.nan
        ov = np.array([r["out_of_view_fraction"] for r in ok], dtype=float)
        entry["left_image_cases"] = int(np.sum(ov > 0))
        out.append(entry)
    return out


def categorical(cases: list[Case]) -> list[str]:
    """Varied settings with non-numeric values (controllers, paths, presets): the groups of a sweep."""
    return [k for k in varied_names(cases) if any(isinstance(c.varied.get(k), (str, bool)) for c in cases)]


def plot_sweep(cases: list[Case], rows: list[dict], path: Path) -> None:
    """rms error against every numeric varied setting, coloured by the categorical groups."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = categorical(cases)
    numeric = [k for k in varied_names(cases) if k not in groups]
    panels = numeric or ["case"]
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.8), dpi=110, squeeze=False)
    labels = [" ".join(str(c.varied.get(g)) for g in groups) or "all" for c in cases]
    for ax, name in zip(axes[0], panels):
        for label in dict.fromkeys(labels):
            sel = [i for i, lab in enumerate(labels) if lab == label and not rows[i].get("error")]
            x = [cases[i].index if name == "case" else cases[i].varied[name] for i in sel]
            ax.scatter(x, [rows[i]["rms_px"] for i in sel], s=14, alpha=0.8, label=label)
        ax.set_xlabel(name)
        ax.set_ylabel("rms tracking error (px)")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def write_case_configs(cases: list[Case], folder: Path) -> list[str]:
    """Each case's resolved config as ``cases/case-NNNN.toml`` (re-run with ``targetlock run --config``)."""
    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for c in cases:
        name = f"cases/case-{c.index:04d}.toml"
        save_toml(_config(c.overrides, f"case {c.index}"), folder.parent / name)
        names.append(name)
    return names


def varied_names(cases: list[Case]) -> list[str]:
    """The settings any case varies, in the spec's order."""
    return list(dict.fromkeys(k for c in cases for k in c.varied))


def sweep_summary(cases: list[Case], rows: list[dict], wall: float, workers: str) -> dict:
    """The figures a sweep prints: per-group statistics, failures and throughput."""
    per_case = np.array([r.get("case_seconds", math.nan) for r in rows], dtype=float)
    busy = float(np.nansum(per_case))
    return {"cases": len(cases), "failed": sum(bool(r.get("error")) for r in rows), "workers": workers,
            "wall_seconds": wall, "case_seconds_median": float(np.nanmedian(per_case)) if per_case.size else math.nan,
            "busy_fraction": busy / wall if wall > 0 else math.nan,
            "groups": group_stats(cases, rows, categorical(cases))}
