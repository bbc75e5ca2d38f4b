"""Endoscope dynamics: handle -> two pull-pull cable pairs -> tip with friction (report §3.2).

Per bending axis a (x or y), with handle angle theta_a (rad) and tip angle Phi_a (rad):

* cable pair stroke  d = r_h·theta - c·Phi          (handle transformer Eq. 3.2, tip Eq. 3.28, c = D/2)
* cable elongations  e+ = d - s0,  e- = -d - s0      (s0: slack per cable; s0 < 0 is pretension)
* pull-only tensions F± = K_c·max(e±, 0)             (Eq. 3.5)
* cable torque       tau_c = c·(F+ - F-)             (power-consistent form of Eq. 3.27)
* tip spring         tau_k = -K_tip·Phi              (Eq. 3.31 with K in N·m/rad)
* friction           tau_f = -mu_f·omega - N_a·sgn(omega),  N_a = mu_n·(|Phi_x| + |Phi_y| + F_n)
  ("both angles", Eq. 3.29 read as the text and Fig. 3.2 require), or N_a = mu_n·|Phi_a|
  ("own angle", the first model, Eq. 3.39)
* tip inertia        J·d(omega)/dt = tau_c + tau_k + tau_f   (Eq. 3.32-3.34)

Integration: a linearly-implicit (backward Euler) time-stepping scheme with set-valued Coulomb
friction, the standard treatment of stick-slip. Each step solves

    (J/dt + mu_f + k·dt)·omega' = J·omega/dt + tau_c + tau_k - N·s,   s in sgn(omega')

where k is the stiffness d(-tau_c - tau_k)/dPhi of the cables currently taut plus the tip spring.
If |J·omega/dt + tau_c + tau_k| <= N the tip sticks (omega' = 0) exactly, so there is no chatter
and no need for the report's tanh(100·omega) smoothing or for event detection; the scheme is
unconditionally stable, first-order convergent, and tends to the quasi-static (massless) force
balance when J -> 0. The 2 axes interact through N (both-angles friction), which is taken at the
start of each step.

Everything runs in one numba kernel over a batch of N endoscopes.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from ..config import param
from .drives import DriveParams, drive_step

__all__ = ["EndoscopeParams", "pack_params", "initial_state", "advance", "simulate", "calibrate_handle_radius", "handle_for_tip", "static_gain",
           "dead_travel", "friction_normal",
           "FRICTION_MODELS"]

FRICTION_MODELS = ("both-angles", "own-angle")

# State layout per endoscope: handle angles [0:2], tip angles [2:4], tip angular rates [4:6] (rad, rad/s).
STATE_SIZE = 6

# Packed parameter layout (one row per endoscope).
_P_RH, _P_C, _P_KC, _P_S0, _P_KT, _P_J, _P_MUF, _P_MUN, _P_FN, _P_MODEL, _P_TAU, _P_VMAX, _P_LO, _P_HI = range(14)
N_PACKED = 14


@dataclass(frozen=True)
class EndoscopeParams:
    """Mechanical parameters of the endoscope (both bending axes alike). SI units.

    Defaults are the ``calibrated`` preset; see docs/model.md for how they were found.
    """
    tip_length: float = param(0.12, unit="m", lo=0.005, hi=0.5, doc="length of the bending section (report: 12 cm)")
    n_elements: int = param(30, lo=1, hi=1000, doc="element pairs of the chained kinematics (report: 30)")
    handle_radius: float = param(0.01672, unit="m/rad", lo=1e-4, hi=0.1,
                                 doc="handle wheel radius, cable stroke per handle radian (transformer 1)")
    cable_arm: float = param(0.006, unit="m", lo=1e-4, hi=0.05,
                             doc="D/2: cable offset from the tip's neutral axis (transformer 2 = 1/cable_arm = 167 rad/m)")
    cable_stiffness: float = param(20000.0, unit="N/m", lo=1.0, hi=1e8, doc="conduit-cable stiffness K_cable (Table 3.1: 20 k)")
    cable_slack: float = param(0.0004, unit="m", lo=-0.01, hi=0.02,
                               doc="slack per cable at the neutral handle (deadband); negative = pretension (looped shaft)")
    tip_stiffness: float = param(1.5, unit="N·m/rad", lo=1e-4, hi=100.0, doc="centring spring of the tip K_tip (Table 3.1)")
    tip_inertia: float = param(5e-5, unit="kg·m²", lo=0.0, hi=1.0,
                               doc="tip inertia about its base (report: 'm_tip = 0.05 g' on the angular 1-junction); 0 = quasi-static")
    mu_f: float = param(0.1, unit="N·m·s/rad", lo=1e-6, hi=100.0, doc="viscous tip friction (Table 3.1)")
    mu_n: float = param(0.1, unit="N·m/rad", lo=0.0, hi=100.0, doc="Coulomb friction growth with bending (Table 3.1)")
    friction_offset: float = param(1.6, unit="rad", lo=0.0, hi=20.0, doc="F_n: friction present at zero bend, as an equivalent angle (Table 3.1)")
    friction_model: str = param("both-angles", choices=FRICTION_MODELS,
                                doc="'both-angles': Eq. 3.29 (second model); 'own-angle': Eq. 3.39 (first model)")


def pack_params(endoscopes: EndoscopeParams | list[EndoscopeParams], drive: DriveParams) -> np.ndarray:
    """Pack endoscope + drive parameters into the (N, N_PACKED) float array the kernel reads."""
    if isinstance(endoscopes, EndoscopeParams):
        endoscopes = [endoscopes]
    out = np.empty((len(endoscopes), N_PACKED))
    for i, e in enumerate(endoscopes):
        out[i] = (e.handle_radius, e.cable_arm, e.cable_stiffness, e.cable_slack, e.tip_stiffness, e.tip_inertia,
                  e.mu_f, e.mu_n, e.friction_offset, FRICTION_MODELS.index(e.friction_model),
                  drive.time_constant, drive.max_velocity, drive.min_angle, drive.max_angle)
    return out


def initial_state(n: int = 1) -> np.ndarray:
    """State array (n, 6) of straight endoscopes at rest with the handles at neutral."""
    return np.zeros((n, STATE_SIZE))


@njit(cache=True, inline="always")
def _tip_axis(theta, phi, omega, normal, p, dt):
    """One implicit step of one bending axis; returns (phi', omega')."""
    c = p[_P_C]
    kc = p[_P_KC]
    s0 = p[_P_S0]
    stroke = p[_P_RH] * theta - c * phi
    e_pos = stroke - s0
    e_neg = -stroke - s0
    tension = 0.0
    taut = 0.0
    if e_pos > 0.0:
        tension += kc * e_pos
        taut += 1.0
    if e_neg > 0.0:
        tension -= kc * e_neg
        taut += 1.0
    tau = c * tension - p[_P_KT] * phi
    stiffness = c * c * kc * taut + p[_P_KT]
    j = p[_P_J]
    b = j * omega / dt + tau
    if abs(b) <= normal:
        return phi, 0.0
    if b > 0.0:
        b -= normal
    else:
        b += normal
    omega_new = b / (j / dt + p[_P_MUF] + stiffness * dt)
    return phi + dt * omega_new, omega_new


@njit(cache=True, inline="always")
def _step_one(s, p, sp0, sp1, dt):
    lo = p[_P_LO]
    hi = p[_P_HI]
    # A non-finite setpoint is ignored (hold): the physics never sees NaN from a caller.
    if sp0 == sp0:
        s[0] = drive_step(s[0], min(max(sp0, lo), hi), dt, p[_P_TAU], p[_P_VMAX])
    if sp1 == sp1:
        s[1] = drive_step(s[1], min(max(sp1, lo), hi), dt, p[_P_TAU], p[_P_VMAX])
    if p[_P_MODEL] == 0.0:
        n = p[_P_MUN] * (abs(s[2]) + abs(s[3]) + p[_P_FN])
        n0 = n
        n1 = n
    else:
        n0 = p[_P_MUN] * abs(s[2])
        n1 = p[_P_MUN] * abs(s[3])
    s[2], s[4] = _tip_axis(s[0], s[2], s[4], n0, p, dt)
    s[3], s[5] = _tip_axis(s[1], s[3], s[5], n1, p, dt)


@njit(cache=True)
def _advance(state, params, setpoints, dt, n_steps):
    for i in range(state.shape[0]):
        s = state[i]
        p = params[i]
        for _ in range(n_steps):
            _step_one(s, p, setpoints[i, 0], setpoints[i, 1], dt)


@njit(cache=True)
def _simulate(state, params, setpoints, dt, substeps, out):
    n_t = setpoints.shape[0]
    for i in range(state.shape[0]):
        s = state[i]
        p = params[i]
        for t in range(n_t):
            for _ in range(substeps):
                _step_one(s, p, setpoints[t, i, 0], setpoints[t, i, 1], dt)
            out[t, i, :] = s


def advance(state: np.ndarray, params: np.ndarray, setpoints: np.ndarray, dt: float, n_steps: int) -> np.ndarray:
    """Advance ``state`` (N, 6) in place by ``n_steps`` internal steps of ``dt`` s.

    ``setpoints`` (N, 2) are handle setpoints in rad, held during the call and clamped to the drive
    range. A non-finite setpoint leaves that axis' drive standing where it is.
    """
    _advance(state, params, np.ascontiguousarray(setpoints, dtype=np.float64), float(dt), int(n_steps))
    return state


def simulate(state: np.ndarray, params: np.ndarray, setpoints: np.ndarray, dt: float, substeps: int = 1) -> np.ndarray:
    """Run a setpoint sequence (T, N, 2) rad, each sample held for ``substeps`` steps of ``dt`` s.

    Returns the state after each sample, (T, N, 6); ``state`` is advanced in place.
    """
    sp = np.ascontiguousarray(setpoints, dtype=np.float64)
    if sp.ndim != 3 or sp.shape[1:] != (state.shape[0], 2):
        raise ValueError(f"setpoints must have shape (T, {state.shape[0]}, 2), got {sp.shape}")
    out = np.empty((sp.shape[0], state.shape[0], STATE_SIZE))
    _simulate(state, params, sp, float(dt), int(substeps), out)
    return out


def static_gain(e: EndoscopeParams) -> float:
    """Tip/handle gain of a frictionless endoscope with one cable taut (rad/rad)."""
    k_c = e.cable_arm ** 2 * e.cable_stiffness
    return e.handle_radius / e.cable_arm * k_c / (k_c + e.tip_stiffness)


def calibrate_handle_radius(e: EndoscopeParams, handle_angle: float = math.radians(110.0),
                            tip_angle: float = math.radians(90.0)) -> float:
    """Handle radius (m/rad) that makes ``handle_angle`` bend the tip to ``tip_angle`` (report §3.4.1).

    Closed-form quasi-static force balance of one axis bent outwards (one cable taut, friction
    opposing the motion, other axis straight):
        c·K_c·(r_h·theta - c·Phi - s0) = K_tip·Phi + N(Phi)
    """
    # handle_for_tip gives the cable stroke when the radius is 1 m/rad.
    return handle_for_tip(dataclasses.replace(e, handle_radius=1.0), tip_angle) / handle_angle


def friction_normal(e: EndoscopeParams, own: float, other: float) -> float:
    """Coulomb friction torque N (N·m) of an axis at tip angle ``own`` (rad), the other axis at ``other``
    (rad): the kernel's friction law for ``e.friction_model``."""
    if e.friction_model == "both-angles":
        return e.mu_n * (abs(own) + abs(other) + e.friction_offset)
    return e.mu_n * abs(own)


def dead_travel(e: EndoscopeParams, handle: np.ndarray, tip: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Handle travel (rad, per axis, signed) left before a tip at rest at ``tip`` (rad) starts to move
    when the handle, now at ``handle`` (rad), turns in ``direction`` (sign per axis; 0: none): the
    cables' slack still to take up plus the friction band still to cross, quasi-statically. 0 where the
    tip would move at once (it is already at its break-away point, or the axis is not asked to move).

    Force balance at break-away in direction s: c·T(d) − K_tip·Phi = s·N, with T the pull-only cable
    pair's net tension at stroke d = r_h·theta − c·Phi (the kernel's force law)."""
    tip = np.asarray(tip, dtype=float)
    c, kc, s0 = e.cable_arm, e.cable_stiffness, e.cable_slack
    out = np.zeros(2)
    for a in range(2):
        s = float(np.sign(direction[a]))
        if s == 0.0:
            continue
        n = friction_normal(e, tip[a], tip[1 - a])
        t = (e.tip_stiffness * tip[a] + s * n) / (c * kc)          # net cable stretch needed (m)
        if s0 >= 0.0:                                                # one cable taut, the other slack
            d = s0 + t if t > 0.0 else -s0 + t
        else:                                                        # pretension: both taut near the centre
            d = t / 2.0 if abs(t) <= -2.0 * s0 else (t + s0 if t > 0.0 else t - s0)
        travel = (d + c * tip[a]) / e.handle_radius - float(handle[a])
        if s * travel > 0.0:
            out[a] = travel
    return out


def handle_for_tip(e: EndoscopeParams, tip_angle: float) -> float:
    """Handle angle (rad) that bends a straight axis out to ``tip_angle`` (rad), quasi-statically.

    A straight tip needs the handle at neutral: 0 for ``tip_angle == 0``."""
    if tip_angle == 0.0:
        return 0.0
    sign = 1.0 if tip_angle > 0 else -1.0
    phi = abs(tip_angle)
    normal = friction_normal(e, phi, 0.0)
    tension = (e.tip_stiffness * phi + normal) / e.cable_arm
    stroke = tension / e.cable_stiffness + e.cable_arm * phi + e.cable_slack
    if e.cable_slack < 0:  # both cables taut near the centre share the load
        stroke = max(stroke, (e.tip_stiffness * phi + normal) / (2 * e.cable_arm * e.cable_stiffness) + e.cable_arm * phi)
    return sign * stroke / e.handle_radius
