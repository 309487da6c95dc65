"""The firmware's speed-control law, in floating point: the reference.

Every design method (fuzzy H-inf, mixed H2/H-inf PID, Ziegler-Nichols) ends
in this one law, which is what the firmware runs.  It is a gain-scheduled,
two-degree-of-freedom PID with optional current feedback:

* premise ``s = |y|`` (measured mechanical speed, rad/s), clamped to the
  premise range ``[N1, N2]``;
* memberships ``mu_j(s)``: a triangular partition of ``[N1, N2]`` with
  ``r`` rules at equally spaced centres ``c_j = N1 + j (N2 - N1)/(r - 1)``
  (``r = 2`` gives the 2016 paper's linear M1, M2; ``r = 1`` gives mu = 1,
  i.e. plain PID);
* blended gains ``K = sum_j mu_j K_j`` for K in (kp, ki, kd, kc);
* per sample k, period ``Ts``::

      e   = r - y
      P   = Kp (b r - y)                       setpoint weight b
      D   = Kd (y[k-1] - y) / Ts, then first-order filtered (derivative on measurement)
      Q   = P + D - Kc i                        everything but the integral
      dI  = Ki Ts e                             scheduled gain inside the integral (bumpless)
      I   = min(I + dI, max(I, u_max - Q))  if dI > 0     integrate only into the output headroom,
            max(I + dI, min(I, u_min - Q))  if dI < 0     never discharge the integrator by force
      I   = I + G_ff (r - r_prev)          reference feedforward (integrator preload), when r changes
      I   = clamp(I, -I_lim, I_lim)                        I_lim = integrator_limit_v
      u   = clamp(Q + I, u_lo, u_hi)

where the output limits ``[u_lo, u_hi]`` are ``[u_min, u_max]`` narrowed by
the current limit when the law has one (``current_limit_a``)::

      u_hi = min(u_max, Kb y + R I_max)       the steady current (u - Kb y)/R stays
      u_lo = max(u_min, Kb y - R I_max)       within +-I_max at every sample
      (each then bounded into [u_min, u_max]: beyond reach both meet at the rail
       next to the EMF)

The reference feedforward ``G_ff`` (``reference_ff_v_s_per_rad``, V per rad/s; 0 = off) moves the
integrator by the steady-state voltage a change of the applied reference needs (r_prev starts at 0
with the law's memory), so that the integrator does not have to climb to it at ``Ki Ts e`` per
sample once the output leaves the current window (:func:`reference_ff_gain`).  It
acts only on reference changes: the load rejection (w -> z) is the law's own.

This back-EMF-based voltage clamp limits the current without waiting for a
current measurement (the speed loop samples far slower than the winding's
L/R), which is what keeps a six-step drive off its overcurrent trip at start;
``Kb`` and ``R`` are the profile's six-step DC-equivalent constants.  The
headroom rule of the integrator uses the same ``[u_lo, u_hi]``.

The headroom rule is conditional integration measured against the output
limits: the integrator stops where the unsaturated output would leave
``[u_min, u_max]``.  It does not bound I itself to the output range, which a
state-feedback law (b = 0) needs: at equilibrium its integrator holds
``u* + Kp y* + Kc i*``, far outside ``[u_min, u_max]``.  ``I_lim`` is the
integrator's own range (what the firmware's fixed-point integrator must
hold); it defaults to ``max(|u_min|, |u_max|)``, which suits b = 1 PIDs.

Units: speeds rad/s (mechanical), current A, output u in volts of the
six-step DC-equivalent line voltage (duty = u / bus voltage; a negative u
reverses the commutation table).  kp in V/(rad/s), ki in V/rad, kd in
V s^2/rad, kc in V/A.

The firmware's fixed-point implementation (``picdrive.firmware.fixedpoint``) and its C
are checked against this reference.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

__all__ = ["Rule", "ScheduledLaw", "LawState", "memberships", "law_step", "law_from_dict", "reference_ff_gain",
           "walk_cap", "direction_hold"]


@dataclass(frozen=True)
class Rule:
    """Gains of one fuzzy rule (SI: V/(rad/s), V/rad, V s^2/rad, V/A)."""

    kp: float
    ki: float
    kd: float = 0.0
    kc: float = 0.0


@dataclass(frozen=True)
class ScheduledLaw:
    """The complete control law the firmware runs (see module docstring)."""

    rules: tuple[Rule, ...]
    premise_rad_s: tuple[float, float]
    sample_time_s: float
    u_min_v: float
    u_max_v: float
    setpoint_weight: float = 1.0
    derivative_filter_hz: float | None = None   # None: unfiltered backward difference
    integrator_limit_v: float | None = None     # None: max(|u_min|, |u_max|)
    current_limit_a: float | None = None        # None: no back-EMF voltage clamp
    kb_v_s_per_rad: float = 0.0                 # clamp: six-step DC-equivalent back-EMF constant
    r_ohm: float = 0.0                          # clamp: six-step DC-equivalent (line) resistance
    reference_ff_v_s_per_rad: float = 0.0       # integrator preload per rad/s of reference change (0 = off)
    notes: str = ""

    def __post_init__(self):
        if not self.rules:
            raise ValueError("a scheduled law needs at least one rule")
        n1, n2 = self.premise_rad_s
        if len(self.rules) > 1 and not n2 > n1:
            raise ValueError(f"premise range {self.premise_rad_s} must be increasing")
        if not self.u_min_v < self.u_max_v:
            raise ValueError(f"output limits [{self.u_min_v}, {self.u_max_v}] must be increasing")
        if not self.sample_time_s > 0:
            raise ValueError("sample_time_s must be positive")
        if self.integrator_limit_v is not None and not self.integrator_limit_v > 0:
            raise ValueError("integrator_limit_v must be positive")
        if self.current_limit_a is not None and not (self.current_limit_a > 0 and self.r_ohm > 0
                                                     and self.kb_v_s_per_rad >= 0):
            raise ValueError("a current-limited law needs current_limit_a > 0, r_ohm > 0 and kb_v_s_per_rad >= 0")

    def output_limits(self, speed_rad_s: float) -> tuple[float, float]:
        """Output limits ``(u_lo, u_hi)`` at a measured speed, V (see module docstring)."""
        if self.current_limit_a is None:
            return self.u_min_v, self.u_max_v
        emf = self.kb_v_s_per_rad * speed_rad_s
        span = self.r_ohm * self.current_limit_a
        # beyond reach (|EMF| > u_max + R I_max) both limits meet at the rail next to the
        # EMF: the least current the bridge can give
        lo = min(max(self.u_min_v, emf - span), self.u_max_v)
        hi = max(min(self.u_max_v, emf + span), self.u_min_v)
        return lo, hi

    @property
    def i_lim_v(self) -> float:
        """Integrator range +-I_lim, V."""
        if self.integrator_limit_v is not None:
            return self.integrator_limit_v
        return max(abs(self.u_min_v), abs(self.u_max_v))

    @property
    def n_rules(self) -> int:
        return len(self.rules)

    def gains_at(self, speed_rad_s: float) -> Rule:
        """Blended gains at a speed."""
        mu = memberships(self, speed_rad_s)
        return Rule(*(float(sum(m * getattr(r, k) for m, r in zip(mu, self.rules)))
                      for k in ("kp", "ki", "kd", "kc")))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["rules"] = [asdict(r) for r in self.rules]
        d["premise_rad_s"] = list(self.premise_rad_s)
        d["form"] = "picdrive.scheduled_pid/1"
        return d


#: the smallest speed error a speed drive is expected to regulate without saturating, rad/s (1 rpm)
PLAUSIBLE_SPEED_ERROR_RAD_S = 2.0 * math.pi / 60.0
#: the smallest current change the current feedback is expected to act on without saturating,
#: as a fraction of the current limit
PLAUSIBLE_CURRENT_FRACTION = 0.01


def plausible_gain_limits(law: ScheduledLaw, profile) -> dict[str, tuple[float, str]]:
    """The largest plausible value of each gain on this drive, with how it is derived: the gain
    that alone drives the whole usable bridge voltage V (bus x max duty) from a 1 rpm speed error
    (kp), a 1 rpm error held for one sample (ki), a 1 rpm change within one sample (kd), or a
    current change of 1 % of the current limit (kc).  A larger gain turns the measurement's
    resolution into full-bridge voltage swings: a typed or edited value, not a design."""
    v = profile.inverter.bus_voltage_v * profile.max_duty()
    e, ts = PLAUSIBLE_SPEED_ERROR_RAD_S, law.sample_time_s
    di = PLAUSIBLE_CURRENT_FRACTION * profile.inverter.current_limit_a
    return {
        "kp": (v / e, f"{v:.4g} V from a 1 rpm error"),
        "ki": (v / (e * ts), f"{v:.4g} V from a 1 rpm error in one {ts * 1e3:g} ms sample"),
        "kd": (v * ts / e, f"{v:.4g} V from a 1 rpm change in one {ts * 1e3:g} ms sample"),
        "kc": (v / di, f"{v:.4g} V from {di * 1e3:.3g} mA (1 % of the current limit)"),
    }


def implausible_gains(law: ScheduledLaw, profile) -> list[str]:
    """What is implausible in the law's gains on this drive, one phrase each (empty: plausible).

    Signs: kp, ki and kd act against the speed error (u rises with r - y); a negative one is
    positive feedback.  kc's sign is the design's (state feedback), only its size is bounded.
    Sizes: :func:`plausible_gain_limits`."""
    units = {"kp": "V/(rad/s)", "ki": "V/rad", "kd": "V s^2/rad", "kc": "V/A"}
    lims = plausible_gain_limits(law, profile)
    out = []
    for j, r in enumerate(law.rules, 1):
        for k, unit in units.items():
            g = getattr(r, k)
            hi, why = lims[k]
            lo = -hi if k == "kc" else 0.0
            if not lo <= g <= hi:
                sign = " (a negative gain is positive feedback: the motor runs away from the setpoint)" \
                    if g < 0 and k != "kc" else ""
                out.append(f"rule {j} {k} = {g:.6g} {unit} is outside the plausible range [{lo:.4g}, {hi:.4g}] "
                           f"{unit} on this drive ({hi:.4g} saturates the bridge: {why}){sign}")
    return out


def law_from_dict(d: dict) -> ScheduledLaw:
    if d.get("form") != "picdrive.scheduled_pid/1":
        raise ValueError(f"unknown control-law form {d.get('form')!r}; expected 'picdrive.scheduled_pid/1'")
    return ScheduledLaw(
        rules=tuple(Rule(**r) for r in d["rules"]),
        premise_rad_s=tuple(d["premise_rad_s"]),
        sample_time_s=d["sample_time_s"], u_min_v=d["u_min_v"], u_max_v=d["u_max_v"],
        setpoint_weight=d.get("setpoint_weight", 1.0),
        derivative_filter_hz=d.get("derivative_filter_hz"),
        integrator_limit_v=d.get("integrator_limit_v"), current_limit_a=d.get("current_limit_a"),
        kb_v_s_per_rad=d.get("kb_v_s_per_rad", 0.0), r_ohm=d.get("r_ohm", 0.0),
        reference_ff_v_s_per_rad=d.get("reference_ff_v_s_per_rad", 0.0), notes=d.get("notes", ""))


def memberships(law: ScheduledLaw, speed_rad_s: float) -> np.ndarray:
    """Rule memberships mu_j at a measured speed (premise |y|, clamped)."""
    r = law.n_rules
    if r == 1:
        return np.ones(1)
    n1, n2 = law.premise_rad_s
    s = min(max(abs(speed_rad_s), n1), n2)
    x = (s - n1) / (n2 - n1) * (r - 1)       # position in rule-spacing units
    j = min(int(math.floor(x)), r - 2)
    frac = x - j
    mu = np.zeros(r)
    mu[j] = 1.0 - frac
    mu[j + 1] = frac
    return mu


@dataclass
class LawState:
    """Controller memory between samples."""

    integ_v: float = 0.0
    y_prev: float | None = None
    d_filt_v: float = 0.0
    r_prev: float = 0.0          # the reference of the last sample (reference feedforward)
    log: list = field(default_factory=list, repr=False)


def law_step(law: ScheduledLaw, st: LawState, r: float, y: float, i: float = 0.0) -> float:
    """One sample of the law: setpoint r and speed y (rad/s), current i (A) -> u (V)."""
    g = law.gains_at(y)
    ts = law.sample_time_s
    e = r - y
    p = g.kp * (law.setpoint_weight * r - y)
    y_prev = y if st.y_prev is None else st.y_prev
    d_raw = g.kd * (y_prev - y) / ts
    if law.derivative_filter_hz:
        tf = 1.0 / (2.0 * math.pi * law.derivative_filter_hz)
        a = ts / (ts + tf)
        st.d_filt_v += a * (d_raw - st.d_filt_v)
    else:
        st.d_filt_v = d_raw
    q = p + st.d_filt_v - g.kc * i
    u_lo, u_hi = law.output_limits(y)
    d_i = g.ki * ts * e
    if d_i > 0:
        st.integ_v = min(st.integ_v + d_i, max(st.integ_v, u_hi - q))
    elif d_i < 0:
        st.integ_v = max(st.integ_v + d_i, min(st.integ_v, u_lo - q))
    if r != st.r_prev:                      # reference feedforward: preload by the change of r
        st.integ_v += law.reference_ff_v_s_per_rad * (r - st.r_prev)
        st.r_prev = r
    lim = law.i_lim_v
    st.integ_v = min(max(st.integ_v, -lim), lim)
    st.y_prev = y
    return min(max(q + st.integ_v, u_lo), u_hi)


def reference_ff_gain(law: ScheduledLaw, w_rad_s: float, u_ss_v: float, i_ss_a: float) -> float:
    """The reference feedforward gain G_ff, V per rad/s, from the drive's no-load steady state at speed
    ``w_rad_s``: voltage ``u_ss_v`` and current ``i_ss_a`` there.

    At y = r in steady state (D = 0) the law's output is ``Kp (b - 1) r - Kc i + I``; the integrator
    that gives ``u_ss`` is ``u_ss + Kp (1 - b) r + Kc i_ss``, so per rad/s of reference
    ``G_ff = u_ss / w + Kp (1 - b) + Kc i_ss / w`` (gains blended at ``w``).  It is linear in r
    (one constant in the firmware): exact at ``w``, at other speeds off by the variation of
    ``u_ss / w`` (the friction's and the commutation's share) and of the blended Kp, Kc.
    """
    if not w_rad_s > 0:
        raise ValueError("reference_ff_gain: the speed must be positive")
    g = law.gains_at(w_rad_s)
    return (u_ss_v + g.kc * i_ss_a) / w_rad_s + g.kp * (1.0 - law.setpoint_weight)


# ---------------------------------------------------------------------------
# The drive's rules around the law (the firmware's core_control runs them on raw values,
# picdrive.firmware.core_program; the averaged six-step simulation on volts)
# ---------------------------------------------------------------------------
def walk_cap(cap, over: bool, step, top):
    """The backup current limiter's cap on |u| after one sample: down by ``step`` (not below 0)
    while the measured current is over the limit, up by ``step`` (not above ``top``) otherwise.

    Parameters
    ----------
    cap, step, top : int or float
        The cap, its step per sample and its ceiling (the bridge's |u|), in one unit (V, or the
        firmware's Q qu counts).
    over : bool
        The sample's current exceeds the limit.

    The firmware's C forms the same values in int16 without overflow (``cap > step ? cap - step
    : 0``, ``cap < top - step ? cap + step : top``)."""
    return max(0 * step, cap - step) if over else min(top, cap + step)


def direction_hold(u, dir_now: int) -> tuple[int, bool]:
    """The bridge table after an output ``u``: ``(dir, hold)``, dir 0 forward, 1 reverse.  A new
    sign of a non-zero u changes the table and switches all outputs off for this sample (hold);
    u = 0 keeps the table."""
    newdir = 1 if u < 0 else 0
    if u != 0 and newdir != dir_now:
        return newdir, True
    return dir_now, False
