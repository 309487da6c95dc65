"""Verification every design passes before it is saved as usable.

``verify_design(profile, result)`` is method-agnostic: it reads the law
(:class:`picdrive.control_law.ScheduledLaw`, the thing the firmware runs)
and, when present, the certificate, and fills ``result.verification`` with
entries ``{"value", "limit", "ok", "unit", "note"}``; any failed entry calls
``result.fail(reason)``.

The plant every law is judged on in simulation is the drive the firmware
runs: the six-step bridge (high-side PWM, low side on) on the motor's
three-phase winding -- the motor twin's plant (``drive.three_phase_plant``, from
:class:`picdrive.gate.BuiltDrive`:
per-phase currents, the floating phase and its body diode, the current
transfer at every commutation, which the DC equivalent has not: with a hall
sector shorter than L/R it delivers less torque per measured ampere, and a
law verified on the DC equivalent overshot 1.2 % in the twin where its
verification said 0.02 %, tests/motors/anaheim_bly171d_24v_4000.toml) --
driven through the hall table; the linear checks use the DC equivalent
(2008 eq 1 constants of the profile); the conduction rule of the bridge (the current cannot
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
  three-phase plant (``drive.hold_torque``, :func:`picdrive.gate.bridge_hold_torque`: commutation
  transfers, which the DC equivalent has not), against the load and friction there; R nominal
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
  (``sim_resistance_uncertainty``); and the step and load step at half the
  step target (``sim_half_speed``: settling, load recovery, final error and
  current judged alike, the overshoot a figure), where the hall-speed
  measurement's lag is twice the target's.
* ``firmware_fits_chip`` (added by ``picdrive design``,
  :func:`picdrive.gate.check_chip`) -- the design's firmware built for the
  PIC18F4431 as ``picdrive firmware`` builds it: flash, static RAM + stack and
  every interrupt's worst case within ``picdrive.firmware.target.BUDGETS``.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from ..analysis.h2hinf import hinf_norm, pid_figures_sampled, sampled_loop
from ..analysis.metrics import step_metrics
from ..analysis.lmi import lmi_margins
from ..analysis.sampled import RPM, sampled_radius, six_step_equilibrium
from ..analysis.steptest import VerifyConfig, run_sim, sector_mean, sector_period_s, sim_plan, step_figures
from ..models.dqmodel import dq_params, max_speed_rad_s
from ..models.tfmodel import motor_tf, sampled_plant, simulate_sampled
from ..models.tsfuzzy import model_for

__all__ = ["verify_design", "pid_model_checks", "failure_message", "BLOCKING_CHECKS", "DRIVE_LIMIT_CHECKS",
           "drive_limit_failed", "RUN_FIGURES", "run_limits", "failed_figures", "run_failures"]


# ---------------------------------------------------------------------------
# The law on the linear six-step drive
# ---------------------------------------------------------------------------
def _sampled_check(profile, law) -> dict:
    worst, where = sampled_radius(profile, law)
    meas = ("the firmware's speed measurement" if profile.sensors.speed_source != "hall" else
            "the encoder's M/T measurement (this profile measures speed from the halls: their period's lag, "
            "which depends on the speed, is judged by the simulation, sim_*)")
    return {"value": worst, "limit": 1.0, "ok": bool(worst < 1.0), "unit": "1",
            "note": f"largest |eig| of the sampled closed loop on the six-step DC-equivalent plant with {meas}; "
                    f"worst at {where}"}


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


HALL_ADVANCES_DEG = (10.0, 20.0, 30.0)
"""Hall advances the hold check tries when the bridge cannot hold the target, electrical deg: the
hall board turned ahead of the back-EMF, so each commutation comes earlier and the current has
the time L/R asks for (30 deg is the usual timing of fast hobby motors)."""


def _hold_check(profile, drive) -> dict:
    eps = float(profile.design.get("resistance_uncertainty", 0.1))
    tgt = profile.speed_step_rpm()
    worst = None
    for rs in (1.0, 1.0 + eps):
        te, need = drive.hold_torque(profile, tgt, r_factor=rs)
        if worst is None or te - need < worst[0] - worst[1]:
            worst = (te, need, rs)
    te, need, rs = worst
    check = {"value": te, "limit": need, "ok": bool(te > need), "unit": "N m",
             "note": f"mean torque the bridge delivers at the step target ({tgt:.0f} rpm held, R x {rs:g}) through "
                     "the firmware's hall table at its largest duty, in the twin's three-phase plant (commutation "
                     "transfers included), vs the load and friction torque there: below it the target cannot "
                     f"be held under the load (hall sector {1e3 * sector_period_s(profile, tgt):.3g} ms, L/R "
                     f"{1e3 * profile.motor.l_line_h / profile.motor.r_line_ohm:.3g} ms)"}
    if not check["ok"]:
        check["fix"] = _hold_fix(profile, drive, tgt, rs)
    return check


def _hold_fix(profile, drive, tgt: float, rs: float) -> str:
    """What holds the target when the bridge cannot: the highest speed it holds (R x ``rs``) as the
    reference, and the smallest hall advance (:data:`HALL_ADVANCES_DEG`) that holds ``tgt``."""
    def margin(p, rpm):
        te, need = drive.hold_torque(p, rpm, r_factor=rs)
        return te - need
    lo, hi = 0.0, tgt                       # the torque margin falls with speed: bisect its zero
    if margin(profile, 0.05 * tgt) <= 0:
        held = "it holds no speed under the load"
    else:
        lo = 0.05 * tgt
        for _ in range(12):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if margin(profile, mid) > 0 else (lo, mid)
        # 1 % below the edge: the sector-averaged torque is not smooth to the last rpm
        held = (f"control.reference_rpm at most {math.floor(0.99 * lo):.0f} rpm (1 % below {lo:.0f} rpm, the highest "
                "speed it holds there)")
    dq = _dq_reachability(profile)
    if dq is not None and not dq["ok"]:
        # the dq model's limit is on the voltage alone: no hall advance passes it
        return f"{held}; a hall advance would not pass dq_hold_rpm, which limits the speed on the voltage alone"
    off = profile.sensors.hall_offset_deg
    for adv in HALL_ADVANCES_DEG:
        q = profile.replace(sensors={"hall_offset_deg": math.remainder(off - adv, 360.0)})
        if margin(q, tgt) > 0:
            adv_text = (f"or the hall board turned {adv:g} deg electrical ahead (sensors.hall_offset_deg = "
                        f"{q.sensors.hall_offset_deg:g}, from {off:g}): commutation {adv:g} deg earlier holds "
                        f"{tgt:.0f} rpm")
            break
    else:
        adv_text = (f"no hall advance up to {HALL_ADVANCES_DEG[-1]:g} deg holds {tgt:.0f} rpm: a higher bus voltage "
                    "or a winding with a higher speed constant")
    return f"{held}, {adv_text}"


def _peak_current_fix(profile, peak_a: float) -> str:
    """The trip or the current limit that would pass a peak of ``peak_a``: the peak over the limit is
    the hall-speed lag and the PWM ripple, which scale with the limit the window holds."""
    inv = profile.inverter
    trip_a = math.ceil(10.0 * peak_a * 1.05) / 10.0
    limit_a = math.floor(10.0 * inv.current_limit_a * inv.overcurrent_trip_a / peak_a * 0.95) / 10.0
    return (f"inverter.overcurrent_trip_a at least {trip_a:g} A (5 % above the peak, if the bridge and the motor "
            f"take it), or inverter.current_limit_a about {limit_a:g} A (the peak scaled to 95 % of the "
            f"{inv.overcurrent_trip_a:g} A trip)")


def _dq_reachability(profile) -> dict | None:
    if profile.motor.back_emf_shape != "sinusoidal":
        return None
    p = dq_params(profile)
    u_max = profile.inverter.bus_voltage_v * profile.max_duty()
    hold = max_speed_rad_s(p, p.kv_vq_per_u * u_max, profile.control.load_torque_n_m) / RPM
    tgt = profile.speed_step_rpm()
    out = {"value": hold, "limit": tgt, "ok": bool(hold >= tgt), "unit": "rpm",
           "note": "speed the dq model (v_d = 0, sinusoidal motor) holds under the load at the bridge voltage; "
                   "must reach the step target"}
    if not out["ok"]:
        # the held speed grows about in proportion to the voltage (the IR drop aside): a first estimate
        bus = profile.inverter.bus_voltage_v
        out["fix"] = (f"control.reference_rpm at most {math.floor(hold):.0f} rpm, or a bus of about "
                      f"{math.ceil(bus * tgt / max(hold, 1e-9)):.0f} V (inverter.bus_voltage_v, from {bus:g} V, within "
                      f"the {profile.inverter.switch_vds_max_v:g} V switch rating)")
    return out


# ---------------------------------------------------------------------------
# Certificate checks (fuzzy designs)
# ---------------------------------------------------------------------------
def _discrete_certificate_checks(profile, cert) -> dict:
    """The sampled-loop certificate (``time_domain = "discrete"``, :mod:`picdrive.design.fuzzy_dhinf`) re-checked
    on the sampled model rebuilt from the profile: the LMIs re-assembled, the closed loop's spectral radius at
    every rule, blend and vertex, and each vertex closed loop's H-inf norm against the certified bound."""
    from ..analysis.dlmi import closed_loop_radius, dhinf_norm, dlmi_margins, normalised, rescaled, sampled_stages
    out: dict[str, Any] = {}
    ts = model_for(profile, cert["model"], cert.get("model_options", {}))
    sm, _ = sampled_stages(profile, ts, cert["model"], tuple(cert.get("zero_gain_states", ())),
                           float(cert.get("effort_weight_rad_s_per_v") or 0.0))
    S = np.asarray(cert["state_scale"], float)
    smn, nb, nc = normalised(rescaled(sm, S / sm.S))
    K = [np.asarray(k, float) for k in cert["K"]]
    radius = cert.get("pole_disk_radius")
    if cert.get("Q") is not None and cert.get("G") is not None:
        Qd = cert.get("Qd")
        marg = dlmi_margins(smn, np.asarray(cert["Q"], float), np.asarray(cert["G"], float),
                            [np.asarray(y, float) for y in cert["Y"]], float(cert["gamma_normalised"]),
                            Qd=None if Qd is None else np.asarray(Qd, float), radius=radius)
        worst = max(marg.values())
        out["lmi_max_eig"] = {"value": worst, "limit": 0.0, "ok": bool(worst < 0.0), "unit": "1",
                              "note": "largest of -(smallest eigenvalue) of Q > 0 and the sampled-loop bounded-real "
                                      "LMIs (every rule pair and vertex), re-assembled (normalised units)"}
    from ..control_law import memberships
    from types import SimpleNamespace
    law_ns = SimpleNamespace(n_rules=len(K), premise_rad_s=tuple(cert["premise_rad_s"]))
    lo, hi = cert["premise_rad_s"]
    mus = [memberships(law_ns, w) for w in np.linspace(lo, hi, 9)]
    rad, where = closed_loop_radius(smn, K, mus)
    lim = 1.0 if radius is None else float(radius)
    out["discrete_spectral_radius"] = {"value": rad, "limit": lim, "ok": bool(rad < lim), "unit": "1",
                                       "note": f"largest |eig| of the sampled closed loop the certificate covers "
                                               f"(rules, 9 blends across the premise, {smn.nv} vertices); worst "
                                               f"at {where}"}
    worst_h = 0.0
    for v in range(smn.nv):
        for i in range(smn.r):
            Cz = smn.C[i] if smn.D is None else smn.C[i] + smn.D[i] @ K[i]
            h = dhinf_norm(smn.A[i][v] + smn.B[i][v] @ K[i], smn.Bw[i][v], Cz) * nb * nc
            worst_h = max(worst_h, h)
    bound = float(cert["certified_gain"])
    out["hinf_norm"] = {"value": worst_h, "limit": bound, "ok": bool(worst_h <= bound * (1 + 1e-6)), "unit": "z/w",
                        "note": "max discrete H-inf norm w -> z of the vertex closed loops (every rule, R nominal "
                                "and at its uncertainty extremes, the EMF range) vs the certified bound"}
    return out


def _certificate_checks(profile, result) -> dict:
    cert = result.certificate or {}
    out: dict[str, Any] = {}
    if "K" not in cert or "model" not in cert:
        return out
    if cert.get("time_domain") == "discrete":
        return _discrete_certificate_checks(profile, cert)
    ts = model_for(profile, cert["model"], cert.get("model_options", {}))
    K = [np.asarray(k, float) for k in cert["K"]]
    if "P" in cert and "Y" in cert and cert.get("gamma") is not None:
        P = np.asarray(cert["P"], float)
        Y = [np.asarray(y, float) for y in cert["Y"]]
        marg = lmi_margins(ts, P, Y, float(cert["gamma"]), float(cert["delta"]), float(cert["alpha"]),
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
#: the figures of a verification run that are checked, with their names in a message and their units
RUN_FIGURES = (("settling_s", "settling (2 % band)", "s"), ("overshoot_pct", "overshoot", "%"),
                ("load_recovery_s", "recovery after the load step", "s"), ("final_error_rpm", "final error", "rpm"),
                ("peak_current_ripple_a", "peak line current", "A"))


def run_limits(profile, plan) -> dict:
    """The limit of each figure of :data:`RUN_FIGURES` as the checks apply it (the real one)."""
    tl, t_end, band = plan["t_load_s"], plan["t_end_s"], VerifyConfig.band
    return {"settling_s": 0.8 * tl, "overshoot_pct": 100 * band, "load_recovery_s": 0.8 * (t_end - tl),
            "final_error_rpm": band * plan["target_rpm"], "peak_current_ripple_a": profile.inverter.overcurrent_trip_a}


def failed_figures(fr: dict, limits: dict) -> list[str]:
    """The keys of :data:`RUN_FIGURES` whose figure in ``fr`` misses its limit in ``limits`` (the final
    error by its magnitude; the overshoot may reach its limit, the others must stay below)."""
    out = []
    for key, _name, _unit in RUN_FIGURES:
        v, lim = fr[key], limits[key]
        if abs(v) > lim if key == "final_error_rpm" else (v > lim if key == "overshoot_pct" else not v < lim):
            out.append(key)
    return out


def run_failures(fr: dict, limits: dict, where: str) -> list[str]:
    """What failed in one run's figures ``fr`` against ``limits``: one phrase per figure, with both numbers."""
    bad = failed_figures(fr, limits)
    return [f"{where}: {name} {_num(fr[key])} {unit} (limit {_num(limits[key])} {unit})"
            for key, name, unit in RUN_FIGURES if key in bad]


def _num(v) -> str:
    """A figure in a message: 5 significant digits (enough to see 6.0085 A against 6 A)."""
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return f"{float(v):.5g}"
    return repr(v)


def _sim_checks(profile, law, drive) -> dict:
    plan = sim_plan(profile)
    measurement = drive.speed_measurement(profile, law)
    out: dict[str, Any] = {}
    target = plan["target_rpm"]
    tl = plan["t_load_s"]
    t_end = plan["t_end_s"]
    band = VerifyConfig.band
    lims = run_limits(profile, plan)
    out["sim_step_target_rpm"] = {"value": target, "limit": plan["profile_target_rpm"], "ok": True, "unit": "rpm",
                                  "note": "profile.speed_step_rpm() (a figure, not a check)"}
    # the step as the drive shows it (the sim_* figures), and apart from it the same run with the verification's
    # injected load-torque disturbance (sim_disturbance): a disturbance figure is not what the user sees
    try:
        sim = run_sim(profile, law, plan, measurement=measurement, disturbances=False,
                      three_phase=drive.three_phase_plant)
    except FloatingPointError:
        out["sim_finite"] = {"value": False, "limit": True, "ok": False, "unit": "", "note": "simulation diverged"}
        return out
    f = step_figures(sim, plan, profile)
    out["sim_settling_s"] = {"value": f["settling_s"], "limit": lims["settling_s"],
                             "ok": bool(f["settling_s"] < lims["settling_s"]), "unit": "s", "phase_s": tl,
                             "note": f"{100 * band:g} % band, step from rest: must settle within 80 % of the "
                                     f"{tl:.4g} s step phase"}
    out["sim_rise_s"] = {"value": f["rise_s"], "limit": tl, "ok": bool(f["rise_s"] < tl), "unit": "s"}
    out["sim_overshoot_pct"] = {"value": f["overshoot_pct"], "limit": lims["overshoot_pct"],
                                "ok": bool(f["overshoot_pct"] <= lims["overshoot_pct"]), "unit": "%",
                                "note": "within the settling band: the bridge cannot brake, a larger overshoot "
                                        "coasts back on friction alone"}
    out["sim_load_recovery_s"] = {"value": f["load_recovery_s"], "limit": lims["load_recovery_s"],
                                  "ok": bool(f["load_recovery_s"] < lims["load_recovery_s"]), "unit": "s",
                                  "phase_s": t_end - tl,
                                  "note": f"back into the {100 * band:g} % band after the load-torque step, within "
                                          f"80 % of the {t_end - tl:.4g} s load phase"}
    out["sim_load_dip_rpm"] = {"value": f["load_dip_rpm"], "limit": target, "ok": bool(f["load_dip_rpm"] < target),
                               "unit": "rpm", "note": "speed dip after the load step (must not stall)"}
    out["sim_speed_ripple_pct"] = {"value": f["ripple_pct"], "limit": None, "ok": True, "unit": "%",
                                   "note": "a figure, not a check: peak-to-peak speed ripple about the sector mean "
                                           "under the load, the commutation's torque ripple (a property of the motor "
                                           "and the six-step bridge; higher loop gains reduce it)"}
    out["sim_peak_rpm"] = {"value": f["peak_rpm_raw"], "limit": profile.control.speed_max_rpm,
                           "ok": bool(f["peak_rpm_raw"] <= profile.control.speed_max_rpm), "unit": "rpm",
                           "note": "raw peak speed vs control.speed_max_rpm"}
    out["sim_final_error_rpm"] = {"value": f["final_error_rpm"], "limit": lims["final_error_rpm"],
                                  "ok": bool(abs(f["final_error_rpm"]) <= lims["final_error_rpm"]), "unit": "rpm",
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
    if not out["sim_peak_bus_current_a"]["ok"]:
        out["sim_peak_bus_current_a"]["fix"] = _peak_current_fix(profile, f["peak_current_ripple_a"])
    # the window holds the mean current at the limit, so the sampled current crosses it by its ripple and
    # the backup's cap leaves the top now and then; that is harmless while the cap stays above what the
    # law asks (the window still sets the output).  Counted: the samples where the cap cut the output.
    n_cap = int(np.sum(sim.cap_cut))
    out["sim_current_backup_samples"] = {"value": n_cap, "limit": 0, "ok": bool(n_cap == 0), "unit": "samples",
                                         "note": "samples where the firmware's walk-down backup (measured current "
                                                 "above the limit) cut the law's output: the window alone must hold "
                                                 f"the current (the cap left the top in {int(np.sum(sim.cap_active))} "
                                                 "samples)"}
    # the same run with the injected disturbance (the 2016 paper's w3), kept apart
    try:
        sd = run_sim(profile, law, plan, measurement=measurement, three_phase=drive.three_phase_plant)
        fd = step_figures(sd, plan, profile)
        dist = {k: round(fd[k], 4) for k, _, _ in RUN_FIGURES}
        dist["current_backup_samples"] = int(np.sum(sd.cap_cut))
        fails = run_failures(fd, lims, "with the disturbance")
        if dist["current_backup_samples"]:
            fails.append(f"with the disturbance: the current walk-down backup cut the output in "
                         f"{dist['current_backup_samples']} samples (limit 0)")
    except FloatingPointError:
        dist, fails = "diverged", ["with the disturbance: the simulation diverged"]
    out["sim_disturbance"] = {"value": dist, "limit": {k: round(v, 4) for k, v in lims.items()},
                              "ok": not fails, "unit": "", "failures": fails,
                              "note": "the same step and load step with the verification's injected load-torque "
                                      f"disturbance w3 (0.1 x the {plan['load_n_m']:g} N m load, 2016 paper) on "
                                      "[0, 0.2] s; the sim_* figures above are the step without it, as the drive "
                                      "shows it"}
    # R at the extremes of its uncertainty: the same step and load step, same limits
    eps = float(profile.design.get("resistance_uncertainty", 0.1))
    worst = {}
    fails = []
    for rs in (1.0 - eps, 1.0 + eps):
        try:
            fr = step_figures(run_sim(profile, law, plan, measurement=measurement, disturbances=False, r_factor=rs,
                                      three_phase=drive.three_phase_plant),
                              plan, profile)
        except FloatingPointError:
            fails.append(f"R x {rs:g}: the simulation diverged")
            worst[f"R x {rs:g}"] = "diverged"
            continue
        fails += run_failures(fr, lims, f"R x {rs:g}")
        worst[f"R x {rs:g}"] = {k: round(fr[k], 4) for k, _, _ in RUN_FIGURES}
    out["sim_resistance_uncertainty"] = {"value": worst, "limit": {k: round(v, 4) for k, v in lims.items()},
                                         "ok": not fails, "unit": "", "failures": fails,
                                         "note": f"step and load step with R x (1 -+ {eps:g})"}
    out["sim_half_speed"] = _half_speed_check(profile, law, drive, plan, measurement)
    return out


def _half_speed_check(profile, law, drive, plan, measurement) -> dict:
    """The step and load step at half the step target (the HIL suite's lower operating point).

    A law checked at the target alone can limit-cycle lower down: from the halls the speed is a
    sector's mean, updated once a sector, so the measurement's lag grows as the speed falls (at
    half the target it is twice the target's).  Judged as the target's run is (:func:`run_limits`
    of the half-speed plan), less the overshoot, which is a figure here."""
    half = dict(plan, target_rpm=0.5 * plan["target_rpm"])
    lims = {**run_limits(profile, half), "overshoot_pct": math.inf}
    note = (f"step from rest to {half['target_rpm']:.0f} rpm and the load step there, R nominal, "
            + ("speed from the halls (a sector's mean: its lag doubles at half speed)"
               if profile.sensors.speed_source == "hall" else "speed from the encoder")
            + "; the overshoot is a figure, not a check")
    limit = {k: round(v, 4) for k, v in lims.items() if math.isfinite(v)}
    try:
        f = step_figures(run_sim(profile, law, half, measurement=measurement, disturbances=False,
                                 three_phase=drive.three_phase_plant), half, profile)
    except FloatingPointError:
        fails = [f"at {half['target_rpm']:.0f} rpm: the simulation diverged"]
        return {"value": "diverged", "limit": limit, "ok": False, "unit": "", "failures": fails, "note": note}
    fails = run_failures(f, lims, f"at {half['target_rpm']:.0f} rpm")
    return {"value": {k: round(float(f[k]), 4) for k, _, _ in RUN_FIGURES}, "limit": limit, "ok": not fails,
            "unit": "", "failures": fails, "note": note}


def with_reference_ff(profile, law, drive=None):
    """``law`` with its reference feedforward gain set (profile ``control.reference_feedforward``;
    :func:`picdrive.control_law.reference_ff_gain` at the profile's step speed): the no-load steady
    state of the speed-dependent averaged model identified from the drive's three-phase plant
    (:func:`picdrive.models.averaged.identify`, what the simulations run on) when ``drive`` is given,
    else of the DC equivalent (u = (Kb + R B / Kt) w, i = B w / Kt)."""
    from ..control_law import reference_ff_gain
    m = profile.motor
    w = profile.speed_step_rpm() * math.pi / 30.0
    if drive is not None:
        from ..models.averaged import identify_cached
        u_ss, i_ss = identify_cached(profile, drive.three_phase_plant).equilibrium(w, 0.0)
    else:
        i_ss = m.viscous_friction_n_m_s * w / m.kt_n_m_per_a
        u_ss = m.kb_v_s_per_rad * w + m.r_line_ohm * i_ss
    return dataclasses.replace(law, reference_ff_v_s_per_rad=reference_ff_gain(law, w, u_ss, i_ss))


def choose_reference_ff(profile, law, drive, mode: str, *, simulate: bool = True):
    """The law with or without its reference feedforward, by the profile's ``control.reference_feedforward``
    (``mode``): ``"on"`` always; ``"auto"`` only when, in the verification's plant
    (:func:`picdrive.analysis.timeoptimal.law_step_to_band`: step from rest to the profile's step speed,
    without load and under the profile's load), the law with it reaches the 1 % band sooner in the worse
    of the two runs and its worse overshoot of the sector-mean speed stays within 1 % (or within the law's
    without it).  ``"auto"`` needs the simulation (``drive``, ``simulate``); without them it keeps the
    law as it is.  Returns ``(law, check)``: the check records the gain and the figures it was chosen on."""
    base = dataclasses.replace(law, reference_ff_v_s_per_rad=0.0)
    ff = with_reference_ff(profile, base, drive)
    g = ff.reference_ff_v_s_per_rad
    if mode == "on":
        return ff, {"value": round(g, 6), "limit": "", "ok": True, "unit": "V s/rad",
                    "note": "control.reference_feedforward = 'on'"}
    if not simulate or drive is None:
        return base, {"value": 0.0, "limit": "", "ok": True, "unit": "V s/rad",
                      "note": "'auto' without the simulation: left off"}
    from ..analysis.timeoptimal import law_step_to_band
    rpm = profile.speed_step_rpm()
    loads = sorted({0.0, float(profile.control.load_torque_n_m)})
    runs = {k: [law_step_to_band(profile, lw, drive, ld, rpm) for ld in loads] for k, lw in (("off", base), ("on", ff))}
    t = {k: max(f["t_band_s"] for f in v) for k, v in runs.items()}
    ovs = {k: max(f["overshoot_pct"] for f in v) for k, v in runs.items()}
    use = t["on"] < t["off"] and ovs["on"] <= max(1.0, ovs["off"])
    note = "; ".join(f"{k}: worst time to the 1 % band {1e3 * t[k]:.1f} ms, worst overshoot {ovs[k]:.2f} %"
                     for k in ("off", "on")) + f" (loads {', '.join(f'{ld:g}' for ld in loads)} N m, step to {rpm:g} rpm)"
    return (ff if use else base), {"value": round(g if use else 0.0, 6), "limit": "auto", "ok": True,
                                   "unit": "V s/rad", "note": ("with the feedforward: " if use else "without: ") + note}


#: checks that fail on a limit of the drive (it cannot hold the target, the law is not the firmware's): their
#: reasons come first, before the figures that fail because of them (and before a method's own earlier reasons)
BLOCKING_CHECKS = ("bridge_hold_torque_n_m", "dq_hold_rpm", "law_current_window", "law_output_limits_v")

#: blocking checks on the drive alone (the bridge, the motor and the target): no gains pass them, so a
#: method stops searching when one fails and names its fix
DRIVE_LIMIT_CHECKS = ("bridge_hold_torque_n_m", "dq_hold_rpm")


def drive_limit_failed(result) -> bool:
    """True when ``result`` failed a check no other gains can pass (:data:`DRIVE_LIMIT_CHECKS`)."""
    v = result.verification or {}
    return any(n in v and not v[n].get("ok", True) for n in DRIVE_LIMIT_CHECKS)


def failure_message(name: str, check: dict) -> str:
    """The reason a failed check gives: the figure that failed and the limit the check applied, with the unit;
    a check over several runs (``failures``) names each failed figure."""
    unit = check.get("unit", "")
    if check.get("failures"):
        head = "; ".join(check["failures"])
    else:
        lim = check.get("limit")
        head = f"{_num(check['value'])}" + (f" (limit {_num(lim)}{' ' + unit if unit else ''})"
                                             if lim not in (None, "") else (f" {unit}" if unit else ""))
    return (f"verification '{name}' failed: {head}" + (f"; fix: {check['fix']}" if check.get("fix") else "")
            + (f": {check['note']}" if check.get("note") else ""))


def verify_design(profile, result, *, drive=None, simulate: bool = True):
    """Run every applicable check, fill ``result.verification``, fail on any failed check.

    Parameters
    ----------
    profile : picdrive.profile.Profile
        The drive the design is for.
    result : picdrive.result.DesignResult
        The design (its law and/or certificate); updated in place.
    drive : object, optional
        The drive as built, for the checks the models cannot make -- an object with
        ``speed_measurement(profile, law) -> dict`` (the firmware's speed measurement, as
        :func:`picdrive.analysis.steptest.run_sim` takes it), ``hold_torque(profile, rpm, *,
        r_factor=1.0) -> (delivered, needed)`` (N m, the bridge in the twin's three-phase plant)
        and ``three_phase_plant(profile, r_factor)`` (the winding the simulations run on):
        :class:`picdrive.gate.BuiltDrive`.  Needed to simulate a law (``simulate``); a design
        without a law, or ``simulate=False``, is checked on the models alone.
    simulate : bool
        Run the step and load-step simulations (the figures in s, %, rpm, A) besides the
        linear checks.

    Returns
    -------
    picdrive.result.DesignResult
        The same result: ``verification`` holds each check's ``value``, ``limit``, ``unit`` and
        ``ok``; ``status`` is ``"verified"`` unless a check failed (then ``"failed"`` with the
        reasons).
    """
    if result.law is not None and simulate and drive is None:
        raise ValueError("verify_design: simulating a law needs the built drive (drive=picdrive.gate.BuiltDrive())")
    ff_mode = getattr(profile.control, "reference_feedforward", "off")
    ff_check = None
    if result.law is not None and ff_mode == "on":
        result.law, ff_check = choose_reference_ff(profile, result.law, drive, "on", simulate=simulate)
    elif result.law is not None and ff_mode == "auto":       # judged as an add-on to the law without it
        result.law = dataclasses.replace(result.law, reference_ff_v_s_per_rad=0.0)
    checks = _law_checks(profile, result, drive, simulate)
    if result.law is not None and ff_mode == "auto":
        # kept only if the law verifies without it and the law with it passes every check too
        plain = result.law
        if not all(c.get("ok", True) for c in checks.values()):     # no step runs for a law that fails anyway
            ff_check = {"value": 0.0, "limit": "auto", "ok": True, "unit": "V s/rad",
                        "note": "left off: the law fails without it"}
        else:
            law_ff, ff_check = choose_reference_ff(profile, plain, drive, "auto", simulate=simulate)
        if ff_check["value"]:
            result.law = law_ff
            checks_ff = _law_checks(profile, result, drive, simulate)
            failed = [k for k, c in checks_ff.items() if not c.get("ok", True)]
            if failed:
                result.law = plain
                ff_check = {**ff_check, "value": 0.0,
                            "note": f"left off: the law with it fails {', '.join(failed)}; " + ff_check["note"]}
            else:
                checks = checks_ff
    if ff_check is not None:
        checks = {"reference_feedforward": ff_check, **checks}
    if result.law is None and not checks:
        checks["nothing_to_verify"] = {"value": "no law and no certificate", "limit": "", "ok": False, "unit": ""}
    result.verification.update(checks)
    failed = [name for name, c in checks.items() if not c.get("ok", True)]
    # a limit of the drive itself first: what fails after it (settling, overshoot) follows from it
    blocking = [n for n in failed if n in BLOCKING_CHECKS]
    for name in blocking + [n for n in failed if n not in BLOCKING_CHECKS]:
        result.fail(failure_message(name, checks[name]))
    if blocking:
        first = [failure_message(n, checks[n]) for n in blocking]
        result.reasons[:] = first + [x for x in result.reasons if x not in first]
    if result.status != "failed" and not result.reasons:
        result.status = "verified"
    return result


def _law_checks(profile, result, drive, simulate: bool) -> dict:
    """Every applicable check of ``result``'s law and certificate (see :func:`verify_design`)."""
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
            checks["bridge_hold_torque_n_m"] = _hold_check(profile, drive)
    checks.update(_certificate_checks(profile, result))
    if law is not None and simulate and checks.get("sampled_spectral_radius", {}).get("ok", True):
        checks.update(_sim_checks(profile, law, drive))
    elif law is not None and simulate:
        checks["sim_skipped"] = {"value": "skipped", "limit": "", "ok": False, "unit": "",
                                 "note": "the sampled closed loop is unstable; no simulation"}
    return checks


# ---------------------------------------------------------------------------
# PID laws on the 2008 transfer function (mixed-pid, zn)
# ---------------------------------------------------------------------------
def pid_model_checks(profile, result: DesignResult, *, ms_max: float | None = None,
                     delay_samples: int = 1, measurement: str = "average", d: float | None = None) -> None:
    """The PID methods' checks of their one-rule law on the 2008 eq 1 model (fills
    ``verification`` with the ``pid_*`` entries, fails on error); :func:`verify_design` follows.

    * the sampled closed loop is stable (spectral radius < 1);
    * eq 6 on the sampled loop <= 1;
    * the sensitivity peak <= ``ms_max`` (when given);
    * a nonlinear simulation of the law (saturation, anti-windup) on eq 1:
      step from rest to ``profile.speed_step_rpm()``, then the profile's
      load-torque step; the step must settle (2 %) before the load is
      applied and the speed must be back within 1 % at the end.
    """
    law = result.law
    g = law.rules[0]
    d = profile.design["perturbation_d"] if d is None else d
    sp = sampled_plant(motor_tf(profile), law.sample_time_s, delay_samples=delay_samples, measurement=measurement)
    fig = pid_figures_sampled(sp, g.kp, g.ki, g.kd, d)
    v = result.verification
    v["pid_sampled_spectral_radius"] = {"value": round(fig["spectral_radius_sampled"], 6), "limit": 1.0,
                                    "ok": fig["stable_sampled"]}
    if not fig["stable_sampled"]:
        result.fail(f"the sampled closed loop at {1 / law.sample_time_s:g} Hz (ZOH, {delay_samples} sample delay, "
                    f"{measurement} speed) is unstable: spectral radius {fig['spectral_radius_sampled']:.4g} >= 1")
        return
    v["pid_hinf_constraint_sampled"] = {"value": round(fig["hinf_constraint_sampled"], 6), "limit": 1.0,
                                    "ok": fig["hinf_constraint_sampled"] <= 1.0}
    if fig["hinf_constraint_sampled"] > 1.0:
        result.fail(f"robust constraint ||P C xi/(1+PC)||_inf = {fig['hinf_constraint_sampled']:.4g} > 1 (eq 6, d = {d:g})")
    if ms_max is not None:
        ok = fig["sensitivity_peak_sampled"] <= ms_max * (1 + 1e-9)
        v["pid_sensitivity_peak"] = {"value": round(fig["sensitivity_peak_sampled"], 4), "limit": ms_max, "ok": ok}
        if not ok:
            result.fail(f"sensitivity peak {fig['sensitivity_peak_sampled']:.4g} exceeds {ms_max:g}")
    else:
        v["pid_sensitivity_peak"] = {"value": round(fig["sensitivity_peak_sampled"], 4)}
    # nonlinear simulation
    A, _, _ = sampled_loop(sp, g.kp, g.ki, g.kd)
    rho = max(fig["spectral_radius_sampled"], 1e-9)
    tau = law.sample_time_s / max(-math.log(rho), 1e-9)
    m = profile.motor
    tau_m = m.inertia_kg_m2 * m.r_line_ohm / (m.kt_n_m_per_a * m.kb_v_s_per_rad)
    phase = min(max(0.1, 12 * tau, 12 * tau_m), 20.0)
    ref = profile.speed_step_rpm() * RPM
    sim = simulate_sampled(profile, law, t_end_s=2 * phase, ref_rad_s=ref, load_n_m=profile.control.load_torque_n_m,
                           t_load_s=phase, delay_samples=delay_samples, measurement=measurement)
    t, w = sim["t_s"], sim["speed_rad_s"]
    first = t < phase
    sm = step_metrics(t[first], w[first], ref)
    end_err = abs(ref - float(np.mean(w[-max(3, len(w) // 50):]))) / ref * 100
    sat = float(np.mean(np.abs(sim["u_v"][first]) >= law.u_max_v * (1 - 1e-9)))
    v["pid_tf_step"] = {"value": {"step_rpm": round(ref / RPM, 2), "rise_ms": round(sm.rise_time_s * 1e3, 3),
                                     "settling_ms": round(sm.settling_time_s * 1e3, 3) if math.isfinite(sm.settling_time_s) else "inf",
                                     "overshoot_pct": round(sm.overshoot_pct, 3),
                                     "saturated_fraction": round(sat, 3)},
                           "limit": f"settles (2 %) within {phase * 1e3:.0f} ms",
                           "ok": math.isfinite(sm.settling_time_s)}
    if not math.isfinite(sm.settling_time_s):
        result.fail(f"the simulated step to {ref / RPM:.0f} rpm (saturating law on eq 1) does not settle "
                    f"within {phase * 1e3:.0f} ms")
    v["pid_tf_load_step"] = {"value": {"load_n_m": profile.control.load_torque_n_m,
                                          "final_error_pct": round(end_err, 4),
                                          "min_speed_rpm": round(float(np.min(w[~first])) / RPM, 2)},
                                "limit": "final error <= 1 %", "ok": end_err <= 1.0}
    if end_err > 1.0:
        result.fail(f"after the {profile.control.load_torque_n_m:g} N m load step the speed is {end_err:.3g} % "
                    "off the reference at the end of the simulation")
