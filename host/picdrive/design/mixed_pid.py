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
from ..analysis.h2hinf import hinf_exact_z, xi_tustin, j3_discrete, j3_jury_dewey, h2_lyapunov, robust_constraint, robust_constraint_z, routh_hurwitz, sampled_loop, sampled_loop_polys, schur_char, schur_stable, sensitivity_peak, sensitivity_peak_z, tracking_error_polys
from ..result import DesignResult
from ..models.tfmodel import TF, SampledPlant, loop_polys, motor_tf, sampled_plant, simulate_sampled, speed_quantum_rad_s

__all__ = ["MixedPidError", "Problem", "make_problem", "term_limits", "evaluate", "design", "pid_law",
           "check_pid_design", "VARIANTS", "DEFAULTS"]

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
                          "target (the bridge cannot brake) <= this, % of the step (half of issue 5's 1 %: the "
                          "model under-predicts the twin's overshoot by up to ~1 point near zero current)"),
    "de_popsize": (15, int, 4, 1000, "de: scipy population multiplier"),
    "de_maxiter": (300, int, 1, 100000, "de: scipy maximum generations"),
}


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
                                          ref_rad_s=pb.step_rad_s, n_sub=4, plant=pb.plant6)
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


def make_problem(profile, variant: str = "drive", **options) -> Problem:
    """Build the problem of a profile (options as in :data:`DEFAULTS`)."""
    if variant not in VARIANTS:
        raise MixedPidError(f"mixed-pid variant {variant!r} is unknown; choose one of {', '.join(VARIANTS)}")
    de = profile.design
    d = _opt(options, "d", de["perturbation_d"])
    ms_max = _opt(options, "ms_max")
    delay = _opt(options, "delay_samples")
    meas = _opt(options, "measurement")
    if meas not in ("average", "instant"):
        raise MixedPidError(f"option measurement={meas!r}: expected 'average' or 'instant'")
    box_lo = np.array([de["kp_range"][0], de["ki_range"][0], de["kd_range"][0]], float)
    box_hi = np.array([de["kp_range"][1], de["ki_range"][1], de["kd_range"][1]], float)
    for name, a, b in zip(("kp_range", "ki_range", "kd_range"), box_lo, box_hi):
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
    if variant == "drive":
        limits = term_limits(sp)
        hi = np.minimum(hi, [limits["kp"], limits["ki"], limits["kd"]])
        if np.any(hi <= lo):
            raise MixedPidError(
                f"the profile's gain box kp {de['kp_range']}, ki {de['ki_range']}, kd {de['kd_range']} lies outside "
                f"the gains the sampled loop at {profile.control.speed_loop_hz:g} Hz tolerates "
                f"(kp < {limits['kp']:.4g}, ki < {limits['ki']:.4g}, kd < {limits['kd']:.4g}); lower the range's "
                "lower bounds in the profile's [design] section")
    pb = Problem(variant=variant, plant=plant, d=d, ts=ts, lo=lo, hi=hi, ms_max=ms_max, sp=sp,
                 profile_box=(box_lo.tolist(), box_hi.tolist()), limits=limits)
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


def _continuous_figures(plant: TF, kp, ki, kd, d) -> dict[str, Any]:
    char, _ = loop_polys(plant, kp, ki, kd)
    stable = bool(routh_hurwitz(char))
    out = {"stable_continuous": stable, "closed_loop_poles_continuous": np.roots(char)}
    if stable:
        ne, de_ = tracking_error_polys(plant, kp, ki, kd, derivative="error")
        nm, dm = tracking_error_polys(plant, kp, ki, kd, derivative="measurement")
        out["j3_continuous_error_form_s"] = float(j3_jury_dewey(ne, de_))
        out["j3_continuous_error_form_lyapunov_s"] = float(h2_lyapunov(ne, de_))
        out["j3_continuous_measurement_form_s"] = float(j3_jury_dewey(nm, dm))
        out["hinf_constraint_continuous"] = float(robust_constraint(plant, kp, ki, kd, d)[0])
    return out


def _sampled_figures(sp: SampledPlant, kp, ki, kd, d) -> dict[str, Any]:
    A, B, C = sampled_loop(sp, kp, ki, kd)
    stable, rho = schur_stable(A)
    out = {"spectral_radius_sampled": float(rho), "stable_sampled": bool(stable),
           "closed_loop_poles_sampled_z": np.linalg.eigvals(A)}
    if stable:
        out["j3_sampled_s"] = float(j3_discrete(A, B, C, sp.ts))
        h, _, wh = robust_constraint_z(sp, kp, ki, kd, d)
        ms, wms = sensitivity_peak_z(sp, kp, ki, kd)
        out.update(hinf_constraint_sampled=float(h), hinf_constraint_sampled_w_rad_s=float(wh),
                   sensitivity_peak_sampled=float(ms), sensitivity_peak_w_rad_s=float(wms),
                   gain_margin_lower_bound=float(ms / (ms - 1.0)) if ms > 1 else math.inf,
                   phase_margin_lower_bound_deg=float(math.degrees(2 * math.asin(min(1.0, 0.5 / ms)))))
    return out


def check_pid_design(profile, result: DesignResult, *, ms_max: float | None = None,
                     delay_samples: int = 1, measurement: str = "average", d: float | None = None) -> None:
    """picdrive's own checks of a PID law on the eq 1 model (fills ``verification``, fails on error).

    * the sampled closed loop is stable (spectral radius < 1);
    * eq 6 on the sampled loop <= 1;
    * the sensitivity peak <= ``ms_max`` (when given);
    * a nonlinear simulation of the law (saturation, anti-windup) on eq 1:
      step from rest to ``profile.speed_step_rpm()``, then the profile's
      load-torque step; the step must settle (2 %) before the load is
      applied and the speed must be back within 1 % at the end.
    """
    law = result.law
    g = law.rules[0]
    d = profile.design["perturbation_d"] if d is None else d
    sp = sampled_plant(motor_tf(profile), law.sample_time_s, delay_samples=delay_samples, measurement=measurement)
    fig = _sampled_figures(sp, g.kp, g.ki, g.kd, d)
    v = result.verification
    v["pid_sampled_spectral_radius"] = {"value": round(fig["spectral_radius_sampled"], 6), "limit": 1.0,
                                    "ok": fig["stable_sampled"]}
    if not fig["stable_sampled"]:
        result.fail(f"the sampled closed loop at {1 / law.sample_time_s:g} Hz (ZOH, {delay_samples} sample delay, "
                    f"{measurement} speed) is unstable: spectral radius {fig['spectral_radius_sampled']:.4g} >= 1")
        return
    v["pid_hinf_constraint_sampled"] = {"value": round(fig["hinf_constraint_sampled"], 6), "limit": 1.0,
                                    "ok": fig["hinf_constraint_sampled"] <= 1.0}
    if fig["hinf_constraint_sampled"] > 1.0:
        result.fail(f"robust constraint ||P C xi/(1+PC)||_inf = {fig['hinf_constraint_sampled']:.4g} > 1 (eq 6, d = {d:g})")
    if ms_max is not None:
        ok = fig["sensitivity_peak_sampled"] <= ms_max * (1 + 1e-9)
        v["pid_sensitivity_peak"] = {"value": round(fig["sensitivity_peak_sampled"], 4), "limit": ms_max, "ok": ok}
        if not ok:
            result.fail(f"sensitivity peak {fig['sensitivity_peak_sampled']:.4g} exceeds {ms_max:g}")
    else:
        v["pid_sensitivity_peak"] = {"value": round(fig["sensitivity_peak_sampled"], 4)}
    # nonlinear simulation
    from ..analysis.metrics import step_metrics
    A, _, _ = sampled_loop(sp, g.kp, g.ki, g.kd)
    rho = max(fig["spectral_radius_sampled"], 1e-9)
    tau = law.sample_time_s / max(-math.log(rho), 1e-9)
    m = profile.motor
    tau_m = m.inertia_kg_m2 * m.r_line_ohm / (m.kt_n_m_per_a * m.kb_v_s_per_rad)
    phase = min(max(0.1, 12 * tau, 12 * tau_m), 20.0)
    ref = profile.speed_step_rpm() * RPM
    sim = simulate_sampled(profile, law, t_end_s=2 * phase, ref_rad_s=ref, load_n_m=profile.control.load_torque_n_m,
                           t_load_s=phase, delay_samples=delay_samples, measurement=measurement)
    t, w = sim["t_s"], sim["speed_rad_s"]
    first = t < phase
    sm = step_metrics(t[first], w[first], ref)
    end_err = abs(ref - float(np.mean(w[-max(3, len(w) // 50):]))) / ref * 100
    sat = float(np.mean(np.abs(sim["u_v"][first]) >= law.u_max_v * (1 - 1e-9)))
    v["pid_tf_step"] = {"value": {"step_rpm": round(ref / RPM, 2), "rise_ms": round(sm.rise_time_s * 1e3, 3),
                                     "settling_ms": round(sm.settling_time_s * 1e3, 3) if math.isfinite(sm.settling_time_s) else "inf",
                                     "overshoot_pct": round(sm.overshoot_pct, 3),
                                     "saturated_fraction": round(sat, 3)},
                           "limit": f"settles (2 %) within {phase * 1e3:.0f} ms",
                           "ok": math.isfinite(sm.settling_time_s)}
    if not math.isfinite(sm.settling_time_s):
        result.fail(f"the simulated step to {ref / RPM:.0f} rpm (saturating law on eq 1) does not settle "
                    f"within {phase * 1e3:.0f} ms")
    v["pid_tf_load_step"] = {"value": {"load_n_m": profile.control.load_torque_n_m,
                                          "final_error_pct": round(end_err, 4),
                                          "min_speed_rpm": round(float(np.min(w[~first])) / RPM, 2)},
                                "limit": "final error <= 1 %", "ok": end_err <= 1.0}
    if end_err > 1.0:
        result.fail(f"after the {profile.control.load_torque_n_m:g} N m load step the speed is {end_err:.3g} % "
                    "off the reference at the end of the simulation")


def run_verify(profile, result: DesignResult) -> DesignResult:
    """picdrive.design.verify.verify_design, when it is part of this checkout."""
    try:
        from .verify import verify_design
    except ModuleNotFoundError as e:
        if e.name != "picdrive.design.verify":
            raise
        result.verification["verify_design"] = {"value": "not available in this checkout"}
        return result
    t0 = time.perf_counter()
    out = verify_design(profile, result)
    result = out if isinstance(out, DesignResult) else result
    result.timings_s["verify_design"] = time.perf_counter() - t0
    return result


def design(profile, *, progress: bool = True, optimizer: str = "ga", seed: int | None = None,
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
    pb = make_problem(profile, variant, **options)
    t_setup = time.perf_counter() - t0
    opt_info: dict[str, Any] = {}
    t1 = time.perf_counter()
    if optimizer == "ga":
        pop = _opt(options, "population", de["ga_population"])
        gens = _opt(options, "generations", de["ga_generations"])
        r = run_ga(pb.cost, pb.lo, pb.hi, population=pop, generations=gens, digits=_opt(options, "digits"),
                   p_crossover=_opt(options, "p_crossover"), p_mutation=_opt(options, "p_mutation"),
                   elite=_opt(options, "elite"), seed=seed, progress=progress, desc=f"GA {profile.name}")
        best, found = r.best, r.best_feasible
        opt_info = {"optimizer": "ga", "population": pop, "generations": gens,
                    "decimal_constants": r.decimal_constants, "best_cost_per_generation": r.history_best,
                    "feasible_fraction_per_generation": r.history_feasible, "evaluations": r.n_evaluations}
    else:
        best, found, opt_info = _run_de(pb, seed, _opt(options, "de_popsize"), _opt(options, "de_maxiter"))
    t_opt = time.perf_counter() - t1
    kp, ki, kd = (float(x) for x in best)
    ev = {k: (v.item() if hasattr(v, "item") else v) for k, v in evaluate(pb, best).items()}
    used = {"variant": variant, "optimizer": optimizer, "seed": seed,
            **{k: (_opt(options, k, de["perturbation_d"]) if k == "d" else
                   _opt(options, k, de["ga_population"]) if k == "population" else
                   _opt(options, k, de["ga_generations"]) if k == "generations" else _opt(options, k))
               for k in DEFAULTS}}
    notes = (f"mixed H2/H-inf PID ({variant} variant, {optimizer}); derivative on measurement, b = 1")
    law = pid_law(profile, kp, ki, kd, notes)
    cert: dict[str, Any] = {
        "gains": {"kp_v_per_rad_s": kp, "ki_v_per_rad": ki, "kd_v_s2_per_rad": kd},
        "cost": "J3 = integral of e^2 for a unit step (eq 22)" if variant == "paper"
                else "J3 = Ts sum e[k]^2 for a unit step of the sampled loop",
        "j3_s": ev["j3"], "sensitivity_peak": ev["ms"], "feasible": bool(ev["feasible"]),
        "step_peak_current_a": ev.get("step_peak_current_a"), "step_peak_speed_rad_s": ev.get("step_peak_speed_rad_s"), "plant_tf": {"num": pb.plant.num, "den": pb.plant.den},
        "perturbation_d": pb.d, "search_box": {"lo": pb.lo, "hi": pb.hi}, "profile_box": pb.profile_box,
        "stability_limits_per_term": pb.limits,
        "volts_per_count_if_position_difference": (kp + kd * profile.control.speed_loop_hz) * speed_quantum_rad_s(profile),
        "optimizer": opt_info,
    }
    cert.update(_continuous_figures(pb.plant, kp, ki, kd, pb.d))
    cert.update(_sampled_figures(pb.sp, kp, ki, kd, pb.d))
    cert["hinf_constraint"] = cert.get("hinf_constraint_continuous" if variant == "paper" else "hinf_constraint_sampled",
                                       math.inf)
    res = DesignResult(method="mixed-pid", variant=variant, status="verified", profile_name=profile.name,
                       profile_sha256=profile.sha256, profile_path=str(profile.path) if profile.path else None,
                       law=law, options=used, certificate=cert,
                       timings_s={"setup": t_setup, "optimizer": t_opt})
    if not found:
        res.fail(f"the {optimizer} found no gains in the box {pb.lo.tolist()}..{pb.hi.tolist()} that meet the "
                 "constraints (stability, eq 6" + (f", ||S||_inf <= {pb.ms_max:g})" if variant == "drive" else ")"))
    t2 = time.perf_counter()
    check_pid_design(profile, res, ms_max=pb.ms_max if variant == "drive" else None,
                     delay_samples=used["delay_samples"], measurement=used["measurement"], d=pb.d)
    res.timings_s["checks"] = time.perf_counter() - t2
    return run_verify(profile, res)


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
