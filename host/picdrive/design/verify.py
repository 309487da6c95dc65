"""Verification every design passes before it is saved as usable.

``verify_design(profile, result)`` is method-agnostic: it reads the law
(:class:`picdrive.control_law.ScheduledLaw`, the thing the firmware runs)
and, when present, the certificate, and fills ``result.verification`` with
entries ``{"value", "limit", "ok", "unit", "note"}``; any failed entry calls
``result.fail(reason)``.

The plant every law is judged on is the drive the firmware runs: the
six-step bridge (high-side PWM, low side on) on the motor's DC equivalent
(2008 eq 1 constants of the profile), with the pair's back-EMF as the hall
table commutates it, the conduction rule of the bridge (the current cannot
reverse while ``0 <= u <`` back-EMF: no braking torque; ``u < 0`` plugs after
one sample with all switches off), the firmware's measurement chain (M/T
speed with half a sample of extrapolation, or -- ``sensors.speed_source =
"hall"`` -- the hall-edge period in Timer5 ticks of the firmware's own plan,
:class:`picdrive.models.simulate.HallSpeedMeter`; one ADC sample of the bus
current) and its current window (:func:`picdrive.models.simulate.simulate_six_step`).
``tests/test_verify_twin.py`` checks that this model predicts the motor twin
(firmware in the loop, three-phase plant) for every committed design.

Checks:

* ``law_current_window`` -- the law carries the firmware's current window
  (``current_limit_a``, ``kb_v_s_per_rad``, ``r_ohm`` = the profile's
  ``inverter.current_limit_a``, ``motor.kb_v_s_per_rad``, ``motor.r_line_ohm``):
  the firmware applies it whatever the design says, so the float law must too.
* ``sampled_spectral_radius`` -- the discrete-time closed loop of the law
  (integrator, derivative memory and filter, current feedback) on the
  linear six-step plant (DC equivalent) sampled at ``speed_loop_hz``, with
  the firmware's speed measurement (``1.5 w_avg[k] - 0.5 w_avg[k-1]``) and the
  command applied one PWM period after the sample; the gains at 0, the rule
  centres and the step target; R nominal and +-``design.resistance_uncertainty``.
  Largest |eigenvalue|, limit 1.
* ``integrator_headroom_v`` -- the integrator range ``I_lim`` against what the
  law's integrator holds at the six-step equilibria up to the step target
  with and without the load (``u* + kp (1 - b) w* + kc i*``).
* ``lmi_max_eig``, ``continuous_max_real_eig``, ``hinf_norm`` -- certificate
  checks (fuzzy designs) on the TS model the certificate refers to (the dq
  model): the LMIs re-assembled, every rule pair and polytope vertex, the
  achieved H-inf norm against the certified bound.
* ``bridge_hold_torque_n_m`` -- the torque the bridge delivers at the step
  target through the hall table at the firmware's largest duty, in the twin's
  three-phase plant (:func:`bridge_hold_torque`: commutation transfers, which
  the DC equivalent has not), against the load and friction there; R nominal
  and +``design.resistance_uncertainty``.
* ``dq_hold_rpm`` (sinusoidal motors only) -- steady-state reachability on the
  dq model (v_d = 0): the step target within what it holds under the load.
  For a trapezoidal motor the dq model does not describe the six-step drive
  (it holds far less than the bridge does) and is not used.
* ``sim_*`` -- nonlinear simulation of the sampled law on the six-step
  drive: a step from rest to ``profile.speed_step_rpm()`` with the 2016
  load-torque disturbance w3, then a load-torque step of
  ``control.load_torque_n_m``: settling within 2 % before the load step and
  again after it, overshoot within the same 2 % band (the bridge cannot brake:
  an overshoot beyond the band coasts back on friction alone), final error
  (all on the speed averaged over one hall sector, :func:`sector_mean`; the
  ripple inside a sector is reported as a figure, ``sim_speed_ripple_pct``;
  no window reaches across the load step),
  peak line current inside the PWM periods (the period average plus the
  periodic RL ripple, :func:`picdrive.models.simulate.pwm_ripple_peak_a`) vs the
  overcurrent trip, the firmware's current
  walk-down backup never needed, saturation in steady state; the same step
  and load step with R at +-``design.resistance_uncertainty``
  (``sim_resistance_uncertainty``).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import scipy.linalg as sla

from ..models.dqmodel import dq_params, max_speed_rad_s
from ..analysis.metrics import step_metrics

__all__ = ["verify_design", "hinf_norm", "sampled_closed_loop", "six_step_closed_loop", "law_check_points",
           "sim_plan", "run_sim", "step_figures", "six_step_equilibrium", "VerifyConfig"]

RPM = 2.0 * math.pi / 60.0


class VerifyConfig:
    """Durations and bands of the verification simulation; tests may shorten the durations."""

    step_phase_s: float = 0.6      # step from rest, then the load step at this time
    load_phase_s: float = 0.6
    band: float = 0.02             # settling band and steady-error limit, fraction of the step target
    commutated: bool = True        # the pair's EMF per rotor angle (simulate.commutated_emf), not the DC Kb


# ---------------------------------------------------------------------------
# H-inf norm (continuous time, D = 0 or general D by frequency refinement)
# ---------------------------------------------------------------------------
def _sigma_max(A, B, C, D, w):
    n = A.shape[0]
    G = C @ np.linalg.solve(1j * w * np.eye(n) - A, B) + D
    return float(np.linalg.svd(G, compute_uv=False)[0])


def hinf_norm(A, B, C, D=None, *, rel_tol: float = 1e-6) -> tuple[float, float]:
    """H-inf norm of ``C (sI - A)^-1 B + D`` and the peak frequency (rad/s).

    Bisection on the Hamiltonian (Boyd, Balakrishnan, Kabamba 1989; the
    two-step refinement of Bruinsma and Steinbuch 1990): for a level g above
    the norm the Hamiltonian has no imaginary eigenvalue.  ``inf`` if A is not
    Hurwitz.
    """
    A, B, C = (np.atleast_2d(np.asarray(M, float)) for M in (A, B, C))
    D = np.zeros((C.shape[0], B.shape[1])) if D is None else np.atleast_2d(np.asarray(D, float))
    ev = np.linalg.eigvals(A)
    if np.max(ev.real) >= 0:
        return math.inf, math.nan
    cand = [0.0] + [abs(e.imag) for e in ev] + [abs(e) for e in ev]
    lb, wpk = 0.0, 0.0
    for w in cand:
        s = _sigma_max(A, B, C, D, w)
        if s > lb:
            lb, wpk = s, w
    if lb == 0.0:
        return 0.0, 0.0
    for _ in range(100):
        g = (1.0 + 2.0 * rel_tol) * lb
        R = g * g * np.eye(D.shape[1]) - D.T @ D
        Ri = np.linalg.inv(R)
        Ah = A + B @ Ri @ D.T @ C
        H = np.block([[Ah, B @ Ri @ B.T],
                      [-C.T @ (np.eye(C.shape[0]) + D @ Ri @ D.T) @ C, -Ah.T]])
        eh = np.linalg.eigvals(H)
        scale = max(1.0, np.max(np.abs(eh)))
        im = np.sort([e.imag for e in eh if abs(e.real) < 1e-8 * scale and e.imag >= 0])
        if im.size == 0:
            return g, wpk
        mids = [0.5 * (im[k] + im[k + 1]) for k in range(im.size - 1)] or [im[0]]
        new = max(((_sigma_max(A, B, C, D, w), w) for w in list(mids) + list(im)), key=lambda p: p[0])
        if new[0] <= lb * (1 + 1e-12):
            return g, wpk
        lb, wpk = new
    return lb, wpk


# ---------------------------------------------------------------------------
# The sampled law on the linearised six-step dq plant
# ---------------------------------------------------------------------------
def sampled_closed_loop(A, b_u, c_y, c_i, gains, ts: float, derivative_filter_hz: float | None) -> np.ndarray:
    """Discrete closed-loop matrix of the law (module doc of control_law) on
    ``x' = A x + b_u u`` sampled with ZOH at ``ts``.

    State ``[x, I, y_prev, d]``; the law is linear when unsaturated:
    ``I+ = I - ki ts y``, ``d+ = (1-a) d + a kd (y_prev - y)/ts``,
    ``u = -kp y + I+ + d+ - kc i`` (deviation coordinates, r = 0).
    """
    n = A.shape[0]
    M = sla.expm(np.block([[A, b_u.reshape(n, 1)], [np.zeros((1, n + 1))]]) * ts)
    Phi, Gam = M[:n, :n], M[:n, n]
    kp, ki, kd, kc = gains.kp, gains.ki, gains.kd, gains.kc
    a = 1.0
    if derivative_filter_hz:
        tf = 1.0 / (2 * math.pi * derivative_filter_hz)
        a = ts / (ts + tf)
    N = n + 3
    # rows of the next state as linear maps of s = [x, I, yp, d]
    Iplus = np.zeros(N); Iplus[:n] = -ki * ts * c_y; Iplus[n] = 1.0
    dplus = np.zeros(N); dplus[:n] = -a * kd / ts * c_y; dplus[n + 1] = a * kd / ts; dplus[n + 2] = 1.0 - a
    u = np.zeros(N); u[:n] = -kp * c_y - kc * c_i; u += Iplus + dplus
    Acl = np.zeros((N, N))
    Acl[:n, :n] = Phi
    Acl[:n, :] += np.outer(Gam, u)
    Acl[n] = Iplus
    Acl[n + 1, :n] = c_y
    Acl[n + 2] = dplus
    return Acl


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
    m = profile.motor
    R, L, J, B = m.r_line_ohm * r_factor, m.l_line_h, m.inertia_kg_m2, m.viscous_friction_n_m_s
    kb, kt = m.kb_v_s_per_rad, m.kt_n_m_per_a
    hd = (1.0 / profile.inverter.pwm_frequency_hz) if delay_s is None else float(delay_s)
    hd = min(max(hd, 0.0), ts)
    # x = [i, w, s] with s' = w (s: angle over the sample), input u
    Ac = np.array([[-R / L, -kb / L, 0.0], [kt / J, -B / J, 0.0], [0.0, 1.0, 0.0]])
    Bc = np.array([1.0 / L, 0.0, 0.0])

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


def _sampled_check(profile, law) -> dict:
    eps = float(profile.design.get("resistance_uncertainty", 0.1))
    worst, where = -1.0, ""
    for w in law_check_points(profile, law):
        g = law.gains_at(w)
        for rs in (1.0 - eps, 1.0, 1.0 + eps):
            Acl = six_step_closed_loop(profile, g, law.sample_time_s, law.derivative_filter_hz, r_factor=rs)
            rad = float(np.max(np.abs(np.linalg.eigvals(Acl))))
            if rad > worst:
                worst, where = rad, f"gains at {w / RPM:.0f} rpm, R x {rs:g}"
    meas = ("the firmware's speed measurement" if profile.sensors.speed_source != "hall" else
            "the encoder's M/T measurement (this profile measures speed from the halls: their period's lag, "
            "which depends on the speed, is judged by the simulation, sim_*)")
    return {"value": worst, "limit": 1.0, "ok": bool(worst < 1.0), "unit": "1",
            "note": f"largest |eig| of the sampled closed loop on the six-step DC-equivalent plant with {meas}; "
                    f"worst at {where}"}


def six_step_equilibrium(profile, omega_rad_s: float, load_n_m: float = 0.0, r_factor: float = 1.0):
    """Steady state of the six-step DC-equivalent drive at a speed: ``(i, u)`` (A, V)."""
    m = profile.motor
    i = (m.viscous_friction_n_m_s * omega_rad_s + load_n_m) / m.kt_n_m_per_a
    return i, m.kb_v_s_per_rad * omega_rad_s + m.r_line_ohm * r_factor * i


def _headroom_check(profile, law) -> dict:
    eps = float(profile.design.get("resistance_uncertainty", 0.1))
    b = law.setpoint_weight
    worst, where = math.inf, ""
    for w in (0.0, profile.speed_step_rpm() * RPM):
        for load in (0.0, profile.control.load_torque_n_m):
            for rs in (1.0 - eps, 1.0 + eps):
                i, u = six_step_equilibrium(profile, w, load, rs)
                g = law.gains_at(w)
                need = abs(u + g.kp * (1.0 - b) * w + g.kc * i)
                room = law.i_lim_v - need
                if room < worst:
                    worst, where = room, f"{w / RPM:.0f} rpm, load {load:g} N m, R x {rs:g}"
    return {"value": worst, "limit": 0.0, "ok": bool(worst >= 0.0), "unit": "V",
            "note": f"I_lim - |u* + kp (1-b) w* + kc i*| at the worst six-step equilibrium ({where}); b = {b:g}"}


def _window_check(profile, law) -> dict:
    want = (profile.inverter.current_limit_a, profile.motor.kb_v_s_per_rad, profile.motor.r_line_ohm)
    have = (law.current_limit_a, law.kb_v_s_per_rad, law.r_ohm)
    ok = have[0] is not None and all(abs(x - y) <= 1e-9 * max(1.0, abs(y)) for x, y in zip(have, want))
    return {"value": list(have), "limit": list(want), "ok": bool(ok), "unit": "A, V s/rad, ohm",
            "note": "the law's current window (current_limit_a, kb_v_s_per_rad, r_ohm) must be the firmware's: "
                    "the profile's inverter.current_limit_a, motor.kb_v_s_per_rad, motor.r_line_ohm"}


def bridge_hold_torque(profile, rpm: float, *, r_factor: float = 1.0) -> tuple[float, float]:
    """Mean electromagnetic torque the bridge delivers at a held speed, and the torque the load and
    friction take there, N m: ``(delivered, needed)``.

    The three-phase plant of the motor twin (``picdrive_hil.plant.CPlant``: per-phase currents,
    the floating phase and its diode, the commutation transfers the DC equivalent does not have)
    at ``rpm`` held constant, driven by the firmware's hall table (high-side PWM, low side on) at
    the largest duty the firmware applies there: bus x max duty, or less where the current window
    ``Kb w + R_line I_lim`` is lower; R x ``r_factor``.  Averaged over whole hall sectors after the
    currents have settled.  A drive whose sector is short against L/R loses torque at each
    commutation; if ``delivered < needed`` the target cannot be held under the load, whatever the
    law."""
    from picdrive_hil.plant import CPlant, plant_from_profile

    from ..firmware.pcpwm import commutation_table
    m, inv, se = profile.motor, profile.inverter, profile.sensors
    w = rpm * RPM
    cp = CPlant(plant_from_profile(profile))
    cp.params.inertia_kg_m2 = 1e9 * max(m.inertia_kg_m2, 1e-9)     # the speed is held
    cp.params.r_phase_ohm *= r_factor
    cp.state.w_rad_s = w
    u = min(inv.bus_voltage_v * profile.max_duty(), m.kb_v_s_per_rad * w + m.r_line_ohm * inv.current_limit_a)
    d = max(0.0, min(1.0, u / inv.bus_voltage_v))
    tab = commutation_table(se.hall_spacing_deg, se.hall_offset_deg, m.back_emf_shape).forward
    h = 1.0 / inv.pwm_frequency_hz
    sector = math.pi / 3 / (m.pole_pairs * max(w, 1e-9))
    tau = m.l_line_h / (m.r_line_ohm * r_factor)
    t_warm = max(10 * tau, 2 * sector)
    n_sect = max(12, math.ceil(0.02 / sector))
    legs_off = [(0.0, 0.0)] * 3

    def legs_for(code):
        st = tab[code]
        if st is None:
            return legs_off
        lg = [(0.0, 0.0)] * 3
        lg[st[0]] = (d, 0.0)
        lg[st[1]] = (0.0, 1.0)
        return lg
    t = 0.0
    while t < t_warm:
        cp.step(legs_for(cp.hall_code()), 0.0, h)
        t += h
    t_end = t + n_sect * sector
    acc = tt = 0.0
    while tt < t_end - t:
        hh = min(h, t_end - t - tt)
        cp.step(legs_for(cp.hall_code()), 0.0, hh)
        acc += cp.state.torque_e_n_m * hh
        tt += hh
    need = m.viscous_friction_n_m_s * w + profile.control.load_torque_n_m
    return acc / tt, need


def _hold_check(profile) -> dict:
    eps = float(profile.design.get("resistance_uncertainty", 0.1))
    tgt = profile.speed_step_rpm()
    worst = None
    for rs in (1.0, 1.0 + eps):
        te, need = bridge_hold_torque(profile, tgt, r_factor=rs)
        if worst is None or te - need < worst[0] - worst[1]:
            worst = (te, need, rs)
    te, need, rs = worst
    return {"value": te, "limit": need, "ok": bool(te > need), "unit": "N m",
            "note": f"mean torque the bridge delivers at the step target ({tgt:.0f} rpm held, R x {rs:g}) through "
                    "the firmware's hall table at its largest duty, in the twin's three-phase plant (commutation "
                    "transfers included), vs the load and friction torque there: below it the target cannot "
                    f"be held under the load (hall sector {1e3 * sector_period_s(profile, tgt):.3g} ms, L/R "
                    f"{1e3 * profile.motor.l_line_h / profile.motor.r_line_ohm:.3g} ms)"}


def _dq_reachability(profile) -> dict | None:
    if profile.motor.back_emf_shape != "sinusoidal":
        return None
    p = dq_params(profile)
    u_max = profile.inverter.bus_voltage_v * profile.max_duty()
    hold = max_speed_rad_s(p, p.kv_vq_per_u * u_max, profile.control.load_torque_n_m) / RPM
    tgt = profile.speed_step_rpm()
    return {"value": hold, "limit": tgt, "ok": bool(hold >= tgt), "unit": "rpm",
            "note": "speed the dq model (v_d = 0, sinusoidal motor) holds under the load at the bridge voltage; "
                    "must reach the step target"}


# ---------------------------------------------------------------------------
# Certificate checks (fuzzy designs)
# ---------------------------------------------------------------------------
def _certificate_checks(profile, result) -> dict:
    cert = result.certificate or {}
    out: dict[str, Any] = {}
    if "K" not in cert or "model" not in cert:
        return out
    from . import fuzzy_hinf
    ts = fuzzy_hinf.model_for(profile, cert["model"], cert.get("model_options", {}))
    K = [np.asarray(k, float) for k in cert["K"]]
    if "P" in cert and "Y" in cert and cert.get("gamma") is not None:
        P = np.asarray(cert["P"], float)
        Y = [np.asarray(y, float) for y in cert["Y"]]
        marg = fuzzy_hinf.lmi_margins(ts, P, Y, float(cert["gamma"]), float(cert["delta"]), float(cert["alpha"]),
                                      float(cert["rho"]), scaled=True)
        worst = max(marg.values())
        out["lmi_max_eig"] = {"value": worst, "limit": 0.0, "ok": bool(worst < 0.0), "unit": "1",
                              "note": "largest eigenvalue of P>0, Xi_ii<0, Xi_ij+Xi_ji<0 (scaled), re-assembled"}
    eps = float(profile.design.get("resistance_uncertainty", 0.1))
    worst_re, worst_h = -math.inf, 0.0
    for v in range(ts.offsets.shape[0]):
        for i in range(ts.r):
            for rs in (-1.0, 0.0, 1.0):
                dA = rs * ts.E_matrix @ (ts.rho * np.eye(ts.E_matrix.shape[1])) @ ts.H1[i] if ts.E is not None \
                    else rs * ts.rho * ts.H1[i]
                Ai = ts.A[i] + ts.offsets[v] + dA
                for j in range(ts.r):
                    re = float(np.max(np.linalg.eigvals(Ai + ts.B[i] @ K[j]).real))
                    worst_re = max(worst_re, re)
                Acl = Ai + ts.B[i] @ K[i]
                h, _ = hinf_norm(Acl, ts.Bw, ts.C[i] + ts.D[i] @ K[i])
                worst_h = max(worst_h, h)
    out["continuous_max_real_eig"] = {"value": worst_re, "limit": 0.0, "ok": bool(worst_re < 0.0), "unit": "1/s",
                                      "note": "max Re eig of A_i + dA_v + B_i K_j over all rule pairs, polytope "
                                              f"vertices and R at +-{eps:g}"}
    if cert.get("certified_gain") is not None:
        bound = float(cert["certified_gain"])
        out["hinf_norm"] = {"value": worst_h, "limit": bound, "ok": bool(worst_h <= bound * (1 + 1e-6)),
                            "unit": "z/w", "note": "max H-inf norm w -> z of the vertex closed loops (R nominal "
                                                   "and at the uncertainty extremes) vs the certified bound"}
    return out


# ---------------------------------------------------------------------------
# Nonlinear simulation on the six-step drive
# ---------------------------------------------------------------------------
def min_step_time_s(profile, rpm: float | None = None) -> float:
    """The fastest the drive can reach ``rpm`` (default the step target) from rest at the current
    limit, ``t_min = J w / (Kt I_lim - T_load)``, s (inf when the limit cannot carry the load)."""
    m = profile.motor
    w = (profile.speed_step_rpm() if rpm is None else rpm) * RPM
    net = m.kt_n_m_per_a * profile.inverter.current_limit_a - profile.control.load_torque_n_m
    return m.inertia_kg_m2 * w / net if net > 0 else math.inf


def sim_plan(profile) -> dict:
    """Step target (rpm), load, durations of the verification simulation.

    Each phase lasts ``VerifyConfig`` 's duration or three times the physical minimum step time
    (:func:`min_step_time_s`), whichever is longer: a high-inertia drive cannot settle within a
    fixed 0.6 s however good its law."""
    t_min = min_step_time_s(profile)
    scale = 1.0
    if math.isfinite(t_min):
        scale = max(1.0, 3.0 * t_min / VerifyConfig.step_phase_s)
    step, load = VerifyConfig.step_phase_s * scale, VerifyConfig.load_phase_s * scale
    return {"target_rpm": profile.speed_step_rpm(), "profile_target_rpm": profile.speed_step_rpm(),
            "capped": False, "load_n_m": profile.control.load_torque_n_m,
            "t_load_s": step, "t_end_s": step + load}


def speed_measurement(profile, law) -> dict:
    """The firmware's speed measurement as :func:`picdrive.models.simulate.simulate_six_step` takes it:
    ``{"measurement": "firmware"}`` (encoder M/T) or ``{"measurement": "hall", "hall": meter}``
    (hall-edge period, :func:`picdrive.models.simulate.hall_speed_meter` of the firmware's own
    fixed-point plan).  Raises the plan's :class:`picdrive.errors.PicdriveError` when no firmware
    can be built for the law."""
    if profile.sensors.speed_source != "hall":
        return {"measurement": "firmware"}
    from ..firmware.fixedpoint import plan_fixed_point
    from ..firmware.pcpwm import plan_pwm
    from ..models.simulate import hall_speed_meter
    return {"measurement": "hall", "hall": hall_speed_meter(profile, plan_fixed_point(profile, law, plan_pwm(profile)))}


def run_sim(profile, law, plan=None, *, disturbances: bool = True, r_factor: float = 1.0,
            commutated: bool | None = None):
    """The verification run on the six-step drive: step from rest to the target (the 2016 load-torque
    disturbance w3 on [0, 0.2] s when ``disturbances``), then the load step, with the firmware's
    speed measurement (:func:`speed_measurement`).  Returns
    :class:`picdrive.models.simulate.SixStepResult`."""
    from ..models.simulate import disturbances_2016, simulate_six_step
    plan = plan or sim_plan(profile)
    load = plan["load_n_m"]
    tl = plan["t_load_s"]
    w3 = None
    if disturbances:
        w3 = lambda t: float(disturbances_2016(t, amplitude=(0.0, 0.0, 0.1 * load))[0, 2])
    return simulate_six_step(profile, law, t_end=plan["t_end_s"], ref_rpm=plan["target_rpm"],
                             load=lambda t: load if t >= tl - 1e-12 else 0.0, torque_disturbance=w3,
                             r_factor=r_factor, **speed_measurement(profile, law),
                             commutated=VerifyConfig.commutated if commutated is None else commutated)


def sector_period_s(profile, rpm: float) -> float:
    """Time one hall sector (60 electrical degrees) lasts at a speed, s: the shortest interval over
    which a six-step drive delivers its mean torque (inside it the pair's EMF, hence the torque per
    ampere, ripples with the rotor angle)."""
    return 60.0 / (max(abs(rpm), 1e-9) * profile.motor.pole_pairs * 6.0)


def sector_mean(profile, y: np.ndarray, ts: float, rpm: float, *, breaks=()) -> np.ndarray:
    """``y`` (samples ``ts`` apart) averaged over one hall sector at ``rpm`` (centred moving mean;
    the ends use what exists).

    ``breaks``: sample indices where a new phase of the run starts (the load step): no window
    reaches across one, so what happens after a phase boundary never leaks into the figures of the
    phase before it (and the other way round); near a boundary the window is the sector next to it
    inside the phase."""
    y = np.asarray(y, float)
    n = max(1, int(round(sector_period_s(profile, rpm) / ts)))
    if n <= 1:
        return y.copy()
    out = np.empty_like(y)
    cuts = [0] + sorted(int(b) for b in breaks if 0 < int(b) < y.size) + [y.size]
    for a, b in zip(cuts[:-1], cuts[1:]):
        seg = y[a:b]
        c = np.concatenate([[0.0], np.cumsum(seg)])
        k = np.arange(seg.size)
        lo = np.clip(k - n // 2, 0, seg.size)
        hi = np.clip(lo + n, 0, seg.size)
        lo = np.maximum(0, hi - n)
        out[a:b] = (c[hi] - c[lo]) / (hi - lo)
    return out


def step_figures(sim, plan, profile=None) -> dict:
    """Step and load-step figures of a verification run (rpm, s, %).

    Settling, overshoot, load recovery and final error are judged on the speed
    averaged over one hall sector at the target (:func:`sector_mean`; with a
    ``profile``), the commutation's own torque ripple being no regulation error;
    ``ripple_pct`` is the peak-to-peak of the raw speed about that mean in the
    last 10 % of the run, ``peak_rpm_raw`` the raw peak."""
    t, raw = sim.t, sim.rpm
    tl, target = plan["t_load_s"], plan["target_rpm"]
    ts = float(t[1] - t[0])
    a = t < tl
    # the load step starts a new phase: no sector window reaches across it
    rpm = sector_mean(profile, raw, ts, target, breaks=(int(np.count_nonzero(a)),)) if profile is not None else raw
    m1 = step_metrics(t[a], rpm[a], target, y0=0.0)
    band = VerifyConfig.band
    dev = np.abs(rpm[~a] - target) / target
    outside = np.nonzero(dev > band)[0]
    rec = 0.0 if outside.size == 0 else (math.inf if outside[-1] == dev.size - 1 else float(t[~a][outside[-1] + 1] - tl))
    n_tail = max(1, int(0.1 * t.size))
    inside = np.nonzero(np.abs(raw - target) <= 0.01 * target)[0]
    return {"settling_s": m1.settling_time_s, "rise_s": m1.rise_time_s, "overshoot_pct": m1.overshoot_pct,
            "peak_rpm": m1.peak, "peak_rpm_raw": float(np.max(sim.omega_fine if sim.omega_fine.size else sim.omega)
                                                       * 60 / (2 * math.pi)),
            "load_recovery_s": rec, "load_dip_rpm": float(target - np.min(rpm[~a])),
            "final_error_rpm": float(target - np.mean(rpm[-n_tail:])),
            "ripple_pct": float(100 * np.ptp(raw[-n_tail:] - rpm[-n_tail:]) / target),
            "t_reach_s": float(t[inside[0]]) if inside.size else math.inf,
            "peak_current_a": float(np.max(np.abs(sim.i_fine))) if sim.i_fine.size else 0.0,
            # with the current's rise inside each PWM period (simulate.pwm_ripple_peak_a); a twin run has none
            "peak_current_ripple_a": float(np.max(sim.i_peak_fine)) if getattr(sim, "i_peak_fine", np.zeros(0)).size
            else (float(np.max(np.abs(sim.i_fine))) if sim.i_fine.size else 0.0)}


def _sim_checks(profile, law) -> dict:
    plan = sim_plan(profile)
    out: dict[str, Any] = {}
    target = plan["target_rpm"]
    tl = plan["t_load_s"]
    t_end = plan["t_end_s"]
    band = VerifyConfig.band
    out["sim_step_target_rpm"] = {"value": target, "limit": plan["profile_target_rpm"], "ok": True, "unit": "rpm",
                                  "note": "profile.speed_step_rpm() (a figure, not a check)"}
    try:
        sim = run_sim(profile, law, plan)
    except FloatingPointError:
        out["sim_finite"] = {"value": False, "limit": True, "ok": False, "unit": "", "note": "simulation diverged"}
        return out
    f = step_figures(sim, plan, profile)
    out["sim_settling_s"] = {"value": f["settling_s"], "limit": tl, "ok": bool(f["settling_s"] < 0.8 * tl),
                             "unit": "s", "note": f"{100 * band:g} % band, step from rest (must settle within 80 % "
                                                  "of the phase)"}
    out["sim_rise_s"] = {"value": f["rise_s"], "limit": tl, "ok": bool(f["rise_s"] < tl), "unit": "s"}
    out["sim_overshoot_pct"] = {"value": f["overshoot_pct"], "limit": 100 * band,
                                "ok": bool(f["overshoot_pct"] <= 100 * band), "unit": "%",
                                "note": "within the settling band: the bridge cannot brake, a larger overshoot "
                                        "coasts back on friction alone"}
    out["sim_load_recovery_s"] = {"value": f["load_recovery_s"], "limit": t_end - tl,
                                  "ok": bool(f["load_recovery_s"] < 0.8 * (t_end - tl)), "unit": "s",
                                  "note": f"back into the {100 * band:g} % band after the load-torque step"}
    out["sim_load_dip_rpm"] = {"value": f["load_dip_rpm"], "limit": target, "ok": bool(f["load_dip_rpm"] < target),
                               "unit": "rpm", "note": "speed dip after the load step (must not stall)"}
    out["sim_speed_ripple_pct"] = {"value": f["ripple_pct"], "limit": None, "ok": True, "unit": "%",
                                   "note": "a figure, not a check: peak-to-peak speed ripple about the sector mean "
                                           "under the load, the commutation's torque ripple (a property of the motor "
                                           "and the six-step bridge; higher loop gains reduce it)"}
    out["sim_peak_rpm"] = {"value": f["peak_rpm_raw"], "limit": profile.control.speed_max_rpm,
                           "ok": bool(f["peak_rpm_raw"] <= profile.control.speed_max_rpm), "unit": "rpm",
                           "note": "raw peak speed vs control.speed_max_rpm"}
    out["sim_final_error_rpm"] = {"value": f["final_error_rpm"], "limit": band * target,
                                  "ok": bool(abs(f["final_error_rpm"]) <= band * target), "unit": "rpm",
                                  "note": "mean over the last 10 % of the run, under the load"}
    u_bridge = profile.inverter.bus_voltage_v * profile.max_duty()
    out["sim_peak_u_v"] = {"value": float(np.max(np.abs(sim.u))), "limit": u_bridge,
                           "ok": bool(np.max(np.abs(sim.u)) <= u_bridge + 1e-9), "unit": "V"}
    t = sim.t
    tail = np.zeros(t.size, bool)
    for t0, t1 in ((0.8 * tl, tl), (t[-1] - 0.2 * (t[-1] - tl), t[-1] + 1)):
        tail |= (t >= t0) & (t < t1)
    sat = sim.saturated
    # on the edge for most of a hall sector (brief touches from the commutation ripple excepted)
    sat_sector = sector_mean(profile, sat.astype(float), law.sample_time_s, target,
                             breaks=(int(np.count_nonzero(t < tl)),)) >= 0.5
    sat_tail = float(np.mean(sat_sector[tail]))
    out["sim_saturated_steady_fraction"] = {"value": sat_tail, "limit": 0.0, "ok": bool(sat_tail == 0.0), "unit": "1",
                                            "note": "fraction of the steady-state windows with u at the edge of "
                                                    "its window for most of a hall sector (raw: "
                                                    f"{float(np.mean(sat[tail])):.3g})"}
    out["sim_saturated_time_s"] = {"value": float(np.sum(sat) * law.sample_time_s), "limit": 0.5 * tl,
                                   "ok": bool(np.sum(sat) * law.sample_time_s <= 0.5 * tl), "unit": "s"}
    trip = profile.inverter.overcurrent_trip_a
    tau = profile.motor.l_line_h / profile.motor.r_line_ohm
    t_pwm = 1.0 / profile.inverter.pwm_frequency_hz
    out["sim_peak_bus_current_a"] = {"value": f["peak_current_ripple_a"], "limit": trip,
                                     "ok": bool(f["peak_current_ripple_a"] < trip), "unit": "A",
                                     "note": f"peak line current inside the PWM periods (the period average peaks at "
                                             f"{f['peak_current_a']:.4g} A; the rise within a period adds up to "
                                             f"{f['peak_current_ripple_a'] - f['peak_current_a']:.3g} A at L/R = "
                                             f"{tau * 1e6:.3g} us, PWM period {t_pwm * 1e6:.3g} us) vs the overcurrent "
                                             f"trip; the current limit is {profile.inverter.current_limit_a:g} A"}
    n_cap = int(np.sum(sim.cap_active))
    out["sim_current_backup_samples"] = {"value": n_cap, "limit": 0, "ok": bool(n_cap == 0), "unit": "samples",
                                         "note": "samples with the firmware's walk-down backup (measured current "
                                                 "above the limit) engaged: the window alone must hold the current"}
    # R at the extremes of its uncertainty: the same step and load step, same limits
    eps = float(profile.design.get("resistance_uncertainty", 0.1))
    worst = {}
    ok = True
    for rs in (1.0 - eps, 1.0 + eps):
        try:
            fr = step_figures(run_sim(profile, law, plan, disturbances=False, r_factor=rs), plan, profile)
        except FloatingPointError:
            ok = False
            worst[f"R x {rs:g}"] = "diverged"
            continue
        good = (fr["settling_s"] < 0.8 * tl and fr["overshoot_pct"] <= 100 * band
                and fr["load_recovery_s"] < 0.8 * (t_end - tl) and abs(fr["final_error_rpm"]) <= band * target
                and fr["peak_current_ripple_a"] < trip)
        ok &= bool(good)
        worst[f"R x {rs:g}"] = {k: round(fr[k], 4) for k in ("settling_s", "overshoot_pct", "load_recovery_s",
                                                             "final_error_rpm", "peak_current_ripple_a")}
    out["sim_resistance_uncertainty"] = {"value": worst, "limit": "the same limits", "ok": ok, "unit": "",
                                         "note": f"step and load step with R x (1 -+ {eps:g})"}
    return out


def verify_design(profile, result, *, simulate: bool = True):
    """Run every applicable check, fill ``result.verification``, fail on any failed check.

    Returns the same result (status ``verified`` unless a check failed)."""
    checks: dict[str, Any] = {}
    law = result.law
    if law is not None:
        checks["law_current_window"] = _window_check(profile, law)
        checks["sampled_spectral_radius"] = _sampled_check(profile, law)
        checks["integrator_headroom_v"] = _headroom_check(profile, law)
        if law.u_max_v > profile.inverter.bus_voltage_v * profile.max_duty() + 1e-9 or \
                law.u_min_v < -profile.inverter.bus_voltage_v * profile.max_duty() - 1e-9:
            checks["law_output_limits_v"] = {"value": [law.u_min_v, law.u_max_v],
                                             "limit": profile.inverter.bus_voltage_v * profile.max_duty(),
                                             "ok": False, "unit": "V", "note": "outside +- bus voltage x max duty"}
        dq = _dq_reachability(profile)
        if dq is not None:
            checks["dq_hold_rpm"] = dq
        if simulate:
            checks["bridge_hold_torque_n_m"] = _hold_check(profile)
    checks.update(_certificate_checks(profile, result))
    if law is not None and simulate and checks.get("sampled_spectral_radius", {}).get("ok", True):
        checks.update(_sim_checks(profile, law))
    elif law is not None and simulate:
        checks["sim_skipped"] = {"value": "skipped", "limit": "", "ok": False, "unit": "",
                                 "note": "the sampled closed loop is unstable; no simulation"}
    if law is None and not checks:
        checks["nothing_to_verify"] = {"value": "no law and no certificate", "limit": "", "ok": False, "unit": ""}
    result.verification.update(checks)
    for name, c in checks.items():
        if not c.get("ok", True):
            lim = c.get("limit")
            result.fail(f"verification '{name}' failed: {c['value']!r} (limit {lim!r} {c.get('unit', '')})"
                        + (f": {c['note']}" if c.get("note") else ""))
    if result.status != "failed" and not result.reasons:
        result.status = "verified"
    return result


# ---------------------------------------------------------------------------
# The same run in the motor twin (firmware in the loop), for validating the model
# ---------------------------------------------------------------------------
def twin_run(profile, design_path, plan=None, *, workdir=None, perturb=None, seed: int = 0):
    """The verification's step and load step on the motor twin (``picdrive_hil``), free-running.

    The firmware is generated from the design file (``picdrive firmware``'s
    codegen) into ``workdir`` (a temporary folder by default) and run
    unchanged in the twin.  Commands go in as frames over the twin's UART
    (``link_timeout`` to its maximum, the speed setpoint, start); t = 0 is the
    firmware's first sample in RUN (one PWM period before its first duty); the
    load-torque step is applied at ``plan["t_load_s"]`` on that clock.
    Returns an object with what :func:`step_figures` reads (``t``, ``rpm``,
    ``omega``, ``omega_fine``, ``i_fine``): the true rotor speed at the law's
    sample instants and every 100 us, the largest phase current."""
    import tempfile
    from pathlib import Path
    from types import SimpleNamespace

    from picdrive_hil.twin import Twin

    from ..link import codec
    from ..firmware import codegen
    plan = plan or sim_plan(profile)
    fw = codegen.generate(profile, str(design_path))
    table = {e.name: e for e in fw.table.entries}
    e_sp, e_to = table["speed_setpoint"], table["link_timeout"]
    ts = 1.0 / profile.control.speed_loop_hz
    with tempfile.TemporaryDirectory(prefix="picdrive-twin-run-") as tmp:
        out = codegen.write_firmware(fw, Path(workdir or tmp) / "fw", check=False)
        tw = Twin(profile, out, perturb=perturb, seed=seed)
        try:
            seq = iter(range(1, 200))

            def send(cmd, args=None):
                tw.uart_write(codec.encode_command(cmd, next(seq), args))
            send("param_set", {"id": e_to.id, "value": e_to.max_raw})
            send("set_speed", {"value": int(round(plan["target_rpm"] / e_sp.scale))})
            tw.run(0.005)
            send("start")
            dt = 1e-4
            parts = [tw.record(0.02, dt)]
            on = np.nonzero(parts[0]["duty_max"] > 0)[0]
            if on.size == 0:
                raise RuntimeError("the firmware never switched the bridge on")
            t0 = float(parts[0]["t_s"][on[0]]) - 1.0 / profile.inverter.pwm_frequency_hz
            parts.append(tw.record(t0 + plan["t_load_s"] - tw.t, dt))
            tw.set_load_torque(plan["load_n_m"])
            parts.append(tw.record(plan["t_end_s"] - plan["t_load_s"] + ts, dt))
        finally:
            tw.close()
    t = np.concatenate([p["t_s"] for p in parts]) - t0
    w = np.concatenate([p["w_rad_s"] for p in parts])
    i = np.concatenate([np.max(np.abs(np.stack([p["i_a"], p["i_b"], p["i_c"]])), axis=0) for p in parts])
    order = np.argsort(t, kind="stable")
    t, w, i = t[order], w[order], i[order]
    keep = np.concatenate([[True], np.diff(t) > 1e-12])
    t, w, i = t[keep], w[keep], i[keep]
    tk = np.arange(int(round(plan["t_end_s"] / ts)) + 1) * ts
    wk = np.interp(tk, t, w)
    sel = t >= 0
    return SimpleNamespace(t=tk, omega=wk, rpm=wk * 60 / (2 * math.pi), omega_fine=w[sel], i_fine=i[sel],
                           t_fine=t[sel])
