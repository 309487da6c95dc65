"""Mixed H2/H-inf PID speed controller by genetic algorithm (Duy et al. 2008).

The 2008 problem: find PID gains (kp, ki, kd) in a box D that minimise the
H2 cost J3 of the unit-step tracking error (eqs 11-15, 22) subject to
nominal closed-loop stability (Step 1) and the robust-stability constraint
``|| P C xi / (1 + P C) ||_inf <= 1`` (eqs 6-10), with the plant of eq 1
and the perturbation xi(s) = d/(s^2 + 0.1 s + 10) (eq 19).

Two variants (``variant=``):

``"paper"``
    The paper's continuous problem as printed: C(s) = kp + ki/s + kd s on
    the error, J3 by eq 22 (Jury-Dewey), the H-inf constraint exact by eq 9.
    Its gains ignore the sampling of the speed loop and the bus voltage;
    on the sampled loop they are usually unstable, and the verification
    says so (the design is then reported as failed, never saved as usable).

``"drive"`` (default)
    The same problem posed for the loop the firmware runs: picdrive's law
    (derivative on the measurement, setpoint weight b = 1, integral
    including the current sample) sampled at ``control.speed_loop_hz``, the
    plant behind a zero-order hold with one sample of computation delay and
    the speed measured as the mean over the last period
    (:func:`picdrive.models.tfmodel.sampled_plant`).  Cost: the discrete J3,
    ``Ts * sum e[k]^2`` of the unit-step error (the sampled counterpart of
    eq 11).  Constraints: Schur stability, eq 6 on the sampled loop (xi by
    the Tustin map prewarped at its resonance), and a sensitivity peak
    ``||1/(1 + L)||_inf <= ms_max`` (default 2: gain margin >= 2, phase
    margin >= 29 deg).  The last is picdrive's addition: with d = 0.1 the
    paper's constraint is ~0.316 for *any* loop with integral action (T ~ 1
    at xi's resonance, 3.16 rad/s), so it never binds and would let the
    optimiser push the loop to the edge of instability.  The search box is
    the profile's box cut down to the gains at which each term alone
    destabilises the sampled loop (Steps 1-2: the domain D).  The bus
    voltage enters as the law's output limits (+- bus voltage x max duty)
    with conditional integration; J3 is the small-signal (unsaturated) cost,
    and the saturated large step and a load-torque step are simulated in the
    verification.

    The search box of a gain whose range the profile does not give is
    derived from the sampled plant (:func:`plant_box`: kp <= Ku,
    ki <= Ku w180, kd <= its own stability limit), so it scales with the
    motor.  Inside the search every chromosome that meets the linear
    constraints is screened by the six-step step from rest (the batched
    DC-equivalent drive with the firmware's window, the verification's
    load-torque disturbance, and the drive's own speed measurement: the
    encoder's M/T, or the hall-edge period for ``sensors.speed_source =
    "hall"``): peak speed and peak current bounded.  The search's best is
    then verified in full (:func:`picdrive.design.verify.verify_design`:
    three-phase plant, R -+ 10 %, settling, current window, saturation); if
    it fails for overshoot or current, the screen is tightened by what the
    verification saw and the search runs again (option ``retunes``, default
    4), so the design returned is the best the search finds that verifies.

``design(profile, ...)`` returns a :class:`~picdrive.result.DesignResult`
whose law is one PID rule of :class:`~picdrive.control_law.ScheduledLaw`.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..control_law import Rule, ScheduledLaw
from ..errors import PicdriveError
from .ga import run_ga
from ..analysis.h2hinf import (hinf_exact_z, j3_discrete, j3_jury_dewey, pid_figures_continuous, pid_figures_sampled,
                               robust_constraint, robust_constraint_z, sampled_loop, sampled_loop_polys, schur_char,
                               schur_stable, sensitivity_peak, sensitivity_peak_z, tracking_error_polys, xi_tustin)
from ..analysis.steptest import load_disturbance, sim_plan
from ..result import DesignResult
from .verify import drive_limit_failed, pid_model_checks, verify_design
from ..models.tfmodel import TF, SampledPlant, motor_tf, sampled_plant, speed_quantum_rad_s

__all__ = ["MixedPidError", "Problem", "make_problem", "term_limits", "plant_box", "phase_crossover_rad_s",
           "evaluate", "design", "pid_law", "run_verify", "VARIANTS", "DEFAULTS"]

VARIANTS = ("drive", "paper")
RPM = 2.0 * math.pi / 60.0

# option -> (default, kind, lo, hi, meaning); None default = from the profile
DEFAULTS: dict[str, tuple] = {
    "d": (None, float, 0.0, 1e6, "perturbation parameter d of xi(s) (default: profile design.perturbation_d)"),
    "ms_max": (2.0, float, 1.05, 100.0, "drive: upper bound of the sensitivity peak ||S||_inf"),
    "delay_samples": (1, int, 0, 1, "drive: samples between measuring the speed and applying the voltage"),
    "measurement": ("average", str, None, None, "drive: speed measurement 'average' (over the period) or 'instant'"),
    "population": (None, int, 4, 100000, "GA population (default: profile design.ga_population)"),
    "generations": (None, int, 1, 100000, "GA generations (default: profile design.ga_generations)"),
    "digits": (7, int, 2, 12, "GA: magnitude digits per gain (Table 1 uses 5)"),
    "p_crossover": (0.8, float, 0.0, 1.0, "GA crossover probability"),
    "p_mutation": (0.05, float, 0.0, 1.0, "GA mutation probability per gene"),
    "elite": (1, int, 0, 1000, "GA: chromosomes copied unchanged to the next generation"),
    "current_fraction": (0.9, float, 0.01, 10.0, "drive: peak line current of the simulated step <= this x "
                         "inverter.overcurrent_trip_a (the current window holds the steady current at the limit)"),
    "overshoot_max_pct": (0.5, float, 0.0, 100.0, "drive: raw peak of the simulated six-step step above the "
                          "target (the bridge cannot brake) <= this, % of the step (half of the 1 % step target: the "
                          "model under-predicts the twin's overshoot by up to ~1 point near zero current)"),
    "de_popsize": (15, int, 4, 1000, "de: scipy population multiplier"),
    "de_maxiter": (300, int, 1, 100000, "de: scipy maximum generations"),
    "retunes": (4, int, 0, 20, "drive: searches after the first when its best fails the verification, each "
                "with the screen tightened by the failure (overshoot allowance, ki bound, peak current)"),
}


#: a gain the search ends on below this fraction of its bound (for a plant-derived bound: of the gain
#: that alone destabilises the loop) is set to 0: it does nothing measurable, and the firmware's fixed
#: point refuses a gain too small to act on one speed LSB
GAIN_FLOOR = 1e-3


class MixedPidError(PicdriveError, ValueError):
    """Bad options for the mixed H2/H-inf PID design."""


@dataclass
class Problem:
    """One mixed H2/H-inf PID problem: plant, variant, constraint data and the box."""

    variant: str
    plant: TF
    d: float
    ts: float
    lo: np.ndarray
    hi: np.ndarray
    ms_max: float
    sp: SampledPlant | None = None
    profile_box: tuple = ()
    limits: dict = field(default_factory=dict)
    profile: Any = None               # drive variant: the large-signal step
    step_rad_s: float = 0.0
    u_max_v: float = math.inf
    current_max_a: float = math.inf
    speed_max_rad_s: float = math.inf       # peak speed of the step: min(speed_max_rpm, target x (1 + overshoot))
    step_sim_s: float = 0.0
    xi_peak: float = math.inf          # ||xi_d||_inf of the Tustin xi (drive)
    step_cache: dict = field(default_factory=dict, repr=False)   # (kp, ki, kd) -> (peak current, peak speed)
    plant6: Any = None                 # the commutated six-step plant of the profile (built on first use)
    box_source: dict = field(default_factory=dict)   # gain -> "profile" (its range) or "plant" (plant_box)
    hall: Any = None                   # the drive's hall speed meter (sensors.speed_source = "hall"), else M/T
    disturbance: Any = None            # the verification's load-torque disturbance during the step (N m of t)

    def cost(self, gains: np.ndarray):
        """GA/DE interface: (cost, feasible) of gains (pop, 3)."""
        ev = evaluate(self, gains)
        return ev["j3"], ev["feasible"]


def evaluate(pb: Problem, gains, *, simulate_all: bool = False) -> dict[str, np.ndarray]:
    """Batched figures of gains (..., 3) = (kp, ki, kd) for a problem.

    Keys: ``j3`` (the variant's cost, s per unit step squared), ``hinf`` (eq 6
    value), ``stable``, ``ms`` (sensitivity peak), ``feasible``.  Drive
    variant: ``hinf`` is exact where ``hinf_exact`` is set; elsewhere (stable
    rows whose bound (1 + ||S||) ||xi|| is <= 1, which certifies eq 6 without
    the root computation) it holds that bound; ``step_peak_current_a`` and
    ``step_peak_speed_rad_s`` of the saturated step (simulated for the rows
    that meet every other constraint, or for every stable row with
    ``simulate_all``; nan elsewhere).
    """
    g = np.asarray(gains, float)
    kp, ki, kd = g[..., 0], g[..., 1], g[..., 2]
    if pb.variant == "paper":
        num, den = tracking_error_polys(pb.plant, kp, ki, kd, derivative="error")
        j3 = j3_jury_dewey(num, den)
        hinf, stable, _ = robust_constraint(pb.plant, kp, ki, kd, pb.d)
        ms, _ = sensitivity_peak(pb.plant, kp, ki, kd)
        feasible = stable & (hinf <= 1.0) & np.isfinite(j3)
    else:
        polys = sampled_loop_polys(pb.sp, kp, ki, kd)
        stable = schur_char(polys[0])
        ms, _ = sensitivity_peak_z(pb.sp, kp, ki, kd, polys=polys, stable=stable)
        # eq 6: ||T xi|| <= ||T|| ||xi|| <= (1 + ||S||) ||xi||; where that bound is <= 1 the constraint
        # holds and the exact value is not needed for the search (it is computed for the result)
        bound = (1.0 + ms) * pb.xi_peak
        need = stable & (bound > 1.0)
        hinf = np.where(stable, bound, np.inf)
        hinf_exact = np.zeros(np.shape(stable), bool)
        if np.any(need):
            kp_, ki_, kd_, need_ = np.broadcast_arrays(kp, ki, kd, need)
            h, _, _ = robust_constraint_z(pb.sp, kp_[need_], ki_[need_], kd_[need_], pb.d)
            hinf = np.array(hinf, float)
            hinf[need_] = h
            hinf_exact = need_
        ok = stable & (hinf <= 1.0) & (ms <= pb.ms_max)
        A, B, C = sampled_loop(pb.sp, kp, ki, kd)
        j3 = j3_discrete(A, B, C, pb.ts, stable=stable)
        feasible = ok & np.isfinite(j3)
        i_pk, w_pk = _step_peaks(pb, kp, ki, kd, stable if simulate_all else feasible)
        feasible = feasible & (i_pk <= pb.current_max_a) & (w_pk <= pb.speed_max_rad_s)
        return {"j3": j3, "hinf": hinf, "hinf_exact": hinf_exact, "stable": stable, "ms": ms,
                "feasible": feasible, "step_peak_current_a": i_pk, "step_peak_speed_rad_s": w_pk}
    return {"j3": j3, "hinf": hinf, "stable": stable, "ms": ms, "feasible": feasible}


def _step_peaks(pb: Problem, kp, ki, kd, rows) -> tuple[np.ndarray, np.ndarray]:
    """Peak |line current| and peak speed of the step from rest on the six-step drive (drive variant:
    :func:`picdrive.models.simulate.simulate_six_step_batch`, the law with its current window, the bridge's
    conduction rule, the firmware's measurement), for the selected rows; nan elsewhere."""
    from ..models.simulate import simulate_six_step_batch, six_step_plant
    kp, ki, kd, rows = np.broadcast_arrays(kp, ki, kd, rows)
    i_pk = np.full(kp.shape, np.nan)
    w_pk = np.full(kp.shape, np.nan)
    if rows.any() and pb.profile is not None:
        idx = np.flatnonzero(rows)
        keys = [(float(a), float(b), float(c)) for a, b, c in zip(kp.flat[idx], ki.flat[idx], kd.flat[idx])]
        new = sorted({k for k in keys if k not in pb.step_cache})          # the GA repeats chromosomes
        if new:
            g = np.array(new)
            if pb.plant6 is None:
                pb.plant6 = six_step_plant(pb.profile, commutated=True)
            sim = simulate_six_step_batch(pb.profile, g[:, 0], g[:, 1], g[:, 2], t_end_s=pb.step_sim_s,
                                          ref_rad_s=pb.step_rad_s, n_sub=4, plant=pb.plant6, hall=pb.hall,
                                          torque_disturbance=pb.disturbance)
            pb.step_cache.update(zip(new, zip(sim["peak_current_a"].tolist(), sim["peak_speed_rad_s"].tolist())))
        i_pk.flat[idx] = [pb.step_cache[k][0] for k in keys]
        w_pk.flat[idx] = [pb.step_cache[k][1] for k in keys]
    return i_pk, w_pk


def term_limits(sp: SampledPlant) -> dict[str, float]:
    """Largest kp, ki, kd for which the sampled loop with that term alone is stable.

    (kp alone: the ultimate gain of the sampled loop, also used by
    Ziegler-Nichols.)  Found by doubling and bisection on the spectral radius.
    """
    n = sp.n

    def stable(term, g):
        k = {"kp": 0.0, "ki": 0.0, "kd": 0.0}
        k[term] = g
        A, _, _ = sampled_loop(sp, k["kp"], k["ki"], k["kd"])
        if k["ki"] == 0.0:                      # the integrator state is decoupled (eigenvalue 1)
            A = np.delete(np.delete(A, n, 0), n, 1)
        return bool(schur_stable(A)[1] < 1.0)        # no margin: tiny ki puts a pole at 1 - O(ki)

    out = {}
    for term in ("kp", "ki", "kd"):
        g = 1e-9
        while stable(term, 2 * g) and g < 1e12:
            g *= 2
        lo, hi = g, 2 * g
        for _ in range(60):
            mid = math.sqrt(lo * hi)
            if stable(term, mid):
                lo = mid
            else:
                hi = mid
        out[term] = lo
    return out


def plant_box(sp: SampledPlant, limits: dict[str, float] | None = None) -> np.ndarray:
    """Upper bounds (kp, ki, kd) of the search box derived from the sampled plant, for the gains
    whose range the profile does not give.

    With ``Ku`` the ultimate gain of the sampled proportional loop (the plant's DC gain and time
    constants behind the hold, the computation delay and the speed measurement at the loop rate:
    :func:`term_limits`) and ``w180`` its phase crossover (:func:`phase_crossover_rad_s`):

    * ``kp <= Ku``: above it the proportional term alone destabilises the loop;
    * ``ki <= Ku w180``: at the phase crossover the integral path's gain ``ki / w180`` then reaches
      the ultimate gain.  Every row of the Ziegler-Nichols ultimate-point table lies inside with
      room to spare (classic ``ki = 0.19 Ku w180``, Pessen's 0.28);
    * ``kd <= `` the derivative term's own stability limit (:func:`term_limits`; at the loop rate
      ``kd / Ts`` acts like a proportional gain on the speed change of one sample).

    So the box scales with the motor: a slow, heavy drive gets a small ki bound, a fast light one
    a large one, where a fixed default (``ki <= 10 V/rad``) bound some motors' designs and left
    others' mostly unstable."""
    lim = term_limits(sp) if limits is None else limits
    return np.array([lim["kp"], lim["kp"] * phase_crossover_rad_s(sp), lim["kd"]], float)


def phase_crossover_rad_s(sp: SampledPlant) -> float:
    """The first phase crossover w180 (rad/s) of the sampled plant, where its phase reaches -180 deg
    below the Nyquist frequency (the frequency of the ultimate oscillation)."""
    from scipy.optimize import brentq
    ptf, ts = sp.tf_z, sp.ts

    def resp(w):
        z = np.exp(1j * w * ts)
        return np.polyval(ptf.num, z) / np.polyval(ptf.den, z)

    w = np.linspace(1e-6, math.pi / ts, 20001)[1:]
    ph = np.unwrap(np.angle(resp(w)))
    k = np.nonzero(ph <= -math.pi)[0]
    if k.size == 0:
        raise MixedPidError("the sampled loop has no phase crossover below the Nyquist frequency: no ultimate gain")
    k = int(k[0])
    return float(brentq(lambda x: np.imag(resp(x)), w[k - 1], w[k], xtol=1e-12))


def _opt(options: dict, name: str, profile_default=None):
    default, kind, lo, hi, meaning = DEFAULTS[name]
    v = options.get(name, default if default is not None else profile_default)
    if kind is str:
        if not isinstance(v, str):
            raise MixedPidError(f"option {name}={v!r}: expected a string ({meaning})")
        return v
    try:
        if isinstance(v, bool):
            raise TypeError
        val = kind(v)
        if kind is int and val != v:
            raise TypeError
    except (TypeError, ValueError):
        raise MixedPidError(f"option {name}={v!r}: expected {'an integer' if kind is int else 'a number'} "
                            f"in [{lo}, {hi}] ({meaning})") from None
    if not (lo <= val <= hi) or (kind is float and not math.isfinite(val)):
        raise MixedPidError(f"option {name}={v!r} is outside [{lo}, {hi}] ({meaning})")
    return val


def make_problem(profile, variant: str = "drive", *, drive=None, **options) -> Problem:
    """Build the problem of a profile (options as in :data:`DEFAULTS`).

    ``drive`` (:class:`picdrive.gate.BuiltDrive`): where the profile measures its speed from the
    halls (``sensors.speed_source = "hall"``), the search's step is simulated with the drive's
    hall-edge measurement (``drive.speed_measurement``), the loop the firmware closes; without
    ``drive``, or with an encoder, with the encoder's M/T measurement."""
    if variant not in VARIANTS:
        raise MixedPidError(f"mixed-pid variant {variant!r} is unknown; choose one of {', '.join(VARIANTS)}")
    de = profile.design
    d = _opt(options, "d", de["perturbation_d"])
    ms_max = _opt(options, "ms_max")
    delay = _opt(options, "delay_samples")
    meas = _opt(options, "measurement")
    if meas not in ("average", "instant"):
        raise MixedPidError(f"option measurement={meas!r}: expected 'average' or 'instant'")
    names = ("kp_range", "ki_range", "kd_range")
    given = set((getattr(profile, "raw", None) or {}).get("design", {})) & set(names)
    box_lo = np.array([de[n][0] for n in names], float)
    box_hi = np.array([de[n][1] for n in names], float)
    for name, a, b in zip(names, box_lo, box_hi):
        if not b > a:
            raise MixedPidError(f"profile field 'design.{name}' = [{a:g}, {b:g}] must be increasing")
        if a < 0:
            raise MixedPidError(f"profile field 'design.{name}' = [{a:g}, {b:g}]: the PID gains of a speed loop "
                                "around this plant must be >= 0; set the lower bound to 0 or more")
    plant = motor_tf(profile)
    ts = 1.0 / profile.control.speed_loop_hz
    sp = sampled_plant(plant, ts, delay_samples=delay, measurement=meas)
    lo, hi = box_lo.copy(), box_hi.copy()
    limits = {}
    box_source = {n[:2]: "profile" for n in names}
    if variant == "drive":
        limits = term_limits(sp)
        cut = np.array([limits["kp"], limits["ki"], limits["kd"]])
        plant_hi = plant_box(sp, limits)
        for j, name in enumerate(names):
            if name not in given:          # no range in the profile: the plant's box
                lo[j], hi[j], cut[j] = 0.0, plant_hi[j], plant_hi[j]
                box_lo[j], box_hi[j] = 0.0, plant_hi[j]
                box_source[name[:2]] = "plant"
        hi = np.minimum(hi, cut)
        if np.any(hi <= lo):
            raise MixedPidError(
                f"the profile's gain box kp {de['kp_range']}, ki {de['ki_range']}, kd {de['kd_range']} lies outside "
                f"the gains the sampled loop at {profile.control.speed_loop_hz:g} Hz tolerates "
                f"(kp < {limits['kp']:.4g}, ki < {limits['ki']:.4g}, kd < {limits['kd']:.4g}); lower the range's "
                "lower bounds in the profile's [design] section")
    pb = Problem(variant=variant, plant=plant, d=d, ts=ts, lo=lo, hi=hi, ms_max=ms_max, sp=sp,
                 profile_box=(box_lo.tolist(), box_hi.tolist()), limits=limits, box_source=box_source)
    if variant == "drive":
        m = profile.motor
        tau = max(m.inertia_kg_m2 * m.r_line_ohm / (m.kt_n_m_per_a * m.kb_v_s_per_rad), m.l_line_h / m.r_line_ohm)
        pb.profile = profile
        pb.step_rad_s = profile.speed_step_rpm() * RPM
        pb.u_max_v = profile.inverter.bus_voltage_v * profile.max_duty()
        pb.current_max_a = _opt(options, "current_fraction") * profile.inverter.overcurrent_trip_a
        pb.speed_max_rad_s = min(profile.control.speed_max_rpm * RPM,
                                 pb.step_rad_s * (1.0 + _opt(options, "overshoot_max_pct") / 100.0))
        pb.step_sim_s = min(max(0.15, 15 * tau), 0.5)
        xi = xi_tustin(d, ts)
        pb.xi_peak = float(hinf_exact_z(xi.num, xi.den)[0])
        w3 = load_disturbance(sim_plan(profile))           # tabled once at the samples (held over each)
        w3_k = np.array([w3(k * ts) for k in range(int(round(pb.step_sim_s / ts)) + 1)])
        pb.disturbance = lambda t: float(w3_k[min(int(round(t / ts)), w3_k.size - 1)])
        if drive is not None and profile.sensors.speed_source == "hall":
            mid = 0.5 * (lo + hi)                  # the meter does not depend on the gains
            pb.hall = drive.speed_measurement(profile, pid_law(profile, *mid))["hall"]
    return pb


def pid_law(profile, kp: float, ki: float, kd: float, notes: str = "") -> ScheduledLaw:
    """One-rule ScheduledLaw (plain PID, b = 1, derivative on measurement) for a profile, with the
    firmware's current window (the profile's current limit, Kb and line R)."""
    u = profile.inverter.bus_voltage_v * profile.max_duty()
    prem = tuple(float(x) * RPM for x in profile.design["premise_rpm"])
    m = profile.motor
    return ScheduledLaw(rules=(Rule(float(kp), float(ki), float(kd)),), premise_rad_s=prem,
                        sample_time_s=1.0 / profile.control.speed_loop_hz, u_min_v=-u, u_max_v=u,
                        setpoint_weight=1.0, derivative_filter_hz=None, notes=notes,
                        current_limit_a=profile.inverter.current_limit_a, kb_v_s_per_rad=m.kb_v_s_per_rad,
                        r_ohm=m.r_line_ohm)


def run_verify(profile, result: DesignResult, drive) -> DesignResult:
    """:func:`picdrive.design.verify.verify_design` against ``drive``, timed in ``timings_s``."""
    t0 = time.perf_counter()
    verify_design(profile, result, drive=drive)
    result.timings_s["verify_design"] = time.perf_counter() - t0
    return result


def design(profile, *, drive=None, progress: bool = True, optimizer: str = "ga", seed: int | None = None,
           variant: str = "drive", **options) -> DesignResult:
    """Mixed H2/H-inf PID design of a profile; the result comes back verified (or failed).

    ``optimizer``: ``"ga"`` (the paper's decimal GA) or ``"de"``
    (``scipy.optimize.differential_evolution`` on the same box and
    constraints).  ``seed`` defaults to the profile's ``design.ga_seed``.
    Other options: see :data:`DEFAULTS`.
    """
    unknown = set(options) - set(DEFAULTS)
    if unknown:
        raise MixedPidError(f"unknown mixed-pid option(s) {', '.join(sorted(unknown))}; accepted: "
                            f"variant, optimizer, seed, {', '.join(DEFAULTS)}")
    if optimizer not in ("ga", "de"):
        raise MixedPidError(f"optimizer {optimizer!r} is unknown; choose 'ga' (genetic algorithm) or 'de' "
                            "(scipy differential evolution)")
    de = profile.design
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= 2**31 - 1):
        raise MixedPidError(f"seed {seed!r}: expected an integer in [0, 2147483647] (the GA's random seed)")
    seed = de["ga_seed"] if seed is None else int(seed)
    t0 = time.perf_counter()
    pb = make_problem(profile, variant, drive=drive, **options)
    t_setup = time.perf_counter() - t0
    used = {"variant": variant, "optimizer": optimizer, "seed": seed,
            **{k: (_opt(options, k, de["perturbation_d"]) if k == "d" else
                   _opt(options, k, de["ga_population"]) if k == "population" else
                   _opt(options, k, de["ga_generations"]) if k == "generations" else _opt(options, k))
               for k in DEFAULTS}}
    retunes = used["retunes"] if variant == "drive" else 0
    tries: list[dict[str, Any]] = []
    t_opt = 0.0
    res = None
    while True:
        screen = {"overshoot_max_pct": 100.0 * (pb.speed_max_rad_s / pb.step_rad_s - 1.0) if pb.step_rad_s else None,
                  "current_max_a": pb.current_max_a, "ki_max": float(pb.hi[1])}
        t1 = time.perf_counter()
        best, found, opt_info = _optimise(pb, profile, optimizer, options, seed, progress)
        best = _snap_small_gains(pb, best)
        t_opt += time.perf_counter() - t1
        if res is not None and not found:        # a tightened screen nothing passes: keep the last design
            tries.append({"screen": screen, "status": "nothing feasible", "failed": []})
            res.timings_s["optimizer"] = t_opt
            break
        res = _result(profile, pb, best, found, opt_info, used, variant, optimizer)
        res.timings_s.update(setup=t_setup, optimizer=t_opt)
        t2 = time.perf_counter()
        pid_model_checks(profile, res, ms_max=pb.ms_max if variant == "drive" else None,
                         delay_samples=used["delay_samples"], measurement=used["measurement"], d=pb.d)
        res.timings_s["checks"] = time.perf_counter() - t2
        run_verify(profile, res, drive)
        g = res.law.rules[0]
        tries.append({"gains": {"kp_v_per_rad_s": g.kp, "ki_v_per_rad": g.ki, "kd_v_s2_per_rad": g.kd},
                      "screen": screen, "status": res.status,
                      "failed": [k for k, c in res.verification.items() if not c.get("ok", True)]})
        if res.ok or not found or len(tries) > retunes or drive_limit_failed(res):
            break
        step = _retune(pb, res)
        if step is None:
            break
        tries[-1]["retune"] = step
    if variant == "drive":
        res.certificate["retune_tries"] = tries
        if not res.ok and len(tries) > 1:
            res.fail(f"no design of {len(tries)} searches verified (each search's best, with the screen "
                     "tightened by the previous one's failure): " + "; ".join(
                         (f"kp {t['gains']['kp_v_per_rad_s']:.4g}, ki {t['gains']['ki_v_per_rad']:.4g}, "
                          f"kd {t['gains']['kd_v_s2_per_rad']:.4g}: {', '.join(t['failed']) or t['status']}")
                         if "gains" in t else f"screen {t['screen']}: nothing feasible" for t in tries))
    return res


def _snap_small_gains(pb: Problem, best) -> np.ndarray:
    """``best`` with every gain below :data:`GAIN_FLOOR` x its search bound set to 0 (where the box
    holds 0), kept only if the snapped gains still meet the search's constraints."""
    best = np.asarray(best, float)
    snapped = np.where((np.abs(best) < GAIN_FLOOR * pb.hi) & (pb.lo <= 0.0), 0.0, best)
    if np.array_equal(snapped, best) or not bool(evaluate(pb, snapped)["feasible"]):
        return best
    return snapped


#: verification checks whose failure the screen can steer away from: a peak speed too high
_OVERSHOOT_CHECKS = ("sim_overshoot_pct", "sim_peak_rpm")
#: ... and a current too high (the trip, or the window needing the firmware's walk-down backup)
_CURRENT_CHECKS = ("sim_peak_bus_current_a", "sim_current_backup_samples")


def _retune(pb: Problem, res: DesignResult) -> dict[str, Any] | None:
    """Tighten the search's screen after ``res`` (the search's best) failed its verification, so the
    next search keeps away from what failed; ``None`` when no failure is one the screen can steer.

    * overshoot (``sim_overshoot_pct``, ``sim_peak_rpm``, or the overshoot at R -+ 10 %): the screen's
      overshoot allowance becomes the failed design's screened overshoot scaled by the verification's
      limit over its figure, x 0.9 (the screen is the DC-equivalent step, the verification the
      three-phase one with disturbances: their ratio is what the screen misses).  Where the screen
      already saw no overshoot, the integral bound comes down to 0.7 x the failed ki instead (the
      overshoot is the integrator's charge at the end of the acceleration; the bridge cannot brake);
    * current (the trip, the walk-down backup, or the peak current at R -+ 10 %): the screen's peak
      current bound becomes 0.9 x the failed design's screened peak."""
    v = res.verification
    g = res.law.rules[0]
    band_pct = float(v.get("sim_overshoot_pct", {}).get("limit", 2.0))
    trip = pb.profile.inverter.overcurrent_trip_a
    ov_fail = [float(v[k]["value"]) if k == "sim_overshoot_pct" else band_pct * 1.25
               for k in _OVERSHOOT_CHECKS if k in v and not v[k].get("ok", True)]
    cur_fail = any(k in v and not v[k].get("ok", True) for k in _CURRENT_CHECKS)
    ru = v.get("sim_resistance_uncertainty", {})
    if not ru.get("ok", True) and isinstance(ru.get("value"), dict):
        for fig in ru["value"].values():
            if isinstance(fig, dict):
                if fig.get("overshoot_pct", 0.0) > band_pct:
                    ov_fail.append(float(fig["overshoot_pct"]))
                if fig.get("peak_current_ripple_a", 0.0) >= trip:
                    cur_fail = True
    if not ov_fail and not cur_fail:
        return None
    ev = evaluate(pb, np.array([g.kp, g.ki, g.kd]), simulate_all=True)
    w_pk, i_pk = float(ev["step_peak_speed_rad_s"]), float(ev["step_peak_current_a"])
    step: dict[str, Any] = {}
    if ov_fail:
        seen = max(0.0, 100.0 * (w_pk / pb.step_rad_s - 1.0))
        worst = max(ov_fail)
        allow = 0.9 * seen * band_pct / max(worst, band_pct)
        if seen > 0.0 and allow < 100.0 * (pb.speed_max_rad_s / pb.step_rad_s - 1.0):
            pb.speed_max_rad_s = pb.step_rad_s * (1.0 + allow / 100.0)
            step["overshoot_max_pct"] = allow
        else:
            pb.hi[1] = max(min(pb.hi[1], 0.7 * g.ki), pb.lo[1] + 1e-12 * max(1.0, pb.hi[1]))
            step["ki_max"] = float(pb.hi[1])
        step["verified_overshoot_pct"] = worst
        step["screened_overshoot_pct"] = seen
    if cur_fail and math.isfinite(i_pk):
        pb.current_max_a = min(pb.current_max_a, 0.9 * i_pk)
        step["current_max_a"] = pb.current_max_a
        step["screened_peak_current_a"] = i_pk
    return step or None


def _optimise(pb: Problem, profile, optimizer: str, options: dict, seed: int, progress: bool):
    """One search of ``pb``: (best gains, found feasible, optimiser record)."""
    de = profile.design
    if optimizer == "ga":
        pop = _opt(options, "population", de["ga_population"])
        gens = _opt(options, "generations", de["ga_generations"])
        r = run_ga(pb.cost, pb.lo, pb.hi, population=pop, generations=gens, digits=_opt(options, "digits"),
                   p_crossover=_opt(options, "p_crossover"), p_mutation=_opt(options, "p_mutation"),
                   elite=_opt(options, "elite"), seed=seed, progress=progress, desc=f"GA {profile.name}")
        return r.best, r.best_feasible, {
            "optimizer": "ga", "population": pop, "generations": gens, "decimal_constants": r.decimal_constants,
            "best_cost_per_generation": r.history_best, "feasible_fraction_per_generation": r.history_feasible,
            "evaluations": r.n_evaluations}
    return _run_de(pb, seed, _opt(options, "de_popsize"), _opt(options, "de_maxiter"))


def _result(profile, pb: Problem, best, found: bool, opt_info: dict, used: dict, variant: str,
            optimizer: str) -> DesignResult:
    """The design result of one search's best gains (not yet verified)."""
    kp, ki, kd = (float(x) for x in best)
    ev = {k: (v.item() if hasattr(v, "item") else v) for k, v in evaluate(pb, best).items()}
    notes = (f"mixed H2/H-inf PID ({variant} variant, {optimizer}); derivative on measurement, b = 1")
    law = pid_law(profile, kp, ki, kd, notes)
    cert: dict[str, Any] = {
        "gains": {"kp_v_per_rad_s": kp, "ki_v_per_rad": ki, "kd_v_s2_per_rad": kd},
        "cost": "J3 = integral of e^2 for a unit step (eq 22)" if variant == "paper"
                else "J3 = Ts sum e[k]^2 for a unit step of the sampled loop",
        "j3_s": ev["j3"], "sensitivity_peak": ev["ms"], "feasible": bool(ev["feasible"]),
        "step_peak_current_a": ev.get("step_peak_current_a"), "step_peak_speed_rad_s": ev.get("step_peak_speed_rad_s"),
        "plant_tf": {"num": pb.plant.num, "den": pb.plant.den},
        "perturbation_d": pb.d, "search_box": {"lo": pb.lo.copy(), "hi": pb.hi.copy()}, "profile_box": pb.profile_box,
        "search_box_source": dict(pb.box_source),
        "stability_limits_per_term": pb.limits,
        "volts_per_count_if_position_difference": (kp + kd * profile.control.speed_loop_hz) * speed_quantum_rad_s(profile),
        "optimizer": opt_info,
    }
    cert.update(pid_figures_continuous(pb.plant, kp, ki, kd, pb.d))
    cert.update(pid_figures_sampled(pb.sp, kp, ki, kd, pb.d))
    cert["hinf_constraint"] = cert.get("hinf_constraint_continuous" if variant == "paper" else "hinf_constraint_sampled",
                                       math.inf)
    res = DesignResult(method="mixed-pid", variant=variant, status="verified", profile_name=profile.name,
                       profile_sha256=profile.sha256, profile_path=str(profile.path) if profile.path else None,
                       law=law, options=used, certificate=cert, timings_s={})
    if not found:
        res.fail(f"the {optimizer} found no gains in the box {pb.lo.tolist()}..{pb.hi.tolist()} that meet the "
                 "constraints (stability, eq 6" + (f", ||S||_inf <= {pb.ms_max:g})" if variant == "drive" else ")"))
    return res


def _run_de(pb: Problem, seed: int, popsize: int, maxiter: int):
    """scipy differential evolution on the same box and constraints (Lampinen's feasibility rules)."""
    from scipy.optimize import NonlinearConstraint, differential_evolution

    big = 1e9
    count = [0]

    def f(x):                                   # x: (3, S)
        count[0] += x.shape[1] if x.ndim == 2 else 1
        ev = evaluate(pb, x.T)
        return np.where(np.isfinite(ev["j3"]), ev["j3"], big)

    def g(x):                                   # (4, S) <= 0
        ev = evaluate(pb, x.T, simulate_all=True)
        fin = lambda a: np.where(np.isfinite(a), a, big)
        h = fin(ev["hinf"]) - 1.0
        if pb.variant != "drive":
            return np.vstack([h])
        m = fin(ev["ms"]) - pb.ms_max
        i = fin(ev["step_peak_current_a"]) - pb.current_max_a
        w = fin(ev["step_peak_speed_rad_s"]) - pb.speed_max_rad_s
        return np.vstack([h, m, i / max(pb.current_max_a, 1e-9), w / max(pb.speed_max_rad_s, 1e-9)])

    span = np.maximum(pb.hi - pb.lo, 1e-300)
    r = differential_evolution(f, list(zip(pb.lo, pb.hi)), constraints=NonlinearConstraint(g, -np.inf, 0.0),
                               seed=seed, popsize=popsize, maxiter=maxiter, tol=1e-10, atol=0.0,
                               polish=False, vectorized=True, updating="deferred")
    ev = evaluate(pb, r.x)
    found = bool(ev["feasible"])
    return np.asarray(r.x, float), found, {"optimizer": "de", "evaluations": count[0], "nit": int(r.nit),
                                           "message": str(r.message), "relative_box": ((r.x - pb.lo) / span).tolist()}
