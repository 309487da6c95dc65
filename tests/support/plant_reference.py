"""Reference model of the twin's plant in scipy: the same equations as
``csrc/plant.c``, integrated in continuous time with event location.

Where the C plant takes fixed steps with the diode states implicit at the end
of each step (fast, for the firmware-in-the-loop twin), this model switches
between conduction modes exactly when a current reaches zero or an open
phase's terminal voltage reaches a rail, and integrates each mode with
``scipy.integrate.solve_ivp`` at tight tolerances.  The two are compared in
``tests/test_plant.py`` on the same inputs.

Also here: the ideal six-step commutation table of a plant (the switch pair
that gives the largest torque in each hall sector), used as an open-loop
driver in the cross-checks.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from scipy.integrate import solve_ivp

from picdrive_hil.plant import PlantModel

TWO_PI = 2.0 * math.pi


def emf_shape(model: PlantModel, th_e):
    """Per-unit back-EMF of phase A at electrical angle th_e (numpy-friendly)."""
    th_e = np.asarray(th_e, dtype=float)
    if model.emf_shape == "sinusoidal":
        return np.sin(th_e)
    t = np.mod(th_e + math.pi / 6, TWO_PI)
    return np.select(
        [t < math.pi / 3, t < math.pi, t < 4 * math.pi / 3],
        [(t - math.pi / 6) / (math.pi / 6), 1.0, 1.0 - (t - math.pi) / (math.pi / 6)],
        -1.0)


def shapes(model: PlantModel, th_e: float) -> np.ndarray:
    return np.array([float(emf_shape(model, th_e - k * TWO_PI / 3)) for k in range(3)])


def hall_code(model: PlantModel, theta_mech: float) -> int:
    th_e = model.pole_pairs * theta_mech
    code = 0
    off, sp = math.radians(model.hall_offset_deg), math.radians(model.hall_spacing_deg)
    for k in range(3):
        if math.fmod(math.fmod(th_e - off - k * sp, TWO_PI) + TWO_PI, TWO_PI) < math.pi:
            code |= 1 << k
    return code


def ideal_commutation_table(model: PlantModel, direction: int = 1) -> dict[int, tuple[int, int]]:
    """hall code -> (phase switched to +bus, phase switched to -bus) with the
    largest mean torque over the hall sector (direction -1: largest negative)."""
    table: dict[int, tuple[int, int]] = {}
    th = np.linspace(0, TWO_PI, 3601)[:-1] / model.pole_pairs
    codes = np.array([hall_code(model, x) for x in th])
    th_e = model.pole_pairs * th
    f = np.stack([emf_shape(model, th_e - k * TWO_PI / 3) for k in range(3)])
    for code in np.unique(codes):
        sel = codes == code
        best, pair = -np.inf, None
        for hi, lo in itertools.permutations(range(3), 2):
            tq = direction * float(np.mean(f[hi, sel] - f[lo, sel]))
            if tq > best:
                best, pair = tq, (hi, lo)
        table[int(code)] = pair
    return table


def sixstep_legs(table: dict[int, tuple[int, int]], duty: float, dead_time_frac: float = 0.0,
                 complementary: bool = False) -> Callable[[int], list[tuple[float, float]]]:
    """Leg fractions for a hall code: high-side PWM on the '+' phase, low side
    on for the '-' phase, the third phase off (floating).  With complementary
    the '+' leg's low switch takes the off time, less the dead time."""
    def legs(code: int):
        out = [(0.0, 0.0)] * 3
        if code not in table:
            return out
        hi, lo = table[code]
        if complementary:
            fh = max(0.0, duty - dead_time_frac) if duty < 1 else 1.0
            fl = max(0.0, 1.0 - duty - dead_time_frac) if duty > 0 else 1.0
            out[hi] = (fh, fl)
        else:
            out[hi] = (duty, 0.0)
        out[lo] = (0.0, 1.0)
        return out
    return legs


@dataclass
class RefResult:
    t: np.ndarray
    i_abc: np.ndarray          # (3, n)
    w: np.ndarray
    theta: np.ndarray
    n_events: int


def simulate_reference(model: PlantModel, legs_of_code: Callable[[int], Sequence[tuple[float, float]]],
                       t_end: float, t_eval: np.ndarray, *, load: Callable[[float], float] = lambda t: 0.0,
                       load_breaks: Sequence[float] = (), w0: float = 0.0, theta0: float = 0.0,
                       rtol: float = 1e-9, atol: float = 1e-9, max_events: int = 200000) -> RefResult:
    """Integrate the plant from rest (or w0, theta0) to t_end with the legs
    chosen from the hall code (an open-loop commutator).  Active load."""
    if model.load_mode != "active":
        raise ValueError("the reference integrates the active-load equations; pass a model with load_mode='active'")
    R, L, lam, P = model.r_phase_ohm, model.l_phase_h, model.lambda_m_v_s, model.pole_pairs
    J, B, vbus, vd = model.inertia_kg_m2, model.friction_n_m_s, model.bus_voltage_v, model.diode_drop_v
    off = math.radians(model.hall_offset_deg)

    def rails(code):
        vp, vm = np.zeros(3), np.zeros(3)
        for x, (fh, fl) in enumerate(legs_of_code(code)):
            fo = max(0.0, 1.0 - fh - fl)
            vp[x] = vbus * fh - vd * fo
            vm[x] = vbus * (1.0 - fl) + vd * fo
        return vp, vm

    def node_voltages(sign, vp, vm):
        return np.where(sign > 0, vp, np.where(sign < 0, vm, 0.0))

    def neutral(sign, v, e):
        S = sign != 0
        return float(np.sum((v - e)[S]) / S.sum()) if S.sum() >= 2 else 0.0

    def choose_mode(i, w, th, code):
        """Signs of the legs: fixed by the current where it is nonzero; for zero
        currents, the consistent pattern (complementarity)."""
        vp, vm = rails(code)
        e = lam * P * w * shapes(model, P * th)
        fixed = np.sign(i)
        free = [x for x in range(3) if fixed[x] == 0]
        cands = []
        for pat in itertools.product((1, -1, 0), repeat=len(free)):
            s = fixed.copy()
            for x, v in zip(free, pat):
                s[x] = v
            n = int(np.count_nonzero(s))
            if n == 1:
                continue
            v = node_voltages(s, vp, vm)
            vn = neutral(s, v, e) if n >= 2 else 0.0
            ok = True
            for x in free:
                if s[x] != 0:
                    di = v[x] - vn - e[x] - R * i[x]
                    ok &= di * s[x] > 0
                else:
                    voc = vn + e[x]
                    ok &= (vp[x] - 1e-9 <= voc <= vm[x] + 1e-9) if n >= 2 else True
            if n == 0:
                # all open: consistent if no pair would start conducting
                for a, b in itertools.permutations(range(3), 2):
                    if vp[a] - vm[b] > e[a] - e[b] + 1e-9:
                        ok = False
            if ok:
                cands.append((len([1 for x in free if s[x] != 0]), s))
        if not cands:
            raise RuntimeError(f"no consistent conduction mode at i={i}, w={w}")
        cands.sort(key=lambda c: c[0])
        return cands[0][1]

    def rhs_factory(sign, code):
        vp, vm = rails(code)
        v = node_voltages(sign, vp, vm)
        S = sign != 0

        def rhs(t, y):
            i, w, th = y[:3], y[3], y[4]
            f = shapes(model, P * th)
            e = lam * P * w * f
            di = np.zeros(3)
            if S.sum() >= 2:
                vn = float(np.sum((v - e)[S]) / S.sum())
                di[S] = (v[S] - vn - e[S] - R * i[S]) / L
            te = P * lam * float(f @ i)
            return [di[0], di[1], di[2], (te - B * w - load(t)) / J, w]
        return rhs, v

    def events_factory(sign, code, rhs, v):
        vp, vm = rails(code)
        S = sign != 0
        evs = []

        def hall_ev(t, y):
            return math.sin(3.0 * (P * y[4] - off))
        hall_ev.terminal = True
        evs.append(hall_ev)
        for x in range(3):
            if sign[x] != 0:
                def zc(t, y, x=x):
                    return y[x]
                zc.terminal = True
                zc.direction = -sign[x]
                zc.leg = x
                evs.append(zc)
            elif S.sum() >= 2:
                def rail_lo(t, y, x=x):
                    e = lam * P * y[3] * shapes(model, P * y[4])
                    vn = float(np.sum((v - e)[S]) / S.sum())
                    return vn + e[x] - vp[x]
                rail_lo.terminal = True
                rail_lo.direction = -1
                def rail_hi(t, y, x=x):
                    e = lam * P * y[3] * shapes(model, P * y[4])
                    vn = float(np.sum((v - e)[S]) / S.sum())
                    return vm[x] - (vn + e[x])
                rail_hi.terminal = True
                rail_hi.direction = -1
                evs += [rail_lo, rail_hi]
        if S.sum() == 0:
            # all open: a pair starts conducting when its EMF difference reaches the rails
            for a, b in itertools.permutations(range(3), 2):
                def pair(t, y, a=a, b=b):
                    e = lam * P * y[3] * shapes(model, P * y[4])
                    return (e[a] - e[b]) - (vp[a] - vm[b])
                pair.terminal = True
                pair.direction = -1
                evs.append(pair)
        return evs

    y = np.array([0.0, 0.0, 0.0, w0, theta0])
    t = 0.0
    # A lone nonzero phase current is impossible in a wye winding (the three sum to zero):
    # after a pair's zero-crossing event it is the event location's residue.  The event
    # is located to ~rtol of the step, which leaves up to a few uA; 1e-4 A is far below
    # any conducting current of the bundled motors and still catches a real inconsistency.
    i_tol = 1e-4
    breaks = sorted(b for b in load_breaks if 0 < b < t_end) + [t_end]
    ts, ys = [], []
    n_ev = 0
    eps_t = 1e-10
    while t < t_end - 1e-15:
        if n_ev > max_events:
            raise RuntimeError("reference: too many events")
        # hall code just ahead in the direction of motion (robust at an edge)
        ahead = y[4] + math.copysign(1e-9, y[3] if y[3] != 0 else 1.0)
        code = hall_code(model, ahead)
        nz = np.nonzero(y[:3])[0]
        if nz.size == 1 and abs(y[nz[0]]) < i_tol:     # residue of a pair's zero crossing
            y[:3] = 0.0
        sign = choose_mode(y[:3], y[3], y[4], code)
        for x in range(3):
            if sign[x] == 0:
                y[x] = 0.0
        rhs, v = rhs_factory(sign, code)
        evs = events_factory(sign, code, rhs, v)
        zc_leg = {k: ev.leg for k, ev in enumerate(evs) if hasattr(ev, "leg")}
        t_stop = next(b for b in breaks if b > t + 1e-15)
        sel = t_eval[(t_eval >= t) & (t_eval <= t_stop)]
        sol = solve_ivp(rhs, (t, t_stop), y, method="RK45", rtol=rtol, atol=atol, events=evs,
                        dense_output=True, max_step=2e-4)
        t1 = float(sol.t[-1])
        keep = sel[sel <= t1]
        if keep.size:
            ts.append(keep)
            ys.append(sol.sol(keep))
        y = sol.y[:, -1].copy()
        if sol.status == 1:
            n_ev += 1
            # step just past the event so it is not found again at the restart
            dy = np.asarray(rhs(t1, y))
            y = y + eps_t * dy
            t = t1 + eps_t
            fired = {k for k, te_ in enumerate(sol.t_events) if len(te_)}
            for k in fired:
                x = zc_leg.get(k)
                if x is not None:
                    y[x] = 0.0
            for x in range(3):
                if sign[x] != 0 and y[x] * sign[x] <= 0:
                    y[x] = 0.0
        else:
            t = t1
    T = np.concatenate(ts) if ts else np.array([])
    Y = np.concatenate(ys, axis=1) if ys else np.zeros((5, 0))
    # t_eval points shared by two segments appear twice: keep the first
    _, idx = np.unique(T, return_index=True)
    T, Y = T[idx], Y[:, idx]
    return RefResult(T, Y[:3], Y[3], Y[4], n_ev)
