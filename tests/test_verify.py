"""verify_design: the six-step drive model, the checks, and bad designs rejected with a reason
(the paper's printed K, an unstable law, a law without the firmware's current window, an overshoot
the bridge cannot brake, an integrator too small, commutation 30 degrees early on a sinusoidal motor)."""
import dataclasses
import math
import warnings

import numpy as np
import pytest

from picdrive.control_law import Rule, ScheduledLaw
from picdrive.profile import load_profile
from picdrive.papers.repro2016 import PRINTED
from picdrive.result import DesignResult
from picdrive.analysis.sampled import six_step_closed_loop
from picdrive.analysis.steptest import run_sim, sector_mean, sim_plan, step_figures
from picdrive.design.verify import verify_design
from picdrive.gate import BuiltDrive, speed_measurement, three_phase_plant
from picdrive.models.simulate import simulate_six_step

DRIVE = BuiltDrive()


@pytest.fixture(scope="module")
def prof():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_profile("assawinchaichote2016")


@pytest.fixture(scope="module")
def duy():
    return load_profile("duy2008")


def _pid(p, kp, ki, kd=0.0, **kw):
    u = p.inverter.bus_voltage_v * p.max_duty()
    m = p.motor
    base = dict(rules=(Rule(kp=kp, ki=ki, kd=kd),), premise_rad_s=(0.0, 300.0), sample_time_s=1e-3,
                u_min_v=-u, u_max_v=u, current_limit_a=p.inverter.current_limit_a, kb_v_s_per_rad=m.kb_v_s_per_rad,
                r_ohm=m.r_line_ohm)
    base.update(kw)
    return ScheduledLaw(**base)


def _result(prof, law=None, cert=None):
    return DesignResult(method="fuzzy-hinf", status="verified", profile_name=prof.name, profile_sha256=prof.sha256,
                        law=law, certificate=cert or {})


def test_paper_printed_K_rejected(prof):
    r = _result(prof, cert={"model": "paper-as-printed", "K": [PRINTED["K1"], PRINTED["K2"]]})
    verify_design(prof, r, drive=DRIVE)
    assert r.status == "failed"
    assert r.verification["continuous_max_real_eig"]["ok"] is False
    assert r.verification["continuous_max_real_eig"]["value"] > 0
    assert any("continuous_max_real_eig" in why for why in r.reasons)


def test_unstable_law_rejected_without_simulating(prof):
    law = _pid(prof, -5.0, -50.0)
    r = _result(prof, law=law)
    verify_design(prof, r, drive=DRIVE)
    assert r.status == "failed"
    assert r.verification["sampled_spectral_radius"]["value"] > 1
    assert "sim_skipped" in r.verification
    assert any("sampled_spectral_radius" in why for why in r.reasons)


def test_law_beyond_the_bridge_rejected(prof):
    law = ScheduledLaw(rules=(Rule(kp=0.0, ki=1.0),), premise_rad_s=(0.0, 300.0), sample_time_s=1e-3,
                       u_min_v=-100.0, u_max_v=100.0)
    r = _result(prof, law=law)
    verify_design(prof, r, simulate=False)
    assert r.status == "failed" and r.verification["law_output_limits_v"]["ok"] is False


def test_six_step_closed_loop_matches_the_simulation(duy):
    """The linear sampled loop (verification's spectral-radius check) against the nonlinear six-step
    simulation around an operating point: a small reference step from equilibrium."""
    m = duy.motor
    g = Rule(kp=0.3, ki=20.0, kd=5e-4)
    law = _pid(duy, g.kp, g.ki, g.kd)
    w0, T, dw = 100.0, 0.01, 0.5

    def eq(w):
        i = (m.viscous_friction_n_m_s * w + T) / m.kt_n_m_per_a
        return i, m.kb_v_s_per_rad * w + m.r_line_ohm * i
    i0, u0 = eq(w0)
    i1, u1 = eq(w0 + dw)
    rpm = 30 / math.pi
    s = simulate_six_step(duy, law, t_end=0.2, ref_rpm=lambda t: (w0 + dw) * rpm if t >= 0.0095 else w0 * rpm,
                          load=T, x0=(i0, w0), integrator0_v=u0)
    A = six_step_closed_loop(duy, g, 1e-3, None)
    k0 = 10
    z = np.array([s.i[k0] - i1, s.omega[k0] - (w0 + dw), -dw, -dw, u0 - u1, u0 - u1, -dw, 0.0])
    lin = []
    for _ in range(150):
        lin.append(z[1])
        z = A @ z
    sim = s.omega[k0:k0 + 150] - (w0 + dw)
    assert np.max(np.abs(np.array(lin) - sim)) <= 0.03 * dw
    assert np.max(np.abs(np.linalg.eigvals(A))) < 1


def test_good_pi_law_passes(duy):
    r = _result(duy, law=_pid(duy, 0.4, 29.0, 9e-4))
    verify_design(duy, r, drive=DRIVE)
    bad = {k: v for k, v in r.verification.items() if not v["ok"]}
    assert r.ok, bad
    v = r.verification
    assert v["sim_step_target_rpm"]["value"] == pytest.approx(duy.speed_step_rpm())     # no model cap any more
    assert v["sim_overshoot_pct"]["value"] <= 2.0 and v["sim_peak_bus_current_a"]["value"] < 3.0
    assert "dq_hold_rpm" not in v                                    # trapezoidal motor: the dq model is not used


def test_law_without_the_firmware_window_fails(duy):
    law = dataclasses.replace(_pid(duy, 0.4, 29.0, 9e-4), current_limit_a=None)
    r = _result(duy, law=law)
    verify_design(duy, r, simulate=False)
    assert r.status == "failed" and r.verification["law_current_window"]["ok"] is False


def test_overshoot_the_bridge_cannot_brake_fails(duy):
    # ZN's "no-overshoot" row on duy2008: the low kp leaves the approach to the integrator, 7 % overshoot
    r = _result(duy, law=_pid(duy, 0.176, 24.7, 8.35e-4))
    verify_design(duy, r, drive=DRIVE)
    assert r.status == "failed"
    assert r.verification["sim_overshoot_pct"]["value"] > 2.0
    assert any("sim_overshoot_pct" in why for why in r.reasons)


def test_integrator_range_too_small_fails(duy):
    # b = 0: at 2400 rpm the integrator holds u* + kp w* = 42 + 0.4 * 251 V, more than 60 V
    r = _result(duy, law=_pid(duy, 0.4, 29.0, setpoint_weight=0.0, integrator_limit_v=60.0))
    verify_design(duy, r, simulate=False)
    assert r.verification["integrator_headroom_v"]["value"] < 0 and r.status == "failed"


def test_commutation_30_degrees_early_on_the_sinusoidal_motor_fails(prof):
    """The 2016 motor with hall_offset_deg = 0 (the table commutates 30 degrees early): inside each
    13 ms sector the pair's EMF runs from half to all of its peak; the twin measured a 9 % overshoot
    and 375..413 rpm at the 380 rpm target.  The model sees it too; with aligned halls the law's
    nominal step is within the limits (on the three-phase winding its R + 10 % step overshoots
    2.06 %, at the 2 % limit: that check is not asserted here)."""
    law = _pid(prof, 0.663, 192.0, 2.28e-3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        early = prof.replace(sensors={"hall_offset_deg": 0.0})
        aligned = prof.replace(sensors={"hall_offset_deg": 30.0})
    r0, r1 = _result(early, law=law), _result(aligned, law=law)
    verify_design(early, r0, drive=DRIVE)
    verify_design(aligned, r1, drive=DRIVE)
    assert r0.status == "failed" and r0.verification["sim_overshoot_pct"]["value"] > 5.0
    ok = {k: c["ok"] for k, c in r1.verification.items() if k != "sim_resistance_uncertainty"}
    assert all(ok.values()), ok
    assert r1.verification["sim_overshoot_pct"]["value"] < 0.5 * r0.verification["sim_overshoot_pct"]["value"]
    assert r1.verification["dq_hold_rpm"]["ok"]                       # sinusoidal: steady-state reach on the dq model


def test_sector_mean_removes_the_commutation_ripple(prof):
    """Under 1 N m the 2016 motor's speed ripples at six times the electrical frequency; the
    figures are judged on the mean over one hall sector, and the ripple is reported."""
    law = _pid(prof, 0.663, 192.0, 2.28e-3)
    plan = sim_plan(prof)
    sim = run_sim(prof, law, plan, measurement=speed_measurement(prof, law), disturbances=False,
                  three_phase=three_phase_plant)
    f = step_figures(sim, plan, prof)
    tail = sim.t > plan["t_end_s"] - 0.1
    raw = sim.rpm[tail]
    avg = sector_mean(prof, sim.rpm, law.sample_time_s, plan["target_rpm"])[tail]
    assert np.ptp(raw) > 2 * np.ptp(avg)
    assert f["ripple_pct"] > 1.0 and abs(f["final_error_rpm"]) < 0.01 * plan["target_rpm"]
