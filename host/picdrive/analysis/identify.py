"""Motor identification: the fits that turn bench measurements into motor values.

Plain functions over measured data (no board access: :mod:`picdrive.console.identify` drives
the board and calls these).  Conventions are :mod:`picdrive.commutation`'s: electrical angle
``th`` with phase A's back-EMF rising through zero at 0; identification vector ``m`` (0..11)
a current at ``-30 + 30 m`` degrees, which holds a free rotor at ``th = 150 + 30 m``.

Every value comes as a :class:`Measured`: the value, its standard uncertainty (same unit) and
how it was obtained.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..commutation import (IDENT_HALL_SELECTIONS, IDENT_VECTORS, emf_unit, hall_code_at, hall_table,
                           ident_hall_vector, ident_vector_angle_deg)

__all__ = ["Measured", "HallFit", "lock_angle_deg", "fit_halls", "fit_encoder", "hall_selection",
           "commutation_factor", "fit_resistance", "fit_time_constant", "fit_back_emf", "fit_friction",
           "inertia_from_transient", "torque_factor", "fit_coast"]


@dataclass(frozen=True)
class Measured:
    """One identified value: ``value`` and its standard uncertainty ``sigma`` (same unit), and
    ``how`` it was measured (one sentence)."""
    value: float
    sigma: float
    how: str

    @property
    def rel(self) -> float:
        """Relative uncertainty (sigma / |value|; inf for a zero value)."""
        return self.sigma / abs(self.value) if self.value else math.inf


def lock_angle_deg(m: int) -> float:
    """Electrical angle (deg, 0..360) a free rotor settles at under identification vector m."""
    return (ident_vector_angle_deg(m) + 180.0) % 360.0


@dataclass(frozen=True)
class HallFit:
    """The hall sensors as the locked-rotor sweep saw them.

    ``codes[m]``: the code read with the rotor held by vector m; ``offset``: hall A's rising edge
    after phase A's back-EMF zero crossing (deg), in the profile's convention; ``interval``: the
    offsets consistent with every lock (deg, lo..hi); ``table``: the six-step table the offset
    gives (:func:`picdrive.commutation.hall_table`)."""
    spacing_deg: int
    codes: tuple[int, ...]
    offset: Measured
    interval: tuple[float, float]
    snapped: bool

    @property
    def table(self):
        return hall_table(self.spacing_deg, self.offset.value)


def _codes_over_offsets(th_deg: float, spacing_deg: int, offsets: np.ndarray) -> np.ndarray:
    """The hall code at one angle for each candidate offset (hall_code_at over offsets)."""
    return np.array([int(hall_code_at(th_deg, spacing_deg, float(o))) for o in offsets])


def fit_halls(codes, spacing_deg: int, *, edge_tol_deg: float = 3.0, snap_deg: float = 30.0):
    """The hall offset from the codes seen at the twelve locks.

    Parameters
    ----------
    codes : sequence of int
        ``codes[m]`` for m = 0..11.
    spacing_deg : int
        The sensors' spacing (60 or 120), from the profile.
    edge_tol_deg : float
        A lock this close to a hall edge may read either side's code (the rotor settles within
        this of its lock angle).
    snap_deg : float
        Hall sensors sit at multiples of this in practice: an offset interval that holds exactly
        one multiple gives that multiple (``snapped``); else the interval's middle.

    Returns
    -------
    HallFit or None
        None when no offset in the profile's convention reproduces the codes (the sensors are
        wired in the other order relative to the phases).
    """
    codes = [int(c) for c in codes]
    grid = np.arange(-180.0, 180.0, 0.25)
    ok = np.ones(grid.shape, dtype=bool)
    for m, c in enumerate(codes):
        th = lock_angle_deg(m)
        want = _codes_over_offsets(th, spacing_deg, grid)
        # near an edge either neighbour's code is accepted
        lo = _codes_over_offsets(th - edge_tol_deg, spacing_deg, grid)
        hi = _codes_over_offsets(th + edge_tol_deg, spacing_deg, grid)
        ok &= (want == c) | (lo == c) | (hi == c)
    if not ok.any():
        return None
    # the feasible offsets form one arc (mod 360); unwrap it around its first point
    idx = np.flatnonzero(ok)
    vals = grid[idx]
    ref = vals[0]
    rel = np.mod(vals - ref + 180.0, 360.0) - 180.0
    lo, hi = ref + rel.min(), ref + rel.max()
    if hi - lo > 120.0:
        return None
    k = np.arange(math.ceil(lo / snap_deg), math.floor(hi / snap_deg) + 1) * snap_deg
    half = 0.5 * (hi - lo) + 0.25
    if len(k) == 1:
        off = float(k[0])
        snapped = True
        how = (f"locked rotor at the twelve vectors: offsets {lo:.1f} .. {hi:.1f} deg fit every lock; "
               f"the one multiple of {snap_deg:g} deg among them")
    else:
        off = 0.5 * (lo + hi)
        snapped = False
        how = f"locked rotor at the twelve vectors: middle of the offsets {lo:.1f} .. {hi:.1f} deg that fit every lock"
    off = (off + 180.0) % 360.0 - 180.0
    return HallFit(spacing_deg=spacing_deg, codes=tuple(codes),
                   offset=Measured(off, half / math.sqrt(3.0), how), interval=(float(lo), float(hi)),
                   snapped=snapped)


def fit_encoder(positions, pole_pairs: int, modulus: int = 65536):
    """Encoder counts per electrical turn, lines and direction from the lock positions.

    Parameters
    ----------
    positions : sequence of int
        The 16-bit position counter at locks m = 0, 1, ..., 12 (the last one back at vector 0
        after a full forward electrical turn).
    pole_pairs : int
        From the profile.
    modulus : int
        Where the position counter wraps: the firmware's quadrature counter resets at 4 x its
        build's encoder lines (65536 for a free-running 16-bit count).

    Returns
    -------
    dict
        ``counts_per_turn`` (signed, counts per electrical turn; negative: the encoder counts
        down while the field turns forward), ``lines`` (Measured, lines per mechanical turn,
        quadrature x4), ``steps`` (the 12 signed step sizes, counts).
    """
    p = np.asarray(positions, dtype=np.int64)
    half = modulus // 2
    steps = ((np.diff(p) + half) % modulus) - half
    total = int(steps.sum())
    lines = abs(total) * pole_pairs / 4.0
    # each lock's angle scatters by about the steps' spread / sqrt 2; the turn is the difference of two
    spread = float(np.std(steps)) if len(steps) > 1 else 0.0
    sigma = max(0.5, spread * pole_pairs / 4.0)
    return {"counts_per_turn": total, "steps": steps.tolist(),
            "lines": Measured(lines, sigma, f"encoder counts over one forward electrical turn of the locked "
                                            f"vector ({total} counts) x pole_pairs {pole_pairs} / 4 (quadrature)")}


def _lock_centres(codes) -> dict[int, float]:
    """Each code's mean lock position, in units of 30 electrical degrees (circular mean)."""
    out = {}
    for c in set(codes):
        ms = [m for m, x in enumerate(codes) if x == c]
        z = sum(complex(math.cos(math.radians(30 * m)), math.sin(math.radians(30 * m))) for m in ms)
        out[c] = math.degrees(math.atan2(z.imag, z.real)) / 30.0
    return out


def hall_selection(codes, spacing_deg: int, direction: int = 1) -> tuple[int, float]:
    """The hall-driven identification selection that turns the rotor in ``direction`` (+1: the
    field's forward), and its mean torque per unit (1 = the current always 90 deg ahead).

    The torque of vector m on a rotor held at lock m_r is proportional to sin(30 (m - m_r) deg);
    the selection whose vectors do best over the codes seen wins (ties: the more advanced)."""
    centres = _lock_centres(codes)
    best = None
    for sel in range(IDENT_HALL_SELECTIONS):
        score, lead = 0.0, 0.0
        for c, mr in centres.items():
            m = ident_hall_vector(sel, c, spacing_deg)
            if m is None:
                score = -math.inf
                break
            a = math.radians(30.0 * (m - mr))
            score += direction * math.sin(a)
            lead += math.remainder(a, 2 * math.pi) * direction
        key = (round(score, 6), lead)
        if best is None or key > best[0]:
            best = (key, sel)
    return best[1], best[0][0] / max(len(centres), 1)


def commutation_factor(sel: int, spacing_deg: int, offset_deg: float, shape: str) -> float:
    """Mean back-EMF of the energised phase pair under hall-driven selection ``sel``, per unit of
    the ideal six-step's (1.0 when the selection commutates at the ideal points).

    The DC-equivalent relations ``V = R I + Kb w`` and ``T = Kt I`` hold with ``Kb g`` and
    ``Kt g`` when the commutation is shifted from the ideal points (a 30-degree shift of a
    trapezoid: g = 0.875)."""
    e, ideal = _pair_emf(sel, spacing_deg, offset_deg, shape, 7200)
    return float(e.mean()) / ideal


def _pair_emf(sel: int, spacing_deg: int, offset_deg: float, shape: str, n: int) -> tuple[np.ndarray, float]:
    """Back-EMF of the phase pair hall-driven selection ``sel`` energises, per unit of the phase
    EMF's peak, at ``n`` electrical angles over a turn (0 where the selection energises nothing),
    and the ideal six-step's mean of it."""
    th = (np.arange(n) + 0.5) * (360.0 / n)
    codes = hall_code_at(th, spacing_deg, offset_deg)
    f = [emf_unit(shape, np.radians(th) - k * 2 * math.pi / 3) for k in range(3)]
    e = np.zeros(n)
    for c in set(codes.tolist()):
        m = ident_hall_vector(sel, int(c), spacing_deg)
        if m is None:
            continue
        (src,), (snk,) = IDENT_VECTORS[m]
        s = codes == c
        e[s] = f[src][s] - f[snk][s]
    return e, (2.0 if shape != "sinusoidal" else 3.0 * math.sqrt(3.0) / math.pi)


def _linfit(x, y):
    """Least squares y = a x + c with the standard errors of a and c."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    A = np.vstack([x, np.ones_like(x)]).T
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    res = y - A @ coef
    dof = max(len(x) - 2, 1)
    s2 = float(res @ res) / dof
    cov = s2 * np.linalg.inv(A.T @ A)
    return float(coef[0]), float(coef[1]), math.sqrt(max(cov[0, 0], 0.0)), math.sqrt(max(cov[1, 1], 0.0))


def fit_resistance(duty, current, bus_v: float, lsb_a: float) -> tuple[Measured, Measured]:
    """Line-to-line resistance and the freewheel drop from locked-rotor currents at several duties.

    With the source's high side switching at duty d and the sink's low side on, the winding sees
    ``d (Vbus + Vd) - Vd`` on average (Vd: the drop of the diode the current freewheels through
    while the high side is off, plus switch drops), so ``I = a d + c`` with ``a = (Vbus + Vd)/R``
    and ``c = -Vd/R``: ``R = Vbus / (a + c)``, ``Vd = -c R``.  The bridge's dead time does not
    act in the override (independent) mode the firmware drives, so the duty needs no correction
    for it.

    Returns
    -------
    (Measured, Measured)
        R line-to-line (ohm) and Vd (V)."""
    d = np.asarray(duty, float)
    i = np.asarray(current, float)
    a, c, sa, sc = _linfit(d, i)
    g = a + c
    r = bus_v / g
    # the current's quantisation (lsb / sqrt 12 per mean) adds to the fit's scatter
    sq = lsb_a / math.sqrt(12.0) / max(float(np.ptp(d)), 1e-9)
    sg = math.hypot(math.hypot(sa, sc), sq)
    sr = r * sg / abs(g)
    vd = -c * r
    how = (f"locked rotor, two-phase vector, {len(d)} duties {d.min():.3f} .. {d.max():.3f}: "
           f"I = a d + c, R = Vbus / (a + c) with Vbus = {bus_v:g} V; line-to-line (two phases in series)")
    return (Measured(r, sr, how),
            Measured(vd, abs(r) * math.hypot(sc, lsb_a / math.sqrt(12.0)),
                     "freewheel diode and switch drop from the intercept (-c R)"))


def fit_time_constant(t_s, current, i_final: float, lsb_a: float, *, min_points: int = 2):
    """Electrical time constant from a locked-rotor current step sampled at the speed-loop rate.

    The samples after the first one showing current are on ``i_final (1 - exp(-t/tau))``;
    the ratios of the successive residuals ``i_final - i`` give tau without knowing when within
    the first sample period the vector was applied.  Residuals under 4 LSB are not used.

    Returns
    -------
    Measured or None
        tau (s); None when fewer than ``min_points`` residuals are usable (tau well under the
        sample period)."""
    t = np.asarray(t_s, float)
    i = np.asarray(current, float)
    on = np.flatnonzero(i > 1.5 * lsb_a)
    if len(on) == 0:
        return None
    k0 = on[0]
    r = i_final - i[k0:]
    tt = t[k0:] - t[k0]
    use = r > 4.0 * lsb_a
    # only the first run of usable residuals (later ones are noise near the plateau)
    n = 0
    while n < len(use) and use[n]:
        n += 1
    if n < min_points:
        return None
    y = np.log(r[:n])
    x = tt[:n]
    if n == 2:
        slope = (y[1] - y[0]) / (x[1] - x[0])
        sy = math.hypot(lsb_a / r[0], lsb_a / r[1]) / math.sqrt(12.0)
        ss = sy / (x[1] - x[0])
    else:
        slope, _, ss, _ = _linfit(x, y)
        sy = math.sqrt(sum((lsb_a / r[k]) ** 2 for k in range(n)) / n) / math.sqrt(12.0)
        ss = math.hypot(ss, sy / max(float(np.ptp(x)), 1e-12))
    if slope >= 0:
        return None
    tau = -1.0 / slope
    # the first sample showing current comes at most one period after the step: a larger share of the
    # final current than one period of this tau allows means the residuals are not the step's
    dt = float(t[1] - t[0])
    if i[k0] > i_final * (1.0 - math.exp(-dt / tau)) * 1.15 + 2.0 * lsb_a:
        return None
    return Measured(tau, tau * ss / abs(slope),
                    f"locked-rotor current step sampled at {1.0 / (t[1] - t[0]):.0f} Hz: log-linear fit of "
                    f"the {n} residuals over 4 LSB")


def fit_back_emf(volts, current, speed_rad_s, r_ohm: Measured, g: float) -> Measured:
    """Kb (V s/rad, six-step DC equivalent) from steady spins: ``V - R I = g Kb w``.

    ``volts``: the pair's mean voltage ``d (Vbus + Vd) - Vd`` at each spin; ``g``: the
    commutation factor of the hall-driven selection (:func:`commutation_factor`).  The winding's
    commutation lag makes ``(V - R I) / (g w)`` grow with the speed; with three or more spins
    that is fitted as a line in ``w`` and Kb taken at ``w = 0``, with two the mean ratio."""
    v = np.asarray(volts, float)
    i = np.asarray(current, float)
    w = np.asarray(speed_rad_s, float)
    k = (v - r_ohm.value * i) / (g * w)
    s_r = r_ohm.sigma * float(np.mean(np.abs(i) / w)) / g
    if len(w) >= 3:
        a, c, sa, sc = _linfit(w, k)
        return Measured(c, math.hypot(sc, s_r),
                        f"steady hall-driven spins at {len(w)} speeds ({w.min():.0f} .. {w.max():.0f} rad/s): "
                        f"(V - R I) / (g w) extrapolated to w = 0 (slope {a:.3g} per rad/s), commutation factor "
                        f"g = {g:.4f}")
    return Measured(float(k.mean()), math.hypot(float(np.ptp(k)) / 2, s_r),
                    f"steady hall-driven spins at {len(w)} speeds: mean of (V - R I) / (g w), g = {g:.4f}")


def fit_friction(torque_n_m, speed_rad_s, sigma_t: float) -> tuple[Measured, Measured]:
    """Viscous and Coulomb friction from the steady torques: ``T = B w + Tc``."""
    b, tc, sb, stc = _linfit(speed_rad_s, torque_n_m)
    w = np.asarray(speed_rad_s, float)
    sq = sigma_t / max(float(np.ptp(w)), 1e-9)
    return (Measured(b, math.hypot(sb, sq), f"steady torque Kt g I at {len(w)} speeds: slope of T = B w + Tc"),
            Measured(tc, math.hypot(stc, sigma_t), "steady torque: intercept of T = B w + Tc"))


def inertia_from_transient(t_s, speed_rad_s, torque_n_m, b: float, tc: float) -> Measured | None:
    """J from a speed transient: ``J (w_end - w_0) = integral of (T - B w - Tc sign w) dt``
    (T = 0 for a coast-down).  None when the speed changed too little to say."""
    t = np.asarray(t_s, float)
    w = np.asarray(speed_rad_s, float)
    tq = np.asarray(torque_n_m, float) if torque_n_m is not None else np.zeros_like(w)
    if len(t) < 5:
        return None
    # mean of the first and last few samples: the speed signal's quantisation averaged
    k = max(2, len(t) // 20)
    dw = float(w[-k:].mean() - w[:k].mean())
    net = tq - b * w - tc * np.sign(w)
    ta, tb = t[:k].mean(), t[-k:].mean()
    sel = (t >= ta) & (t <= tb)
    integral = float(np.trapezoid(net[sel], t[sel]))
    if abs(dw) < 1e-9 or integral == 0.0:
        return None
    j = integral / dw
    if j <= 0:
        return None
    sw = float(np.std(np.diff(w))) / math.sqrt(k)
    return Measured(j, j * abs(sw / dw), f"speed transient {w[:k].mean():.0f} -> {w[-k:].mean():.0f} rad/s "
                                        f"over {tb - ta:.2f} s: J = integral (T - B w - Tc) dt / dw")


def torque_factor(v_pair: float, r_ohm: float, l_h: float, kb: float, w_rad_s: float, sel: int,
                  spacing_deg: int, offset_deg: float, shape: str, pole_pairs: int) -> float:
    """Mean torque per unit of ``Kb x mean current`` of a hall-driven spin (1 for flat current
    under ideal commutation).

    Under a shifted commutation the pair's current is not flat: it is larger where the back-EMF
    is low, so the torque per mean ampere falls below the EMF's commutation factor.  The pair
    circuit ``L di/dt = v_pair - R i - e_pair(th)`` (line-to-line R, L; current held at or above
    zero by the freewheel diodes; commutation taken as instantaneous) is integrated over
    electrical turns at the steady speed until periodic, and ``mean(e_pair i) / (w Kb mean(i))``
    returned."""
    n = 720
    e, ideal = _pair_emf(sel, spacing_deg, offset_deg, shape, n)
    ep = e / ideal * kb * w_rad_s
    we = abs(w_rad_s) * pole_pairs
    if we <= 0 or l_h <= 0:
        i = np.maximum((v_pair - ep) / r_ohm, 0.0)
    else:
        dt = math.radians(360.0 / n) / we
        a = math.exp(-dt * r_ohm / l_h)
        i = np.zeros(n)
        x = max(v_pair - float(ep.mean()), 0.0) / r_ohm
        for _ in range(40):
            x0 = x
            for k in range(n):
                x = max((v_pair - ep[k]) / r_ohm + (x - (v_pair - ep[k]) / r_ohm) * a, 0.0)
                i[k] = x
            if abs(x - x0) <= 1e-9 * max(abs(x), 1e-12):
                break
    im = float(i.mean())
    if im <= 0:
        return 1.0
    return float((ep * i).mean()) / (kb * w_rad_s * im)


def fit_coast(t_s, speed_rad_s, b_viscous: Measured):
    """Coast-down with the outputs off: ``J dw/dt = -B w - Tc`` gives
    ``w(t) = (w0 + c) exp(-t / tau) - c`` with ``tau = J / B`` and ``c = Tc / B``; with B from the
    steady spins, ``J = B tau`` and ``Tc = B c``.  Only the part above 5 % of the first speed is
    fitted.  None when the speed fell by less than a quarter (tau and c not separable).

    Returns
    -------
    (Measured, Measured) or None
        J (kg m^2) and Tc (N m)."""
    from scipy.optimize import curve_fit
    t = np.asarray(t_s, float)
    w = np.asarray(speed_rad_s, float)
    if len(t) < 20:
        return None
    w0 = float(np.mean(w[:5]))
    keep = w > 0.05 * w0
    # from the first sample that is clearly falling (the outputs went off a little after recording began)
    t, w = t[keep], w[keep]
    if len(t) < 20 or w[-1] > 0.75 * w0:
        return None
    t = t - t[0]

    def model(x, a, tau, c):
        return a * np.exp(-x / tau) - c
    tau0 = float(t[-1]) / max(math.log(w0 / max(w[-1], 1e-9)), 0.1)
    try:
        p, cov = curve_fit(model, t, w, p0=(w0, tau0, 0.0), maxfev=5000)
    except (RuntimeError, ValueError):
        return None
    a, tau, c = (float(x) for x in p)
    if not (tau > 0 and np.all(np.isfinite(cov))):
        return None
    s_tau, s_c = math.sqrt(max(cov[1, 1], 0.0)), math.sqrt(max(cov[2, 2], 0.0))
    j = b_viscous.value * tau
    sj = j * math.hypot(b_viscous.rel, s_tau / tau)
    tc = b_viscous.value * c
    stc = math.hypot(b_viscous.sigma * abs(c), b_viscous.value * s_c)
    how = (f"coast-down {w0:.0f} -> {w[-1]:.0f} rad/s: w(t) = (w0 + c) exp(-t/tau) - c fitted, tau = "
           f"{tau:.4g} s, J = B tau")
    return Measured(j, sj, how), Measured(tc, stc, how + ", Tc = B c")
