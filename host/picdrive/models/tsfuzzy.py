"""Takagi-Sugeno fuzzy models of the dq motor (2016 paper, section 4 and eq. 36).

A TS model with ``r`` rules over the premise ``x1 = omega_m`` (mechanical
rad/s) in ``[N1, N2]``::

    dx/dt = sum_i mu_i(omega) [(A_i + dA_v + F H1_i) x + (B_i + F H2_i) u + Bw w]
    z     = sum_i mu_i(omega) [(C_i + F H3_i) x + (D_i + F H4_i) u],      ||F|| <= rho

``mu_i`` are the triangular memberships of :func:`picdrive.control_law.memberships`
(the same function the firmware's law uses; ``r = 2`` gives the paper's
``M1 = (N2 - x1)/(N2 - N1)``, ``M2 = (x1 - N1)/(N2 - N1)``).  Rule i's
matrices are the model at the rule centre ``c_i``.  ``dA_v`` (optional) are
the vertices of an *unscheduled* polytope (e.g. the equilibrium currents of a
tracking model); the controller does not know v, so a design must hold for
all of them.  ``H1`` realises Assumption 1 (the paper's R +-10 %).

Because the only nonlinearity of the dq model (L_d = L_q) is ``omega * i``,
which is linear in ``omega`` for fixed currents, the TS model with linear
memberships is *exact* on ``[N1, N2]`` (sector nonlinearity), not an
approximation: ``A(omega) = sum_i mu_i(omega) A_i``.  For a salient machine
(L_d != L_q) the reluctance torque ``(L_d - L_q) i_d i_q`` is not in the TS
model (it is zero at the linearisation point ``i = 0``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from types import SimpleNamespace

import numpy as np

from ..control_law import memberships
from .dqmodel import DqParams, dq_params, equilibrium, jacobian, max_speed_rad_s
from .tfmodel import motor_ss

__all__ = ["TSModel", "mechanical_corner_rad_s", "rule_centres", "paper_model", "tracking_model", "six_step_model",
           "operating_region", "emf_range", "model_for", "paper_as_printed_model", "PAPER_TABLE1", "PAPER_PREMISE_RAD_S"]


@dataclass(frozen=True)
class TSModel:
    """A TS fuzzy model with norm-bounded uncertainty (Assumption 1)."""

    A: np.ndarray                    # (r, n, n)
    B: np.ndarray                    # (r, n, m)
    Bw: np.ndarray                   # (n, p)
    C: np.ndarray                    # (r, s, n)
    D: np.ndarray                    # (r, s, m)
    H1: np.ndarray                   # (r, q, n)  dA = F H1
    H2: np.ndarray                   # (r, q, m)  dB = F H2
    H3: np.ndarray                   # (r, q3, n) dC = F H3
    H4: np.ndarray                   # (r, q3, m) dD = F H4
    rho: float
    premise_rad_s: tuple[float, float]
    dA: np.ndarray | None = None     # (nv, n, n) unscheduled polytope offsets (None: one vertex, 0)
    E: np.ndarray | None = None      # (n, k) uncertainty input: dA = E F H1 (None: identity, the paper's dA = F H1)
    state_names: tuple[str, ...] = ()
    input_names: tuple[str, ...] = ()
    disturbance_names: tuple[str, ...] = ()
    output_names: tuple[str, ...] = ()
    info: dict = field(default_factory=dict, compare=False)

    @property
    def r(self) -> int:
        return self.A.shape[0]

    @property
    def n(self) -> int:
        return self.A.shape[1]

    @property
    def m(self) -> int:
        return self.B.shape[2]

    @property
    def E_matrix(self) -> np.ndarray:
        return np.eye(self.n) if self.E is None else self.E

    @property
    def offsets(self) -> np.ndarray:
        return np.zeros((1, self.n, self.n)) if self.dA is None else self.dA

    def mu(self, speed_rad_s: float) -> np.ndarray:
        """Memberships at a speed: exactly :func:`picdrive.control_law.memberships`."""
        return memberships(SimpleNamespace(n_rules=self.r, premise_rad_s=self.premise_rad_s), speed_rad_s)

    def blended(self, speed_rad_s: float, vertex: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """``(A(mu), B(mu))`` at a speed (polytope vertex ``vertex``)."""
        mu = self.mu(speed_rad_s)
        return (np.tensordot(mu, self.A, 1) + self.offsets[vertex], np.tensordot(mu, self.B, 1))

    def with_(self, **kw) -> "TSModel":
        return replace(self, **kw)


def mechanical_corner_rad_s(motor) -> float:
    """The motor's open-loop mechanical corner ``(B + Kt Kb / R_line) / J``, rad/s: the inverse of
    its mechanical time constant with the winding's back-EMF damping."""
    m = motor
    return (m.viscous_friction_n_m_s + m.kt_n_m_per_a * m.kb_v_s_per_rad / m.r_line_ohm) / m.inertia_kg_m2


def rule_centres(premise_rad_s, r: int) -> np.ndarray:
    """Centres ``c_j = N1 + j (N2 - N1)/(r - 1)`` of the triangular memberships, rad/s."""
    n1, n2 = premise_rad_s
    return np.array([0.5 * (n1 + n2)]) if r == 1 else np.linspace(n1, n2, r)


def _params(profile_or_params) -> DqParams:
    return profile_or_params if isinstance(profile_or_params, DqParams) else dq_params(profile_or_params)


def _premise(profile, premise_rad_s):
    if premise_rad_s is not None:
        return tuple(float(v) for v in premise_rad_s)
    lo, hi = profile.design["premise_rpm"]
    return (lo * 2 * math.pi / 60, hi * 2 * math.pi / 60)


def _state_scale(profile, p: DqParams, prem) -> np.ndarray:
    """Typical magnitudes of ``[omega_m, i_q, i_d]`` (for the LMI's numerical scaling only)."""
    i_s = profile.inverter.current_limit_a if not isinstance(profile, DqParams) else 10.0
    return np.array([max(prem[1], 1.0), i_s, i_s])


def _input_scale(profile, m: int) -> np.ndarray:
    v = profile.inverter.bus_voltage_v if not isinstance(profile, DqParams) else 48.0
    return np.full(m, v)


def paper_model(profile, *, rules: int | None = None, premise_rad_s=None,
                resistance_uncertainty: float | None = None, rho: float | None = None) -> TSModel:
    """The 2016 paper's TS model (eq. 36, section 6) on the corrected dq model.

    States ``[omega_m, i_q, i_d]``, inputs ``[v_q, v_d]``, disturbances
    ``[w1, w2, w3]`` (``Bw`` of the paper, with ``-1/J`` for the mechanical
    speed), output ``z = omega_m``; ``H1 = diag(0, -eps R/L_q, -eps R/L_d)``
    with ``eps`` the relative R uncertainty; ``H2 = H3 = H4 = 0``.
    Rule i is the linearisation at ``(omega = c_i, i_q = i_d = 0)``.
    """
    p = _params(profile)
    d = profile.design if not isinstance(profile, DqParams) else {}
    r = int(rules if rules is not None else d.get("rules", 2))
    prem = _premise(profile, premise_rad_s)
    eps = resistance_uncertainty if resistance_uncertainty is not None else d.get("resistance_uncertainty", 0.1)
    rho = rho if rho is not None else d.get("rho", 1.0)
    cs = rule_centres(prem, r)
    A = np.stack([jacobian(p, (c, 0.0, 0.0))[0] for c in cs])
    B1 = jacobian(p, (0.0, 0.0, 0.0))[1]
    B = np.repeat(B1[None], r, 0)
    Bw = np.array([[0.0, 0.0, -1.0 / p.j_kg_m2], [0.0, 0.1, 0.0], [0.1, 0.0, 0.0]])
    C = np.repeat(np.array([[1.0, 0.0, 0.0]])[None], r, 0)
    D = np.zeros((r, 1, 2))
    H1 = np.repeat(np.diag([0.0, -eps * p.r_ohm / p.lq_h, -eps * p.r_ohm / p.ld_h])[None], r, 0)
    return TSModel(A=A, B=B, Bw=Bw, C=C, D=D, H1=H1, H2=np.zeros((r, 3, 2)), H3=np.zeros((r, 1, 3)),
                   H4=np.zeros((r, 1, 2)), rho=float(rho), premise_rad_s=prem,
                   state_names=("omega_m", "i_q", "i_d"), input_names=("v_q", "v_d"),
                   disturbance_names=("w1", "w2", "w3"), output_names=("omega_m",),
                   info={"rule_centres_rad_s": cs, "resistance_uncertainty": eps,
                         "state_scale": _state_scale(profile, p, prem), "input_scale": _input_scale(profile, 2)})


def operating_region(profile, premise_rad_s=None) -> dict:
    """Equilibria a speed controller must hold: speeds up to the step target
    (``profile.speed_step_rpm()``, the six-step DC equivalent's reach, which the
    twin confirms) within the premise range, loads 0..``control.load_torque_n_m``.

    Returns the top speed, the box of the dq model's equilibrium currents there
    (v_d = 0; they exist whatever voltage they need) and the speed the dq model
    holds at the bridge voltage (``omega_hold_rad_s``: for a sinusoidal motor its
    steady-state reach, for a trapezoidal one far below what the six-step bridge
    holds, see docs/design-fuzzy.md).
    """
    p = _params(profile)
    prem = _premise(profile, premise_rad_s)
    u_max = profile.inverter.bus_voltage_v * profile.max_duty()
    load = profile.control.load_torque_n_m
    w_hold = max_speed_rad_s(p, p.kv_vq_per_u * u_max, load)
    w_top = min(prem[1], profile.speed_step_rpm() * 2 * math.pi / 60)
    iq_hi, id_hi, vq_hi = equilibrium(p, w_top, load)
    return {"u_max_v": u_max, "load_n_m": load, "omega_hold_rad_s": w_hold, "omega_top_rad_s": w_top,
            "iq_max_a": iq_hi, "id_max_a": id_hi, "u_top_v": vq_hi / p.kv_vq_per_u}


def tracking_model(profile, *, inputs: str = "six-step", rules: int | None = None, premise_rad_s=None,
                   resistance_uncertainty: float | None = None, rho: float | None = None,
                   integral_weight_rad_s: float | None = None) -> TSModel:
    """Deviation model about an equilibrium with integral action on the speed error.

    States ``[d_omega, d_i_q, d_i_d, d_z]`` with ``z = int (r - omega_m) dt``
    (rad), so ``d_z' = -d_omega``.  Exact for L_d = L_q:
    ``omega i - omega* i* = omega d_i + i* d_omega``; the scheduled part
    ``omega d_i`` is the rule matrices, the unscheduled part ``i* d_omega``
    (equilibrium currents in the :func:`operating_region` box) is the polytope
    ``dA`` (4 vertices).  ``inputs``: ``"six-step"`` (one input u, the six-step
    DC-equivalent voltage, ``v_q = k_v u``, ``v_d = 0``) or ``"dq"`` (``v_q, v_d``).
    Output ``z = [d_omega, w_i d_z]`` (``w_i``: integral weight, rad/s).
    """
    base = paper_model(profile, rules=rules, premise_rad_s=premise_rad_s,
                       resistance_uncertainty=resistance_uncertainty, rho=rho)
    p = _params(profile)
    r, n = base.r, 4
    A = np.zeros((r, n, n))
    A[:, :3, :3] = base.A
    A[:, 3, 0] = -1.0
    if inputs == "six-step":
        B = np.zeros((r, n, 1))
        B[:, 1, 0] = p.kv_vq_per_u / p.lq_h
        input_names = ("u",)
    elif inputs == "dq":
        B = np.zeros((r, n, 2))
        B[:, :3, :] = base.B
        input_names = ("v_q", "v_d")
    else:
        raise ValueError(f"inputs must be 'six-step' or 'dq', not {inputs!r}")
    m = B.shape[2]
    Bw = np.vstack([base.Bw, np.zeros((1, 3))])
    reg = operating_region(profile, base.premise_rad_s)
    if integral_weight_rad_s is None:
        # integral weight: the open-loop mechanical corner (B + K_t K_b / R_line)/J, so that
        # the integral of the speed error is weighed on the motor's own time scale
        integral_weight_rad_s = 0.2 * mechanical_corner_rad_s(profile.motor)
    wi = float(integral_weight_rad_s)
    C = np.zeros((r, 2, n))
    C[:, 0, 0] = 1.0
    C[:, 1, 3] = wi
    D = np.zeros((r, 2, m))
    # R uncertainty enters the two current equations only: dA = E F H1 with E = [e_iq, e_id]
    # (the paper's dA = F H1 with a full 3x3 F also lets it leak into the speed equation,
    # which makes Theorem 1 needlessly conservative; see docs/design-fuzzy.md)
    E = np.zeros((n, 2))
    E[1, 0] = E[2, 1] = 1.0
    H1 = np.zeros((r, 2, n))
    H1[:, :, :3] = base.H1[:, 1:3, :]
    offs = []
    A0 = jacobian(p, (0.0, 0.0, 0.0))[0]
    for iq in (0.0, reg["iq_max_a"]):
        for id_ in (0.0, reg["id_max_a"]):
            d4 = np.zeros((n, n))
            d4[:3, :3] = jacobian(p, (0.0, iq, id_))[0] - A0
            offs.append(d4)
    return TSModel(A=A, B=B, Bw=Bw, C=C, D=D, H1=H1, H2=np.zeros((r, 2, m)), H3=np.zeros((r, 1, n)),
                   H4=np.zeros((r, 1, m)), rho=base.rho, premise_rad_s=base.premise_rad_s, dA=np.stack(offs), E=E,
                   state_names=("d_omega_m", "d_i_q", "d_i_d", "d_z"), input_names=input_names,
                   disturbance_names=base.disturbance_names, output_names=("d_omega_m", "w_i d_z"),
                   info={**base.info, "operating_region": reg, "integral_weight_rad_s": wi, "inputs": inputs,
                         "state_scale": np.append(base.info["state_scale"], base.info["state_scale"][0] / wi),
                         "input_scale": base.info["input_scale"][:m]})


def emf_range(profile) -> tuple[float, float]:
    """Smallest and largest back-EMF constant of the phase pair the forward hall table drives,
    over a turn (V per mechanical rad/s; :func:`picdrive.models.simulate.commutated_emf`)."""
    from .simulate import commutated_emf
    k, _ = commutated_emf(profile)
    k = k[k > 0]
    return float(np.min(k)), float(np.max(k))


def six_step_model(profile, *, rules: int | None = None, premise_rad_s=None,
                   resistance_uncertainty: float | None = None, rho: float | None = None,
                   integral_weight_rad_s: float | None = None, emf_polytope: bool = True,
                   averaged=None) -> TSModel:
    """Tracking model of the six-step drive: the DC equivalent (2008 eq 1) with integral action.

    States ``[d_omega, d_i, d_z]`` (mechanical rad/s, line current A, ``z = int (r - omega) dt``
    in rad), input ``u`` (the six-step DC-equivalent voltage, V)::

        J d_omega' = k_e d_i - B d_omega - w3
        L d_i'     = u - R d_i - k_e d_omega + 0.1 L w2
        d_z'       = -d_omega

    The measurements the firmware has are the speed and the bus current, which
    is this line current, so every state but ``z`` (which the law integrates)
    is measured.  ``k_e`` is the back-EMF (= torque) constant of the phase pair
    the hall table drives: it moves with the rotor angle inside each sector
    between the bounds of :func:`emf_range` (the controller does not know the
    angle), so with ``emf_polytope`` the model is the 2-vertex polytope over
    ``k_e`` (``dA``); without it ``k_e = Kb``.  The DC equivalent is linear, so
    the r rules (centres of the law's memberships) share their matrices; the
    certificate then holds for every blend of the rule gains.  R uncertainty
    as Assumption 1 on the current equation (``dA = E F H1``,
    ``H1 = -eps R/L`` on ``d_i``).  Output ``z = [d_omega, w_i d_z]``.

    ``averaged``: a speed-dependent averaged model (:class:`picdrive.models.averaged.AveragedModel`)
    instead of the DC equivalent: rule j's ``(A_j, B_j)`` is its linearisation at the rule centre
    ``c_j`` under the profile's load (effective resistance ``R_e(c_j)``, counter-voltage slope,
    torque per ampere ``k_t(c_j)`` and their speed derivatives), so the rules differ and Theorem 1
    returns distinct ``K_j``; ``H1_j = -eps R_e(c_j)/L``.  The EMF polytope is kept (the ripple
    inside a sector is what the law sees between samples).
    """
    m = profile.motor
    d = profile.design
    r = int(rules if rules is not None else d.get("rules", 2))
    prem = _premise(profile, premise_rad_s)
    eps = resistance_uncertainty if resistance_uncertainty is not None else d.get("resistance_uncertainty", 0.1)
    rho = rho if rho is not None else d.get("rho", 1.0)
    R, L, J, B, kb = m.r_line_ohm, m.l_line_h, m.inertia_kg_m2, m.viscous_friction_n_m_s, m.kb_v_s_per_rad
    n = 3
    Am, Bs = motor_ss(profile)                 # the DC equivalent in [i, w]; here the states are [w, i, z]
    A0 = np.array([[Am[1, 1], Am[1, 0], 0.0], [Am[0, 1], Am[0, 0], 0.0], [-1.0, 0.0, 0.0]])
    A = np.repeat(A0[None], r, 0)
    Bm = np.repeat(np.array([[0.0], [Bs[0, 0]], [0.0]])[None], r, 0)
    cs = rule_centres(prem, r)
    r_rule = np.full(r, R)
    if averaged is not None:
        for j, c in enumerate(cs):
            Aa, Ba = averaged.linearise(float(c), profile.control.load_torque_n_m)
            A[j, :2, :2] = Aa
            Bm[j, :2, :] = Ba
            r_rule[j] = averaged.r_e(float(c))
    Bw = np.array([[0.0, 0.0, Bs[1, 1]], [0.0, 0.1, 0.0], [0.0, 0.0, 0.0]])
    if integral_weight_rad_s is None:
        integral_weight_rad_s = 0.2 * (B + m.kt_n_m_per_a * kb / R) / J
    wi = float(integral_weight_rad_s)
    C = np.zeros((r, 2, n))
    C[:, 0, 0] = 1.0
    C[:, 1, 2] = wi
    D = np.zeros((r, 2, 1))
    E = np.array([[0.0], [1.0], [0.0]])
    H1 = np.zeros((r, 1, n))
    H1[:, 0, 1] = -eps * r_rule / L
    k_lo, k_hi = emf_range(profile)
    offs = None
    if emf_polytope:
        G = np.array([[0.0, 1.0 / J, 0.0], [-1.0 / L, 0.0, 0.0], [0.0, 0.0, 0.0]])
        offs = np.stack([(k - kb) * G for k in (k_lo, k_hi)])
    w_top = min(prem[1], profile.speed_step_rpm() * 2 * math.pi / 60)
    i_s = profile.inverter.current_limit_a
    return TSModel(A=A, B=Bm, Bw=Bw, C=C, D=D, H1=H1, H2=np.zeros((r, 1, 1)), H3=np.zeros((r, 1, n)),
                   H4=np.zeros((r, 1, 1)), rho=float(rho), premise_rad_s=prem, dA=offs, E=E,
                   state_names=("d_omega_m", "d_i", "d_z"), input_names=("u",),
                   disturbance_names=("w1", "w2", "w3"), output_names=("d_omega_m", "w_i d_z"),
                   info={"rule_centres_rad_s": cs, "resistance_uncertainty": eps,
                         "averaged": averaged is not None,
                         "integral_weight_rad_s": wi, "inputs": "six-step", "emf_range_v_s": (k_lo, k_hi),
                         "state_scale": np.array([max(w_top, 1.0), i_s, max(w_top, 1.0) / wi]),
                         "input_scale": np.array([profile.inverter.bus_voltage_v])})


#: the 2016 paper's Table 1 (its section 6 example), as printed: pole pairs, L (H), R (ohm),
#: J (kg m^2), B (N m s), lambda_m (V s)
PAPER_TABLE1 = {"P": 2, "L": 0.0018, "R": 0.5, "J": 0.003, "B": 0.0008, "lambda_m": 0.311}
#: its premise bounds N1, N2 as printed (inserted into A_1, A_2)
PAPER_PREMISE_RAD_S = (0.0, 3000.0)


def paper_as_printed_model(N=None):
    """Section 6's TS model exactly as printed (numbers of Table 1, x1 electrical rad/s).

    ``A_i`` with ``-B/J, 3/2 P/J lambda_m`` in row 1, ``N_i`` in the coupling
    terms; ``B_1 = B_2``, ``Bw`` with ``-P/J``, ``C = diag(1, 0, 0)`` (as the
    1 x 3 output ``x1``), ``H1 = diag(0, -0.1 R/L, -0.1 R/L)``.
    """
    t = PAPER_TABLE1
    P_, L, R, J, B, lam = t["P"], t["L"], t["R"], t["J"], t["B"], t["lambda_m"]
    N = PAPER_PREMISE_RAD_S if N is None else N

    def A(n):
        return np.array([[-B / J, 1.5 * P_ / J * lam, 0.0],
                         [-lam / L, -R / L, -L / L * n],
                         [0.0, L / L * n, -R / L]])
    Bm = np.array([[0.0, 0.0], [1 / L, 0.0], [0.0, 1 / L]])
    Bw = np.array([[0.0, 0.0, -P_ / J], [0.0, 0.1, 0.0], [0.1, 0.0, 0.0]])
    H1 = np.diag([0.0, -0.1 * R / L, -0.1 * R / L])
    return TSModel(A=np.stack([A(N[0]), A(N[1])]), B=np.stack([Bm, Bm]), Bw=Bw,
                   C=np.stack([np.array([[1.0, 0, 0]])] * 2), D=np.zeros((2, 1, 2)), H1=np.stack([H1, H1]),
                   H2=np.zeros((2, 3, 2)), H3=np.zeros((2, 1, 3)), H4=np.zeros((2, 1, 2)), rho=1.0,
                   premise_rad_s=(float(N[0]), float(N[1])),
                   state_names=("omega_e", "i_q", "i_d"), input_names=("v_q", "v_d"),
                   disturbance_names=("w1", "w2", "w3"), output_names=("omega_e",),
                   info={"state_scale": np.array([max(N[1], 1.0), 10.0, 10.0]),
                         "input_scale": np.array([48.0, 48.0])})


def model_for(profile, model: str, options: dict | None = None):
    """Rebuild the TS model a certificate refers to (``paper``, ``tracking-dq``, ``tracking-six-step``,
    ``six-step``, ``six-step-averaged``: the speed-dependent averaged model whose identified table
    is ``options["averaged"]``, :meth:`picdrive.models.averaged.AveragedModel.to_dict`)."""
    o = dict(options or {})
    kw = {k: o[k] for k in ("rules", "resistance_uncertainty", "rho") if o.get(k) is not None}
    if model == "paper":
        return paper_model(profile, **kw)
    if model == "paper-as-printed":
        return paper_as_printed_model()
    if o.get("integral_weight_rad_s") is not None:
        kw["integral_weight_rad_s"] = o["integral_weight_rad_s"]
    if model in ("tracking-dq", "tracking-six-step"):
        return tracking_model(profile, inputs=model.split("-", 1)[1], **kw)
    if model in ("six-step", "six-step-averaged"):
        if o.get("emf_polytope") is not None:
            kw["emf_polytope"] = bool(o["emf_polytope"])
        if model == "six-step-averaged":
            from .averaged import model_from_dict
            if not isinstance(o.get("averaged"), dict):
                raise ValueError("model 'six-step-averaged' needs its identified table (model_options['averaged'])")
            kw["averaged"] = model_from_dict(profile, o["averaged"])
        return six_step_model(profile, **kw)
    raise ValueError(f"unknown fuzzy model {model!r}")
