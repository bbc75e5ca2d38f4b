"""Step response for tuning I (report §5.2, Fig. 6.1).

The target is selected a quarter of the image width off centre (-180 px) with the tip straight;
the lock engages at t = 0 and the response of the x offset is measured for several I values:

* rise time: from 10 % to 90 % of the way from -180 px to 0;
* overshoot: largest excursion past 0, in px and in % of the step;
* settling time: last time the offset is outside ±5 % of the step (9 px).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from .target_lock import RunConfig, run_target_lock

__all__ = ["step_metrics", "run_step_responses", "plot_step_responses"]


def step_metrics(t: np.ndarray, x: np.ndarray, step: float) -> dict:
    """Rise, overshoot and settling of ``x`` (px) over ``t`` (s) for a step starting at ``step`` px."""
    frac = 1.0 - x / step              # 0 at the start, 1 at the centre
    ok = np.isfinite(frac)
    t, frac, x = t[ok], frac[ok], x[ok]
    def first(cond):
        idx = np.flatnonzero(cond)
        return float(t[idx[0]]) if idx.size else math.nan
    t10, t90 = first(frac >= 0.1), first(frac >= 0.9)
    over = float(np.max(np.maximum(frac - 1.0, 0.0))) if frac.size else math.nan
    outside = np.flatnonzero(np.abs(x) > 0.05 * abs(step))
    settle = float(t[outside[-1] + 1]) if outside.size and outside[-1] + 1 < t.size else (math.nan if outside.size else 0.0)
    return {"rise_time_s": t90 - t10, "overshoot_px": over * abs(step), "overshoot_pct": 100.0 * over,
            "settling_time_s": settle, "final_px": float(x[-1]) if x.size else math.nan}


def run_step_responses(cfg: RunConfig, i_values: list[float]) -> list[dict]:
    """One step response per I value; returns metrics plus the (t, x) series."""
    step = cfg.twin.scene.step_offset_px[0]
    out = []
    for i in i_values:
        c = dataclasses.replace(cfg, controller=dataclasses.replace(cfg.controller, i_gain=float(i)))
        s = run_target_lock(c)
        data = s["_data"]
        t = np.concatenate([[0.0], data[:, 0]])
        x = np.concatenate([[step], data[:, 1]])
        m = step_metrics(t, x, step)
        m.update({"i_gain": float(i), "_t": t, "_x": x})
        out.append(m)
    return out


def plot_step_responses(results: list[dict], cfg: RunConfig, path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5), dpi=110)
    for r in results:
        ax.plot(r["_t"], r["_x"], lw=1.2, drawstyle="steps-post",
                label=f"I = {r['i_gain']:g}: rise {r['rise_time_s']:.2f} s, overshoot {r['overshoot_pct']:.0f} %, "
                      f"settle {r['settling_time_s']:.2f} s")
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xlabel("time since target selection (s)")
    ax.set_ylabel("target offset x (px)")
    ax.set_title(f"Step response, {cfg.controller.kind}, latency {cfg.twin.camera.latency:g} s, "
                 f"{cfg.twin.camera.fps:g} fps (report Fig. 6.1)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
