"""Several controllers and/or latencies on the same scenario (report Fig. 6.4, 6.6, 6.7)."""
from __future__ import annotations

import dataclasses


from .target_lock import RunConfig, run_target_lock

__all__ = ["compare", "plot_compare", "with_latency", "with_controller"]


def with_latency(cfg: RunConfig, latency: float) -> RunConfig:
    """``cfg`` with a video latency of ``latency`` s that the lab has measured: the plant's and the one
    the controller assumes (and the frames are stamped with) move together."""
    twin = dataclasses.replace(cfg.twin, camera=dataclasses.replace(cfg.twin.camera, latency=float(latency)))
    knowledge = dataclasses.replace(cfg.knowledge, latency=float(latency))
    return dataclasses.replace(cfg, twin=twin, knowledge=knowledge)


def with_controller(cfg: RunConfig, kind: str) -> RunConfig:
    return dataclasses.replace(cfg, controller=dataclasses.replace(cfg.controller, kind=kind))


def compare(cfg: RunConfig, controllers: list[str], latencies: list[float]) -> list[dict]:
    """Run every controller at every latency on ``cfg``'s scenario; one summary per case."""
    rows = []
    for lat in latencies:
        for kind in controllers:
            rows.append(run_target_lock(with_latency(with_controller(cfg, kind), lat)))
    return rows


def plot_compare(rows: list[dict], cfg: RunConfig, path, title: str | None = None) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4.8), dpi=110)
    for r in rows:
        d = r["_data"]
        ax.plot(d[:, 0], d[:, 3], lw=1.0,
                label=f"{r['controller']}, {r['latency_s']:g} s: rms {r['rms_px']:.0f}, peak {r['peak_px']:.0f} px")
    ax.axvspan(0, cfg.loop.metrics_after, color="0.92")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("total tracking error (px)")
    ax.set_title(title or f"Tracking error on the {cfg.twin.scene.path} path")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper right")
    ax.set_ylim(bottom=0)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
