"""Fixed-point plan of the firmware and a bit-exact Python model of its arithmetic.

The firmware runs :mod:`picdrive.control_law` (the float reference) in
integers.  :func:`plan_fixed_point` chooses every Q format from the design's
numbers with headroom, quantises every coefficient and reports its error,
and refuses what cannot be represented.  The functions below the plan are the
Python model of the C in ``firmware_templates/drive_core.c.j2``: :func:`law_step`
and :func:`core_control` and :func:`speed_hall` are compiled from the programs of
:mod:`picdrive.firmware.core_program` (which also render the C of ``core_law``,
``core_control``, ``core_speed_hall`` and the PIC18 assembly of the first two);
:func:`speed_encoder` and :func:`duty_counts` follow the C operation for operation.
The tests run model and C on the same random vectors and require 0 LSB
difference (the gcc/ctypes harness is tests/support/core_c.py; the fixed-point
loop against the float law, tests/support/fixed_loop.py).

Formats (``Q n`` = integer with LSB 2^-n of the unit):

======================  =======  ======================================================
quantity                type     format
======================  =======  ======================================================
speed, setpoint, premise int16   Q ``qs`` rad/s (mechanical)
output u, limits, P, D   int16 / int32  Q ``qu`` V
integrator               int32   Q ``qi`` = ``qu`` + 16 V (less when +-I_lim needs it)
current                  int16   ADC counts (10 bit, 5 V reference), signed by direction
kp                       int16   Q ``q_kp`` V/(rad/s)
ki Ts                    int16   Q ``q_kits`` V/(rad/s)  (ki times the sample time)
kd / Ts                  int16   Q ``q_kdts`` V/(rad/s)  (kd over the sample time)
kc                       int16   Q ``q_kc`` V per ADC count
setpoint weight b        int16   Q14 (0 .. 2)
D filter coefficient     uint16  Q15, ``Ts / (Ts + 1/(2 pi f))``
memberships              int16   Q12 (4096 = 1)
======================  =======  ======================================================

Arithmetic rules (both in C and here): products of two 16-bit values are
formed in 32 bits; right shifts are floor divisions by powers of two
(``asr32``: correct for negative numbers without relying on
implementation-defined ``>>``); left shifts saturate; 32-bit sums saturate;
16-bit results saturate.  Gain Q formats leave a factor 2 of headroom above
the largest design gain so that gains can be raised at run time.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from ..board import FCY_HZ
from ..errors import PicdriveError
from ..profile import bus_guard
from . import core_program
from .core_layout import CORE_LAW, CORE_PARAMS, CORE_STATE, MU_ONE, model_class

__all__ = ["FixedPointError", "Coef", "FixedPointPlan", "plan_fixed_point", "ParamSpec",
           "param_specs", "signal_specs", "law_parameters", "INT16_MIN", "INT16_MAX", "INT32_MIN", "INT32_MAX",
           "sat16", "sat32", "asr32", "shl_sat32", "shift32", "mul_q15", "premise_k",
           "law_step", "LawState", "LawParams", "speed_encoder", "t2_ticks", "speed_hall", "duty_counts",
           "CoreState", "core_control", "core_reset", "law_params_from_plan", "reference_ff"]

INT16_MIN, INT16_MAX = -32768, 32767
INT32_MIN, INT32_MAX = -(1 << 31), (1 << 31) - 1
ADC_COUNTS = 1024          # 10-bit converter, code = Vin / Vref * 1024
ADC_VREF_V = 5.0
REL_ERR_LIMIT = 0.01       # largest accepted quantisation error of a coefficient
GAIN_HEADROOM = 2.0
MT_K_MIN = 65538           # smallest M/T speed constant whose CORE_MT_DMAX = (2^32 - 1) // K is <= 65534


class FixedPointError(PicdriveError, ValueError):
    """A coefficient or range cannot be represented in the firmware's formats."""


# ---------------------------------------------------------------------------
# Integer primitives (mirror of the C helpers in drive_core.c)
# ---------------------------------------------------------------------------
def sat16(x: int) -> int:
    return INT16_MIN if x < INT16_MIN else INT16_MAX if x > INT16_MAX else x


def sat32(x: int) -> int:
    return INT32_MIN if x < INT32_MIN else INT32_MAX if x > INT32_MAX else x


def asr32(x: int, n: int) -> int:
    """floor(x / 2^n)."""
    return x >> n


def shl_sat32(x: int, n: int) -> int:
    return sat32(x << n)


def shift32(x: int, s: int) -> int:
    """x * 2^-s: floor right shift for s >= 0, saturating left shift for s < 0."""
    return asr32(x, s) if s >= 0 else shl_sat32(x, -s)


def mul_q15(x: int, a: int) -> int:
    """floor(x * a / 2^15) for int32 x and 0 <= a <= 32768."""
    return (x * a) >> 15


def premise_k(n1: int, n2: int, n_rules: int, mu_sh: int) -> int:
    """Membership slope: ((r - 1) << (12 + mu_sh)) / (n2 - n1), truncated, at most 65535."""
    if n_rules <= 1:
        return 0
    span = n2 - n1
    if span <= 0:
        return 0xFFFF
    k = ((n_rules - 1) << (12 + mu_sh)) // span
    return min(k, 0xFFFF)


# ---------------------------------------------------------------------------
# The plan
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Coef:
    """One quantised coefficient: raw = round(value * 2^q)."""

    name: str
    value: float
    q: int
    raw: int
    unit: str
    source: str

    @property
    def quantised(self) -> float:
        return self.raw * 2.0 ** -self.q

    @property
    def rel_error(self) -> float:
        return 0.0 if self.value == 0 else abs(self.quantised - self.value) / abs(self.value)


@dataclass(frozen=True)
class FixedPointPlan:
    n_rules: int
    ts_s: float
    qs: int
    qu: int
    qi: int
    q_kp: int
    q_kits: int
    q_kdts: int
    q_kc: int
    shift_p: int
    shift_i: int
    shift_d: int
    shift_c: int
    mu_sh: int
    kp: tuple
    kits: tuple
    kdts: tuple
    kc: tuple
    premise_lo: int
    premise_hi: int
    b_q14: int
    dfilt_a: int                 # 0 = no derivative filter
    u_min: int
    u_max: int
    u_limit: int                 # |u| the bridge can apply (bus x max duty), raw
    i_lim: int                   # integrator range +-I_lim, Q qi
    # speed measurement
    speed_source: str            # "encoder" | "hall"
    pdec: int                    # QEI velocity postscaler (1: Timer5 restarts at every count)
    ps5: int
    k_speed: int
    ts_ticks: int                # speed-loop period in Timer5 ticks (encoder M/T method)
    counts_per_rev: int
    speed_res_at_max: float      # relative resolution at the top speed
    speed_min_rpm: float         # lowest measurable speed
    # output
    kduty: int
    duty_sh: int
    pdc_max: int
    duty_full: int
    # current
    counts_per_a: float
    ilim: int
    itrip: int
    cap_step: int
    kb: int                      # back-EMF constant, Q q_kb V/(rad/s) (current-limit voltage window)
    q_kb: int
    shift_kb: int
    r_cnt: int                   # line resistance per ADC count of current, Q q_r V/count
    q_r: int
    shift_r: int
    # timing
    t2_pre: int
    t2_post: int
    pr2: int
    loop_div: int
    tcy_per_tick: int
    loop_hz: float
    stall_ms: int
    link_timeout_ms: int
    bus_voltage_v: float
    bus_counts_per_v: float = 0.0  # AN1 counts per V of bus (profile.bus_guard)
    bus_taper_start: int = 0     # AN1 counts: braking current full up to here (profile.bus_guard)
    bus_taper_end: int = 0       # AN1 counts: braking current 0 from here
    kff: int = 0                 # reference feedforward, Q q_kff V/(rad/s); 0 = off
    q_kff: int = 0
    shift_ff: int = 0            # q_kff + qs - qi
    coefs: tuple = field(default=())
    notes: tuple = field(default=())

    @property
    def speed_lsb_rad_s(self) -> float:
        return 2.0 ** -self.qs

    @property
    def t2_t5_shift(self) -> int:
        """log2 of Timer5 ticks per Timer2 count (prescalers 1:t2_pre and 1:ps5 of Tcy, both
        powers of two): a change of TMR2 at the speed sample, in Timer5 ticks, is the change
        shifted left by this (right, floor, when negative).  C: CORE_T2_T5_SH."""
        return (self.t2_pre.bit_length() - 1) - (self.ps5.bit_length() - 1)

    def to_speed_raw(self, w_rad_s: float) -> int:
        return sat16(math.floor(w_rad_s * 2 ** self.qs))

    def lines(self) -> list[str]:
        out = [
            f"Q formats   speed Q{self.qs} ({2 ** -self.qs:.4g} rad/s, range +-{32768 * 2 ** -self.qs:.0f} rad/s), "
            f"u Q{self.qu} ({2 ** -self.qu:.3g} V), integrator Q{self.qi}, kp Q{self.q_kp}, ki*Ts Q{self.q_kits}, "
            f"kd/Ts Q{self.q_kdts}, kc Q{self.q_kc} (V/count)",
            f"shifts      P {self.shift_p}, I {self.shift_i}, D {self.shift_d}, C {self.shift_c}; memberships Q12, "
            f"slope shift {self.mu_sh}",
        ]
        for c in self.coefs:
            out.append(f"  {c.name:<18} {c.value:>13.6g} {c.unit:<10} -> {c.raw:>6} x 2^-{c.q:<3} = "
                       f"{c.quantised:.6g} (error {100 * c.rel_error:.4f} %)  [{c.source}]")
        if self.speed_source == "encoder":
            out.append(f"speed       encoder M/T: counts per sample over the edge-to-edge time (QEI x4, "
                       f"{self.counts_per_rev} counts/rev; Timer5 1:{self.ps5} restarted at every count), "
                       f"extrapolated half a sample: time resolution {100 * self.speed_res_at_max:.3f} % of a sample, "
                       f"lowest measurable {self.speed_min_rpm:.1f} rpm")
        else:
            out.append(f"speed       hall-edge period, Timer5 1:{self.ps5}: resolution {100 * self.speed_res_at_max:.3f} % "
                       f"at the top speed, lowest measurable {self.speed_min_rpm:.1f} rpm")
        out.append(f"speed loop  Timer2 1:{self.t2_pre} x (PR2 {self.pr2} + 1) x 1:{self.t2_post}"
                   f"{'' if self.loop_div == 1 else f' x {self.loop_div} interrupts'}: {self.loop_hz:.3f} Hz")
        out.append(f"current     {self.counts_per_a:.2f} counts/A; limit {self.ilim} counts; ADC trip {self.itrip} counts")
        for n in self.notes:
            out.append(f"note        {n}")
        return out


def _q_for(max_abs: float, headroom: float) -> int:
    """Largest q with max_abs * headroom * 2^q <= 32767."""
    return math.floor(math.log2(INT16_MAX / (max_abs * headroom)))


def _quantise_group(name: str, values: list[float], ref: float, unit: str, source: str,
                    scale_label: str) -> tuple[int, list[Coef]]:
    m = max(abs(v) for v in values)
    q = _q_for(m if m > 0 else ref, GAIN_HEADROOM)
    coefs = []
    for j, v in enumerate(values, 1):
        raw = round(v * 2 ** q)
        c = Coef(f"rule{j}_{name}", v, q, raw, unit, source)
        if abs(raw) > INT16_MAX:
            raise FixedPointError(f"rule {j} {scale_label} = {v:.6g} {unit} does not fit int16 in Q{q}")
        if c.rel_error > REL_ERR_LIMIT:
            raise FixedPointError(
                f"rule {j} {scale_label} = {v:.6g} {unit} cannot be represented: next to the largest "
                f"{scale_label} of the rules ({m:.6g} {unit}) it quantises to {c.quantised:.6g} "
                f"(error {100 * c.rel_error:.2f} % > {100 * REL_ERR_LIMIT:g} %); the rules' gains differ "
                "by too much for one int16 format - redesign with closer rule gains or set this one to 0")
        coefs.append(c)
    return q, coefs


def _timer2(loop_hz: float) -> tuple[int, int, int, int, int, float]:
    """Timer2 prescale, postscale, PR2 and interrupts per speed-loop sample.

    The fewest interrupts per sample whose period is within 1e-4 of
    Fcy / loop_hz (exact for rates that divide 10 MHz), else the closest.
    """
    target = FCY_HZ / loop_hz
    overall = None
    for div in range(1, 257):
        best = None
        for pre in (1, 4, 16):
            for post in range(1, 17):
                pr = round(target / (div * pre * post)) - 1
                if not 0 <= pr <= 255:
                    continue
                ticks = pre * post * (pr + 1)
                err = abs(ticks * div - target) / target
                key = (round(err, 9), -(pr + 1), pre)
                if best is None or key < best[0]:
                    best = (key, pre, post, pr, div, ticks)
        if best is None:
            continue
        if best[0][0] <= 1e-4:
            overall = best
            break
        if overall is None or best[0][0] < overall[0][0]:
            overall = best
    if overall is None:
        raise FixedPointError(f"control.speed_loop_hz = {loop_hz:g} Hz cannot be paced by Timer2")
    _, pre, post, pr, div, ticks = overall
    achieved = FCY_HZ / (ticks * div)
    if abs(achieved - loop_hz) / loop_hz > 0.005:
        raise FixedPointError(f"control.speed_loop_hz = {loop_hz:g} Hz: Timer2 reaches {achieved:.3f} Hz at best "
                              "(> 0.5 % off); choose a rate that divides 10 MHz")
    return pre, post, pr, div, ticks, achieved


def speed_q(w_max_rad_s: float) -> int:
    """Q format of the speed: the largest q (at most 14) that holds 1.25 x the top speed in 16 bits."""
    return min(_q_for(w_max_rad_s, 1.25), 14)


def profile_top_speed_rad_s(profile, premise_hi_rad_s: float | None = None) -> float:
    """The top speed the firmware's speed format must hold, rad/s: the speed range, the reference and the
    fuzzy premise's upper end (a design's, or the profile's ``design.premise_rpm`` with > 1 rule)."""
    co, rpm = profile.control, 2 * math.pi / 60
    if premise_hi_rad_s is None and int(profile.design.get("rules", 1)) > 1:
        premise_hi_rad_s = float(profile.design["premise_rpm"][1]) * rpm
    return max(co.speed_max_rpm * rpm, co.reference_rpm * rpm, premise_hi_rad_s or 0.0)


def encoder_speed_constant(encoder_lines: int, ts: float, qs: int, w_max_rad_s: float) -> tuple[int, int]:
    """Timer5 prescaler and the M/T speed constant K (speed Q qs = K x counts / ticks) of an encoder.

    The firmware saturates a count step above CORE_MT_DMAX = (2^32 - 1) // K, held in 16-bit
    arithmetic: K must be at least 65538 (CORE_MT_DMAX <= 65534), so a fine encoder on a fast
    motor (x4 counts per revolution, 2^qs LSB per rad/s) is refused here, naming the limit."""
    cpr = 4 * encoder_lines
    ps5 = next((c for c in (1, 2, 4, 8) if 65536 * c >= 2 * ts * FCY_HZ), 0)
    if not ps5:
        raise FixedPointError(f"speed loop period {ts * 1e3:g} ms is longer than half a Timer5 overflow at 1:8 "
                              f"({65536 * 8 / FCY_HZ * 1e3 / 2:.1f} ms); raise control.speed_loop_hz")
    k_speed = round(2 * math.pi * FCY_HZ / (ps5 * cpr) * 2 ** qs)
    if k_speed < MT_K_MIN:
        lines_max = math.floor(2 * math.pi * FCY_HZ * 2 ** qs / (ps5 * MT_K_MIN) / 4)
        rpm_max = 0.0
        for q in range(qs + 1, 15):       # the top speed whose finer speed format makes K large enough
            if round(2 * math.pi * FCY_HZ / (ps5 * cpr) * 2 ** q) >= MT_K_MIN:
                rpm_max = INT16_MAX / (1.25 * 2 ** q) * 60 / (2 * math.pi)
                break
        alt = (f", or keep it and bring the top speed (control.speed_max_rpm, reference_rpm, design.premise_rpm) "
               f"down to {math.floor(rpm_max)} rpm") if rpm_max > 0 else ""
        raise FixedPointError(
            f"sensors.encoder_lines = {encoder_lines} at a top speed of {w_max_rad_s * 60 / (2 * math.pi):.0f} rpm "
            f"is beyond the firmware's 16-bit M/T speed arithmetic (speed constant K = {k_speed} < {MT_K_MIN}, "
            f"CORE_MT_DMAX = {0xFFFFFFFF // max(k_speed, 1)} > 65534): use an encoder of at most {lines_max} "
            f"lines{alt}")
    return ps5, k_speed


def check_profile_arithmetic(profile) -> None:
    """Refuse, before any design work, a profile the firmware's fixed-point plan cannot hold
    (the encoder's speed arithmetic); :func:`plan_fixed_point` checks the same with the design's law."""
    se = profile.sensors
    if se.speed_source == "encoder":
        w_max = profile_top_speed_rad_s(profile)
        encoder_speed_constant(se.encoder_lines, 1.0 / profile.control.speed_loop_hz, speed_q(w_max), w_max)


def plan_fixed_point(profile, law, pwm_plan) -> FixedPointPlan:
    """Choose the formats, quantise the law, plan speed measurement, duty and timing.

    ``law`` is a :class:`picdrive.control_law.ScheduledLaw`; ``pwm_plan`` a
    :class:`picdrive.pcpwm.PwmPlan`.  Raises :class:`FixedPointError` naming
    the coefficient and the fix when something cannot be represented.
    """
    inv, se, co, mo = profile.inverter, profile.sensors, profile.control, profile.motor
    guard = bus_guard(inv, strict=False)     # codegen refuses a profile without a guard window
    ts = law.sample_time_s
    loop_hz = co.speed_loop_hz
    if abs(ts * loop_hz - 1.0) > 1e-6:
        raise FixedPointError(f"the design samples at {1 / ts:g} Hz but control.speed_loop_hz = {loop_hz:g} Hz: "
                              "re-run 'picdrive design' on this profile")
    notes: list[str] = []
    w_max = profile_top_speed_rad_s(profile, law.premise_rad_s[1] if law.n_rules > 1 else 0.0)
    qs = speed_q(w_max)
    u_bridge = inv.bus_voltage_v * pwm_plan.max_duty
    u_abs = max(abs(law.u_min_v), abs(law.u_max_v), u_bridge)
    qu = _q_for(u_abs, 2.0)
    if qu < -8:
        raise FixedPointError(f"output limits of {u_abs:g} V are too large to represent")
    # integrator: its own range +-I_lim (ScheduledLaw.i_lim_v), 16 bits finer than u where that fits
    i_lim_v = law.i_lim_v
    qi = min(qu + 16, math.floor(math.log2((INT32_MAX - 1) / i_lim_v)))
    if qi < qu:
        raise FixedPointError(f"integrator range +-{i_lim_v:g} V (integrator_limit_v) does not fit 32 bits at the "
                              f"output's resolution {2 ** -qu:g} V; lower integrator_limit_v")
    counts_per_a = inv.current_sense_v_per_a * ADC_COUNTS / ADC_VREF_V
    coefs: list[Coef] = []

    rules = law.rules
    # reference magnitudes for groups that are all zero (their parameter range)
    q_kp, c_kp = _quantise_group("kp", [r.kp for r in rules], u_abs / w_max, "V/(rad/s)",
                                 "design law rules[j].kp", "kp")
    q_kits, c_ki = _quantise_group("ki*Ts", [r.ki * ts for r in rules], u_abs * ts / w_max, "V/(rad/s)",
                                   "design ki x Ts", "ki x Ts")
    q_kdts, c_kd = _quantise_group("kd/Ts", [r.kd / ts for r in rules], u_abs / w_max, "V/(rad/s)",
                                   "design kd / Ts", "kd / Ts")
    q_kc, c_kc = _quantise_group("kc", [r.kc / counts_per_a for r in rules],
                                 u_abs / max(1.0, inv.overcurrent_trip_a * counts_per_a), "V/count",
                                 "design kc / (counts per A)", "kc")
    coefs += c_kp + c_ki + c_kd + c_kc
    shift_p = q_kp + qs - qu
    shift_i = q_kits + qs - qi
    shift_d = q_kdts + qs - qu
    shift_c = q_kc - qu
    for name, s, group in (("kp", shift_p, c_kp), ("ki", shift_i, c_ki), ("kd", shift_d, c_kd),
                           ("kc", shift_c, c_kc)):
        nonzero = any(c.raw for c in group)
        if s > 31:
            if nonzero:
                raise FixedPointError(
                    f"{name} gains ({', '.join(f'{c.value:.3g}' for c in group)}) are too small to act: one "
                    f"speed LSB times the gain is below 2^-31 of the output LSB; check the design's units")
        if s < -15:
            raise FixedPointError(f"{name} gains ({', '.join(f'{c.value:.3g}' for c in group)}) are too large: "
                                  "any error saturates the output; check the design's units")
    shift_p, shift_i, shift_d, shift_c = (min(s, 31) for s in (shift_p, shift_i, shift_d, shift_c))

    b = law.setpoint_weight
    if not 0.0 <= b < 2.0:
        raise FixedPointError(f"setpoint weight b = {b:g} outside [0, 2): cannot be represented in Q14")
    b_q14 = min(INT16_MAX, round(b * 16384))
    coefs.append(Coef("setpoint_weight", b, 14, b_q14, "1", "design law setpoint_weight"))
    if law.derivative_filter_hz:
        tf = 1.0 / (2 * math.pi * law.derivative_filter_hz)
        a = ts / (ts + tf)
        dfilt_a = max(1, round(a * 32768))
        coefs.append(Coef("dfilter_a", a, 15, dfilt_a, "1", "Ts / (Ts + 1/(2 pi f_D))"))
    else:
        dfilt_a = 0

    n1, n2 = law.premise_rad_s
    p_lo = sat16(max(0, round(n1 * 2 ** qs)))
    p_hi = sat16(max(0, round(n2 * 2 ** qs)))
    mu_sh = 0
    if law.n_rules > 1:
        if p_hi - p_lo < 16:
            raise FixedPointError(f"premise range [{n1:g}, {n2:g}] rad/s is narrower than 16 speed LSBs")
        # slope k = ((r-1) << (12 + sh)) / span kept <= 4095 for the design's span, so that the
        # premise can be narrowed 16-fold at run time before k saturates at 65535
        span = p_hi - p_lo
        for sh in range(16, -1, -1):
            if ((law.n_rules - 1) << (12 + sh)) // span <= 4095:
                mu_sh = sh
                break
        coefs.append(Coef("premise_lo", n1, qs, p_lo, "rad/s", "design premise_rad_s[0]"))
        coefs.append(Coef("premise_hi", n2, qs, p_hi, "rad/s", "design premise_rad_s[1]"))
    u_limit = min(INT16_MAX, math.floor(u_bridge * 2 ** qu))
    u_min = max(-u_limit, round(law.u_min_v * 2 ** qu))
    u_max = min(u_limit, round(law.u_max_v * 2 ** qu))
    if law.u_max_v > u_bridge * (1 + 1e-9) or law.u_min_v < -u_bridge * (1 + 1e-9):
        notes.append(f"design output limits [{law.u_min_v:.4g}, {law.u_max_v:.4g}] V exceed the bridge's "
                     f"+-{u_bridge:.4g} V (bus x max duty): clamped")
    if not u_min < u_max:
        raise FixedPointError(f"output limits [{law.u_min_v:g}, {law.u_max_v:g}] V are empty after quantisation")
    coefs.append(Coef("u_min", law.u_min_v, qu, u_min, "V", "design u_min_v (within bus x max duty)"))
    coefs.append(Coef("u_max", law.u_max_v, qu, u_max, "V", "design u_max_v (within bus x max duty)"))
    i_lim = min(INT32_MAX, round(i_lim_v * 2 ** qi))
    coefs.append(Coef("i_lim", i_lim_v, qi, i_lim, "V", "design integrator_limit_v (or max |u limit|)"))

    # ---- speed measurement ----
    if se.speed_source == "encoder":
        # M/T method: speed = counts in the sample / time between the last count edges of this
        # sample and of the previous one (the average over about one sample), extrapolated half a
        # sample with the previous average (the speed at the sample instant, which the design's
        # law assumes).  The QEI in velocity mode with PDEC 1:1 and CAP1REN restarts Timer5 at
        # every count, so TMR5 read at a sample is the time since the last edge.
        cpr = 4 * se.encoder_lines
        pdec = 1
        ps5, k_speed = encoder_speed_constant(se.encoder_lines, ts, qs, w_max)
        ts_ticks = round(ts * FCY_HZ / ps5)
        period_max = ts_ticks
        speed_min_rpm = FCY_HZ / (ps5 * 65536) * 60 / cpr
        counts = cpr
    else:
        edges = 6 * mo.pole_pairs
        eps_max = co.speed_max_rpm / 60 * edges
        pdec = 1
        ps5 = 8
        for cand in (1, 2, 4, 8):
            if FCY_HZ / (cand * 65536) * 60 / edges <= 0.05 * co.speed_max_rpm:
                ps5 = cand
                break
        k_speed = round(2 * math.pi / edges * FCY_HZ / ps5 * 2 ** qs)
        ts_ticks = round(ts * FCY_HZ / ps5)
        period_max = FCY_HZ / (ps5 * eps_max)
        speed_min_rpm = FCY_HZ / (ps5 * 65536) * 60 / edges
        counts = edges
    if k_speed >= 1 << 32:
        raise FixedPointError("speed constant does not fit 32 bits")
    res = 1.0 / period_max

    # ---- duty ----
    full = pwm_plan.period.duty_full_counts
    duty_sh = 0
    for sh in range(31, -1, -1):
        k = full * 2.0 ** (sh - qu) / inv.bus_voltage_v
        if k <= 0xFFFF:
            duty_sh = sh
            break
    kduty = round(full * 2.0 ** (duty_sh - qu) / inv.bus_voltage_v)
    coefs.append(Coef("kduty", full / inv.bus_voltage_v * 2.0 ** -qu, duty_sh, kduty, "counts/LSB",
                      "4 (PTPER + 1) / bus_voltage_v"))

    # ---- current ----
    ilim = min(1023, round(inv.current_limit_a * counts_per_a))
    itrip_f = inv.overcurrent_trip_a * counts_per_a
    itrip = 1024 if itrip_f >= 1023.5 else round(itrip_f)
    if itrip == 1024:
        notes.append(f"overcurrent_trip_a = {inv.overcurrent_trip_a:g} A is beyond the ADC range "
                     f"({1023 / counts_per_a:.3g} A): only FLTA protects above it")
    cap_step = max(1, round(u_limit * ts / 0.010))
    # current-limit voltage window: |i| <= I_lim in steady state while u stays within
    # Kb w -+ R_line I_lim (the DC-equivalent motor; no overshoot for an RL circuit driven from below)
    kb_v = mo.kb_v_s_per_rad
    q_kb = _q_for(kb_v, 1.0)
    kb_raw = round(kb_v * 2 ** q_kb)
    r_cnt_v = mo.r_line_ohm / counts_per_a
    q_r = _q_for(r_cnt_v, 1.0)
    r_raw = round(r_cnt_v * 2 ** q_r)
    shift_kb, shift_r = q_kb + qs - qu, q_r - qu
    if not (-15 <= shift_kb <= 31 and -15 <= shift_r <= 31):
        raise FixedPointError(f"motor constants Kb = {kb_v:g} V s/rad, R = {mo.r_line_ohm:g} ohm cannot be "
                              "represented for the current-limit window")
    coefs.append(Coef("kb", kb_v, q_kb, kb_raw, "V/(rad/s)", "motor kb_v_s_per_rad (current-limit window)"))
    coefs.append(Coef("r_per_count", r_cnt_v, q_r, r_raw, "V/count", "motor r_line_ohm / counts per A"))

    # reference feedforward (integrator preload per speed LSB of reference change)
    g_ff = getattr(law, "reference_ff_v_s_per_rad", 0.0)
    kff = q_kff = shift_ff = 0
    if g_ff:
        q_kff = _q_for(abs(g_ff), 1.0)
        kff = round(g_ff * 2 ** q_kff)
        shift_ff = q_kff + qs - qi
        if not -31 <= shift_ff <= 31:
            raise FixedPointError(f"reference feedforward {g_ff:g} V s/rad cannot be represented "
                                  "(set control.reference_feedforward = \"off\")")
        coefs.append(Coef("kff", g_ff, q_kff, kff, "V/(rad/s)", "design reference_ff_v_s_per_rad"))

    pre, post, pr2, div, ticks, achieved = _timer2(loop_hz)
    return FixedPointPlan(
        n_rules=law.n_rules, ts_s=ts, qs=qs, qu=qu, qi=qi, q_kp=q_kp, q_kits=q_kits, q_kdts=q_kdts, q_kc=q_kc,
        shift_p=shift_p, shift_i=shift_i, shift_d=shift_d, shift_c=shift_c, mu_sh=mu_sh,
        kp=tuple(c.raw for c in c_kp), kits=tuple(c.raw for c in c_ki), kdts=tuple(c.raw for c in c_kd),
        kc=tuple(c.raw for c in c_kc), premise_lo=p_lo, premise_hi=p_hi, b_q14=b_q14, dfilt_a=dfilt_a,
        u_min=u_min, u_max=u_max, u_limit=u_limit, i_lim=i_lim,
        speed_source=se.speed_source, pdec=pdec, ps5=ps5, k_speed=k_speed, ts_ticks=ts_ticks, counts_per_rev=counts,
        speed_res_at_max=res, speed_min_rpm=speed_min_rpm,
        kduty=kduty, duty_sh=duty_sh, pdc_max=pwm_plan.pdc_max, duty_full=full,
        counts_per_a=counts_per_a, ilim=ilim, itrip=itrip, cap_step=cap_step,
        kb=kb_raw, q_kb=q_kb, shift_kb=shift_kb, r_cnt=r_raw, q_r=q_r, shift_r=shift_r,
        t2_pre=pre, t2_post=post, pr2=pr2, loop_div=div, tcy_per_tick=ticks, loop_hz=achieved,
        stall_ms=int(round(co.stall_timeout_ms)), link_timeout_ms=int(round(profile.uart.link_timeout_ms)),
        bus_voltage_v=inv.bus_voltage_v, bus_counts_per_v=guard.counts_per_v,
        bus_taper_start=guard.taper_start, bus_taper_end=guard.taper_end, kff=kff, q_kff=q_kff, shift_ff=shift_ff,
        coefs=tuple(coefs), notes=tuple(notes))


# ---------------------------------------------------------------------------
# Protocol-facing: parameter and signal scaling
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class ParamSpec:
    """A parameter or signal as the firmware stores it: engineering = raw x scale."""

    name: str
    ctype: str
    scale: float
    unit: str
    min_raw: int
    max_raw: int
    default_raw: int

    def to_raw(self, value: float) -> int:
        raw = round(value / self.scale)
        return min(max(raw, self.min_raw), self.max_raw)

    def to_eng(self, raw: int) -> float:
        return raw * self.scale


def param_specs(plan: FixedPointPlan, profile) -> dict[str, ParamSpec]:
    """Scales, limits and defaults of the writable parameters (protocol overrides)."""
    rpm_per_lsb = 2.0 ** -plan.qs * 60 / (2 * math.pi)
    smax = min(INT16_MAX, round(profile.control.speed_max_rpm / rpm_per_lsb))
    out: dict[str, ParamSpec] = {
        "speed_setpoint": ParamSpec("speed_setpoint", "int16", rpm_per_lsb, "rpm", -smax, smax, 0),
        "controller": ParamSpec("controller", "uint8", 1.0, "enum", 0, 1, 0 if plan.n_rules == 1 else 1),
    }
    for j in range(plan.n_rules):
        out[f"rule{j + 1}_kp"] = ParamSpec(f"rule{j + 1}_kp", "int16", 2.0 ** -plan.q_kp, "V/(rad/s)",
                                           INT16_MIN, INT16_MAX, plan.kp[j])
        out[f"rule{j + 1}_ki"] = ParamSpec(f"rule{j + 1}_ki", "int16", 2.0 ** -plan.q_kits / plan.ts_s, "V/rad",
                                           INT16_MIN, INT16_MAX, plan.kits[j])
        out[f"rule{j + 1}_kd"] = ParamSpec(f"rule{j + 1}_kd", "int16", 2.0 ** -plan.q_kdts * plan.ts_s,
                                           "V s^2/rad", INT16_MIN, INT16_MAX, plan.kdts[j])
        out[f"rule{j + 1}_kc"] = ParamSpec(f"rule{j + 1}_kc", "int16", 2.0 ** -plan.q_kc * plan.counts_per_a,
                                           "V/A", INT16_MIN, INT16_MAX, plan.kc[j])
    out["premise_low"] = ParamSpec("premise_low", "int16", rpm_per_lsb, "rpm", 0, INT16_MAX, plan.premise_lo)
    out["premise_high"] = ParamSpec("premise_high", "int16", rpm_per_lsb, "rpm", 0, INT16_MAX, plan.premise_hi)
    out["setpoint_weight"] = ParamSpec("setpoint_weight", "int16", 2.0 ** -14, "1", 0, INT16_MAX, plan.b_q14)
    out["u_min"] = ParamSpec("u_min", "int16", 2.0 ** -plan.qu, "V", -plan.u_limit, 0, plan.u_min)
    out["u_max"] = ParamSpec("u_max", "int16", 2.0 ** -plan.qu, "V", 0, plan.u_limit, plan.u_max)
    out["current_limit"] = ParamSpec("current_limit", "int16", 1.0 / plan.counts_per_a, "A", 0, 1023, plan.ilim)
    out["accel_limit"] = ParamSpec("accel_limit", "uint16", rpm_per_lsb / plan.ts_s, "rpm/s", 0, 65535, 0)
    out["link_timeout"] = ParamSpec("link_timeout", "uint16", 1.0, "ms", 20, 60000, plan.link_timeout_ms)
    out["stall_timeout"] = ParamSpec("stall_timeout", "uint16", 1.0, "ms", 10, 60000, plan.stall_ms)
    return out


def law_parameters(law) -> dict[str, float]:
    """The run-time parameters a control law sets, in engineering units: the same names as
    :func:`param_specs` (whose defaults are these values quantised by the build's plan).

    Parameters
    ----------
    law : picdrive.control_law.ScheduledLaw
        The design's law.

    Returns
    -------
    dict
        ``rule<j>_kp`` (V/(rad/s)), ``rule<j>_ki`` (V/rad), ``rule<j>_kd`` (V s^2/rad),
        ``rule<j>_kc`` (V/A) for each rule j = 1..r; ``setpoint_weight`` (1); ``u_min``,
        ``u_max`` (V); with two rules or more ``premise_low``, ``premise_high`` (rpm); when the
        law has a back-EMF window ``current_limit`` (A).  What the law holds beyond these
        (derivative filter, integrator limit, Kb, R) is fixed by the build.
    """
    rpm = 60.0 / (2.0 * math.pi)
    values: dict[str, float] = {}
    for j, rule in enumerate(law.rules, 1):
        for k in ("kp", "ki", "kd", "kc"):
            values[f"rule{j}_{k}"] = float(getattr(rule, k))
    values["setpoint_weight"] = float(law.setpoint_weight)
    values["u_min"] = float(law.u_min_v)
    values["u_max"] = float(law.u_max_v)
    if law.n_rules > 1:
        values["premise_low"] = float(law.premise_rad_s[0]) * rpm
        values["premise_high"] = float(law.premise_rad_s[1]) * rpm
    if getattr(law, "current_limit_a", None) is not None:
        values["current_limit"] = float(law.current_limit_a)   # I_lim of the back-EMF voltage window
    return values


def signal_specs(plan: FixedPointPlan) -> dict[str, ParamSpec]:
    """Scales of the telemetry signals (read-only)."""
    rpm_per_lsb = 2.0 ** -plan.qs * 60 / (2 * math.pi)
    v = 2.0 ** -plan.qu
    return {
        "speed": ParamSpec("speed", "int16", rpm_per_lsb, "rpm", INT16_MIN, INT16_MAX, 0),
        "setpoint": ParamSpec("setpoint", "int16", rpm_per_lsb, "rpm", INT16_MIN, INT16_MAX, 0),
        "voltage": ParamSpec("voltage", "int16", v, "V", INT16_MIN, INT16_MAX, 0),
        "current": ParamSpec("current", "int16", 1.0 / plan.counts_per_a, "A", -1023, 1023, 0),
        "integrator": ParamSpec("integrator", "int16", v, "V", INT16_MIN, INT16_MAX, 0),
        "duty": ParamSpec("duty", "int16", 1.0, "counts", -plan.duty_full, plan.duty_full, 0),
        "hall": ParamSpec("hall", "uint8", 1.0, "", 0, 7, 0),
        "state": ParamSpec("state", "uint8", 1.0, "", 0, 255, 0),
        "fault": ParamSpec("fault", "uint8", 1.0, "", 0, 255, 0),
        "mu1": ParamSpec("mu1", "int16", 1.0 / MU_ONE, "1", 0, MU_ONE, MU_ONE),
        "position": ParamSpec("position", "int16", 1.0, "counts", INT16_MIN, INT16_MAX, 0),
        "bus_voltage": ParamSpec("bus_voltage", "int16", 1.0 / plan.bus_counts_per_v, "V", 0, 1023, 0),
    }


# ---------------------------------------------------------------------------
# The model of drive_core.c (names as in the C)
# ---------------------------------------------------------------------------
LawParams = model_class(CORE_PARAMS, "LawParams", "core_params_t of the C (raw values, copied from the parameter "
                        "store): picdrive.firmware.core_layout.CORE_PARAMS.")
LawState = model_class(CORE_LAW, "LawState", "core_law_t of the C: core_layout.CORE_LAW.")


def law_params_from_plan(plan: FixedPointPlan) -> LawParams:
    return LawParams(kp=list(plan.kp), kits=list(plan.kits), kdts=list(plan.kdts), kc=list(plan.kc),
                     premise_lo=plan.premise_lo, premise_hi=plan.premise_hi,
                     mu_k=premise_k(plan.premise_lo, plan.premise_hi, plan.n_rules, plan.mu_sh),
                     b_q14=plan.b_q14, u_min=plan.u_min, u_max=plan.u_max,
                     controller=0 if plan.n_rules == 1 else 1, ilim=plan.ilim)


_MODEL = core_program.model({"sat32": sat32, "shift32": shift32, "shl_sat32": shl_sat32,
                             "duty_counts": lambda plan, u: duty_counts(plan, u)})
law_step = _MODEL["law_step"]
law_step.__doc__ = """One sample of the fixed-point law (C: core_law).  Returns u (Q qu).

Generated from :data:`picdrive.firmware.core_program.LAW` (the program the C is rendered from):
``law_step(plan, p, st, r, y, i, umin, umax, ff=0)``, ``st`` a :class:`LawState`; ``ff``: the
reference feedforward of the sample (Q qi, C: core_s.ff, :func:`reference_ff`), added to the
integrator after the headroom rule and before its clamp (plans with kff only)."""


CoreState = model_class(CORE_STATE, "CoreState", "core_state_t of the C: core_layout.CORE_STATE.",
                        nested={"core_law_t": LawState})


def core_reset(plan: FixedPointPlan, st: CoreState) -> None:
    """C: core_reset (start of RUN): law memory cleared, limits opened, direction kept."""
    st.law = LawState()
    st.r_applied = 0
    st.cap = plan.u_limit
    st.u = 0
    st.hold = 0
    st.pdc = 0


def _s16(x: int) -> int:
    """uint16 -> int16 (two's complement, as the C cast on gcc and XC8)."""
    x &= 0xFFFF
    return x - 0x10000 if x & 0x8000 else x


def t2_ticks(plan: FixedPointPlan, dt2: int) -> int:
    """A change of TMR2 (counts, -255..255) in Timer5 ticks (C: CORE_T2_T5(x))."""
    sh = plan.t2_t5_shift
    return dt2 << sh if sh >= 0 else dt2 >> -sh


def speed_encoder(plan: FixedPointPlan, st: CoreState, pos: int, t5: int, t2: int, ovf: int) -> int:
    """Speed (Q qs) from the QEI position and Timer5 (C: core_speed_encoder).

    M/T average ``w_avg`` = counts since the last sample x K / ticks between
    the last count edges; output ``w_avg + (w_avg - previous w_avg) / 2``
    (half a sample of extrapolation).  ``pos``: POSCNT; ``t5``: Timer5 ticks
    since the last count edge; ``t2``: TMR2 (0..255) read with them: the
    sample's instant after the speed-loop interrupt's Timer2 period match
    (entry latency and the code before the read), so the time between two
    samples is Ts plus the change of TMR2 in Timer5 ticks; ``ovf``: Timer5
    overflowed (no edge for 65536 ticks).  Without a count in the sample the
    average may only fall, to one count over the time since the last edge.
    """
    d = _s16(pos - st.pos_prev)
    st.pos_prev = pos & 0xFFFF
    prev = st.w_avg
    t2_prev, st.t2_prev = st.t2_prev, t2 & 0xFF
    if ovf:
        st.speed_valid = 0
    if d != 0:
        dt = (plan.ts_ticks - t5 + st.t5_prev + t2_ticks(plan, (t2 & 0xFF) - t2_prev)
              if st.speed_valid else plan.ts_ticks)
        if dt < 1:
            dt = 1
        mag = -d if d < 0 else d
        if mag > (0xFFFFFFFF // plan.k_speed):     # the 32-bit product would overflow: saturate
            w = INT16_MAX
        else:
            w = (mag * plan.k_speed) // dt
        if w > INT16_MAX:
            w = INT16_MAX
        st.w_avg = -w if d < 0 else w
        if not st.speed_valid:
            prev = st.w_avg                         # no history: no extrapolation
        st.speed_valid = 1
    elif st.speed_valid and t5 != 0:
        bound = min(plan.k_speed // t5, INT16_MAX)  # at most one count in the time since the last edge
        mag = -st.w_avg if st.w_avg < 0 else st.w_avg
        if bound < mag:
            st.w_avg = -bound if st.w_avg < 0 else bound
    else:
        st.w_avg = 0
        prev = 0
    st.t5_prev = t5
    st.speed = sat16(st.w_avg + asr32(st.w_avg - prev, 1))
    return st.speed


speed_hall = _MODEL["speed_hall"]
speed_hall.__doc__ = """Speed (Q qs) from the hall-edge period (C: core_speed_hall): ``speed_hall(plan, st,
period, elapsed, valid, forward)``, generated from
:data:`picdrive.firmware.core_program.SPEED_HALL`: ``min(K / max(period, elapsed), 32767)``,
signed by the direction, 0 without a valid period."""


def duty_counts(plan: FixedPointPlan, u: int) -> int:
    mag = -u if u < 0 else u
    d = (mag * plan.kduty) >> plan.duty_sh
    return plan.pdc_max if d > plan.pdc_max else d


def reference_ff(plan: FixedPointPlan, dr: int) -> int:
    """The integrator preload (Q qi) of a change ``dr`` of the applied reference (speed LSB):
    shift(kff x sat16(dr)), 0 without a change or without feedforward (C: core_s.ff)."""
    dr = sat16(dr)
    return shift32(plan.kff * dr, plan.shift_ff) if plan.kff and dr else 0


core_control = _MODEL["core_control"]
core_control.__doc__ = """C: core_control: current limits, setpoint ramp, law, duty and direction.  Returns u.

Generated from :data:`picdrive.firmware.core_program.CONTROL`: ``core_control(plan, p, st,
target, adc)``, ``st`` a :class:`CoreState`.  Current limits: the output window ``Kb y -+
R_line I_lim`` (in steady state the current stays within +-I_lim; I_lim = the
``current_limit`` parameter) and, as a backup on the measured bus current, a cap on |u| walked
down while the current exceeds I_lim and back up when it does not."""
