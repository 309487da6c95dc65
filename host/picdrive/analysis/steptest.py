"""The verification's step test on the six-step drive and its figures.

:func:`sim_plan` fixes the step target, the load and the durations;
:func:`run_sim` runs the step from rest, the 2016 load-torque disturbance and
the load step on the six-step drive model (:func:`picdrive.models.simulate.simulate_six_step`)
with the firmware's speed measurement; :func:`step_figures` judges a run (the
model's, or the twin's: :func:`picdrive.gate.twin_run`) on the speed averaged
over a hall sector (:func:`sector_mean`).  The console's step command and the
HIL suite use the same figures.
"""
from __future__ import annotations

import math

import numpy as np

from ..profile import VERIFY_PHASE_PER_MIN_STEP
from .metrics import step_metrics

__all__ = ["VerifyConfig", "sim_plan", "run_sim", "sector_period_s", "sector_mean",
           "step_figures"]

RPM = 2.0 * math.pi / 60.0      # rad/s per rpm


class VerifyConfig:
    """Durations and bands of the verification simulation; tests may shorten the durations."""

    step_phase_s: float = 0.6      # step from rest, then the load step at this time
    load_phase_s: float = 0.6
    band: float = 0.02             # settling band and steady-error limit, fraction of the step target
    commutated: bool = True        # the pair's EMF per rotor angle (simulate.commutated_emf), not the DC Kb


def sim_plan(profile) -> dict:
    """Step target (rpm), load, durations of the verification simulation.

    Each phase lasts ``VerifyConfig`` 's duration or three times the physical minimum step time
    (:meth:`picdrive.profile.Profile.min_step_time_s`), whichever is longer: a high-inertia drive
    cannot settle within a fixed 0.6 s however good its law (the profile loader refuses a drive
    whose window would be absurd, :data:`picdrive.profile.VERIFY_MAX_PWM_PERIODS`)."""
    t_min = profile.min_step_time_s()
    scale = 1.0
    if math.isfinite(t_min):
        scale = max(1.0, VERIFY_PHASE_PER_MIN_STEP * t_min / VerifyConfig.step_phase_s)
    step, load = VerifyConfig.step_phase_s * scale, VerifyConfig.load_phase_s * scale
    return {"target_rpm": profile.speed_step_rpm(), "profile_target_rpm": profile.speed_step_rpm(),
            "capped": False, "load_n_m": profile.control.load_torque_n_m,
            "t_load_s": step, "t_end_s": step + load}


def load_disturbance(plan: dict):
    """The verification's load-torque disturbance of a run (the 2016 paper's w3, N m against the motor,
    10 % of the plan's load torque, on [0, 0.2] s), a function of time."""
    from ..models.simulate import disturbances_2016
    load = plan["load_n_m"]
    return lambda t: float(disturbances_2016(t, amplitude=(0.0, 0.0, 0.1 * load))[0, 2])


def run_sim(profile, law, plan=None, *, measurement: dict, disturbances: bool = True, r_factor: float = 1.0,
            commutated: bool | None = None, three_phase=None):
    """The verification run on the six-step drive: step from rest to the target (the 2016 load-torque
    disturbance w3 on [0, 0.2] s when ``disturbances``), then the load step, R x ``r_factor``.

    ``measurement``: the firmware's speed measurement as
    :func:`picdrive.models.simulate.simulate_six_step` takes it: ``{"measurement": "firmware"}``
    (encoder M/T) or ``{"measurement": "hall", "hall": meter}``; the built drive gives it
    (:meth:`picdrive.gate.BuiltDrive.speed_measurement`).  ``three_phase``: a factory
    ``(profile, r_factor) -> plant`` of the motor's three-phase winding to simulate instead of the
    DC equivalent (:meth:`picdrive.gate.BuiltDrive.three_phase_plant`, what the verification
    uses).  Returns :class:`picdrive.models.simulate.SixStepResult`."""
    from ..models.simulate import simulate_six_step
    plan = plan or sim_plan(profile)
    load = plan["load_n_m"]
    tl = plan["t_load_s"]
    w3 = load_disturbance(plan) if disturbances else None
    return simulate_six_step(profile, law, t_end=plan["t_end_s"], ref_rpm=plan["target_rpm"],
                             load=lambda t: load if t >= tl - 1e-12 else 0.0, torque_disturbance=w3,
                             r_factor=r_factor, **measurement,
                             commutated=VerifyConfig.commutated if commutated is None else commutated,
                             three_phase=None if three_phase is None else three_phase(profile, r_factor))


def sector_period_s(profile, rpm: float) -> float:
    """Time one hall sector (60 electrical degrees) lasts at a speed, s: the shortest interval over
    which a six-step drive delivers its mean torque (inside it the pair's EMF, hence the torque per
    ampere, ripples with the rotor angle)."""
    return 60.0 / (max(abs(rpm), 1e-9) * profile.motor.pole_pairs * 6.0)


def sector_mean(profile, y: np.ndarray, ts: float, rpm: float, *, breaks=()) -> np.ndarray:
    """``y`` (samples ``ts`` apart) averaged over one hall sector at ``rpm`` (centred moving mean;
    the ends use what exists).

    ``breaks``: sample indices where a new phase of the run starts (the load step): no window
    reaches across one, so what happens after a phase boundary never leaks into the figures of the
    phase before it (and the other way round); near a boundary the window is the sector next to it
    inside the phase."""
    y = np.asarray(y, float)
    n = max(1, int(round(sector_period_s(profile, rpm) / ts)))
    if n <= 1:
        return y.copy()
    out = np.empty_like(y)
    cuts = [0] + sorted(int(b) for b in breaks if 0 < int(b) < y.size) + [y.size]
    for a, b in zip(cuts[:-1], cuts[1:]):
        seg = y[a:b]
        c = np.concatenate([[0.0], np.cumsum(seg)])
        k = np.arange(seg.size)
        lo = np.clip(k - n // 2, 0, seg.size)
        hi = np.clip(lo + n, 0, seg.size)
        lo = np.maximum(0, hi - n)
        out[a:b] = (c[hi] - c[lo]) / (hi - lo)
    return out


def step_figures(sim, plan, profile=None) -> dict:
    """Step and load-step figures of a verification run (rpm, s, %).

    Settling, overshoot, load recovery and final error are judged on the speed
    averaged over one hall sector at the target (:func:`sector_mean`; with a
    ``profile``), the commutation's own torque ripple being no regulation error;
    ``ripple_pct`` is the peak-to-peak of the raw speed about that mean in the
    last 10 % of the run, ``peak_rpm_raw`` the raw peak."""
    t, raw = sim.t, sim.rpm
    tl, target = plan["t_load_s"], plan["target_rpm"]
    ts = float(t[1] - t[0])
    a = t < tl
    # the load step starts a new phase: no sector window reaches across it
    rpm = sector_mean(profile, raw, ts, target, breaks=(int(np.count_nonzero(a)),)) if profile is not None else raw
    m1 = step_metrics(t[a], rpm[a], target, y0=0.0)
    band = VerifyConfig.band
    dev = np.abs(rpm[~a] - target) / target
    outside = np.nonzero(dev > band)[0]
    rec = 0.0 if outside.size == 0 else (math.inf if outside[-1] == dev.size - 1 else float(t[~a][outside[-1] + 1] - tl))
    n_tail = max(1, int(0.1 * t.size))
    inside = np.nonzero(np.abs(raw - target) <= 0.01 * target)[0]
    return {"settling_s": m1.settling_time_s, "rise_s": m1.rise_time_s, "overshoot_pct": m1.overshoot_pct,
            "peak_rpm": m1.peak, "peak_rpm_raw": float(np.max(sim.omega_fine if sim.omega_fine.size else sim.omega)
                                                       * 60 / (2 * math.pi)),
            "load_recovery_s": rec, "load_dip_rpm": float(target - np.min(rpm[~a])),
            "final_error_rpm": float(target - np.mean(rpm[-n_tail:])),
            "ripple_pct": float(100 * np.ptp(raw[-n_tail:] - rpm[-n_tail:]) / target),
            "t_reach_s": float(t[inside[0]]) if inside.size else math.inf,
            "peak_current_a": float(np.max(np.abs(sim.i_fine))) if sim.i_fine.size else 0.0,
            # with the current's rise inside each PWM period (simulate.pwm_ripple_peak_a); a twin run has none
            "peak_current_ripple_a": float(np.max(sim.i_peak_fine)) if getattr(sim, "i_peak_fine", np.zeros(0)).size
            else (float(np.max(np.abs(sim.i_fine))) if sim.i_fine.size else 0.0)}
