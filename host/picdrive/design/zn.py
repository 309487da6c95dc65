"""Ziegler-Nichols PID of a drive profile, and the 2016 paper's ZN gains as a preset.

Rule (``rule=``):

``"ultimate"`` (default) — Ziegler & Nichols' ultimate-sensitivity rule on
    the *sampled* speed loop: the gain Ku at which the proportional loop
    (zero-order hold, one sample of computation delay, speed averaged over
    the period, :func:`picdrive.models.tfmodel.sampled_plant`) reaches the stability
    limit, and the period Tu = 2 pi / w180 of that oscillation (w180: the
    phase crossover of the sampled plant).  Then ``kp = 0.6 Ku``,
    ``Ti = Tu/2``, ``Td = Tu/8`` (ki = kp/Ti, kd = kp Td).  This is the rule
    that describes the loop the firmware closes: the plant of eq 1 is
    second order without delay, so its continuous proportional loop never
    oscillates (no finite Ku); only the hold, the delay and the measurement
    give it one, and they are exactly what limits the achievable gain.

``"some-overshoot"``, ``"no-overshoot"`` — the milder rows of the same
    ultimate-point table: ``kp = Ku/3, Ti = Tu/2, Td = Tu/3`` and
    ``kp = 0.2 Ku, Ti = Tu/2, Td = Tu/3``.  A speed PID without a current
    loop limits the current only through its gains; where the classic rule
    drives more than ``inverter.current_limit_a`` into the motor on the
    profile's step (the 2016 motor: R = 1 ohm line to line), these are the
    ZN answer that respects it.

``"tyreus-luyben"`` — the backed-off row of the same table (Tyreus &
    Luyben 1992): ``kp = Ku/2.2, Ti = 2.2 Tu, Td = Tu/6.3``; about a sixth of
    the classic integral gain.

``"backed-off"``, ``"backed-off-4"`` — the classic row with its integral
    time stretched two and four times (``Ti = Tu``, ``Ti = 2 Tu``: ki x 1/2,
    x 1/4; kp and Td as classic).  The bridge cannot brake, so what
    overshoots on a speed step is the integrator's charge at the end of the
    acceleration; these keep the classic's proportional and derivative action
    and back the integral off.

``"pessen"`` — Pessen's integral rule (``kp = 0.7 Ku, Ti = 0.4 Tu,
    Td = 0.15 Tu``), the faster row, for a loop the milder rows leave too slow.

``"reaction-curve"`` — the open-loop step-response rule on the continuous
    plant (tangent at the inflection point: apparent dead time L, time
    constant T, DC gain K; ``kp = 1.2 T/(K L)``, ``Ti = 2 L``, ``Td = L/2``).
    Offered for comparison: the apparent dead time of an overdamped second
    order plant is a property of its two lags, not of the sampled loop, and
    for an underdamped plant (the 2016 motor) the rule is ill-posed.

``preset="paper2016"`` — Assawinchaichote & Chayaopas 2016 (Figure 5,
    Table 2): Kp = 0.43, Ki = 2.30, Kd = 0.28.  Their PID acts on the speed
    error in rpm (the paper's reference, 2400 rpm, and its fuzzy premise
    [0, 3000] are in rpm) and outputs v_q (V, dq frame).  On picdrive's law
    (error in rad/s, output the six-step line voltage u) the gains become
    ``K_law = K_paper * (60 / 2 pi) * (Kb / (P lambda_m))``: rad/s -> rpm,
    and u/v_q = Kb/(P lambda_m), the ratio of the six-step DC-equivalent
    back-EMF constant to the dq one (3 sqrt(3)/pi = 1.654 for a sinusoidal
    machine, 2 for a trapezoidal one), which gives the same operating point.
    See docs/design-pid.md for why rpm (and not rad/s) and what the gains do.
"""
from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import PicdriveError
from ..analysis.h2hinf import pid_figures_continuous, pid_figures_sampled
from .mixed_pid import MixedPidError, phase_crossover_rad_s, pid_law, run_verify, term_limits
from .verify import drive_limit_failed, pid_model_checks
from ..result import DesignResult
from ..models.tfmodel import TF, SampledPlant, motor_tf, sampled_plant

__all__ = ["ZnError", "PRESETS", "RULES", "ultimate_point", "reaction_curve", "zn_gains", "paper2016_gains",
           "paper2016_unit_study", "design"]

PRESETS = {"paper2016": {"kp": 0.43, "ki": 2.30, "kd": 0.28,
                         "source": "Assawinchaichote & Chayaopas 2016, Remark 1 / Figure 5 / Table 2",
                         "units": "error in rpm, output v_q in V"}}
# (kp / Ku, Ti / Tu, Td / Tu) of the ultimate-point rules: Ziegler & Nichols' classic PID, the two
# milder variants of the same table (Seborg, Edgar & Mellichamp; "some" / "no overshoot"), the
# backed-off rows (Tyreus & Luyben; the classic with Ti x 2 and x 4) and Pessen's integral rule
ULTIMATE_RULES = {"ultimate": (0.6, 0.5, 0.125), "some-overshoot": (1.0 / 3.0, 0.5, 1.0 / 3.0),
                  "no-overshoot": (0.2, 0.5, 1.0 / 3.0), "tyreus-luyben": (1.0 / 2.2, 2.2, 1.0 / 6.3),
                  "backed-off": (0.6, 1.0, 0.125), "backed-off-4": (0.6, 2.0, 0.125),
                  "pessen": (0.7, 0.4, 0.15)}
RULES = (*ULTIMATE_RULES, "reaction-curve")


class ZnError(PicdriveError, ValueError):
    """Bad options for the Ziegler-Nichols design."""


def ultimate_point(sp: SampledPlant) -> dict[str, float]:
    """Ultimate gain and period of the sampled proportional loop.

    ``Ku = 1/|P(e^{j w180 Ts})|`` at the first phase crossover w180 of the
    sampled plant; cross-checked against the gain at which the closed-loop
    spectral radius reaches 1 (:func:`picdrive.design.mixed_pid.term_limits`).
    """
    try:
        w180 = phase_crossover_rad_s(sp)
    except MixedPidError as e:
        raise ZnError(str(e)) from None
    z = np.exp(1j * w180 * sp.ts)
    ku = 1.0 / abs(np.polyval(sp.tf_z.num, z) / np.polyval(sp.tf_z.den, z))
    ku_bisect = term_limits(sp)["kp"]
    return {"ku_v_per_rad_s": ku, "tu_s": 2 * math.pi / w180, "w180_rad_s": w180, "ku_bisection": ku_bisect}


def reaction_curve(plant: TF) -> dict[str, float]:
    """Inflection-tangent parameters (K, L, T) of the plant's unit step response.

    Raises :class:`ZnError` when the response overshoots (the rule assumes a
    monotone S-shaped curve).
    """
    from scipy import signal
    poles = plant.poles()
    tmax = 10.0 / min(abs(p.real) for p in poles)
    t = np.linspace(0.0, tmax, 40001)
    _, y = signal.step((plant.num, plant.den), T=t)
    K = plant.dcgain()
    if np.max(y) > K * (1 + 1e-6):
        raise ZnError("the plant's step response overshoots (complex poles): the reaction-curve rule does not apply; "
                      "use rule=ultimate")
    dy = np.gradient(y, t)
    i = int(np.argmax(dy))
    slope = dy[i]
    L = t[i] - y[i] / slope
    T = K / slope
    return {"K": K, "L_s": L, "T_s": T}


def zn_gains(rule: str, sp: SampledPlant, plant: TF) -> tuple[float, float, float, dict[str, Any]]:
    """(kp, ki, kd, figures) of the classic ZN PID by the given rule."""
    if rule in ULTIMATE_RULES:
        u = ultimate_point(sp)
        ku, tu = u["ku_v_per_rad_s"], u["tu_s"]
        a, b, c = ULTIMATE_RULES[rule]
        kp, ti, td = a * ku, b * tu, c * tu
        return kp, kp / ti, kp * td, {**u, "ti_s": ti, "td_s": td}
    if rule == "reaction-curve":
        r = reaction_curve(plant)
        kp, ti, td = 1.2 * r["T_s"] / (r["K"] * r["L_s"]), 2.0 * r["L_s"], 0.5 * r["L_s"]
        return kp, kp / ti, kp * td, {**r, "ti_s": ti, "td_s": td}
    raise ZnError(f"ZN rule {rule!r} is unknown; choose one of {', '.join(RULES)}")


def paper2016_gains(profile) -> tuple[float, float, float, float]:
    """The 2016 paper's Kp, Ki, Kd on picdrive's law for a profile: (kp, ki, kd, factor)."""
    m = profile.motor
    factor = (60.0 / (2.0 * math.pi)) * m.kb_v_s_per_rad / (m.pole_pairs * m.lambda_m_v_s)
    pr = PRESETS["paper2016"]
    return pr["kp"] * factor, pr["ki"] * factor, pr["kd"] * factor, factor


def paper2016_unit_study(profile="assawinchaichote2016", *, t_end_s: float = 5.0) -> dict[str, dict[str, float]]:
    """Which units make the 2016 PID (Kp 0.43, Ki 2.30, Kd 0.28) give its Table 2 (0.22 s, 4.16 %)?

    The paper's PID acts on v_q of the dq model without a voltage limit.
    With i_d = 0 the dq model (:mod:`picdrive.models.dqmodel`, corrected eq 5) is
    linear: ``w/v_q = 1.5 P lambda / ((Lq s + R)(J s + B) + 1.5 P^2 lambda^2)``.
    For the speed error in rad/s, in rpm, and in electrical rad/s, with the
    derivative on the error (the paper's form) and on the measurement, this
    returns the 2 % settling time (s) and overshoot (%) of a unit step (the
    loop is linear: the step size does not matter).
    """
    from scipy import signal

    from ..models.dqmodel import dq_params
    from ..analysis.metrics import step_metrics
    from ..profile import load_profile

    prof = load_profile(profile) if isinstance(profile, (str, Path)) else profile
    p = dq_params(prof)
    kt = 1.5 * p.pole_pairs * p.lambda_m_v_s
    num = np.array([kt])
    den = np.polyadd(np.polymul([p.lq_h, p.r_ohm], [p.j_kg_m2, p.b_n_m_s]), [kt * p.pole_pairs * p.lambda_m_v_s])
    pr = PRESETS["paper2016"]
    t = np.linspace(0.0, t_end_s, 40001)
    out = {}
    for unit, sc in (("rad/s", 1.0), ("rpm", 60.0 / (2.0 * math.pi)), ("electrical rad/s", float(p.pole_pairs))):
        for form in ("error", "measurement"):
            c = sc * np.array([pr["kd"], pr["kp"], pr["ki"]])
            char = np.polyadd(np.polymul(den, [1.0, 0.0]), np.polymul(num, c))
            cn = c if form == "error" else np.array([0.0, c[1], c[2]])
            _, y = signal.step((np.polymul(num, cn), char), T=t)
            m = step_metrics(t, y, 1.0)
            out[f"{unit}, derivative on {form}"] = {"settling_s": m.settling_time_s, "overshoot_pct": m.overshoot_pct,
                                                     "stable": bool(np.all(np.roots(char).real < 0))}
    return out


# rule="auto": the classic row, the milder rows of the table, the classic with its integral backed off,
# then Pessen's faster row (for a loop the others leave too slow)
AUTO_ORDER = ("ultimate", "some-overshoot", "no-overshoot", "backed-off", "tyreus-luyben", "backed-off-4", "pessen")


def design(profile, *, drive=None, progress: bool = True, preset: str | None = None, rule: str = "auto",
           delay_samples: int = 1, measurement: str = "average", **options) -> DesignResult:
    """Ziegler-Nichols PID (or the ``paper2016`` preset) for a profile, verified.

    ``rule="auto"`` (default): the rows of the ultimate-sensitivity table in
    the order :data:`AUTO_ORDER` (classic, some-overshoot, no-overshoot, the
    classic with Ti x 2, Tyreus-Luyben, the classic with Ti x 4, Pessen), and
    the first whose law passes the verification on the six-step drive is kept
    (the bridge cannot brake, so the overshoot limit of the verification is
    what selects most often; on the duy2008 motor the milder rows overshoot
    *more*: their lower kp leaves the approach to the integrator, which is why
    the backed-off rows keep the classic kp and lower ki).  The rows tried are
    recorded (``certificate.rule_tries``: each row's gains, status and
    reasons) and the row kept is the result's ``variant`` and
    ``certificate.rule``; a refusal is the classic row's design with its
    reasons first, then every row's first reason.
    ``progress`` is accepted for the common interface (ZN has no long steps).
    """
    if rule == "auto" and preset is None and not options:
        tries, res, first = [], None, None
        for row in AUTO_ORDER:
            res = design(profile, drive=drive, progress=progress, rule=row, delay_samples=delay_samples,
                         measurement=measurement)
            tries.append({"rule": row, "status": res.status, "gains": dict(res.certificate["gains"]),
                          "reasons": list(res.reasons)})
            first = first or res
            if res.ok or drive_limit_failed(res):      # no other row can pass a limit of the drive
                break
        if not res.ok:       # refused: the classic row's design and reasons first (a physical limit shows there)
            res = first
        res.certificate["rule_tries"] = tries
        res.options["rule"] = "auto"
        if not res.ok and len(tries) > 1:
            res.fail("no row of the ZN table passed the verification: " +
                     "; ".join(f"{t['rule']}: {t['reasons'][0] if t['reasons'] else t['status']}" for t in tries))
        return res
    if options:
        raise ZnError(f"unknown zn option(s) {', '.join(sorted(options))}; accepted: preset, rule, "
                      "delay_samples, measurement")
    if preset is not None and preset not in PRESETS:
        raise ZnError(f"zn preset {preset!r} is unknown; choose one of {', '.join(PRESETS)} (or none for ZN tuning)")
    if delay_samples not in (0, 1) or measurement not in ("average", "instant"):
        raise ZnError("delay_samples must be 0 or 1 and measurement 'average' or 'instant'")
    t0 = time.perf_counter()
    plant = motor_tf(profile)
    sp = sampled_plant(plant, 1.0 / profile.control.speed_loop_hz, delay_samples=delay_samples,
                       measurement=measurement)
    cert: dict[str, Any] = {"plant_tf": {"num": plant.num, "den": plant.den}}
    if preset == "paper2016":
        kp, ki, kd, factor = paper2016_gains(profile)
        pr = PRESETS["paper2016"]
        variant = "paper2016"
        cert.update(preset=pr, law_gain_factor=factor,
                    conversion="K_law = K_paper * (60/2pi) [rpm per rad/s] * Kb/(P lambda_m) [u per v_q]")
    else:
        if rule not in RULES:
            raise ZnError(f"ZN rule {rule!r} is unknown; choose one of auto, {', '.join(RULES)}")
        kp, ki, kd, fig = zn_gains(rule, sp, plant)
        variant = rule
        cert.update(rule=rule, **fig)
    cert["gains"] = {"kp_v_per_rad_s": kp, "ki_v_per_rad": ki, "kd_v_s2_per_rad": kd}
    d = profile.design["perturbation_d"]
    cert.update(pid_figures_continuous(plant, kp, ki, kd, d))
    cert.update(pid_figures_sampled(sp, kp, ki, kd, d))
    law = pid_law(profile, kp, ki, kd, notes=f"Ziegler-Nichols ({variant}); derivative on measurement, b = 1")
    res = DesignResult(method="zn", variant=variant, status="verified", profile_name=profile.name,
                       profile_sha256=profile.sha256, profile_path=str(profile.path) if profile.path else None,
                       law=law, options={"preset": preset, "rule": rule, "delay_samples": delay_samples,
                                         "measurement": measurement},
                       certificate=cert, timings_s={"design": time.perf_counter() - t0})
    t1 = time.perf_counter()
    pid_model_checks(profile, res, ms_max=None, delay_samples=delay_samples, measurement=measurement, d=d)
    res.timings_s["checks"] = time.perf_counter() - t1
    return run_verify(profile, res, drive)
