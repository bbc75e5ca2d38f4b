"""Hysteresis and deadband sweep (report §2.2, §3.1, §3.5; Fig. 3.2 / 3.15).

The handle of one axis sweeps left-right with growing amplitude while the other axis' tip is held
at a chosen bend. All held angles run as one batch through the model kernel. The curves are then
measured:

* ``hysteresis_width_deg``: the largest handle-angle gap between the increasing-handle and the
  decreasing-handle branch of the largest cycle at equal tip angle;
* ``reversal_width_deg``: per sweep amplitude, how far the handle turns back before the tip
  follows (the stall at each reversal) — it grows with the bend;
* ``deadband_deg``: the handle-angle span of the stall near the centre on the returning branch;
* ``stop_angle_deg``: the tip angle at which the returning tip stalls (0 when it does not);
* ``total_gain``: tip angle / handle angle at full bend (report: 90/110).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import median_filter

from ..config import ConfigError, param
from ..model.endoscope import handle_for_tip, initial_state, pack_params, simulate
from ..model.twin import TwinConfig

__all__ = ["HysteresisConfig", "HysteresisResult", "run_sweep", "run_sweep_on_rig", "analyse_curve", "plot"]


@dataclass(frozen=True)
class HysteresisConfig:
    twin: TwinConfig = field(default_factory=TwinConfig)
    axis: int = param(0, lo=0, hi=1, doc="swept axis (0: x, 1: y); the other one is held")
    held_angles_deg: tuple[float, ...] = param((0.0, 30.0, 50.0, 70.0), unit="deg", lo=-120.0, hi=120.0,
                                               doc="tip bends of the held axis, one curve each")
    amplitudes_deg: tuple[float, ...] = param((30.0, 55.0, 80.0, 110.0), unit="deg", lo=1.0, hi=115.0,
                                              doc="handle sweep amplitudes, growing")
    sweep_speed_deg_s: float = param(10.0, unit="deg/s", lo=0.1, hi=90.0, doc="handle speed (slow: quasi-static)")
    sample_rate: float = param(200.0, unit="Hz", lo=10.0, hi=10000.0, doc="recorded samples per second")

    def check(self, prefix: str = "") -> None:
        if list(self.amplitudes_deg) != sorted(self.amplitudes_deg):
            raise ConfigError(f"{prefix}amplitudes_deg = {self.amplitudes_deg} must grow")
        if not self.held_angles_deg:
            raise ConfigError(f"{prefix}held_angles_deg must name at least one angle")


@dataclass
class HysteresisResult:
    time: np.ndarray          # (T,) s
    handle: np.ndarray        # (T, C) rad, swept handle per curve
    tip: np.ndarray           # (T, C) rad, swept tip angle per curve
    held_tip: np.ndarray      # (T, C) rad, the held axis' tip angle
    held_handle: np.ndarray   # (T, C) rad, the held axis' handle angle
    phase: np.ndarray         # (T,) int, index of the sweep cycle (-1 while positioning)
    curves: list[dict]
    total_gain: float


def _sweep_profile(cfg: HysteresisConfig) -> tuple[np.ndarray, np.ndarray]:
    """Swept handle setpoint (rad) and cycle index per sample: 0 -> +A -> -A -> 0 per amplitude,
    ending with one more -A -> +A so the largest cycle has both complete branches."""
    dt = 1.0 / cfg.sample_rate
    speed = math.radians(cfg.sweep_speed_deg_s)
    knots = [0.0]
    phases = []
    for k, a in enumerate(cfg.amplitudes_deg):
        a = math.radians(a)
        for target in (a, -a, 0.0):
            knots.append(target)
            phases.append(k)
    a = math.radians(cfg.amplitudes_deg[-1])
    last = len(cfg.amplitudes_deg) - 1
    knots[-1] = -a  # the last cycle runs on to -A, then back up to +A
    knots.append(a)
    phases.append(last)
    pos, idx = [], []
    for i in range(len(knots) - 1):
        n = max(2, int(round(abs(knots[i + 1] - knots[i]) / speed / dt)))
        seg = np.linspace(knots[i], knots[i + 1], n, endpoint=False)
        pos.append(seg)
        idx.append(np.full(n, phases[i]))
    pos.append(np.array([knots[-1]]))
    idx.append(np.array([last]))
    return np.concatenate(pos), np.concatenate(idx).astype(int)


def _program(cfg: HysteresisConfig, sample_rate: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Handle setpoints (T, curves, 2) rad at ``sample_rate``, cycle index per sample (-1 while the
    held axis is being positioned: bent out over 3 s, settled 1 s), and the positioning length."""
    dt_sample = 1.0 / sample_rate
    sweep, phase = _sweep_profile(dataclasses.replace(cfg, sample_rate=sample_rate))
    e = cfg.twin.endoscope
    held_handle = np.array([handle_for_tip(e, math.radians(h)) for h in cfg.held_angles_deg])
    n_pos = int(round(4.0 / dt_sample))
    ramp = np.clip(np.arange(n_pos) / (3.0 / dt_sample), 0.0, 1.0)
    setpoints = np.zeros((n_pos + sweep.size, len(held_handle), 2))
    swept, held = cfg.axis, 1 - cfg.axis
    setpoints[:n_pos, :, held] = ramp[:, None] * held_handle[None, :]
    setpoints[n_pos:, :, held] = held_handle[None, :]
    setpoints[n_pos:, :, swept] = sweep[:, None]
    return setpoints, np.concatenate([np.full(n_pos, -1), phase]), n_pos


def _result(cfg: HysteresisConfig, t, handle, tip, held_tip, held_handle, phase, n_pos) -> HysteresisResult:
    curves = []
    for c in range(handle.shape[1]):
        m = analyse_curve(handle[n_pos:, c], tip[n_pos:, c], phase[n_pos:], len(cfg.amplitudes_deg))
        m["second_angle_deg"] = float(cfg.held_angles_deg[c])
        m["second_angle_measured_deg"] = float(np.degrees(np.nanmean(held_tip[n_pos:, c])))
        curves.append(m)
    zero = int(np.argmin(np.abs(np.asarray(cfg.held_angles_deg))))
    return HysteresisResult(t, handle, tip, held_tip, held_handle, phase, curves, curves[zero]["total_gain"])


def run_sweep(cfg: HysteresisConfig) -> HysteresisResult:
    """Simulate the sweep for every held angle (one batch) and measure the curves."""
    twin = cfg.twin
    dt_sample = 1.0 / cfg.sample_rate
    substeps = max(1, int(round(dt_sample / twin.model_dt)))
    setpoints, phase, n_pos = _program(cfg, cfg.sample_rate)
    n = setpoints.shape[1]
    out = simulate(initial_state(n), pack_params([twin.endoscope] * n, twin.drive), setpoints,
                   dt_sample / substeps, substeps)
    swept, held = cfg.axis, 1 - cfg.axis
    t = np.arange(setpoints.shape[0]) * dt_sample
    return _result(cfg, t, out[:, :, swept], out[:, :, 2 + swept], out[:, :, 2 + held], out[:, :, held], phase, n_pos)


def run_sweep_on_rig(cfg: HysteresisConfig, rig, *, clock=None, progress: bool = False) -> HysteresisResult:
    """The same sweep through a rig's drives, the tip measured by the rig (motion capture), in real time,
    sampled (setpoints sent, positions read) at ``cfg.sample_rate`` like the simulated sweep.

    Curves run one after the other; between them both handles return to neutral over 3 s.
    ``rig`` needs ``drives`` and ``tip_measurement() -> (angles rad, capture time s monotonic)``.
    Handle angles are the drives' positions, interpolated to each motion-capture sample's capture
    time: a tip sample some milliseconds old must meet the handle angle of that moment (report §3.1).
    ``progress``: a progress bar (sweep seconds) on stderr.
    """
    import sys
    import time

    from tqdm import tqdm

    from ..loop.clock import WallClock
    clock = clock or WallClock()
    drives = rig.drives
    rpt = drives.rad_per_tick
    if not drives.homed:
        drives.home()
    sample_rate = cfg.sample_rate
    setpoints, phase, n_pos = _program(cfg, sample_rate)
    n_t, n = setpoints.shape[:2]
    handle = np.full((n_t, n, 2), np.nan)
    t_handle = np.full((n_t, n), np.nan)
    tips = np.full((n_t, n, 2), np.nan)
    t_tip = np.full((n_t, n), np.nan)
    back = np.linspace(1.0, 0.0, int(3.0 * sample_rate))
    bar = tqdm(total=round(n * (n_t + back.size) / sample_rate), unit="s", file=sys.stderr, leave=False,
               disable=None if progress else True)
    clock.start()
    k_total = 0
    for c in range(n):
        for k in range(n_t):
            k_total += 1
            if k_total % int(sample_rate) == 0:
                bar.update(1)
            clock.sleep_until(k_total / sample_rate)
            drives.send_setpoints(np.rint(setpoints[k, c] / rpt).astype(np.int64))
            handle[k, c] = drives.positions() * rpt
            t_handle[k, c] = time.monotonic()
            tips[k, c], t_tip[k, c] = rig.tip_measurement()
        last = setpoints[-1, c]
        for f in back:  # return to neutral before the next curve
            k_total += 1
            if k_total % int(sample_rate) == 0:
                bar.update(1)
            clock.sleep_until(k_total / sample_rate)
            drives.send_setpoints(np.rint(f * last / rpt).astype(np.int64))
    bar.close()
    # Handle angle at each tip sample's capture time; a missed mocap sample holds the previous one.
    for c in range(n):
        for a in range(2):
            handle[:, c, a] = np.interp(t_tip[:, c], t_handle[:, c], handle[:, c, a])
    for c in range(n):
        for a in range(2):
            col = tips[:, c, a]
            idx = np.where(np.isfinite(col), np.arange(n_t), 0)
            tips[:, c, a] = col[np.maximum.accumulate(idx)]
    # Motion capture carries glitches (a sample received late, marker noise); the width is a
    # largest gap, so one glitch would set it. A 5-sample median removes them and leaves every
    # monotone stretch of the trace unchanged. The handle (the drives' encoders) needs none.
    tips = median_filter(tips, size=(5, 1, 1), mode="nearest")
    swept, held = cfg.axis, 1 - cfg.axis
    t = np.arange(n_t) / sample_rate
    return _result(cfg, t, handle[:, :, swept], tips[:, :, swept], tips[:, :, held], handle[:, :, held], phase, n_pos)


def _branch_gap(inc_h, inc_t, dec_h, dec_t) -> np.ndarray:
    """Handle-angle gap (rad) between branches at equal tip angle, over the common tip range."""
    lo = max(inc_t.min(), dec_t.min())
    hi = min(inc_t.max(), dec_t.max())
    if hi - lo < 1e-6:
        return np.zeros(1)
    levels = np.linspace(lo, hi, 400)[1:-1]
    # Handle angle where each branch first reaches a level: the running extreme makes the tip
    # monotone along its branch, so stalls become flat steps and interpolation is well defined.
    inc_env = np.maximum.accumulate(inc_t)
    dec_env = np.minimum.accumulate(dec_t)
    i_inc = np.searchsorted(inc_env, levels, side="left")
    i_dec = np.searchsorted(-dec_env, -levels, side="left")
    ok = (i_inc < inc_h.size) & (i_dec < dec_h.size)
    return inc_h[i_inc[ok]] - dec_h[i_dec[ok]]


def _stalls(h, t, gain):
    """Runs (start, end) of samples where the tip does not follow the handle (slope < 5 % of gain)."""
    dh = np.abs(np.diff(h))
    dt = np.abs(np.diff(t))
    stuck = dt < 0.05 * gain * np.maximum(dh, 1e-12)
    runs, start = [], None
    for i, s in enumerate(stuck):
        if s and start is None:
            start = i
        elif not s and start is not None:
            runs.append((start, i))
            start = None
    if start is not None:
        runs.append((start, len(stuck)))
    return runs


def analyse_curve(handle: np.ndarray, tip: np.ndarray, phase: np.ndarray, n_cycles: int) -> dict:
    """Measure one hysteresis curve (handle and tip in rad; phase: cycle index per sample)."""
    last = phase == n_cycles - 1
    h, t = handle[last], tip[last]
    i_top = int(np.argmax(h))
    i_bot = i_top + int(np.argmin(h[i_top:]))
    dec_h, dec_t = h[i_top:i_bot + 1], t[i_top:i_bot + 1]
    inc_h, inc_t = h[i_bot:], t[i_bot:]
    gain = float(t[i_top] / h[i_top]) if h[i_top] > 0 else float("nan")
    width = float(np.max(_branch_gap(inc_h, inc_t, dec_h, dec_t)))

    # The stall after each reversal at +A: how far the handle returns before the tip follows.
    reversal = []
    for k in range(n_cycles):
        sel = np.flatnonzero(phase == k)
        hk, tk = handle[sel], tip[sel]
        top = int(np.argmax(hk))
        # The tip lags the handle by its viscous time constant, so the stall starts a few samples late.
        early = np.flatnonzero(hk[top:] < hk[top] - 0.05 * (hk[top] - hk.min()))
        limit = int(early[0]) if early.size else hk.size - top
        runs = [r for r in _stalls(hk[top:], tk[top:], gain) if r[0] <= limit]
        reversal.append(float(np.degrees(hk[top] - hk[top + runs[0][1]])) if runs else 0.0)

    # Returning branches (towards and through the centre): look for a stall near the centre.
    deadbands, stops = [], []
    for bh, bt in ((dec_h, dec_t), (inc_h, inc_t)):
        peak = np.max(np.abs(bt))
        central = [r for r in _stalls(bh, bt, gain)
                   if r[0] > 2 and abs(bt[r[0]]) < 0.5 * peak and np.sign(bt[r[0]]) == np.sign(bt[0])]
        if central:
            s, e_ = central[0]
            deadbands.append(abs(bh[e_] - bh[s]))
            stops.append(abs(bt[s]))
        else:
            deadbands.append(0.0)
            stops.append(0.0)
    return {
        "hysteresis_width_deg": math.degrees(width),
        "reversal_width_deg": reversal,
        "deadband_deg": math.degrees(float(np.mean(deadbands))),
        "stop_angle_deg": math.degrees(float(np.mean(stops))),
        "total_gain": gain,
    }


def plot(result: HysteresisResult, cfg: HysteresisConfig, path) -> None:
    """Tip angle against handle angle, one curve per held angle (Fig. 3.2 / 3.15 style)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 6), dpi=110)
    sweeping = result.phase >= 0
    for c, held in enumerate(cfg.held_angles_deg):
        m = result.curves[c]
        ax.plot(np.degrees(result.handle[sweeping, c]), np.degrees(result.tip[sweeping, c]), lw=1.1,
                label=f"held {held:g}°: width {m['hysteresis_width_deg']:.1f}°, deadband {m['deadband_deg']:.1f}°")
    axis = "xy"[cfg.axis]
    ax.set_xlabel(f"handle angle {axis} (deg)")
    ax.set_ylabel(f"tip angle {axis} (deg)")
    ax.set_title(f"Hysteresis sweep, preset '{cfg.twin.preset}' (gain {result.total_gain:.3f})")
    ax.axhline(0, color="0.8", lw=0.6)
    ax.axvline(0, color="0.8", lw=0.6)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
