"""The averaged six-step model (:mod:`picdrive.models.averaged`) against the three-phase plant, open loop.

:func:`check_point` runs the motor twin's three-phase plant (a factory passed in,
``picdrive.gate.three_phase_plant``) free-running through the hall table at the
voltage the averaged model says holds a speed under a load, then steps that
voltage by ``du_frac`` (down: the bridge needs no headroom for it) and
compares, with the DC equivalent's prediction beside:

* steady speed (rpm) and mean sensed current (A), means over whole sectors;
* the small-signal gain ``d w / d u`` (rpm/V) between the two steady states (the model's too);
* the 63 % time of the step (s) on the speed averaged over one sector at the
  point (centred moving mean): the model's response is smoothed by the same
  window, so the two times are read alike.
"""
from __future__ import annotations

import math

import numpy as np

from ..models.averaged import AveragedModel, open_loop_run
from ..models.tfmodel import motor_ss
from .steptest import RPM, sector_mean, sector_period_s

__all__ = ["check_point", "dc_prediction"]


def _t63(t: np.ndarray, y: np.ndarray, y0: float, y1: float) -> float:
    target = y0 + 0.632 * (y1 - y0)
    hit = np.nonzero((y - target) * np.sign(y1 - y0) >= 0.0)[0]
    return float(t[hit[0]]) if hit.size else math.inf


def _model_t63(profile, A, B, dt: float, n: int, rpm: float, h: float) -> float:
    import scipy.linalg as sla
    k = A.shape[0]
    M = sla.expm(np.block([[A, B.reshape(k, 1)], [np.zeros((1, k + 1))]]) * h)
    F, G = M[:k, :k], M[:k, k]
    x = np.zeros(k)
    y = np.empty(n)
    for j in range(n):
        x = F @ x + G
        y[j] = x[0]
    t = (np.arange(n) + 1) * h
    sm = sector_mean(profile, np.concatenate([np.zeros(n), y]), h, rpm, breaks=())[n:]
    return _t63(t, sm, 0.0, float(-np.linalg.solve(A, B).reshape(-1)[0]))


def dc_prediction(profile, u_v: float, load_n_m: float) -> dict:
    """DC equivalent (2008 eq 1): steady speed (rad/s), current (A), gain (rad/s per V), state matrices."""
    m = profile.motor
    kt, kb, r, b = m.kt_n_m_per_a, m.kb_v_s_per_rad, m.r_line_ohm, m.viscous_friction_n_m_s
    w = max(0.0, (kt * u_v / r - load_n_m) / (b + kt * kb / r))
    Am, Bm = motor_ss(profile)                           # states [i, w]
    A = np.array([[Am[1, 1], Am[1, 0]], [Am[0, 1], Am[0, 0]]])
    B = np.array([[0.0], [Bm[0, 0]]])
    return {"w": w, "i": (u_v - kb * w) / r, "gain": kt / r / (b + kt * kb / r), "A": A, "B": B}


def check_point(profile, model: AveragedModel, plant_factory, rpm: float, load_n_m: float, *,
                du_frac: float = 0.05) -> dict:
    """Model and DC equivalent against the plant at ``rpm`` under ``load_n_m`` (see module docstring).

    Returns ``{"rpm", "load", "u", "twin": {...}, "model": {...}, "dc": {...}}`` with ``w_rpm``,
    ``i_a``, ``gain_rpm_per_v``, ``t63_s`` in each."""
    w_t = rpm * RPM
    u0, _ = model.equilibrium(w_t, load_n_m)
    if u0 > model.u_bridge_v:
        raise ValueError(f"{rpm:g} rpm under {load_n_m:g} N m needs {u0:.3g} V > the bridge's {model.u_bridge_v:.3g} V")
    du = -du_frac * u0
    u1 = u0 + du
    m = profile.motor
    sector = sector_period_s(profile, rpm)
    tau = m.inertia_kg_m2 * model.r_e(w_t) / (model.kt(w_t) * model.e(w_t) / w_t)
    t_set = max(10 * tau, 4 * sector, 0.05)
    t_meas = sector * max(4, math.ceil(0.02 / sector))
    t_step = t_set + t_meas
    run = open_loop_run(profile, plant_factory(profile, 1.0), lambda t: u0 if t < t_step else u1,
                        2 * t_step, load_n_m, w0_rad_s=w_t)
    t, w, i = run["t"], run["w"], run["i"]
    h = float(t[1] - t[0])

    def means(t1):
        sel = (t > t1 - t_meas) & (t <= t1)
        return float(np.mean(w[sel])), float(np.mean(i[sel]))
    w0, i0 = means(t_step)
    w1, _ = means(2 * t_step)
    after = t > t_step
    ks = int(np.count_nonzero(~after))
    sm = sector_mean(profile, w, h, rpm, breaks=())
    twin_t63 = _t63(t[after] - t_step, sm[after], w0, w1)
    n = int(np.count_nonzero(after))
    A, B = model.linearise(w_t, load_n_m)
    dc = dc_prediction(profile, u0, load_n_m)
    # the gain as the twin's is read: between the steady states at u0 and u0 + du (a -5 % step reaches deep
    # into the knee of discontinuous conduction, where the slope at u0 alone would not describe it)
    g_model = (model.steady_speed(u1, load_n_m) - model.steady_speed(u0, load_n_m)) / du
    return {"rpm": rpm, "load": load_n_m, "u": u0, "du": du,
            "twin": {"w_rpm": w0 / RPM, "i_a": i0, "gain_rpm_per_v": (w1 - w0) / du / RPM, "t63_s": twin_t63},
            "model": {"w_rpm": rpm, "i_a": model.current(u0, w_t), "gain_rpm_per_v": g_model / RPM,
                      "t63_s": _model_t63(profile, A, B, h, n, rpm, h)},
            "dc": {"w_rpm": dc["w"] / RPM, "i_a": dc["i"], "gain_rpm_per_v": dc["gain"] / RPM,
                   "t63_s": _model_t63(profile, dc["A"], dc["B"], h, n, rpm, h)},
            "_steps": ks}
