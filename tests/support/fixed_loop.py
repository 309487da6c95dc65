"""The fixed-point speed loop against the float law in closed loop, on the six-step DC equivalent.

:func:`closed_loop_compare` runs the firmware's arithmetic (:mod:`picdrive.firmware.fixedpoint`'s
bit-exact model) and :func:`picdrive.control_law.law_step` on the same plant
(:func:`picdrive.models.tfmodel.motor_ss`, the one copy of 2008 eq 1);
:func:`measurement_lag_effect` the float law alone with two speed measurements.  Used by
tests/test_fixedpoint.py (the 0.5 % limit) and bench/firmware.py (the figures).  A check of the
firmware against the design, used by no command: it lives with the test harnesses
(docs/architecture.md, "The house"); the firmware layer may not import the models.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.linalg import expm

from picdrive.board import FCY_HZ
from picdrive.control_law import LawState, law_step as float_step
from picdrive.firmware.fixedpoint import (INT16_MAX, CoreState, FixedPointPlan, core_control, core_reset,
                                          law_params_from_plan, sat16, speed_encoder)
from picdrive.models.tfmodel import motor_ss

__all__ = ["dc_plant_discrete", "closed_loop_compare", "measurement_lag_effect"]


def dc_plant_discrete(profile, ts: float):
    """The six-step DC equivalent (:func:`picdrive.models.tfmodel.motor_ss`, 2008 eq 1) with the
    angle as a third state, discretised with a zero-order hold of ``ts`` s.

    States [line current A, speed rad/s, angle rad], inputs [voltage V, load torque N m];
    returns ``(Ad, Bd)``, (3, 3) and (3, 2).
    """
    A, B = motor_ss(profile)
    M = np.zeros((5, 5))
    M[:2, :2], M[:2, 3:] = A, B
    M[2, 1] = 1.0                                     # angle' = speed
    E = expm(M * ts)
    return E[:3, :3], E[:3, 3:]


def closed_loop_compare(profile, law, plan: FixedPointPlan, *, t_end_s: float = 1.0,
                        setpoint_rpm: float | None = None, load_step_s: float | None = None,
                        load_n_m: float | None = None, measurement: str = "firmware",
                        float_measurement: str | None = None) -> dict:
    """Simulate the speed loop twice on the six-step DC-equivalent plant (2008 eq 1).

    Float: :func:`picdrive.control_law.law_step` on the true current, its
    output applied as is.  Fixed: :func:`core_control` (the firmware's
    arithmetic) on the bus current through the 10-bit ADC, its output applied
    as whole PDC counts of the bus voltage; the current limits are disabled
    (the float reference has none).  Plant: ``L di/dt = v - R i - Kb w``,
    ``J dw/dt = Kt i - B w - T_load``, exact zero-order-hold discretisation.

    Speed seen by the loops (``measurement``; the float loop sees the exact
    version of the same measurement unless ``float_measurement`` says
    otherwise):

    * ``"firmware"``: what the firmware measures -- speed: encoder by the M/T
      method on whole counts and Timer5 ticks, extrapolated half a sample
      (the angle history between samples is interpolated linearly), halls:
      the speed quantised to Q qs; current:
      the bus shunt, which sees the line current only in the applied
      direction (0 when it reverses).  The float loop gets the true speed at
      the sample and the exact shunt current.
    * ``"instant"``: the speed at the sample instant (fixed: quantised to Q qs).
    * ``"average"``: the exact average over the previous sample, for both.

    Returns the time vector, both speeds (rad/s), and the RMS and largest
    speed deviation as fractions of the setpoint.
    """
    if measurement not in ("firmware", "instant", "average"):
        raise ValueError(f"measurement {measurement!r}")
    fmeas = float_measurement or ("average" if measurement == "average" else "instant")
    ts = law.sample_time_s
    Ad, Bd = dc_plant_discrete(profile, ts)
    sp_rpm = profile.speed_step_rpm() if setpoint_rpm is None else setpoint_rpm
    w_ref = sp_rpm * 2 * math.pi / 60
    t_load = profile.control.load_torque_n_m if load_n_m is None else load_n_m
    t_step = 0.5 * t_end_s if load_step_s is None else load_step_s
    n = int(round(t_end_s / ts))
    t = np.arange(n) * ts
    xf = np.zeros(3)
    xq = np.zeros(3)
    thf_prev = thq_prev = 0.0
    dir_f = 1.0
    wf, wq = np.zeros(n), np.zeros(n)
    stf = LawState()
    p = law_params_from_plan(plan)
    if law.current_limit_a is None:    # the float reference has no window: disable the firmware's
        p.ilim = INT16_MAX
    st = CoreState()
    core_reset(plan, st)
    target = plan.to_speed_raw(w_ref)
    vbus = profile.inverter.bus_voltage_v
    cpr = plan.counts_per_rev
    tick_s = plan.ps5 / FCY_HZ
    enc = measurement == "firmware" and plan.speed_source == "encoder"
    hist = [(0.0, 0.0)]                     # (t, theta) at past samples, for the edge times
    for k in range(n):
        tl = t_load if t[k] >= t_step else 0.0
        wf[k], wq[k] = xf[1], xq[1]
        # float loop
        yf = xf[1] if fmeas == "instant" else (xf[2] - thf_prev) / ts
        thf_prev = xf[2]
        if measurement == "firmware":          # the bus shunt: current of the applied direction only
            i_f = max(0.0, xf[0] * dir_f) * dir_f
        else:
            i_f = xf[0]
        uf = float_step(law, stf, w_ref, yf, i_f)
        if uf != 0.0:
            dir_f = -1.0 if uf < 0 else 1.0
        # fixed loop: what the firmware measures
        w, th = xq[1], xq[2]
        t_now = t[k]
        if enc:
            # M/T inputs: the count, and Timer5 ticks since the last count edge (angle history
            # between samples interpolated linearly)
            c = math.floor(th * cpr / (2 * math.pi))
            sgn = 1 if th >= hist[-1][1] else -1
            edge = (c if sgn > 0 else c + 1) * 2 * math.pi / cpr
            t_edge = _time_at(hist, t_now, th, edge)
            ticks = 65536 if t_edge is None else math.floor((t_now - t_edge) / tick_s)
            speed_encoder(plan, st, c & 0xFFFF, min(ticks, 65535), 0, 1 if ticks >= 65536 else 0)  # TMR2 0: sampled on time
        else:
            yq = w if measurement == "instant" else (th - thq_prev) / ts
            st.speed = sat16(math.floor(yq * 2 ** plan.qs))
        thq_prev = th
        hist.append((t_now, th))
        if len(hist) > 4096:
            del hist[:2048]
        i_bus = xq[0] * (-1.0 if st.dir else 1.0)
        adc = min(1023, max(0, math.floor(i_bus * plan.counts_per_a)))
        core_control(plan, p, st, target, adc)
        v = st.pdc / plan.duty_full * vbus * (-1.0 if st.dir else 1.0)
        if st.hold:
            v = 0.0
        xf = Ad @ xf + Bd @ np.array([uf, tl])
        xq = Ad @ xq + Bd @ np.array([v, tl])
    dev = (wq - wf) / w_ref
    return {"t_s": t, "w_float": wf, "w_fixed": wq, "setpoint_rad_s": w_ref,
            "rms_dev": float(np.sqrt(np.mean(dev ** 2))), "max_dev": float(np.max(np.abs(dev)))}


def _time_at(hist, t_now, th_now, target):
    """When did the angle pass ``target`` (linear interpolation over the sample history)?"""
    t1, a1 = t_now, th_now
    for t0, a0 in reversed(hist):
        if (a0 - target) * (a1 - target) <= 0 and a0 != a1:
            return t0 + (target - a0) / (a1 - a0) * (t1 - t0)
        t1, a1 = t0, a0
    return None


def measurement_lag_effect(profile, law, *, t_end_s: float = 1.0) -> dict:
    """Float law only: the speed with an instantaneous measurement against the
    speed with the average over the previous sample (what position-based
    measurement gives).  Not a fixed-point effect: how sensitive the design is
    to the measurement the firmware can make."""
    ts = law.sample_time_s
    Ad, Bd = dc_plant_discrete(profile, ts)
    w_ref = profile.speed_step_rpm() * 2 * math.pi / 60
    n = int(round(t_end_s / ts))
    out = {}
    for meas in ("instant", "average"):
        x, th_prev, st, ws = np.zeros(3), 0.0, LawState(), np.zeros(n)
        for k in range(n):
            tl = profile.control.load_torque_n_m if k * ts >= 0.5 * t_end_s else 0.0
            ws[k] = x[1]
            y = x[1] if meas == "instant" else (x[2] - th_prev) / ts
            th_prev = x[2]
            u = float_step(law, st, w_ref, y, x[0])
            x = Ad @ x + Bd @ np.array([u, tl])
        out[meas] = ws
    dev = (out["average"] - out["instant"]) / w_ref
    return {"rms_dev": float(np.sqrt(np.mean(dev ** 2))), "max_dev": float(np.max(np.abs(dev)))}
