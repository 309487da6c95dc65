"""The sampled law on the linear six-step drive (the DC equivalent, 2008 eq 1 constants).

:func:`six_step_closed_loop` is the discrete closed loop of the law (integrator,
derivative memory and filter, current feedback) with the firmware's speed
measurement and the command applied one PWM period after the sample;
:func:`sampled_radius` its largest |eigenvalue| over the law's gains at the
check points and R at its uncertainty; :func:`six_step_equilibrium` the
drive's steady state at a speed.
"""
from __future__ import annotations

import math

import numpy as np
import scipy.linalg as sla

from ..models.tfmodel import motor_ss

__all__ = ["six_step_closed_loop", "law_check_points", "sampled_radius", "six_step_equilibrium"]

RPM = 2.0 * math.pi / 60.0      # rad/s per rpm


def six_step_closed_loop(profile, gains, ts: float, derivative_filter_hz: float | None, *, r_factor: float = 1.0,
                         delay_s: float | None = None) -> np.ndarray:
    """Discrete closed-loop matrix of the law on the linear six-step plant (DC equivalent).

    Plant ``L i' = u - R i - Kb w``, ``J w' = Kt i - B w`` (R x ``r_factor``);
    the command of sample k acts from ``t_k + delay_s`` (default one PWM
    period) to ``t_{k+1} + delay_s``; the speed the law sees is the firmware's
    ``y_k = 1.5 w_avg[k] - 0.5 w_avg[k-1]`` (``w_avg`` the mean over the last
    sample); the current it sees is the line current at the sample.  State
    ``[i, w, w_avg, w_avg_prev, u_prev, I, y_prev, d]``; the law is linear when
    unsaturated (deviation coordinates, r = 0)."""
    Am, Bm = motor_ss(profile, r_factor=r_factor)
    hd = (1.0 / profile.inverter.pwm_frequency_hz) if delay_s is None else float(delay_s)
    hd = min(max(hd, 0.0), ts)
    # x = [i, w, s] with s' = w (s: angle over the sample), input u
    Ac = np.zeros((3, 3))
    Ac[:2, :2] = Am
    Ac[2, 1] = 1.0
    Bc = np.array([Bm[0, 0], 0.0, 0.0])

    def zoh(h):
        M = sla.expm(np.block([[Ac, Bc[:, None]], [np.zeros((1, 4))]]) * h)
        return M[:3, :3], M[:3, 3]
    F1, G1 = zoh(hd)
    F2, G2 = zoh(ts - hd)
    kp, ki, kd, kc = gains.kp, gains.ki, gains.kd, gains.kc
    a = 1.0
    if derivative_filter_hz:
        a = ts / (ts + 1.0 / (2 * math.pi * derivative_filter_hz))
    N = 8

    def step(z):
        i, w, wa, wap, up, I, yp, d = z
        y = 1.5 * wa - 0.5 * wap
        I1 = I - ki * ts * y
        d1 = (1 - a) * d + a * kd * (yp - y) / ts
        u = -kp * y + I1 + d1 - kc * i
        x = F1 @ np.array([i, w, 0.0]) + G1 * up
        x = F2 @ x + G2 * u
        return np.array([x[0], x[1], x[2] / ts, wa, u, I1, y, d1])
    return np.column_stack([step(e) for e in np.eye(N)])


def law_check_points(profile, law) -> list[float]:
    """Speeds (rad/s) at which the sampled loop is checked: 0, the rule centres, the step target."""
    from ..models.tsfuzzy import rule_centres
    pts = {0.0}
    n1, n2 = law.premise_rad_s
    if law.n_rules > 1:
        pts.update(float(c) for c in rule_centres((n1, n2), law.n_rules))
    pts.add(profile.speed_step_rpm() * RPM)
    return sorted(pts)


def sampled_radius(profile, law, plant_at=None) -> tuple[float, str]:
    """Largest |eigenvalue| of :func:`six_step_closed_loop` over the law's gains at
    :func:`law_check_points` and R nominal and at -+``design.resistance_uncertainty``, and where
    it occurs (a phrase).  Below 1: the sampled loop is stable there.  ``plant_at(w)``: the plant
    (a profile-like object, see :func:`six_step_closed_loop`) at check speed ``w`` rad/s; default the
    profile's DC equivalent at every speed (the verification's check)."""
    eps = float(profile.design.get("resistance_uncertainty", 0.1))
    worst, where = -1.0, ""
    for w in law_check_points(profile, law):
        g = law.gains_at(w)
        plant = profile if plant_at is None else plant_at(w)
        for rs in (1.0 - eps, 1.0, 1.0 + eps):
            Acl = six_step_closed_loop(plant, g, law.sample_time_s, law.derivative_filter_hz, r_factor=rs)
            rad = float(np.max(np.abs(np.linalg.eigvals(Acl))))
            if rad > worst:
                worst, where = rad, f"gains at {w / RPM:.0f} rpm, R x {rs:g}"
    return worst, where


def six_step_equilibrium(profile, omega_rad_s: float, load_n_m: float = 0.0, r_factor: float = 1.0):
    """Steady state of the six-step DC-equivalent drive at a speed: ``(i, u)`` (A, V)."""
    m = profile.motor
    i = (m.viscous_friction_n_m_s * omega_rad_s + load_n_m) / m.kt_n_m_per_a
    return i, m.kb_v_s_per_rad * omega_rad_s + m.r_line_ohm * r_factor * i
