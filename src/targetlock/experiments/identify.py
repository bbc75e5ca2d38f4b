"""Identification of the endoscope model from a recorded hysteresis sweep (issue 9 §4).

A sweep (``targetlock hysteresis``, on the twin or ``--rig``) records, per curve, both handle angles
and both tip angles. For a candidate parameter set the recorded handle angles are replayed through
the model kernel (drives bypassed: the handle *is* the recorded angle) and the simulated tip angles
are compared with the measured ones; ``scipy.optimize.least_squares`` minimises the difference.
Every model evaluation is one batch call of the numba kernel: all curves at once, and for the
Jacobian all forward-difference candidates at once; the multi-start screens many random candidates
in one call too.

**What a sweep can tell.** Divide the tip's torque balance by the cable stiffness at the tip,
k_c = c²·K_c (c: cable arm, K_c: cable stiffness). With g = r_h/c, σ = s₀/c and κ = K_tip/k_c, per axis

    [(g·θ − Φ − σ)₊ − (Φ − g·θ − σ)₊] = κ·Φ + (μ_n/k_c)·(|Φ_x| + |Φ_y| + F_n)·sgn ω + (μ_f/k_c)·ω
                                         + (J/k_c)·dω/dt

1. Only ratios to k_c appear: multiplying K_c, K_tip, μ_n, μ_f and J by one factor, or r_h, s₀ and
   1/c together with c²·K_c fixed, leaves every recorded angle unchanged. The stiffness scale, the
   cable arm, the cable stiffness, the handle radius and the slack in metres are *not* identifiable
   from angles (that would need a force or torque). J/k_c (a time constant² of ~(8 ms)²) is far
   below what a 100-200 Hz sweep resolves; J is kept.
2. Where one cable is taut (most of a sweep) the balance reads, divided by g,
   θ = σ/g + Φ/G ± (μ_n/(k_c·g))·(|Φ_x| + |Φ_y| + F_n) + (μ_f/(k_c·g))·ω with G = g/(1 + κ):
   the static gain G, the slack as a handle angle s₀/r_h, the friction terms per handle angle and
   F_n (separated from μ_n by the bend dependence) are determined by any sweep; g and κ are not
   separately.
3. g and κ separate only where the cable tension changes shape: with slack, the returning tip
   stalls at Φ_stop = μ_n·(|Φ_other| + F_n)/(K_tip − μ_n) on its spring alone; with pretension, both
   cables pull near the centre and the slope there is (1 + κ/2)/g instead of (1 + κ)/g. With no
   slack and no pretension (s₀ ≈ 0) κ is not determined.

So the fit runs on the coordinates of :data:`RATIOS` (five always identifiable, the compliance ratio
κ when the sweep shows it), keeps c and K_c of the starting preset to fix the scale, and reports a
standard error per coordinate from the Jacobian with a flag saying whether this sweep determines
it. The written preset reproduces the measured behaviour; its K_tip, μ_n, μ_f, r_h, s₀ are only
meaningful together with the preset's c and K_c.
"""
from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from ..config import ConfigError, commented_toml, from_dict, param, to_dict
from ..model.drives import DriveParams
from ..model.endoscope import EndoscopeParams, pack_params, simulate, static_gain
from ..model.twin import TwinConfig
from .hysteresis import HysteresisConfig, _program

__all__ = ["RATIOS", "NOT_IDENTIFIABLE", "IdentifyConfig", "Sweep", "IdentifyResult", "load_sweep", "ratios",
           "with_ratios", "replay", "identify", "preset_toml", "plot_fit", "run_identify", "print_summary"]

# The fitted coordinates: (name, unit, meaning). All but the slack are fitted in log space. The
# first five are determined by any sweep; the last separates the cable's compliance from the
# transformer ratio and is seen only where the cables' tension changes shape (slack or pretension).
RATIOS = (
    ("static_gain", "rad/rad", "r_h/c / (1 + K_tip/(c²·K_c)): tip/handle gain with one cable taut, no friction"),
    ("slack_handle", "rad", "s0/r_h: slack per cable as a handle angle (negative: pretension)"),
    ("friction_handle", "rad/rad", "mu_n/(c·K_c·r_h): handle angle Coulomb friction holds back, per rad of "
                                   "|phi_x| + |phi_y| + F_n"),
    ("friction_offset", "rad", "F_n: friction at zero bend as an equivalent angle"),
    ("viscous_handle", "s", "mu_f/(c·K_c·r_h): handle angle viscous friction holds back, per rad/s of tip rate"),
    ("compliance_ratio", "1", "K_tip/(c²·K_c): tip spring over cable stiffness at the tip"),
)
_LOG = np.array([True, False, True, True, True, True])
_STEP = np.array([2e-3, 1e-4, 2e-3, 2e-3, 2e-3, 2e-3])   # forward-difference steps in fit coordinates
# A weak pull of log(compliance_ratio) towards the starting preset, in rad of tip angle per unit of
# log: a factor e off the preset costs as much as one sample off by 1.1°, against thousands of samples
# when the sweep determines it; where it does not, it stays at the preset's value instead of drifting.
_PRIOR_WEIGHT = 0.02

# Fixed physical parameters that are not identifiable from angles, with the reason (summary.json).
NOT_IDENTIFIABLE = {
    "cable_stiffness": "c²·K_c sets the scale of all torques; angles fix ratios to it, not the scale: kept",
    "cable_arm": "appears only in r_h/c, s0/c and c²·K_c: kept",
    "handle_radius": "only r_h/c is observed; metres per radian follow from the preset's cable arm",
    "cable_slack": "only s0/r_h is observed; metres follow from the preset's cable arm",
    "tip_stiffness": "only K_tip/(c²·K_c) is observed; N·m/rad follow from the preset's scale",
    "mu_n": "only mu_n/(c·K_c·r_h) is observed; N·m/rad follow from the preset's scale",
    "mu_f": "only mu_f/(c·K_c·r_h) is observed; N·m·s/rad follow from the preset's scale",
    "tip_inertia": "J/(c²·K_c) is a time constant² far below a sample period squared: invisible; kept",
    "tip_length, n_elements": "kinematics: the sweep measures angles, not positions; kept",
    "friction_model": "a model choice, not a value: kept from the preset",
}



@dataclass(frozen=True)
class IdentifyConfig:
    """The fit's starting point and settings. ``twin.endoscope`` is where the fit starts and sets the
    scale (cable arm, cable stiffness) that angles cannot; ``twin.model_dt`` the replay's step."""
    twin: TwinConfig = dataclasses.field(default_factory=TwinConfig)
    n_starts: int = param(48, lo=1, hi=10000, doc="random starting candidates screened in one batch")
    seed: int = param(0, lo=0, hi=2**63 - 1, doc="seed of the multi-start")


# Drives bypassed in the replay: the handle follows the recorded angle at once.
_REPLAY_DRIVE = DriveParams(time_constant=0.0, max_velocity_ticks=1e9, min_angle=-6.3, max_angle=6.3)


@dataclass
class Sweep:
    """A recorded sweep. ``handle`` and ``tip`` are (T, C, 2) rad on axes (x, y), C curves."""
    time: np.ndarray
    handle: np.ndarray
    tip: np.ndarray
    config: HysteresisConfig
    source: str

    @property
    def sample_period(self) -> float:
        return float(np.median(np.diff(self.time)))


def load_sweep(folder: str | Path) -> Sweep:
    """Read a ``targetlock hysteresis`` run folder (config.toml, timeseries.csv, summary.json)."""
    folder = Path(folder)
    for name in ("config.toml", "timeseries.csv"):
        if not (folder / name).is_file():
            raise ConfigError(f"{folder}: no {name}; RUN_FOLDER must be a run folder of 'targetlock hysteresis'")
    try:
        cfg = from_dict(HysteresisConfig, tomllib.loads((folder / "config.toml").read_text()))
    except ConfigError as exc:
        raise ConfigError(f"{folder / 'config.toml'}: not a hysteresis config: {exc}") from None
    with open(folder / "timeseries.csv") as fh:
        columns = fh.readline().strip().split(",")
    need = {"t", "curve", "handle_deg", "tip_deg", "held_tip_deg"}
    if not need <= set(columns):
        raise ConfigError(f"{folder / 'timeseries.csv'}: needs columns {', '.join(sorted(need))}, "
                          f"has {', '.join(columns)}")
    data = np.loadtxt(folder / "timeseries.csv", delimiter=",", skiprows=1, ndmin=2)
    col = {c: data[:, i] for i, c in enumerate(columns)}
    curve = col["curve"].astype(int)
    n_c = len(cfg.held_angles_deg)
    if set(np.unique(curve)) != set(range(n_c)):
        raise ConfigError(f"{folder / 'timeseries.csv'}: curves {sorted(set(curve))} do not match the config's "
                          f"{n_c} held angles")
    counts = np.bincount(curve)
    if counts.min() != counts.max() or counts[0] < 10:
        raise ConfigError(f"{folder / 'timeseries.csv'}: curves have unequal or too few samples ({counts.tolist()})")
    n_t = counts[0]

    def per_curve(name):
        return np.stack([np.radians(col[name][curve == c]) for c in range(n_c)], axis=1)

    swept, held = cfg.axis, 1 - cfg.axis
    handle = np.empty((n_t, n_c, 2))
    tip = np.empty((n_t, n_c, 2))
    handle[:, :, swept] = per_curve("handle_deg")
    tip[:, :, swept] = per_curve("tip_deg")
    tip[:, :, held] = per_curve("held_tip_deg")
    if "held_handle_deg" in col:
        handle[:, :, held] = per_curve("held_handle_deg")
    else:  # older run folders: the held handle is the program's setpoint
        setpoints, _, _ = _program(cfg, cfg.sample_rate)
        if setpoints.shape[0] != n_t:
            raise ConfigError(f"{folder}: {n_t} samples per curve, but the config's program has {setpoints.shape[0]}")
        handle[:, :, held] = setpoints[:, :, held]
    if not np.all(np.isfinite(handle)):
        raise ConfigError(f"{folder / 'timeseries.csv'}: handle angles must all be finite")
    source = "twin"
    if (folder / "summary.json").is_file():
        import json
        source = json.loads((folder / "summary.json").read_text()).get("source", source)
    return Sweep(col["t"][curve == 0], handle, tip, cfg, source)


def ratios(e: EndoscopeParams) -> np.ndarray:
    """The fitted coordinates of ``e`` (order of :data:`RATIOS`)."""
    k_c = e.cable_arm ** 2 * e.cable_stiffness
    g = e.handle_radius / e.cable_arm
    kappa = e.tip_stiffness / k_c
    return np.array([g / (1 + kappa), e.cable_slack / e.handle_radius, e.mu_n / (k_c * g), e.friction_offset,
                     e.mu_f / (k_c * g), kappa])


def with_ratios(scale: EndoscopeParams, r: np.ndarray) -> EndoscopeParams:
    """``scale`` with the coordinates ``r`` imposed; its cable arm and cable stiffness (the scale) are kept."""
    c = scale.cable_arm
    k_c = c ** 2 * scale.cable_stiffness
    kappa = float(r[5])
    g = float(r[0]) * (1 + kappa)
    return dataclasses.replace(scale, handle_radius=g * c, cable_slack=float(r[1]) * g * c,
                               tip_stiffness=kappa * k_c, mu_n=float(r[2]) * k_c * g,
                               friction_offset=float(r[3]), mu_f=float(r[4]) * k_c * g)


def _to_fit(r: np.ndarray) -> np.ndarray:
    return np.where(_LOG, np.log(np.maximum(np.abs(r), 1e-12)), r)


def _from_fit(z: np.ndarray) -> np.ndarray:
    return np.where(_LOG, np.exp(z), z)


def _start_tip(sweep: Sweep) -> np.ndarray:
    """Initial tip angles (C, 2) rad: per axis, the mean measured tip angle before that axis' handle
    first moves (a resting tip held by friction stays where it is, so every such sample measures
    it; an axis whose handle never moves is averaged over the whole sweep)."""
    moved = np.abs(sweep.handle - sweep.handle[:1]) > 1e-4
    n_t = sweep.handle.shape[0]
    first = np.where(moved.any(axis=0), moved.argmax(axis=0), n_t)
    start = np.zeros(sweep.handle.shape[1:])
    for c, a in np.ndindex(*start.shape):
        window = sweep.tip[:max(1, first[c, a]), c, a]
        start[c, a] = np.nanmean(window) if np.isfinite(window).any() else 0.0
    return start


def replay(sweep: Sweep, candidates: list[EndoscopeParams], model_dt: float, chunk: int = 8,
           block: int = 2000) -> np.ndarray:
    """Tip angles (K, T, C, 2) rad of K candidate endoscopes driven by the recorded handle angles.

    The handle moves linearly between recorded samples (one setpoint per internal step of about
    ``model_dt`` s), as a drive does between encoder reads. Each curve starts at rest from its
    measured tip angles (see :func:`_start_tip`). One batch call of the kernel runs
    ``chunk`` candidates × C curves over ``block`` samples (both bound the memory of long sweeps).
    """
    n_t, n_c, _ = sweep.handle.shape
    period = sweep.sample_period
    sub = max(1, int(round(period / model_dt)))
    # Setpoints of the internal steps between samples k-1 and k, ending exactly on sample k.
    prev = np.concatenate([sweep.handle[:1], sweep.handle[:-1]])
    frac = (np.arange(1, sub + 1) / sub)[None, :, None, None]
    fine = (prev[:, None] + frac * (sweep.handle - prev)[:, None]).reshape(n_t * sub, n_c, 2)
    start = _start_tip(sweep)
    out = np.empty((len(candidates), n_t, n_c, 2))
    for i in range(0, len(candidates), chunk):
        part = candidates[i:i + chunk]
        k = len(part)
        state = np.zeros((k * n_c, 6))
        state[:, 0:2] = np.tile(sweep.handle[0], (k, 1))
        state[:, 2:4] = np.tile(start, (k, 1))
        params = pack_params([e for e in part for _ in range(n_c)], _REPLAY_DRIVE)
        for t0 in range(0, n_t, block):  # time blocks bound the memory; the state carries over
            t1 = min(n_t, t0 + block)
            tips = simulate(state, params, np.tile(fine[t0 * sub:t1 * sub], (1, k, 1)), period / sub)
            out[i:i + k, t0:t1] = tips[sub - 1::sub, :, 2:4].reshape(t1 - t0, k, n_c, 2).transpose(1, 0, 2, 3)
    return out


@dataclass
class IdentifyResult:
    endoscope: EndoscopeParams          # fitted (the scale of the starting preset)
    start: EndoscopeParams              # the starting preset
    ratios: np.ndarray                  # fitted coordinates (order of RATIOS)
    std_error: np.ndarray               # their standard errors (same units)
    identifiable: list[bool]            # ratio determined by this sweep (3 std errors within 10 %)
    rms_deg: float                      # residual rms of the tip angles (deg)
    fitted_tip: np.ndarray              # (T, C, 2) rad
    n_evaluations: int

    def summary(self) -> dict:
        return {
            "residual_rms_deg": self.rms_deg,
            "ratios": {name: {"value": float(v), "std_error": float(s), "unit": unit, "meaning": doc,
                              "identifiable": ok}
                       for (name, unit, doc), v, s, ok in zip(RATIOS, self.ratios, self.std_error, self.identifiable)},
            "endoscope": to_dict(self.endoscope),
            "not_identifiable": NOT_IDENTIFIABLE,
            "kernel_evaluations": self.n_evaluations,
        }


def identify(sweep: Sweep, start: EndoscopeParams, *, model_dt: float = 0.001, n_starts: int = 48,
             seed: int = 0) -> IdentifyResult:
    """Least-squares fit of the coordinates of :data:`RATIOS` to ``sweep``, starting around ``start``
    (whose cable arm and cable stiffness fix the scale; ``model_dt`` s is the replay's step).

    Multi-start: ``n_starts`` candidates drawn around ``start`` (×/÷ 1.5, slack ±2 mm at the preset's
    handle radius) are screened in batches of 8; the best three are refined with ``least_squares``
    (Jacobian by forward differences, one batch call per Jacobian).
    """
    measured = sweep.tip
    valid = np.isfinite(measured)
    if valid.sum() < 20:
        raise ConfigError("the sweep has fewer than 20 finite tip samples")
    n_eval = 0

    z0 = _to_fit(ratios(start))

    def residuals_of(zs: np.ndarray) -> np.ndarray:
        nonlocal n_eval
        n_eval += len(zs)
        tips = replay(sweep, [with_ratios(start, _from_fit(z)) for z in zs], model_dt)
        prior = _PRIOR_WEIGHT * (zs[:, 5:6] - z0[5])
        return np.concatenate([(tips - measured)[:, valid], prior], axis=1)

    cache: dict[bytes, np.ndarray] = {}

    def fun(z):
        key = z.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = residuals_of(z[None])[0]
        return cache[key]

    def jac(z):
        base = fun(z)
        zs = z[None, :] + np.diag(_STEP)
        return ((residuals_of(zs) - base[None, :]) / _STEP[:, None]).T

    rng = np.random.default_rng(seed)
    radius = start.handle_radius
    cands = z0 + np.where(_LOG, rng.uniform(-math.log(1.5), math.log(1.5), (n_starts, 6)),
                          rng.uniform(-0.002 / radius, 0.002 / radius, (n_starts, 6)))
    cands[0] = z0
    costs = np.concatenate([np.sum(residuals_of(cands[i:i + 8]) ** 2, axis=1) for i in range(0, n_starts, 8)])
    sols = [least_squares(fun, cands[i], jac=jac, x_scale="jac", xtol=1e-8, ftol=1e-10, max_nfev=60)
            for i in np.argsort(costs)[:3]]
    z = min(sols, key=lambda sol: sol.cost).x
    res = fun(z)
    j = jac(z)
    dof = max(1, res.size - z.size)
    s2 = float(res @ res) / dof
    # Standard errors from the Gauss-Newton covariance, mapped from fit coordinates to the ratios.
    cov = s2 * np.linalg.pinv(j.T @ j)
    r = _from_fit(z)
    se = np.sqrt(np.maximum(np.diag(cov), 0.0)) * np.where(_LOG, r, 1.0)
    # Determined: three standard errors within 10 % of the value; the slack, which may be ~0, against
    # at least the equivalent of 0.1 mm at the preset's handle radius.
    ref = np.where(_LOG, np.abs(r), np.maximum(np.abs(r), 1e-4 / radius))
    ok = [bool(x) for x in 3.0 * se <= 0.1 * ref]
    fitted = replay(sweep, [with_ratios(start, r)], model_dt)[0]
    rms = math.degrees(math.sqrt(float(np.mean(res[:-1] ** 2))))
    return IdentifyResult(with_ratios(start, r), start, r, se, ok, rms, fitted, n_eval)


def preset_toml(e: EndoscopeParams, base_preset: str, note: str) -> str:
    """A config file (TOML) that other commands accept with ``--config``: the twin's endoscope section."""
    return commented_toml({"twin": {"preset": base_preset, "endoscope": to_dict(e)}}, note)


def plot_fit(sweep: Sweep, fitted_tip: np.ndarray, path) -> None:
    """Measured and fitted tip angle against handle angle, both axes, one colour per curve."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 5.5), dpi=100)
    cfg = sweep.config
    for a, ax in enumerate(axes):
        for c, held in enumerate(cfg.held_angles_deg):
            colour = f"C{c}"
            ax.plot(np.degrees(sweep.handle[:, c, a]), np.degrees(sweep.tip[:, c, a]), ".", ms=1.5, color=colour,
                    alpha=0.35, label=f"held {held:g}°: measured" if a == cfg.axis else None)
            ax.plot(np.degrees(sweep.handle[:, c, a]), np.degrees(fitted_tip[:, c, a]), "-", lw=1.0, color=colour,
                    label=f"held {held:g}°: fitted" if a == cfg.axis else None)
        role = "swept" if a == cfg.axis else "held"
        ax.set_xlabel(f"handle angle {'xy'[a]} (deg)")
        ax.set_ylabel(f"tip angle {'xy'[a]} (deg)")
        ax.set_title(f"axis {'xy'[a]} ({role})")
        ax.grid(alpha=0.3)
    axes[cfg.axis].legend(fontsize=7, loc="upper left")
    fig.suptitle(f"Identification: measured ({sweep.source}) and fitted tip angles")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def run_identify(run_folder: str | Path, cfg: IdentifyConfig, out: str | Path | None = None, *,
                 overwrite: bool = False) -> dict:
    """``targetlock identify``: fit, write ``fitted.toml``, ``identify.png`` and ``summary.json``."""
    import time

    from .runfolder import RunFolder
    sweep = load_sweep(run_folder)
    with RunFolder("identify", cfg, out, overwrite=overwrite) as run:
        t0 = time.perf_counter()
        res = identify(sweep, cfg.twin.endoscope, model_dt=cfg.twin.model_dt, n_starts=cfg.n_starts, seed=cfg.seed)
        seconds = time.perf_counter() - t0
        note = (f"Endoscope identified by 'targetlock identify' from {Path(run_folder).resolve()}\n"
                f"(residual rms {res.rms_deg:.3f} deg). Use with --config. Only ratios to c^2*K_c are identified;\n"
                f"cable_arm and cable_stiffness are the starting preset's and fix the scale (docs/model.md).")
        (run.file("fitted.toml")).write_text(preset_toml(res.endoscope, cfg.twin.preset, note))
        plot_fit(sweep, res.fitted_tip, run.file("identify.png"))
        summary = {"source": sweep.source, "run_folder_measured": str(Path(run_folder)), **res.summary(),
                   "static_gain": static_gain(res.endoscope), "start_preset": cfg.twin.preset, "seconds": seconds,
                   "fitted_preset": str(run.file("fitted.toml")), "run_folder": str(run.path)}
        run.write_summary(summary)
    return summary


def print_summary(summary: dict) -> None:
    """The fitted ratios, a line each, for the terminal."""
    print(f"identified from {summary['run_folder_measured']} ({summary['source']}): residual rms "
          f"{summary['residual_rms_deg']:.3f} deg, static gain {summary['static_gain']:.3f}, "
          f"{summary['seconds']:.1f} s")
    for name, r in summary["ratios"].items():
        flag = "" if r["identifiable"] else "   NOT determined by this sweep"
        print(f"  {name:16s} {r['value']:10.4f} ± {r['std_error']:.4f} {r['unit']:8s}{flag}")
    print(f"fitted preset (use with --config): {summary['fitted_preset']}")
    print(f"run folder: {summary['run_folder']}")
