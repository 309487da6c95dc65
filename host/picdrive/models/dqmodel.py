"""The nonlinear dq model of a PM brushless motor (2016 paper eq. 5/36, corrected).

State ``x = [omega_m, i_q, i_d]``: **mechanical** rotor speed in rad/s (the
architecture's convention; the paper's ``x1`` is the electrical speed
``omega_e = P omega_m``) and the rotor-frame currents in A
(amplitude-invariant Park transform, phase peak values).

Equations (SI, ``P`` pole pairs, ``lambda_m`` flux linkage in V s per
electrical rad)::

    J  d(omega_m)/dt = 3/2 P (lambda_m i_q + (L_d - L_q) i_d i_q) - B omega_m - T_L - w3
    L_q d(i_q)/dt    = v_q - R i_q - P omega_m L_d i_d - P omega_m lambda_m + 0.1 L_q w2
    L_d d(i_d)/dt    = v_d - R i_d + P omega_m L_q i_q              + 0.1 L_d w1

Corrections to the printed eq. 5 / 36 (see ``docs/design-fuzzy.md``): the
left-hand sides of the current equations are derivatives (the dots were lost
in the text extraction); the i_d equation has ``-R/L_d i_d`` (the printed
``+R/L_d`` makes the winding resistance inject energy; eq. 6 and the TS
matrices A_1, A_2 print ``-R/L_d``); the speed equation's torque term carries
``P`` once for mechanical speed (the printed eq. 5 mixes ``3/2 P/J lambda i_q``,
right for mechanical speed, with ``-P/J T_L``, right for electrical speed);
the reluctance torque is ``(L_d - L_q) i_d i_q`` (eq. 4 prints ``L_q - L_d``;
it vanishes for the paper's L_d = L_q).  The disturbances enter as in eq. 36:
``0.1 w1`` and ``0.1 w2`` in A/s into the current equations, ``w3`` as a load
torque in N m (the paper's ``-P/J w3`` is the same thing in electrical speed).

Six-step drive.  The firmware commands one voltage ``u``: the six-step
DC-equivalent line voltage (bus voltage x duty).  With hall commutation
aligned to the back-EMF the applied voltage vector sits on the q axis
(``v_d = 0``) and power balance over a commutation cycle of a lossless
inverter gives::

    v_q   = k_v u,      k_v = P lambda_m / K_b          (back-EMF match: u = K_b omega_m  <=>  v_q = P lambda_m omega_m)
    i_bus = k_i i_q,    k_i = 3/2 P lambda_m / K_t      (torque match:   K_t i_bus = 3/2 P lambda_m i_q)

so that ``u i_bus = 3/2 v_q i_q`` (the dq electrical power) when ``K_t = K_b``.
For a sinusoidal machine ``K_b = 3 sqrt(3)/pi P lambda_m`` and ``k_v = 0.605``,
``k_i = 0.907``; for a trapezoidal one ``K_b = 2 P lambda_m``, ``k_v = 0.5``,
``k_i = 0.75``.  :func:`six_step_gains` is the one place this mapping lives.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

__all__ = ["DqParams", "dq_params", "derivatives", "jacobian", "torque_n_m", "six_step_gains",
           "equilibrium", "max_speed_rad_s", "electrical_power_w", "stored_energy_j"]

RPM = 2.0 * math.pi / 60.0       # rad/s per rpm


@dataclass(frozen=True)
class DqParams:
    """Per-phase dq parameters (SI) and the six-step mapping of a drive."""

    pole_pairs: int
    r_ohm: float              # per-phase resistance
    ld_h: float
    lq_h: float
    j_kg_m2: float
    b_n_m_s: float            # viscous friction, N m s/rad (mechanical)
    lambda_m_v_s: float       # V s per electrical rad, phase peak
    kv_vq_per_u: float        # v_q per volt of six-step u
    ki_ibus_per_iq: float     # bus amperes per ampere of i_q

    def replace(self, **kw) -> "DqParams":
        d = self.__dict__.copy()
        d.update(kw)
        return DqParams(**d)


def six_step_gains(motor) -> tuple[float, float]:
    """``(k_v, k_i)``: ``v_q = k_v u`` and ``i_bus = k_i i_q`` for a profile's motor (see module doc)."""
    pl = motor.pole_pairs * motor.lambda_m_v_s
    return pl / motor.kb_v_s_per_rad, 1.5 * pl / motor.kt_n_m_per_a


def dq_params(profile) -> DqParams:
    """The dq parameters of a :class:`picdrive.profile.Profile` (per-phase values)."""
    m = profile.motor
    kv, ki = six_step_gains(m)
    return DqParams(pole_pairs=m.pole_pairs, r_ohm=m.r_phase_ohm, ld_h=m.ld_phase_h, lq_h=m.lq_phase_h,
                    j_kg_m2=m.inertia_kg_m2, b_n_m_s=m.viscous_friction_n_m_s, lambda_m_v_s=m.lambda_m_v_s,
                    kv_vq_per_u=kv, ki_ibus_per_iq=ki)


def torque_n_m(p: DqParams, iq, id_=0.0):
    """Electromagnetic torque, N m."""
    return 1.5 * p.pole_pairs * (p.lambda_m_v_s * iq + (p.ld_h - p.lq_h) * id_ * iq)


def derivatives(p: DqParams, x, vq, vd=0.0, load_n_m=0.0, w=(0.0, 0.0, 0.0)) -> np.ndarray:
    """dx/dt of ``x = [omega_m, i_q, i_d]`` for voltages ``v_q, v_d`` (V), load torque (N m)
    and the 2016 disturbances ``w = (w1, w2, w3)``."""
    om, iq, id_ = x
    pw = p.pole_pairs * om
    return np.array([
        (torque_n_m(p, iq, id_) - p.b_n_m_s * om - load_n_m - w[2]) / p.j_kg_m2,
        (vq - p.r_ohm * iq - pw * p.ld_h * id_ - pw * p.lambda_m_v_s) / p.lq_h + 0.1 * w[1],
        (vd - p.r_ohm * id_ + pw * p.lq_h * iq) / p.ld_h + 0.1 * w[0],
    ])


def jacobian(p: DqParams, x) -> tuple[np.ndarray, np.ndarray]:
    """Linearisation at ``x``: ``(A, B)`` with inputs ``[v_q, v_d]``."""
    om, iq, id_ = x
    P, L_d, L_q = p.pole_pairs, p.ld_h, p.lq_h
    A = np.array([
        [-p.b_n_m_s / p.j_kg_m2, 1.5 * P * (p.lambda_m_v_s + (L_d - L_q) * id_) / p.j_kg_m2,
         1.5 * P * (L_d - L_q) * iq / p.j_kg_m2],
        [-(P * L_d * id_ + P * p.lambda_m_v_s) / L_q, -p.r_ohm / L_q, -P * om * L_d / L_q],
        [P * L_q * iq / L_d, P * om * L_q / L_d, -p.r_ohm / L_d],
    ])
    B = np.array([[0.0, 0.0], [1.0 / L_q, 0.0], [0.0, 1.0 / L_d]])
    return A, B


def equilibrium(p: DqParams, omega_m: float, load_n_m: float = 0.0, vd: float = 0.0):
    """Steady state at a mechanical speed: ``(i_q, i_d, v_q)``.

    ``v_d`` is held (0 for the six-step drive); ``i_q`` carries friction and
    load.  Solved exactly (torque is linear in i_q for fixed i_d; iterate the
    salient term to convergence, exact in one pass for L_d = L_q).
    """
    P = p.pole_pairs
    pw = P * omega_m
    id_ = 0.0
    for _ in range(50):
        iq = (p.b_n_m_s * omega_m + load_n_m) / (1.5 * P * (p.lambda_m_v_s + (p.ld_h - p.lq_h) * id_))
        id_new = (vd + pw * p.lq_h * iq) / p.r_ohm
        if abs(id_new - id_) <= 1e-12 * (1 + abs(id_new)):
            id_ = id_new
            break
        id_ = id_new
    iq = (p.b_n_m_s * omega_m + load_n_m) / (1.5 * P * (p.lambda_m_v_s + (p.ld_h - p.lq_h) * id_))
    vq = p.r_ohm * iq + pw * p.ld_h * id_ + pw * p.lambda_m_v_s
    return iq, id_, vq


def max_speed_rad_s(p: DqParams, vq_max: float, load_n_m: float = 0.0) -> float:
    """Highest steady mechanical speed with ``v_d = 0`` and ``v_q <= vq_max``, rad/s (0 if none)."""
    f = lambda w: equilibrium(p, w, load_n_m)[2] - vq_max
    if f(0.0) >= 0:
        return 0.0
    hi = 1.0
    while f(hi) < 0:
        hi *= 2.0
        if hi > 1e7:
            return math.inf
    return brentq(f, 0.0, hi, xtol=1e-9)


def electrical_power_w(p: DqParams, x, vq, vd=0.0) -> float:
    """Power into the motor terminals, W (amplitude-invariant dq: 3/2 (v_q i_q + v_d i_d))."""
    return 1.5 * (vq * x[1] + vd * x[2])


def stored_energy_j(p: DqParams, x) -> float:
    """Kinetic plus magnetic energy, J (``J w^2/2 + 3/4 (L_q i_q^2 + L_d i_d^2)``)."""
    return 0.5 * p.j_kg_m2 * x[0] ** 2 + 0.75 * (p.lq_h * x[1] ** 2 + p.ld_h * x[2] ** 2)
