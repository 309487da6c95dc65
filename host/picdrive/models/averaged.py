"""Speed-dependent averaged model of the six-step drive (per commutation sector).

The DC equivalent (2008 eq 1: ``L i' = u - R i - Kb w``, ``J w' = Kt i - B w``)
is linear in speed, but the six-step drive is not: when the winding's L/R is
not short against a hall sector (60 electrical degrees), the current does not
reach its DC-equivalent value inside the sector, the outgoing phase's current
freewheels through a body diode at every commutation (the current transfer),
and halls placed ahead of the EMF (``hall_offset_deg = 0``: 30 degrees of
advance) commutate early, which gains back part of what the inductance costs.
All of that changes the sector-mean current and torque per volt with the
speed.

This model keeps the DC equivalent's structure and lets its coefficients
depend on the speed::

    L di/dt = u - R_e(w) i - E(w)                    (line current, sector mean; A)
    J dw/dt = k_t(w) i + T_0(w) - B w - T_load       (mechanical rad/s)

``u`` is the six-step DC-equivalent voltage (duty x bus voltage, V), ``i`` the
sector mean of the current the firmware senses (the switch that carries the
line current: the twin's ``i_link_on``), ``R_e`` an effective resistance (ohm),
``E`` the sector-mean counter voltage (V; ``Kb w`` in the DC equivalent),
``k_t`` the torque per sensed ampere (N m/A) and ``T_0`` a torque offset (N m;
0 in the DC equivalent): the affine summary, in steady state ``i = (u - E)/R_e``
and torque ``k_t i + T_0`` at each speed.  Below the counter voltage the current
flows in part of each sector only (discontinuous conduction: the pair's EMF
ripples above the applied voltage), where the steady state is not affine; the
model's steady state therefore comes from per-speed *maps* of the measured
sector means (current and torque against ``u``, knee included), of which the
affine form is the summary, and its small-signal form from their local slopes
(:meth:`AveragedModel.linearise`).

Identification (:func:`identify`): the motor's three-phase winding (the motor
twin's plant, ``picdrive.gate.three_phase_plant``, passed in as a factory: this
layer imports no twin) is driven through the profile's hall table at a few
duties with its speed *held* at each speed of a grid (infinite inertia); the
sector means of current and torque in periodic steady state make the maps and,
fitted as affine functions of ``u``, the summary, whose four coefficients are
interpolated over the speed grid by a shape-preserving cubic (PCHIP, clamped to
the identified range).  Free-running checks against the same plant
(:func:`open_loop_run`, ``bench/averaged.py``, ``tests/test_averaged.py``)
judge steady speed, mean current, the small-signal gain ``dw/du`` and the
63 % time of a small voltage step.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

__all__ = ["SectorPoint", "AveragedModel", "hold_sector_means", "identify", "identify_cached", "open_loop_run",
           "model_from_dict"]

RPM = 2.0 * math.pi / 60.0


@dataclass(frozen=True)
class SectorPoint:
    """The identified coefficients at one held speed (SI)."""

    w_rad_s: float
    r_e_ohm: float           # effective resistance: d u / d i at this speed
    e_v: float               # counter voltage: u at which the sector-mean current is 0
    kt_n_m_per_a: float      # torque per sensed ampere
    t0_n_m: float            # torque offset
    fit_rms_a: float = 0.0   # rms residual of the current's affine fit, A


@dataclass(frozen=True)
class AveragedModel:
    """The speed-dependent averaged model (see module docstring); coefficients by PCHIP over the identified speeds."""

    l_h: float                       # line inductance
    j_kg_m2: float
    b_n_m_s: float
    kb_v_s_per_rad: float            # the DC equivalent's Kb (for comparison)
    r_line_ohm: float                # the DC equivalent's R
    u_bridge_v: float                # bus voltage x max duty
    points: tuple[SectorPoint, ...]
    w_ref_rad_s: float               # top identified speed
    coef: dict = field(default_factory=dict, compare=False)   # name -> scipy PchipInterpolator over w
    maps: tuple = ()                 # per identified speed (w, u's, sector-mean currents, torques), u increasing
    _map_fns: tuple = field(default=(), compare=False, repr=False)

    @property
    def w_range(self) -> tuple[float, float]:
        return self.points[0].w_rad_s, self.points[-1].w_rad_s

    def _poly(self, name: str, w: float, der: int = 0) -> float:
        lo, hi = self.w_range
        x = min(max(abs(w), lo), hi)
        f = self.coef[name]
        if der:
            if not lo < abs(w) < hi:
                return 0.0                 # clamped: constant outside the identified range
            return float(f.derivative()(x))
        return float(f(x))

    @property
    def e_slope_top(self) -> float:
        """d E / d w at the top identified speed (one-sided), V s/rad: the counter voltage's slope above the grid."""
        return float(self.coef["e"].derivative()(self.w_range[1]))

    def r_e(self, w: float) -> float:
        """Effective resistance at speed ``w`` (rad/s), ohm."""
        return self._poly("r_e", w)

    def e(self, w: float) -> float:
        """Sector-mean counter voltage at ``w``, V (the DC equivalent's ``Kb w``)."""
        lo, hi = self.w_range
        if abs(w) < lo:             # below the grid: the DC equivalent's proportional EMF, scaled to match
            return self._poly("e", lo) * abs(w) / lo
        if abs(w) > hi:             # above it: the line through the top with the top's slope (the EMF keeps rising)
            return self._poly("e", hi) + self.e_slope_top * (abs(w) - hi)
        return self._poly("e", w)

    def kt(self, w: float) -> float:
        """Torque per sensed ampere at ``w``, N m/A."""
        return self._poly("kt", w)

    def t0(self, w: float) -> float:
        """Torque offset at ``w``, N m."""
        lo = self.w_range[0]
        if abs(w) < lo:
            return self._poly("t0", lo) * abs(w) / lo
        return self._poly("t0", w)

    def _map_at(self, k: int, u: float) -> tuple[float, float]:
        """Sector-mean (current, torque) of the identified speed ``k`` at voltage ``u`` (PCHIP inside the
        measured voltages; outside, the line through the two nearest points, current not below 0)."""
        fi, ft, ug, ig, tg = self._map_fns[k]
        if ug[0] <= u <= ug[-1]:
            return max(0.0, float(fi(u))), float(ft(u))
        a, b = (0, 1) if u < ug[0] else (-2, -1)
        si = (ig[b] - ig[a]) / (ug[b] - ug[a])
        st = (tg[b] - tg[a]) / (ug[b] - ug[a])
        i = ig[a] + si * (u - ug[a])
        if i <= 0.0:
            return 0.0, 0.0
        return i, tg[a] + st * (u - ug[a])

    def _steady(self, u: float, w: float) -> tuple[float, float]:
        w = abs(w)
        ws = [m[0] for m in self.maps]
        if w <= ws[0]:
            # below the grid: the lowest speed's map at the voltage that leaves the same IR drop
            return self._map_at(0, u + self.e(ws[0]) - self.e(w))
        if w >= ws[-1]:
            return self._map_at(len(ws) - 1, u + self.e(ws[-1]) - self.e(w))
        k = int(np.searchsorted(ws, w)) - 1
        x = (w - ws[k]) / (ws[k + 1] - ws[k])
        # between identified speeds at the same voltage above the counter voltage (the knee moves with E)
        v = u - self.e(w)
        i0, t0 = self._map_at(k, self.e(ws[k]) + v)
        i1, t1 = self._map_at(k + 1, self.e(ws[k + 1]) + v)
        return (1 - x) * i0 + x * i1, (1 - x) * t0 + x * t1

    def current(self, u: float, w: float) -> float:
        """Steady sector-mean current at voltage ``u`` and speed ``w``, A (not below 0: the bridge cannot brake).
        With ``maps``: the identified sector means (discontinuous conduction included), interpolated;
        without: the affine summary ``(u - E)/R_e``."""
        if self.maps:
            return self._steady(u, w)[0]
        return max(0.0, (u - self.e(w)) / self.r_e(w))

    def torque(self, u: float, w: float) -> float:
        """Steady sector-mean torque, N m."""
        if self.maps:
            return self._steady(u, w)[1] if self._steady(u, w)[0] > 0.0 else 0.0
        i = self.current(u, w)
        return self.kt(w) * i + self.t0(w) if i > 0.0 else 0.0

    def equilibrium(self, w: float, load_n_m: float) -> tuple[float, float]:
        """``(u, i)`` holding speed ``w`` under ``load_n_m``: V, A."""
        i = (self.b_n_m_s * w + load_n_m - self.t0(w)) / self.kt(w)
        u = self.r_e(w) * i + self.e(w)
        if not self.maps:
            return u, i
        need = self.b_n_m_s * w + load_n_m
        lo, hi = 0.0, max(u, self.e(w)) + 2.0 * self.r_line_ohm + 1.0
        while self.torque(hi, w) < need:
            hi += hi - lo
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            if self.torque(mid, w) < need:
                lo = mid
            else:
                hi = mid
        u = 0.5 * (lo + hi)
        return u, self.current(u, w)

    def steady_speed(self, u: float, load_n_m: float) -> float:
        """Speed the drive settles at with voltage ``u`` and load ``load_n_m``, rad/s (0 if it cannot turn)."""
        f = lambda w: self.torque(u, w) - self.b_n_m_s * w - load_n_m
        lo, hi = 0.0, max(u / max(self.e(self.w_range[1]) / self.w_range[1], 1e-12), self.w_range[1]) * 1.5
        if f(1e-9) <= 0.0:
            return 0.0
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            if f(mid) > 0.0:
                lo = mid
            else:
                hi = mid
        return 0.5 * (lo + hi)

    def linearise(self, w: float, load_n_m: float) -> tuple[np.ndarray, np.ndarray]:
        """Small-signal ``(A, B)`` about the equilibrium at ``w`` under the load, states ``[d_w, d_i]``, input ``d_u``.

        Affine summary: ``d_i' = (d_u - R_e d_i - (E' + R_e' i*) d_w)/L``,
        ``d_w' = (k_t d_i + (k_t' i* + T_0' - B) d_w)/J`` (primes: d/dw).  With ``maps``: the same form
        from the maps' local slopes (``a = di/du``, ``b = di/dw``, ``c = dT/du``, ``d = dT/dw``, steady state):
        ``L d_i' = d_u + (b d_w - d_i)/a``, ``J d_w' = (c/a) d_i + (d - b c/a - B) d_w``."""
        if self.maps:
            u, _ = self.equilibrium(w, load_n_m)
            hu = 1e-3 * self.r_line_ohm
            hw = 1e-3 * self.w_range[1]
            ip, tp = self._steady(u + hu, w)
            im, tm = self._steady(u - hu, w)
            a, c = (ip - im) / (2 * hu), (tp - tm) / (2 * hu)
            ip, tp = self._steady(u, w + hw)
            im, tm = self._steady(u, max(w - hw, 0.0))
            dw_ = w + hw - max(w - hw, 0.0)
            b, d = (ip - im) / dw_, (tp - tm) / dw_
            k = c / a
            A = np.array([[(d - b * k - self.b_n_m_s) / self.j_kg_m2, k / self.j_kg_m2],
                          [b / a / self.l_h, -1.0 / a / self.l_h]])
            return A, np.array([[0.0], [1.0 / self.l_h]])
        _, i = self.equilibrium(w, load_n_m)
        lo, hi = self.w_range
        if abs(w) < lo:                 # the proportional EMF below the grid (e)
            de = self.e(lo) / lo
        elif abs(w) >= hi:              # the top's slope above it (e)
            de = self.e_slope_top
        else:
            de = self._poly("e", w, 1)
        dr = self._poly("r_e", w, 1)
        dk = self._poly("kt", w, 1)
        dt0 = self._poly("t0", w, 1) if abs(w) >= self.w_range[0] else self.t0(self.w_range[0]) / self.w_range[0]
        A = np.array([[(dk * i + dt0 - self.b_n_m_s) / self.j_kg_m2, self.kt(w) / self.j_kg_m2],
                      [-(de + dr * i) / self.l_h, -self.r_e(w) / self.l_h]])
        B = np.array([[0.0], [1.0 / self.l_h]])
        return A, B

    def dc_form(self, w: float, load_n_m: float):
        """The linearisation at ``w`` (rad/s) under ``load_n_m`` (:meth:`linearise`) written as a DC
        equivalent's constants (``L i' = u - R i - Kb w``, ``J w' = Kt i - B w``): a motor-like object
        (``l_line_h``, ``r_line_ohm`` = the local R_e, ``kb_v_s_per_rad``, ``kt_n_m_per_a``,
        ``inertia_kg_m2``, ``viscous_friction_n_m_s``: SI) that :func:`picdrive.models.tfmodel.motor_ss`
        reads, so the DC equivalent's analyses (e.g. the sampled loop,
        :func:`picdrive.analysis.sampled.six_step_closed_loop`, given a profile whose ``motor`` it is)
        run on the averaged model at that speed."""
        from types import SimpleNamespace
        A, _ = self.linearise(w, load_n_m)
        L, J = self.l_h, self.j_kg_m2
        return SimpleNamespace(l_line_h=L, r_line_ohm=-A[1, 1] * L, kb_v_s_per_rad=-A[1, 0] * L,
                               kt_n_m_per_a=A[0, 1] * J, inertia_kg_m2=J, viscous_friction_n_m_s=-A[0, 0] * J)

    def to_dict(self) -> dict:
        return {"form": "picdrive.averaged_six_step/1", "l_h": self.l_h, "j_kg_m2": self.j_kg_m2,
                "b_n_m_s": self.b_n_m_s, "kb_v_s_per_rad": self.kb_v_s_per_rad, "r_line_ohm": self.r_line_ohm,
                "u_bridge_v": self.u_bridge_v, "w_ref_rad_s": self.w_ref_rad_s,
                "points": [[p.w_rad_s, p.r_e_ohm, p.e_v, p.kt_n_m_per_a, p.t0_n_m, p.fit_rms_a] for p in self.points],
                "maps": [[w, list(u), list(i), list(t)] for w, u, i, t in self.maps]}


def _fit(points: Sequence[SectorPoint]) -> dict:
    from scipy.interpolate import PchipInterpolator
    x = np.array([p.w_rad_s for p in points])
    return {"r_e": PchipInterpolator(x, [p.r_e_ohm for p in points]),
            "e": PchipInterpolator(x, [p.e_v for p in points]),
            "kt": PchipInterpolator(x, [p.kt_n_m_per_a for p in points]),
            "t0": PchipInterpolator(x, [p.t0_n_m for p in points])}


def _build(profile, points: Sequence[SectorPoint], maps=()) -> AveragedModel:
    from scipy.interpolate import PchipInterpolator
    m, inv = profile.motor, profile.inverter
    pts = tuple(sorted(points, key=lambda p: p.w_rad_s))
    w_ref = pts[-1].w_rad_s
    maps = tuple(sorted(((float(w), tuple(map(float, u)), tuple(map(float, i)), tuple(map(float, t)))
                         for w, u, i, t in maps), key=lambda r: r[0]))
    fns = tuple((PchipInterpolator(u, i), PchipInterpolator(u, t), u, i, t) for _, u, i, t in maps)
    return AveragedModel(l_h=m.l_line_h, j_kg_m2=m.inertia_kg_m2, b_n_m_s=m.viscous_friction_n_m_s,
                         kb_v_s_per_rad=m.kb_v_s_per_rad, r_line_ohm=m.r_line_ohm,
                         u_bridge_v=inv.bus_voltage_v * profile.max_duty(), points=pts, w_ref_rad_s=w_ref,
                         coef=_fit(pts), maps=maps, _map_fns=fns)


def model_from_dict(profile, d: dict) -> AveragedModel:
    """Rebuild a model saved by :meth:`AveragedModel.to_dict` (the design certificate keeps it)."""
    if d.get("form") != "picdrive.averaged_six_step/1":
        raise ValueError(f"unknown averaged-model form {d.get('form')!r}")
    return _build(profile, [SectorPoint(*map(float, row)) for row in d["points"]], d.get("maps", ()))


def _legs_for(table, code: int, duty: float):
    """The firmware's bridge rule for a hall code: high-side PWM on the source, low side on at the sink."""
    st = table[code]
    legs = [(0.0, 0.0)] * 3
    if st is None or duty <= 0.0:
        return legs
    legs[st[0]] = (duty, 0.0)
    legs[st[1]] = (0.0, 1.0)
    return legs


def hold_sector_means(profile, plant, w_rad_s: float, u_v: float) -> tuple[float, float]:
    """Sector-mean sensed current (A) and torque (N m) of ``plant`` held at ``w_rad_s`` with voltage ``u_v``.

    ``plant``: a three-phase plant at rest with the interface of the motor twin's ``CPlant``
    (``step(legs, load, h)``, ``hall_code()``, ``state.w_rad_s``, ``state.torque_e_n_m``,
    ``state.i_link_on_a``, ``params.inertia_kg_m2``); its inertia is made huge so the speed is held.
    Averaged over whole sectors (at least 12 and 20 ms) after ``max(10 L/R, 2 sectors)``."""
    from ..commutation import hall_table
    m, inv, se = profile.motor, profile.inverter, profile.sensors
    tab = hall_table(se.hall_spacing_deg, se.hall_offset_deg, m.back_emf_shape).forward
    plant.params.inertia_kg_m2 = 1e9 * max(m.inertia_kg_m2, 1e-9)
    plant.state.w_rad_s = w_rad_s
    d = max(0.0, min(u_v / inv.bus_voltage_v, 1.0))
    h = 1.0 / inv.pwm_frequency_hz
    sector = math.pi / 3 / (m.pole_pairs * max(w_rad_s, 1e-9))
    t = 0.0
    while t < max(10 * m.l_line_h / m.r_line_ohm, 2 * sector):
        plant.step(_legs_for(tab, plant.hall_code(), d), 0.0, h)
        t += h
    n = max(1, int(round(max(12, math.ceil(0.02 / sector)) * sector / h)))
    acc_t = acc_i = 0.0
    for _ in range(n):
        plant.step(_legs_for(tab, plant.hall_code(), d), 0.0, h)
        acc_t += plant.state.torque_e_n_m
        acc_i += plant.state.i_link_on_a
    return acc_i / n, acc_t / n


def identify(profile, plant_factory: Callable, *, speeds_rpm: Sequence[float] | None = None,
             current_fractions: Sequence[float] = (0.03, 0.1, 0.3, 0.6, 0.9),
             knee_fractions: Sequence[float] = (0.2, 0.12, 0.07, 0.04, 0.02, 0.01, 0.0, -0.005, -0.01, -0.02)
             ) -> AveragedModel:
    """Identify :class:`AveragedModel` from the three-phase plant (``plant_factory(profile, r_factor)``).

    Speeds: default 11 points from 3 % to 100 % of the step target (``profile.speed_step_rpm()``).
    At each, the voltages ``Kb w + f R I_lim`` for ``f`` in ``current_fractions`` that the bridge
    reaches (at least three: below the bridge's edge otherwise), the sector means fitted by least
    squares: ``i = (u - E)/R_e``, ``T = k_t i + T_0`` (the affine summary); then the knee: the
    voltages ``(1 - q) E`` for ``q`` in ``knee_fractions`` (below the counter voltage by up to 20 %,
    the span of the pair's EMF ripple inside a sector), where the current goes to zero in part of
    each sector (discontinuous conduction).  Every measured point goes into the speed's map
    (``AveragedModel.maps``)."""
    m, inv = profile.motor, profile.inverter
    top = profile.speed_step_rpm()
    if speeds_rpm is None:
        speeds_rpm = [top * f for f in (0.03, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)]
    ub = inv.bus_voltage_v * profile.max_duty()
    span = m.r_line_ohm * inv.current_limit_a
    pts, maps = [], []
    for rpm in speeds_rpm:
        w = rpm * RPM
        u0 = m.kb_v_s_per_rad * w
        us = np.array([u0 + f * span for f in current_fractions if u0 + f * span <= ub])
        if us.size < 3:                                   # at the bridge's edge: the last volts below it
            us = np.linspace(ub - 0.3 * span, ub, 3)
        data = [hold_sector_means(profile, plant_factory(profile, 1.0), w, float(u)) for u in us]
        ii = np.array([d[0] for d in data])
        tt = np.array([d[1] for d in data])
        g, c = np.polyfit(us, ii, 1)                    # i = g u + c
        res = ii - (g * us + c)
        kt, t0 = np.polyfit(ii, tt, 1)
        pts.append(SectorPoint(w_rad_s=w, r_e_ohm=1.0 / g, e_v=-c / g, kt_n_m_per_a=float(kt), t0_n_m=float(t0),
                               fit_rms_a=float(np.sqrt(np.mean(res ** 2)))))
        e = -c / g
        knee = [(1.0 - q) * e for q in knee_fractions if 0.0 < (1.0 - q) * e < us[0] - 1e-3 * span]
        data += [hold_sector_means(profile, plant_factory(profile, 1.0), w, float(u)) for u in knee]
        uu = np.concatenate([us, knee])
        order = np.argsort(uu)
        maps.append((w, uu[order], np.array([d[0] for d in data])[order], np.array([d[1] for d in data])[order]))
    return _build(profile, pts, maps)


#: identifications of this process, by the physical content they depend on (see :func:`identify_cached`)
_IDENTIFIED: dict[tuple, AveragedModel] = {}
_IDENTIFIED_MAX = 32


def identify_cached(profile, plant_factory: Callable) -> AveragedModel:
    """:func:`identify` with the default grid, remembered in this process.

    The key is what the identification depends on: the profile's motor, inverter, sensors and
    control sections (frozen dataclasses, compared by value: not the profile's name, design
    section or file) and the plant factory's function (module and qualified name).  The same
    physical drive designed again (another rule count, premise or option; a test's second design)
    then costs nothing; any change of a physical number identifies afresh.  At most
    ``_IDENTIFIED_MAX`` models are kept (oldest dropped)."""
    fn = getattr(plant_factory, "__func__", plant_factory)
    key = (repr((profile.motor, profile.inverter, profile.sensors, profile.control)),
           getattr(fn, "__module__", ""), getattr(fn, "__qualname__", repr(fn)))
    model = _IDENTIFIED.get(key)
    if model is None:
        model = identify(profile, plant_factory)
        if len(_IDENTIFIED) >= _IDENTIFIED_MAX:
            _IDENTIFIED.pop(next(iter(_IDENTIFIED)))
        _IDENTIFIED[key] = model
    return model


def open_loop_run(profile, plant, u_of_t: Callable[[float], float], t_end_s: float, load_n_m: float,
                  *, w0_rad_s: float = 0.0, u_cap: Callable[[float], float] | None = None) -> dict:
    """Free-running three-phase ``plant`` (twin interface, see :func:`hold_sector_means`) at voltage ``u(t)``
    through the hall table, under a constant load torque opposing the motion; every PWM period.
    ``u_cap(w)``: a speed-dependent ceiling on the voltage (V, at the present true speed w, rad/s).

    Returns arrays ``t`` (s), ``w`` (rad/s), ``i`` (sensed current, A)."""
    from ..commutation import hall_table
    m, inv, se = profile.motor, profile.inverter, profile.sensors
    tab = hall_table(se.hall_spacing_deg, se.hall_offset_deg, m.back_emf_shape).forward
    h = 1.0 / inv.pwm_frequency_hz
    n = int(round(t_end_s / h))
    plant.state.w_rad_s = w0_rad_s
    t = np.arange(1, n + 1) * h
    w = np.empty(n)
    i = np.empty(n)
    for k in range(n):
        u = u_of_t(k * h)
        if u_cap is not None:
            u = min(u, u_cap(plant.state.w_rad_s))
        d = max(0.0, min(u / inv.bus_voltage_v, 1.0))
        plant.step(_legs_for(tab, plant.hall_code(), d), load_n_m if plant.state.w_rad_s > 0.0 else 0.0, h)
        w[k] = plant.state.w_rad_s
        i[k] = plant.state.i_link_on_a
    return {"t": t, "w": w, "i": i}
