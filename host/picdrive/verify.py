"""Verification every design passes before it is saved as usable.

``verify_design(profile, result)`` is method-agnostic: it reads the law
(:class:`picdrive.control_law.ScheduledLaw`, the thing the firmware runs)
and, when present, the certificate, and fills ``result.verification`` with
entries ``{"value", "limit", "ok", "unit", "note"}``; any failed entry calls
``result.fail(reason)``.  Checks:

* ``sampled_spectral_radius`` -- the *discrete-time* closed loop of the law
  (its integrator, derivative memory and filter included) sampled at
  ``speed_loop_hz`` with a zero-order hold, on the dq model linearised at the
  equilibria of every premise point (rule centres; speed 0 and the step
  target too) with and without the profile's load, and R at nominal and
  +-``design.resistance_uncertainty``: largest |eigenvalue|, limit 1.
* ``lmi_max_eig`` (certificates with P, Y_j): the LMIs re-assembled from the
  profile's model and the certificate, largest eigenvalue, limit 0 (in the
  scaled coordinates of the solver, an exact congruence).
* ``continuous_max_real_eig`` (certificates with K_j): ``A_i + dA_v + B_i K_j``
  for every rule pair and polytope vertex, R at the uncertainty extremes.
* ``hinf_norm`` (certificates with K_j): the H-inf norm w -> z of each
  vertex closed loop (exact, Hamiltonian bisection), limit the certified bound.
* ``sim_*`` -- nonlinear simulation of the sampled law on the dq model
  (six-step drive): a step from rest to the step target with the 2016
  disturbances (:func:`picdrive.simulate.disturbances_2016`), then a
  load-torque step of ``control.load_torque_n_m``: settling within 2 % before
  the load step and again after it, peak speed vs ``speed_max_rpm``, peak
  bus current vs ``current_limit_a``, peak |u| vs the bridge voltage,
  saturation in steady state, final speed error.

The step target is ``profile.speed_step_rpm()``, capped at 95 % of the speed
the dq model with the six-step drive (``v_d = 0``) can hold under the load
(:func:`picdrive.tsfuzzy.operating_region`); when the cap applies, the entry
``sim_step_target_rpm`` says so.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import scipy.linalg as sla

from .dqmodel import dq_params, equilibrium, jacobian
from .metrics import step_metrics

__all__ = ["verify_design", "hinf_norm", "sampled_closed_loop", "law_check_points", "sim_plan", "run_sim",
           "VerifyConfig"]

RPM = 2.0 * math.pi / 60.0


class VerifyConfig:
    """Durations of the verification simulation (s); tests may shorten them."""

    step_phase_s: float = 0.6      # step from rest, then the load step at this time
    load_phase_s: float = 0.6
    n_sub: int = 20


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
    n = A.shape[0]
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


def law_check_points(profile, law) -> list[float]:
    """Speeds (rad/s) at which the sampled loop is checked: 0, the rule centres, the step target."""
    from .tsfuzzy import operating_region, rule_centres
    pts = {0.0}
    n1, n2 = law.premise_rad_s
    if law.n_rules > 1:
        pts.update(float(c) for c in rule_centres((n1, n2), law.n_rules))
    pts.add(operating_region(profile)["omega_top_rad_s"])
    return sorted(pts)


def _sampled_check(profile, law) -> dict:
    p0 = dq_params(profile)
    eps = float(profile.design.get("resistance_uncertainty", 0.1))
    worst, where = -1.0, ""
    for w in law_check_points(profile, law):
        g = law.gains_at(w)
        for load in (0.0, profile.control.load_torque_n_m):
            for rs in (1.0 - eps, 1.0, 1.0 + eps):
                p = p0.replace(r_ohm=p0.r_ohm * rs)
                iq, id_, _ = equilibrium(p, w, load)
                A, B = jacobian(p, (w, iq, id_))
                b_u = B[:, 0] * p.kv_vq_per_u
                Acl = sampled_closed_loop(A, b_u, np.array([1.0, 0, 0]), np.array([0, p.ki_ibus_per_iq, 0]), g,
                                          law.sample_time_s, law.derivative_filter_hz)
                rad = float(np.max(np.abs(np.linalg.eigvals(Acl))))
                if rad > worst:
                    worst, where = rad, f"{w / RPM:.0f} rpm, load {load:g} N m, R x {rs:g}"
    return {"value": worst, "limit": 1.0, "ok": bool(worst < 1.0), "unit": "1",
            "note": f"largest |eig| of the sampled closed loop; worst at {where}"}


# ---------------------------------------------------------------------------
# Certificate checks (fuzzy designs)
# ---------------------------------------------------------------------------
def _certificate_checks(profile, result) -> dict:
    cert = result.certificate or {}
    out: dict[str, Any] = {}
    if "K" not in cert or "model" not in cert:
        return out
    from . import fuzzy_hinf, tsfuzzy
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
# Nonlinear simulation
# ---------------------------------------------------------------------------
def sim_plan(profile) -> dict:
    """Step target (rpm), load, durations of the verification simulation."""
    from .tsfuzzy import operating_region
    reg = operating_region(profile)
    target = reg["omega_top_rad_s"] / RPM
    return {"target_rpm": target, "profile_target_rpm": profile.speed_step_rpm(),
            "capped": bool(target < profile.speed_step_rpm() * (1 - 1e-9)),
            "hold_rpm": reg["omega_hold_rad_s"] / RPM, "load_n_m": profile.control.load_torque_n_m,
            "t_load_s": VerifyConfig.step_phase_s, "t_end_s": VerifyConfig.step_phase_s + VerifyConfig.load_phase_s}


def run_sim(profile, law, plan=None, *, disturbances: bool = True, params=None):
    """The verification run: step from rest to the target, 2016 disturbances, load step."""
    from .simulate import disturbances_2016, simulate_law, step_load
    plan = plan or sim_plan(profile)
    load = plan["load_n_m"]
    dist = None
    if disturbances:
        dist = lambda t: disturbances_2016(t, amplitude=(1.0, 1.0, 0.1 * load))[0]
    return simulate_law(profile, law, t_end=plan["t_end_s"], ref_rpm=plan["target_rpm"],
                        load=step_load(plan["t_load_s"], load), disturbance=dist, params=params,
                        n_sub=VerifyConfig.n_sub)


def _sim_checks(profile, law) -> dict:
    plan = sim_plan(profile)
    sim = run_sim(profile, law, plan)
    out: dict[str, Any] = {}
    out["sim_step_target_rpm"] = {
        "value": plan["target_rpm"], "limit": plan["profile_target_rpm"], "ok": True, "unit": "rpm",
        "note": ("capped at 95 % of the speed the dq model with the six-step drive holds under load "
                 f"({plan['hold_rpm']:.0f} rpm)" if plan["capped"] else "profile.speed_step_rpm()")}
    if not np.all(np.isfinite(sim.omega)):
        out["sim_finite"] = {"value": False, "limit": True, "ok": False, "unit": "", "note": "simulation diverged"}
        return out
    t, rpm = sim.t, sim.rpm
    tl = plan["t_load_s"]
    target = plan["target_rpm"]
    a = t < tl
    m1 = step_metrics(t[a], rpm[a], target, y0=0.0)
    out["sim_settling_s"] = {"value": m1.settling_time_s, "limit": tl, "ok": bool(m1.settling_time_s < 0.8 * tl),
                             "unit": "s", "note": "2 % band, step from rest (must settle within 80 % of the phase)"}
    out["sim_rise_s"] = {"value": m1.rise_time_s, "limit": tl, "ok": bool(m1.rise_time_s < tl), "unit": "s"}
    out["sim_overshoot_pct"] = {"value": m1.overshoot_pct,
                                "limit": max(0.0, (profile.control.speed_max_rpm / target - 1) * 100),
                                "ok": bool(m1.peak <= profile.control.speed_max_rpm), "unit": "%",
                                "note": "the peak must stay below control.speed_max_rpm"}
    # after the load step: recovery into the 2 % band
    dev = np.abs(rpm[~a] - target) / target
    outside = np.nonzero(dev > 0.02)[0]
    rec = 0.0 if outside.size == 0 else (math.inf if outside[-1] == dev.size - 1 else float(t[~a][outside[-1] + 1] - tl))
    out["sim_load_recovery_s"] = {"value": rec, "limit": t[-1] - tl, "ok": bool(rec < 0.8 * (t[-1] - tl)),
                                  "unit": "s", "note": "back into the 2 % band after the load-torque step"}
    out["sim_load_dip_rpm"] = {"value": float(target - np.min(rpm[~a])), "limit": target, "ok": bool(np.min(rpm[~a]) > 0),
                               "unit": "rpm", "note": "speed dip after the load step (must not stall)"}
    n_tail = max(1, int(0.1 * t.size))
    err = float(target - np.mean(rpm[-n_tail:]))
    out["sim_final_error_rpm"] = {"value": err, "limit": 0.02 * target, "ok": bool(abs(err) <= 0.02 * target),
                                  "unit": "rpm", "note": "mean over the last 10 % of the run"}
    u_bridge = profile.inverter.bus_voltage_v * profile.max_duty()
    out["sim_peak_u_v"] = {"value": float(np.max(np.abs(sim.u))), "limit": u_bridge,
                           "ok": bool(np.max(np.abs(sim.u)) <= u_bridge + 1e-9), "unit": "V"}
    tail = np.zeros(t.size, bool)
    for t0, t1 in ((0.8 * tl, tl), (t[-1] - 0.2 * (t[-1] - tl), t[-1] + 1)):
        tail |= (t >= t0) & (t < t1)
    sat_tail = float(np.mean(sim.saturated[tail]))
    out["sim_saturated_steady_fraction"] = {"value": sat_tail, "limit": 0.0, "ok": bool(sat_tail == 0.0), "unit": "1",
                                            "note": "fraction of the steady-state windows with u at its limit"}
    out["sim_saturated_time_s"] = {"value": float(np.sum(sim.saturated) * law.sample_time_s), "limit": 0.5 * tl,
                                   "ok": bool(np.sum(sim.saturated) * law.sample_time_s <= 0.5 * tl), "unit": "s"}
    ipk = float(np.max(np.abs(sim.i_bus)))
    out["sim_peak_bus_current_a"] = {"value": ipk, "limit": profile.inverter.current_limit_a,
                                     "ok": bool(ipk <= profile.inverter.current_limit_a), "unit": "A"}
    # integrator headroom at the end (b = 0 designs hold u* + kp w + kc i in the integrator)
    return out


def verify_design(profile, result, *, simulate: bool = True):
    """Run every applicable check, fill ``result.verification``, fail on any failed check.

    Returns the same result (status ``verified`` unless a check failed)."""
    checks: dict[str, Any] = {}
    law = result.law
    if law is not None:
        checks["sampled_spectral_radius"] = _sampled_check(profile, law)
        if law.u_max_v > profile.inverter.bus_voltage_v * profile.max_duty() + 1e-9 or \
                law.u_min_v < -profile.inverter.bus_voltage_v * profile.max_duty() - 1e-9:
            checks["law_output_limits_v"] = {"value": [law.u_min_v, law.u_max_v],
                                             "limit": profile.inverter.bus_voltage_v * profile.max_duty(),
                                             "ok": False, "unit": "V", "note": "outside +- bus voltage x max duty"}
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
