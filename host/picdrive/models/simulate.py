"""Simulation helpers: the dq motor under the sampled control law.

* :func:`simulate_law` -- the nonlinear dq model (:mod:`picdrive.models.dqmodel`)
  driven by the firmware's law (:func:`picdrive.control_law.law_step`)
  sampled at ``law.sample_time_s`` with a zero-order hold, through the
  six-step mapping ``v_q = k_v u``, ``v_d = 0``; measured speed = mechanical
  speed, measured current = bus current ``k_i i_q``; load-torque profile and
  the 2016 disturbances; the bridge saturates ``|u|`` at bus voltage x max duty.
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

from ..control_law import LawState, direction_hold, law_step, walk_cap
from .dqmodel import DqParams, derivatives, dq_params

__all__ = ["SimResult", "simulate_law", "disturbances_2016", "step_load",
           "SixStepPlant", "SixStepResult", "six_step_plant", "simulate_six_step",
           "W_WINDOW_S", "HallSpeedMeter", "hall_speed_meter", "pwm_ripple_peak_a"]

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


# ---------------------------------------------------------------------------
# The six-step drive: DC-equivalent plant with the bridge's conduction rule
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class SixStepPlant:
    """Constants of the six-step model (SI; line = two phases in series)."""

    r_ohm: float                 # line resistance (perturbed)
    l_h: float                   # line inductance
    kb_v_s_per_rad: float        # DC-equivalent back-EMF constant (= Kt)
    kt_n_m_per_a: float
    j_kg_m2: float
    b_n_m_s: float
    bus_voltage_v: float
    u_bridge_v: float            # bus voltage x max duty
    pwm_period_s: float
    current_limit_a: float       # firmware's current limit (the walk-down backup)
    adc_counts_per_a: float      # 10-bit ADC counts per ampere of bus current (0: not quantised)
    pole_pairs: int = 1
    emf_table: tuple = ()        # commutated model: ((fwd k_e per angle step), (rev ...)), V s/rad; () = DC equivalent


EMF_TABLE_N = 1440       # angle steps per electrical turn of the commutated EMF table (0.25 deg)


def commutated_emf(profile) -> tuple[np.ndarray, np.ndarray]:
    """Back-EMF constant of the phase pair the commutation table drives, per electrical angle.

    ``(k_fwd, k_rev)``, each ``EMF_TABLE_N`` values of ``lambda_m P (f_source - f_sink)``
    (V per mechanical rad/s) over one electrical turn: the forward and the reverse
    table of :func:`picdrive.commutation.hall_table` from the profile's hall
    placement.  Its mean over the aligned sector is the DC equivalent ``Kb``; with
    ``hall_offset_deg = 0`` the table commutates 30 degrees early and the pair's
    EMF (and torque per ampere) ripples within every sector.
    """
    from ..commutation import emf_unit, hall_code_at, hall_table
    m, se = profile.motor, profile.sensors
    tab = hall_table(se.hall_spacing_deg, se.hall_offset_deg, m.back_emf_shape)
    th = (np.arange(EMF_TABLE_N) + 0.5) * (2 * math.pi / EMF_TABLE_N)
    codes = hall_code_at(np.degrees(th), se.hall_spacing_deg, se.hall_offset_deg)
    f = [emf_unit(m.back_emf_shape, th - k * 2 * math.pi / 3) for k in range(3)]
    k = m.lambda_m_v_s * m.pole_pairs
    out = []
    for states in (tab.forward, tab.reverse):
        kk = np.zeros(EMF_TABLE_N)
        for c in range(8):
            st = states[c]
            if st is None:
                continue
            sel = codes == c
            kk[sel] = k * (f[st[0]][sel] - f[st[1]][sel])
        out.append(kk)
    return out[0], out[1]


def six_step_plant(profile, *, r_factor: float = 1.0, commutated: bool = False) -> SixStepPlant:
    """The six-step plant of a profile (2008 eq 1 constants), R scaled by ``r_factor``;
    ``commutated``: the pair's EMF per rotor angle (:func:`commutated_emf`) instead of ``Kb``."""
    m, inv = profile.motor, profile.inverter
    tab = ()
    if commutated:
        kf, kr = commutated_emf(profile)
        tab = (tuple(kf.tolist()), tuple(kr.tolist()))
    return SixStepPlant(r_ohm=m.r_line_ohm * r_factor, l_h=m.l_line_h, kb_v_s_per_rad=m.kb_v_s_per_rad,
                        kt_n_m_per_a=m.kt_n_m_per_a, j_kg_m2=m.inertia_kg_m2, b_n_m_s=m.viscous_friction_n_m_s,
                        bus_voltage_v=inv.bus_voltage_v, u_bridge_v=inv.bus_voltage_v * profile.max_duty(),
                        pwm_period_s=1.0 / inv.pwm_frequency_hz, current_limit_a=inv.current_limit_a,
                        adc_counts_per_a=1023.0 / 5.0 * inv.current_sense_v_per_a, pole_pairs=m.pole_pairs,
                        emf_table=tab)


def pwm_ripple_peak_a(v_on_v: float, r_ohm: float, l_h: float, duty: float, period_s: float) -> float:
    """How far the current's peak inside a PWM period lies above its period average, A.

    An RL winding (with any back-EMF held over the period) switched between ``v_on_v`` for
    ``duty`` of the period and 0 V for the rest (high-side PWM, the low side on: the current
    freewheels through the source leg's low-side diode and the sink's low side: about 0 V across
    the pair), in its periodic steady state:
    ``i_max = (V/R) (1 - a) / (1 - a b)`` above the all-off level, ``a = exp(-d T/tau)``,
    ``b = exp(-(1-d) T/tau)``, while the period average is ``d V/R`` (L di/dt averages to 0);
    the back-EMF shifts both alike.  Models that average each PWM period (this module, the twin)
    miss this excess: it is about ``V d (1-d) T / (2 L)`` for ``tau >> T`` and approaches
    ``V/R (1 - d)`` when ``tau << T``."""
    if not 0.0 < duty < 1.0 or r_ohm <= 0.0:
        return 0.0
    tau = l_h / r_ohm
    a = math.exp(-duty * period_s / tau)
    b = math.exp(-(1.0 - duty) * period_s / tau)
    return v_on_v / r_ohm * ((1.0 - a) / (1.0 - a * b) - duty)


@dataclass(frozen=True)
class HallSpeedMeter:
    """The firmware's speed measurement from hall edges (``sensors.speed_source = "hall"``).

    drive.c.j2 ``hall_edge()`` latches Timer5 at every hall edge (``h_period`` = ticks between
    the last two edges, ``h_fwd`` = the edge followed the forward sequence); each speed-loop
    sample ``measure()`` / ``core_speed_hall()`` reads ``w = K / max(h_period, elapsed)``
    (``elapsed`` = ticks since the last edge: a slowing rotor reads no faster than the time it has
    been silent), negative for a backward edge, and 0 until two edges were seen or once
    ``age_max`` samples passed without an edge.  So the law sees the mean speed over the last
    hall sector (60 electrical degrees), which lags the true speed by about half a sector, and
    nothing below ``k / 65536`` ticks; the resolution is one Timer5 tick in the period."""

    edges_per_rev: int           # 6 x pole pairs
    tick_s: float                # Timer5 tick, s (prescaler / Fcy)
    k_raw: int                   # CORE_K_SPEED: speed (Q qs) x period (ticks)
    qs: int                      # speed Q format
    age_max: int                 # FW_HALL_AGE_MAX, samples
    offset_deg: float            # sensors.hall_offset_deg (edges at offset + m x 60 electrical degrees)
    pole_pairs: int

    @property
    def lowest_rad_s(self) -> float:
        """Slowest speed with a period inside the 16-bit timer, rad/s."""
        return 2 * math.pi / self.edges_per_rev / (65535 * self.tick_s)


def hall_speed_meter(profile, plan) -> HallSpeedMeter:
    """The hall speed measurement of the firmware a fixed-point ``plan``
    (:func:`picdrive.firmware.fixedpoint.plan_fixed_point`) builds for ``profile``."""
    from ..board import FCY_HZ
    # FW_HALL_AGE_MAX as codegen renders it (tests/test_verify_hardware.py checks the two agree)
    age_max = max(2, min(255, math.floor(65536 * plan.ps5 / FCY_HZ * plan.loop_hz) - 1))
    return HallSpeedMeter(edges_per_rev=6 * profile.motor.pole_pairs, tick_s=plan.ps5 / FCY_HZ, k_raw=plan.k_speed,
                          qs=plan.qs, age_max=age_max, offset_deg=profile.sensors.hall_offset_deg,
                          pole_pairs=profile.motor.pole_pairs)


@dataclass
class SixStepResult:
    """Samples of :func:`simulate_six_step` (at the law's sample instants unless named ``_fine``)."""

    t: np.ndarray                # s
    omega: np.ndarray            # true mechanical speed, rad/s
    y: np.ndarray                # measured speed the law saw, rad/s
    i: np.ndarray                # line current (forward sense), A
    i_meas: np.ndarray           # bus current the law saw, A
    u: np.ndarray                # law output, V
    u_lo: np.ndarray             # output window of the law at the sample, V
    u_hi: np.ndarray
    direction: np.ndarray        # bridge state applied over the next sample: +1, -1, 0 (all off)
    integ: np.ndarray            # law integrator, V
    ref: np.ndarray              # rad/s
    load: np.ndarray             # N m
    cap_active: np.ndarray       # firmware's walk-down backup cap below the bridge voltage
    t_fine: np.ndarray           # s, every PWM period
    omega_fine: np.ndarray
    i_fine: np.ndarray
    i_peak_fine: np.ndarray = field(default_factory=lambda: np.zeros(0))   # |i| + the PWM ripple above the
                                                                            # period average (pwm_ripple_peak_a)
    cap_cut: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # the backup cap cut the law's output
    v_bus_fine: np.ndarray = field(default_factory=lambda: np.zeros(0))   # DC bus, V, every PWM period (the
                                                                          # three-phase plant's capacitor; else
                                                                          # the profile's bus_voltage_v)

    @property
    def rpm(self) -> np.ndarray:
        return self.omega * 60.0 / (2.0 * math.pi)

    @property
    def saturated(self) -> np.ndarray:
        """u at the edge of the law's output window (or the bridge)."""
        return (self.u >= self.u_hi - 1e-9) | (self.u <= self.u_lo + 1e-9)

    @property
    def i_bus(self) -> np.ndarray:
        """Line (= DC-link while conducting) current at the samples, A."""
        return self.i


def _three_phase_step(cp, tab, legs_off, d_dir: int, d_duty: float, tl: float, td: float, w: float,
                      h: float) -> tuple[float, float, float, float, float]:
    """One PWM period of the three-phase plant under the firmware's bridge rule (high-side PWM on the
    hall table's source, low side on at its sink; ``d_dir`` 0: all off); the passive load ``tl``
    (opposes motion, holds a standing rotor, never reverses it) plus the signed torque ``td``.
    Returns (line current in the forward sense, speed, angle, torque, peak switched current)."""
    legs = legs_off
    if d_dir != 0:
        pair = (tab.forward if d_dir > 0 else tab.reverse)[cp.hall_code()]
        if pair is not None:
            legs = [(0.0, 0.0)] * 3
            legs[pair[0]] = (d_duty, 0.0)
            legs[pair[1]] = (0.0, 1.0)
    if w > 0.0:
        tload = tl
    elif w < 0.0:
        tload = -tl
    else:
        te0 = cp.state.torque_e_n_m - td
        tload = te0 if abs(te0) <= tl else math.copysign(tl, te0)
    cp.step(legs, tload + td, h)
    w1 = cp.state.w_rad_s
    if w != 0.0 and tl > 0.0 and (w1 > 0.0) != (w > 0.0) and (tload > 0.0) == (w > 0.0):
        w1 = cp.state.w_rad_s = 0.0
    i_link = cp.state.i_link_on_a
    return (i_link if d_dir >= 0 else -i_link), w1, cp.state.theta_rad, cp.state.torque_e_n_m, cp.state.i_peak_a


def simulate_six_step(profile, law, *, t_end: float, ref_rpm: float | Callable[[float], float],
                      load: float | Callable[[float], float] = 0.0, r_factor: float = 1.0,
                      measurement: str = "firmware", commutated: bool = False,
                      torque_disturbance: Callable[[float], float] | None = None,
                      plant: SixStepPlant | None = None, x0=(0.0, 0.0), integrator0_v: float = 0.0,
                      hall: HallSpeedMeter | None = None, three_phase=None) -> SixStepResult:
    """The six-step drive under the firmware's law, averaged over each PWM period.

    Plant (DC equivalent, 2008 eq 1, the profile's ``r_line_ohm``, ``l_line_h``,
    ``kb_v_s_per_rad``, ``kt_n_m_per_a``; R x ``r_factor``)::

        L di/dt = v - R i - k_e w          J dw/dt = k_e i - B w - T_load

    with ``k_e = Kb`` (``commutated=False``) or the EMF constant of the phase
    pair the hall table drives at the rotor angle (:func:`commutated_emf`; the
    line current is carried over at a commutation).  ``x0 = (i, w)`` starts
    the drive running (as if at that speed for a while: the measurement's
    history is ``w``; the law's integrator starts at ``integrator0_v``, its
    speed memory at ``w``).  ``load`` is a passive
    load-torque magnitude (function of time); ``torque_disturbance`` a signed
    torque (N m, function of time, held over each sample) that acts against
    the motor, like the 2016 paper's w3.

    Bridge (high-side PWM, low side on; the twin's inverter rule reduced to
    the two conducting phases): in the forward table with duty ``d`` the line
    voltage is ``d Vbus`` while ``i > 0`` and ``Vbus`` (body diodes) while
    ``i < 0``; at ``i = 0`` the current stays zero while the back-EMF lies in
    between.  So the current cannot reverse while ``0 <= u < Kb w < Vbus``: it
    decays to zero and there is no braking torque.  Reverse table (``u < 0``):
    the mirror image (``-d Vbus`` / ``-Vbus``), plugging.  All switches off:
    ``-Vbus`` / ``+Vbus`` (the current dies against the bus).  The load is
    passive (opposes motion, holds a standing rotor), as the twin's default.

    Firmware (docs/firmware.md): every sample ``Ts`` the law
    (:func:`picdrive.control_law.law_step`, with its back-EMF current window)
    sees the speed by the M/T method with half a sample of extrapolation
    (``measurement="firmware"``: ``w_avg + (w_avg - w_avg_prev)/2``, ``w_avg``
    the exact mean over the last sample; ``"instant"``: the true speed;
    ``"hall"``: the hall-edge period of :class:`HallSpeedMeter` ``hall``, edges
    located inside each PWM period, timed in Timer5 ticks) and
    the bus current as one ADC sample of the current in the applied direction
    (0 while all switches are off; 10-bit quantised); its output is applied
    from the next PWM period on; a change of sign switches all outputs off
    for one sample first; the walk-down backup caps |u| while the measured
    current exceeds the current limit.  Each PWM period: the current exactly
    (exponential, speed held at its start), a current zero inside the period
    located on that exponential, then the speed by the trapezoidal rule.

    ``three_phase``: a three-phase plant to use instead (the motor twin's
    winding, ``picdrive_hil.plant.CPlant``, built by the caller for this
    profile with R x ``r_factor`` and an active load, at rest: per-phase
    currents, the floating phase and its body diode, the current transfer at
    every commutation), driven through the profile's hall table (high-side
    PWM, low side on) by the same firmware rules, one PWM period per step;
    the law then sees the current of the switch that carries the line
    current (the twin's ``link_on`` signal).  A drive whose hall sector is
    short against L/R loses torque at each commutation, which the DC
    equivalent does not have.  ``plant`` and ``commutated`` then do not
    apply and ``x0`` must be at rest.
    """
    if measurement not in ("firmware", "instant", "hall"):
        raise ValueError(f"measurement {measurement!r}: 'firmware', 'instant' or 'hall'")
    if measurement == "hall" and hall is None:
        raise ValueError("measurement 'hall' needs the firmware's HallSpeedMeter (hall=)")
    pl = plant if plant is not None else six_step_plant(profile, r_factor=r_factor, commutated=commutated)
    ts = law.sample_time_s
    n_sub = max(1, int(round(ts / pl.pwm_period_s)))
    h = ts / n_sub
    R, L, J, B = pl.r_ohm, pl.l_h, pl.j_kg_m2, pl.b_n_m_s
    tau = L / R
    g_h = math.exp(-h / tau)
    vbus = pl.bus_voltage_v
    kb = pl.kb_v_s_per_rad
    tab = pl.emf_table
    n_tab = len(tab[0]) if tab else 0
    ang_k = pl.pole_pairs * n_tab / (2 * math.pi)
    rfun = ref_rpm if callable(ref_rpm) else (lambda t, v=float(ref_rpm): v)
    lfun = load if callable(load) else (lambda t, v=float(load): v)
    dfun = torque_disturbance
    n = int(round(t_end / ts)) + 1
    rpm = 2.0 * math.pi / 60.0
    o = {k: np.zeros(n) for k in ("t", "omega", "y", "i", "im", "u", "lo", "hi", "dir", "I", "ref", "load")}
    cap_on = np.zeros(n, bool)
    cap_cut = np.zeros(n, bool)
    nf = n * n_sub
    tf, wf, jf, pf = np.zeros(nf), np.zeros(nf), np.zeros(nf), np.zeros(nf)
    vf = np.full(nf, float(vbus))
    ripple = {}                                      # duty -> the PWM ripple above the period average
    i, w, th = float(x0[0]), float(x0[1]), 0.0
    st = LawState(integ_v=float(integrator0_v), y_prev=w if w != 0.0 else None)
    th_prev, w_avg_prev, valid = -w * ts, w, w != 0.0
    # bridge state applied now: direction (+1/-1/0) and duty; a running start applies the integrator's voltage
    d_dir = 0 if integrator0_v == 0.0 else (1 if integrator0_v > 0 else -1)
    d_duty = min(abs(integrator0_v), pl.u_bridge_v) / vbus
    dir_fw = 1 if d_dir < 0 else 0   # firmware's cs.dir: 0 forward, 1 reverse
    tab_dir = dir_fw                 # table whose pair carries the current (0 fwd, 1 rev)
    cap = pl.u_bridge_v
    cap_step = pl.u_bridge_v * ts / 0.010
    i_lim_counts = math.floor(pl.current_limit_a * pl.adc_counts_per_a + 0.5) if pl.adc_counts_per_a else None
    kf = 0
    if measurement == "hall":
        # hall edges: electrical angle offset + m x 60 deg; edge index of the present angle
        e_per_rad = hall.pole_pairs * 3.0 / math.pi
        e_off = hall.offset_deg / 60.0
        h_idx = math.floor(th * e_per_rad - e_off)
        h_last = h_period = 0
        h_fwd, h_count, h_age = True, 0, 0
        w_lsb = 2.0 ** -hall.qs
    cp = three_phase
    if cp is not None:
        from ..commutation import hall_table
        if x0[0] != 0.0 or x0[1] != 0.0 or cp.state.w_rad_s != 0.0:
            raise ValueError("a three-phase run starts at rest (x0 = (0, 0))")
        ctab = hall_table(profile.sensors.hall_spacing_deg, profile.sensors.hall_offset_deg,
                          profile.motor.back_emf_shape)
        legs_off = [(0.0, 0.0)] * 3
    for k in range(n):
        t = k * ts
        # ---- measurements at the sample
        if measurement == "hall":
            now = math.floor(t / hall.tick_s + 1e-9) & 0xFFFF
            y = 0.0
            if h_count >= 2 and h_age < hall.age_max:
                p = max(h_period, (now - h_last) & 0xFFFF)
                if p:
                    y = min(hall.k_raw // p, 32767) * w_lsb * (1.0 if h_fwd else -1.0)
            h_age = min(h_age + 1, 255)
        elif measurement == "instant" or (k == 0 and not valid):
            y = w if measurement == "instant" else 0.0
        else:
            w_avg = (th - th_prev) / ts
            if not valid:                           # first counts: no history, no extrapolation
                w_avg_prev, valid = w_avg, w_avg != 0.0
            y = w_avg + 0.5 * (w_avg - w_avg_prev)
            w_avg_prev = w_avg
        th_prev = th
        if d_dir != 0 and d_duty > 0.0:
            i_link = max(0.0, d_dir * i)
            if pl.adc_counts_per_a:
                adc = min(1023, math.floor(i_link * pl.adc_counts_per_a))
                i_link = adc / pl.adc_counts_per_a
                over = adc > i_lim_counts
            else:
                over = i_link > pl.current_limit_a
            i_m = d_dir * i_link
        else:
            i_m, over = 0.0, False
        # the firmware's walk-down backup on the measured current
        cap = walk_cap(cap, over, cap_step, pl.u_bridge_v)
        r = rfun(t) * rpm
        lo, hi = law.output_limits(y)
        u_law = law_step(law, st, r, y, i_m)
        u = min(max(u_law, -cap, -pl.u_bridge_v), cap, pl.u_bridge_v)
        cap_on[k] = cap < pl.u_bridge_v - 1e-9
        cap_cut[k] = abs(u_law) > cap + 1e-9       # the backup, not the window, set the output
        dir_fw, hold = direction_hold(u, dir_fw)
        n_dir = 0 if hold else (-1 if dir_fw else 1)
        n_duty = abs(u) / vbus
        tl = lfun(t)
        td = dfun(t) if dfun is not None else 0.0
        o["t"][k], o["omega"][k], o["y"][k], o["i"][k], o["im"][k] = t, w, y, i, i_m
        o["u"][k], o["lo"][k], o["hi"][k], o["dir"][k], o["I"][k] = u, lo, hi, n_dir, st.integ_v
        o["ref"][k], o["load"][k] = r, tl
        # ---- plant over the sample, PWM period by PWM period (the new command from the second one on)
        for s in range(n_sub):
            if s == 1:
                d_dir, d_duty = n_dir, n_duty
                if d_dir:
                    tab_dir = 0 if d_dir > 0 else 1
            if d_dir > 0:
                v_pos, v_neg = d_duty * vbus, vbus
            elif d_dir < 0:
                v_pos, v_neg = -vbus, -d_duty * vbus
            else:
                v_pos, v_neg = -vbus, vbus
            if cp is not None:
                i1, w1, th1, te, pk3 = _three_phase_step(cp, ctab, legs_off, d_dir, d_duty, tl, td, w, h)
            elif n_tab:
                # the current and voltage here are in the forward sense (u < 0: -d Vbus); the reverse
                # table drives its own pair source -> sink with +d Vbus, so in the forward sense its
                # EMF constant is minus that pair's (plugging brakes a forward-turning rotor)
                ke = tab[tab_dir][int((th + 0.5 * h * w) * ang_k) % n_tab]
                if tab_dir:
                    ke = -ke
            else:
                ke = kb
            if cp is None:
                e = ke * w
                if i > 0.0 or (i == 0.0 and e < v_pos):
                    v = v_pos
                elif i < 0.0 or (i == 0.0 and e > v_neg):
                    v = v_neg
                else:
                    v = None
                if v is None:
                    i1, hc = 0.0, 0.0
                else:
                    i_inf = (v - e) / R
                    i1 = i_inf + (i - i_inf) * g_h
                    hc = h
                    if (i > 0.0 and i1 < 0.0) or (i < 0.0 and i1 > 0.0):
                        hc = tau * math.log((i - i_inf) / (0.0 - i_inf))      # the current zero
                        i1 = 0.0
                # torque: mean over the conducting part (exact mean of the exponential)
                if hc > 0.0 and v is not None:
                    gc = math.exp(-hc / tau)
                    i_mean = (i_inf * hc + (i - i_inf) * tau * (1.0 - gc)) / h
                else:
                    i_mean = 0.0
                te = ke * i_mean - td
                if w > 0.0:
                    tload = tl
                elif w < 0.0:
                    tload = -tl
                else:                                        # passive load holds a standing rotor
                    tload = te if abs(te) <= tl else math.copysign(tl, te)
                w1 = (w * (1.0 - 0.5 * h * B / J) + h / J * (te - tload)) / (1.0 + 0.5 * h * B / J)
                if w != 0.0 and tl > 0.0 and (w1 > 0.0) != (w > 0.0) and (tload > 0.0) == (w > 0.0):
                    w1 = 0.0                                 # a passive load stops the rotor, never reverses it
                th1 = th + 0.5 * h * (w + w1)
            if measurement == "hall":
                idx = math.floor(th1 * e_per_rad - e_off)
                while idx != h_idx:                       # the edges crossed in this period, in order
                    fwd = idx > h_idx
                    edge = (h_idx + (1 if fwd else 0) + e_off) / e_per_rad
                    frac = (edge - th) / (th1 - th) if th1 != th else 1.0
                    tick = math.floor((t + s * h + min(max(frac, 0.0), 1.0) * h) / hall.tick_s) & 0xFFFF
                    h_period, h_last = (tick - h_last) & 0xFFFF, tick
                    h_fwd, h_count, h_age = fwd, min(h_count + 1, 2), 0
                    h_idx += 1 if fwd else -1
            th = th1
            i, w = i1, w1
            tf[kf], wf[kf], jf[kf] = t + (s + 1) * h, w, i
            pk = abs(i)
            if cp is not None:
                pk = pk3
                vf[kf] = cp.state.v_bus_v
            elif v is not None and d_dir != 0 and (v == v_pos if d_dir > 0 else v == v_neg) and 0.0 < d_duty < 1.0:
                ex = ripple.get(d_duty)
                if ex is None:
                    ex = ripple[d_duty] = pwm_ripple_peak_a(vbus, R, L, d_duty, pl.pwm_period_s)
                pk += ex
            pf[kf] = pk
            kf += 1
        if not (math.isfinite(w) and math.isfinite(i)) or abs(w) > 1e7:
            raise FloatingPointError("six-step simulation diverged")
    return SixStepResult(t=o["t"], omega=o["omega"], y=o["y"], i=o["i"], i_meas=o["im"], u=o["u"], u_lo=o["lo"],
                         u_hi=o["hi"], direction=o["dir"], integ=o["I"], ref=o["ref"], load=o["load"],
                         cap_active=cap_on, t_fine=tf[:kf], omega_fine=wf[:kf], i_fine=jf[:kf],
                         i_peak_fine=pf[:kf], cap_cut=cap_cut, v_bus_fine=vf[:kf])


def simulate_six_step_batch(profile, kp, ki, kd, *, t_end_s: float, ref_rad_s: float, load_n_m: float = 0.0,
                            n_sub: int = 4, r_factor: float = 1.0, commutated: bool = False,
                            plant: SixStepPlant | None = None, hall: HallSpeedMeter | None = None,
                            torque_disturbance: Callable[[float], float] | None = None) -> dict:
    """:func:`simulate_six_step` (``measurement="firmware"``, or ``"hall"`` with ``hall`` given;
    forward table) for many one-rule PID laws at once.

    The law is ``control_law.law_step`` written for arrays: one rule, b = 1,
    unfiltered derivative on the measurement, the profile's current window
    ``Kb y -+ R I_lim`` inside ``+-`` bus x max duty, integration only into the
    window's headroom, integrator range the bridge voltage (the default of a
    PID law).  The plant: the same conduction rule, passive load, firmware
    measurement and one-PWM-period command delay as :func:`simulate_six_step`;
    each sample is integrated over the delay period and then ``n_sub`` equal
    sub-steps (with ``n_sub = Ts/T_pwm - 1`` the schedule is exactly
    :func:`simulate_six_step`'s; a test keeps the two equal).  The walk-down
    backup is not modelled.  ``torque_disturbance``: a signed torque (N m, function of time, held
    over each sample) against the motor, as :func:`simulate_six_step`'s.  Returns ``speed_rad_s`` and ``current_a`` at the
    samples, shape (samples, batch), and per law ``peak_speed_rad_s``,
    ``peak_current_a`` over every sub-step.
    """
    kp, ki, kd = (np.atleast_1d(np.asarray(v, float)) for v in (kp, ki, kd))
    kp, ki, kd = np.broadcast_arrays(kp, ki, kd)
    pl = plant if plant is not None else six_step_plant(profile, r_factor=r_factor, commutated=commutated)
    ts = 1.0 / profile.control.speed_loop_hz
    R, L, J, B, kb = pl.r_ohm, pl.l_h, pl.j_kg_m2, pl.b_n_m_s, pl.kb_v_s_per_rad
    tab = np.asarray(pl.emf_table[0]) if pl.emf_table else None      # forward table (a PID's step from rest)
    ang_k = pl.pole_pairs * (tab.size if tab is not None else 1) / (2 * math.pi)
    tau = L / R
    vbus, ub = pl.bus_voltage_v, pl.u_bridge_v
    span = R * pl.current_limit_a
    hd = min(pl.pwm_period_s, ts)
    steps = [hd] + [(ts - hd) / n_sub] * n_sub
    gs = [math.exp(-h / tau) for h in steps]
    n = int(round(t_end_s / ts)) + 1
    m = kp.size
    i = np.zeros(m); w = np.zeros(m); th = np.zeros(m)
    th_prev = np.zeros(m); wa_prev = np.zeros(m); valid = np.zeros(m, bool)
    d_dir = np.zeros(m); d_duty = np.zeros(m); dir_fw = np.zeros(m, bool)
    integ = np.zeros(m); y_prev = None
    r = float(ref_rad_s)
    w_out = np.zeros((n, m)); i_out = np.zeros((n, m))
    w_pk = np.zeros(m); i_pk = np.zeros(m)
    if hall is not None:          # the hall-edge period in Timer5 ticks, as simulate_six_step's "hall"
        e_per_rad = hall.pole_pairs * 3.0 / math.pi
        e_off = hall.offset_deg / 60.0
        h_idx = np.full(m, math.floor(-e_off), np.int64)
        h_last = np.zeros(m, np.int64); h_period = np.zeros(m, np.int64)
        h_fwd = np.ones(m, bool); h_count = np.zeros(m, np.int64); h_age = np.zeros(m, np.int64)
        w_lsb = 2.0 ** -hall.qs
    for k in range(n):
        w_out[k], i_out[k] = w, i
        if hall is not None:
            now = math.floor(k * ts / hall.tick_s + 1e-9) & 0xFFFF
            p_h = np.maximum(h_period, (now - h_last) & 0xFFFF)
            live = (h_count >= 2) & (h_age < hall.age_max) & (p_h > 0)
            y = np.where(live, np.minimum(hall.k_raw // np.maximum(p_h, 1), 32767) * w_lsb, 0.0)
            y = np.where(h_fwd, y, -y)
            h_age = np.minimum(h_age + 1, 255)
        elif k == 0:
            y = np.zeros(m)
        else:
            wa = (th - th_prev) / ts
            first = ~valid
            wa_prev = np.where(first, wa, wa_prev)
            valid = valid | (wa != 0.0)
            y = wa + 0.5 * (wa - wa_prev)
            wa_prev = wa
        th_prev = th.copy()
        lo = np.minimum(np.maximum(-ub, kb * y - span), ub)
        hi = np.maximum(np.minimum(ub, kb * y + span), -ub)
        e = r - y
        q = kp * e + kd * ((y if y_prev is None else y_prev) - y) / ts
        di = ki * ts * e
        up = np.minimum(integ + di, np.maximum(integ, hi - q))
        dn = np.maximum(integ + di, np.minimum(integ, lo - q))
        integ = np.where(di > 0, up, np.where(di < 0, dn, integ))
        integ = np.clip(integ, -ub, ub)
        u = np.minimum(np.maximum(q + integ, lo), hi)
        y_prev = y
        newdir = u < 0
        hold = (u != 0.0) & (newdir != dir_fw)
        dir_fw = np.where(u != 0.0, newdir, dir_fw)
        n_dir = np.where(hold, 0.0, np.where(dir_fw, -1.0, 1.0))
        n_duty = np.abs(u) / vbus
        t_sub = k * ts
        td = float(torque_disturbance(k * ts)) if torque_disturbance is not None else 0.0
        for s, (h, g) in enumerate(zip(steps, gs)):
            if s <= 1:                          # the bridge's rails change only with the command
                if s == 1:
                    d_dir, d_duty = n_dir, n_duty
                v_pos = np.where(d_dir > 0, d_duty * vbus, -vbus)
                v_neg = np.where(d_dir < 0, -d_duty * vbus, vbus)
            ke = kb if tab is None else tab[((th + 0.5 * h * w) * ang_k).astype(np.int64) % tab.size]
            em = ke * w
            pos = (i > 0) | ((i == 0) & (em < v_pos))
            neg = ~pos & ((i < 0) | ((i == 0) & (em > v_neg)))
            cond = pos | neg
            v = np.where(pos, v_pos, v_neg)
            i_inf = (v - em) / R
            i1 = i_inf + (i - i_inf) * g
            cross = cond & (i * i1 < 0)
            if cross.any():                                   # a current zero inside the step
                with np.errstate(divide="ignore", invalid="ignore"):
                    hc = np.where(cross, tau * np.log(np.where(cross, (i - i_inf) / (0.0 - i_inf), 1.0)), h)
                hc = np.where(cond, hc, 0.0)
                gc = np.exp(-hc / tau)
            else:
                hc = np.where(cond, h, 0.0)
                gc = np.where(cond, g, 1.0)
            i1 = np.where(cond & ~cross, i1, 0.0)
            i_mean = np.where(cond, (i_inf * hc + (i - i_inf) * tau * (1.0 - gc)) / h, 0.0)
            te = ke * i_mean - td
            if load_n_m > 0:
                tload = np.where(w > 0, load_n_m, np.where(w < 0, -load_n_m,
                                                           np.where(np.abs(te) <= load_n_m, te,
                                                                    np.copysign(load_n_m, te))))
            else:
                tload = 0.0
            w1 = (w * (1.0 - 0.5 * h * B / J) + h / J * (te - tload)) / (1.0 + 0.5 * h * B / J)
            if load_n_m > 0:
                w1 = np.where((w != 0) & ((w1 > 0) != (w > 0)) & ((tload > 0) == (w > 0)), 0.0, w1)
            th1 = th + 0.5 * h * (w + w1)
            if hall is not None:
                idx = np.floor(th1 * e_per_rad - e_off).astype(np.int64)
                cr = np.flatnonzero(idx != h_idx)           # the laws whose rotor crossed an edge in this step
                if cr.size:
                    nc = idx[cr] - h_idx[cr]                # edges crossed (signed)
                    fwd = nc > 0
                    t0, t1 = th[cr], th1[cr]
                    dth = np.where(t1 != t0, t1 - t0, 1.0)

                    def tick(b, a, d):                     # Timer5 at the edge of boundary b inside the step
                        frac = np.minimum(np.maximum(((b + e_off) / e_per_rad - a) / d, 0.0), 1.0)
                        return np.floor((t_sub + frac * h) / hall.tick_s).astype(np.int64) & 0xFFFF
                    ic = idx[cr]
                    last = tick(np.where(fwd, ic, ic + 1), t0, dth)
                    prev = h_last[cr]
                    two = np.flatnonzero(np.abs(nc) >= 2)   # two edges in one step: the period is between them
                    if two.size:
                        prev[two] = tick(np.where(fwd[two], ic[two] - 1, ic[two] + 2), t0[two], dth[two])
                    h_period[cr] = (last - prev) & 0xFFFF
                    h_last[cr] = last
                    h_fwd[cr] = fwd
                    h_count[cr] = np.minimum(h_count[cr] + np.abs(nc), 2)
                    h_age[cr] = 0
                    h_idx[cr] = ic
                t_sub += h
            th = th1
            i, w = i1, w1
            w_pk = np.maximum(w_pk, w)
            i_pk = np.maximum(i_pk, np.abs(i))
    return {"speed_rad_s": w_out, "current_a": i_out, "peak_speed_rad_s": w_pk, "peak_current_a": i_pk}
