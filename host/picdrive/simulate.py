"""Simulation helpers: the dq motor under the sampled control law.

* :func:`simulate_law` -- the nonlinear dq model (:mod:`picdrive.dqmodel`)
  driven by the firmware's law (:func:`picdrive.control_law.law_step`)
  sampled at ``law.sample_time_s`` with a zero-order hold, through the
  six-step mapping ``v_q = k_v u``, ``v_d = 0``; measured speed = mechanical
  speed, measured current = bus current ``k_i i_q``; load-torque profile and
  the 2016 disturbances; the bridge saturates ``|u|`` at bus voltage x max duty.
* :func:`simulate_state_feedback` -- the same plant under a two-input (v_q,
  v_d) fuzzy state feedback ``u = sum mu_j K_j x`` (+ optional integral
  action), sampled, for designs that have no six-step law.
* :func:`disturbances_2016` -- the paper's w1, w2, w3 (Fig. 6), reconstructed.

The plant is integrated with classical RK4 on ``n_sub`` sub-steps per sample
(default 20: 50 us at 1 kHz, well below the electrical time constants of the
bundled motors, 2.5-3.6 ms, and the electrical rotation period).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .control_law import LawState, law_step
from .dqmodel import DqParams, derivatives, dq_params

__all__ = ["SimResult", "simulate_law", "simulate_state_feedback", "disturbances_2016", "step_load",
           "W_WINDOW_S"]

W_WINDOW_S = 0.2       # the 2016 disturbances act on [0, 0.2] s (Fig. 7: the energy ratio is constant after 0.2 s)


@dataclass
class SimResult:
    t: np.ndarray            # s, sample instants
    omega: np.ndarray        # mechanical rad/s
    iq: np.ndarray
    id: np.ndarray
    u: np.ndarray            # commanded control (six-step u in V, or (n, 2) v_q, v_d)
    ref: np.ndarray          # rad/s
    load: np.ndarray         # N m
    saturated: np.ndarray    # bool per sample
    i_bus: np.ndarray = field(default_factory=lambda: np.zeros(0))
    w: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def rpm(self) -> np.ndarray:
        return self.omega * 60.0 / (2.0 * math.pi)


def disturbances_2016(t, *, amplitude=(1.0, 1.0, 0.1), window_s: float = W_WINDOW_S, seed: int = 2016,
                      hold_s: float = 1e-3) -> np.ndarray:
    """The 2016 paper's disturbance inputs ``w = (w1, w2, w3)`` at times ``t`` (shape (len(t), 3)).

    Fig. 6 is not in the text.  Reconstruction (our assumption, stated in
    docs/design-fuzzy.md): finite-energy signals (Definition 1 needs
    w in L2; Fig. 7's ratio settles after 0.2 s), so each is zero after
    ``window_s``; w1, w2 ("process noise", entering as 0.1 w in A/s into the
    current equations) are uniform white noise in [-1, 1] held for 1 ms;
    w3 ("disturbance from torque load", N m) the same noise scaled by
    ``amplitude[2]`` (callers pass 10 % of the profile's load torque).
    Deterministic for a seed.
    """
    t = np.atleast_1d(np.asarray(t, float))
    n_hold = int(math.ceil(window_s / hold_s)) + 1
    rng = np.random.default_rng(seed)
    table = rng.uniform(-1.0, 1.0, size=(n_hold, 3)) * np.asarray(amplitude, float)
    k = np.clip((t / hold_s).astype(int), 0, n_hold - 1)
    out = table[k]
    out[(t < 0) | (t >= window_s)] = 0.0
    return out


def step_load(t_step: float, torque_n_m: float) -> Callable[[float], float]:
    """A load-torque step at ``t_step``."""
    return lambda t: torque_n_m if t >= t_step else 0.0


def _rk4(f, x, t, h, n):
    for _ in range(n):
        k1 = f(t, x)
        k2 = f(t + h / 2, x + h / 2 * k1)
        k3 = f(t + h / 2, x + h / 2 * k2)
        k4 = f(t + h, x + h * k3)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        t += h
    return x


def _wfun(disturbance):
    if disturbance is None:
        return lambda t: (0.0, 0.0, 0.0)
    if callable(disturbance):
        return disturbance
    raise TypeError("disturbance must be None or a function t -> (w1, w2, w3)")


def simulate_law(profile, law, *, t_end: float, ref_rpm: float | Callable[[float], float],
                 load: float | Callable[[float], float] = 0.0, disturbance=None, params: DqParams | None = None,
                 x0=(0.0, 0.0, 0.0), n_sub: int = 20) -> SimResult:
    """The dq motor (six-step drive) under the sampled law (see module doc)."""
    p = params if params is not None else dq_params(profile)
    ts = law.sample_time_s
    u_bridge = profile.inverter.bus_voltage_v * profile.max_duty()
    rfun = ref_rpm if callable(ref_rpm) else (lambda t, v=float(ref_rpm): v)
    lfun = load if callable(load) else (lambda t, v=float(load): v)
    wfun = _wfun(disturbance)
    n = int(round(t_end / ts)) + 1
    out = {k: np.zeros(n) for k in ("t", "omega", "iq", "id", "u", "ref", "load", "ibus")}
    sat = np.zeros(n, bool)
    ws = np.zeros((n, 3))
    st = LawState()
    x = np.array(x0, float)
    rpm = 2 * math.pi / 60
    for k in range(n):
        t = k * ts
        r = rfun(t) * rpm
        i_bus = p.ki_ibus_per_iq * x[1]
        u = law_step(law, st, r, x[0], i_bus)
        ua = min(max(u, -u_bridge), u_bridge)
        sat[k] = (u >= law.u_max_v - 1e-9) or (u <= law.u_min_v + 1e-9) or ua != u
        vq = p.kv_vq_per_u * ua
        out["t"][k], out["omega"][k], out["iq"][k], out["id"][k] = t, x[0], x[1], x[2]
        out["u"][k], out["ref"][k], out["load"][k], out["ibus"][k] = ua, r, lfun(t), i_bus
        ws[k] = wfun(t)
        f = lambda tt, xx: derivatives(p, xx, vq, 0.0, lfun(tt), wfun(tt))
        x = _rk4(f, x, t, ts / n_sub, n_sub)
        if not np.all(np.isfinite(x)) or abs(x[0]) > 1e7:
            # diverged: fill the rest with the last finite values so metrics still run
            for kk in range(k + 1, n):
                out["t"][kk] = kk * ts
            out["omega"][k + 1:] = np.nan
            break
    return SimResult(t=out["t"], omega=out["omega"], iq=out["iq"], id=out["id"], u=out["u"], ref=out["ref"],
                     load=out["load"], saturated=sat, i_bus=out["ibus"], w=ws)


def simulate_state_feedback(profile, K_rules, premise_rad_s, *, t_end: float, ref_rpm=0.0, load=0.0,
                            disturbance=None, params: DqParams | None = None, integral: bool = False,
                            sample_time_s: float | None = None, v_max: float | None = None,
                            x0=(0.0, 0.0, 0.0), n_sub: int = 20, memberships_of=None) -> SimResult:
    """The dq motor under a two-input fuzzy state feedback, sampled with ZOH.

    Without integral action (the paper's regulator) ``[v_q, v_d] = sum mu_j K_j x``
    (K_j 2x3, the paper's sign: ``u = K x``).  With ``integral=True`` K_j is
    2x4 on ``[omega - r, i_q, i_d, z]``, ``z = int (r - omega)``, plus the
    voltage that holds the reference at no load as feedforward is *not* added
    (the integrator finds it).  ``v_max`` limits ``|(v_q, v_d)|`` (None: no
    limit, as in the paper).
    """
    p = params if params is not None else dq_params(profile)
    ts = sample_time_s if sample_time_s is not None else 1.0 / profile.control.speed_loop_hz
    rfun = ref_rpm if callable(ref_rpm) else (lambda t, v=float(ref_rpm): v)
    lfun = load if callable(load) else (lambda t, v=float(load): v)
    wfun = _wfun(disturbance)
    Ks = [np.asarray(k, float) for k in K_rules]
    from types import SimpleNamespace
    from .control_law import memberships
    lawlike = SimpleNamespace(n_rules=len(Ks), premise_rad_s=tuple(premise_rad_s))
    n = int(round(t_end / ts)) + 1
    T = np.zeros(n); Om = np.zeros(n); Iq = np.zeros(n); Id = np.zeros(n); U = np.zeros((n, 2)); R = np.zeros(n)
    Ld = np.zeros(n); sat = np.zeros(n, bool); ws = np.zeros((n, 3))
    x = np.array(x0, float)
    z = 0.0
    rpm = 2 * math.pi / 60
    for k in range(n):
        t = k * ts
        r = rfun(t) * rpm
        mu = memberships(lawlike, x[0])
        Kb = sum(m_ * K for m_, K in zip(mu, Ks))
        if integral:
            v = Kb @ np.array([x[0] - r, x[1], x[2], z])
        else:
            v = Kb @ x
        mag = float(np.hypot(v[0], v[1]))
        if v_max is not None and mag > v_max:
            v = v * (v_max / mag)
            sat[k] = True
        T[k], Om[k], Iq[k], Id[k], U[k], R[k], Ld[k] = t, x[0], x[1], x[2], v, r, lfun(t)
        ws[k] = wfun(t)
        f = lambda tt, xx: derivatives(p, xx, v[0], v[1], lfun(tt), wfun(tt))
        x = _rk4(f, x, t, ts / n_sub, n_sub)
        z += ts * (r - Om[k])
        if not np.all(np.isfinite(x)) or abs(x[0]) > 1e9:
            T[k + 1:] = np.arange(k + 1, n) * ts
            Om[k + 1:] = np.nan
            break
    return SimResult(t=T, omega=Om, iq=Iq, id=Id, u=U, ref=R, load=Ld, saturated=sat,
                     i_bus=p.ki_ibus_per_iq * Iq, w=ws)
