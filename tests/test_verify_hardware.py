"""The verifier judges what this firmware will do on this hardware: one test per defect it must catch.

The defects, each of which an earlier verifier missed:

* halls-only speed was verified with the encoder's M/T measurement: a mixed-pid design of the
  Orbray BMS10-1003 micro motor at 3000 rpm was marked verified and swings by 1,500 rpm in the twin;
* the sector-mean speed window reached across the load step: a good zn design of a 48 V
  industrial motor under a 1 N m test load read "settling inf" and was refused;
* the peak current was judged on the PWM-period average: on the 40 us micro motor the check read
  0.49 A where the current inside the PWM period peaks at 0.70 A;
* fuzzy-hinf on that micro motor failed with a solver error and "try a larger gamma";
* the six-step model's reverse table drove a forward-turning rotor on instead of braking it;
* a drive whose hall sector is short against L/R (maxon EC 45 flat, 8 pole pairs) was verified on
  the DC equivalent and held 75-105 rpm below its target under load in the twin.
"""
import math
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from picdrive.profile import load_profile

MOTORS = Path(__file__).resolve().parent / "motors"


def _load(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_profile(str(path))


@pytest.fixture(scope="module")
def micro():
    return _load(MOTORS / "orbray_bms10_1003.toml")


@pytest.fixture(scope="module")
def micro_zn(micro):
    from picdrive.gate import run_design
    res = run_design(micro, "zn", progress=False)
    assert res.ok, res.reasons
    return res


# --------------------------------------------------------------------- halls-only speed
def test_hall_speed_meter_is_the_firmware_s(micro, micro_zn, tmp_path):
    """The verification's hall measurement has the Timer5 tick, speed constant and age limit the
    generated firmware is built with."""
    from picdrive.firmware import codegen
    from picdrive.result import save_design
    from picdrive.gate import speed_measurement
    path = tmp_path / "micro.zn.design.json"
    save_design(micro_zn, path)
    fw = codegen.generate(micro, str(path))
    params = fw.files["drive_params.h"]
    meas = speed_measurement(micro, micro_zn.law)
    assert meas["measurement"] == "hall"
    hall = meas["hall"]
    assert hall.age_max == int(re.search(r"#define FW_HALL_AGE_MAX (\d+)u", params).group(1))
    assert hall.k_raw == int(re.search(r"#define CORE_K_SPEED UINT32_C\((\d+)\)", params).group(1))
    assert hall.edges_per_rev == 6
    # the firmware's own report: lowest measurable speed with Timer5 1:1 and 6 edges per turn
    assert hall.lowest_rad_s * 60 / (2 * math.pi) == pytest.approx(1525.9, abs=0.1)


def test_halls_only_micro_motor_at_low_speed_is_judged_on_the_hall_measurement(micro, tmp_path):
    """At 3000 rpm a hall sector of the 1-pole-pair micro motor lasts 3.3 ms, longer than the 1 ms
    sample: the law sees a stale, lagging speed.  A law tuned for an encoder's measurement swung
    1857..3345 rpm in the twin; the verification sees that overshoot itself.  The mixed-pid search,
    which scores the drive's own hall measurement, finds a law that holds at the target, and the
    verification refuses it at half the target, where the sector is twice as long."""
    import dataclasses
    from picdrive.design.verify import verify_design
    from picdrive.gate import BuiltDrive, run_design
    text = (MOTORS / "orbray_bms10_1003.toml").read_text().replace("reference_rpm = 20000.0", "reference_rpm = 3000.0")
    p = tmp_path / "orbray_3000.toml"
    p.write_text(text)
    prof = _load(p)
    assert prof.sensors.speed_source == "hall"
    res = run_design(prof, "mixed-pid", progress=False)
    # at the target the search's law holds; at half of it (a 6.7 ms sector) no law it found does, and
    # the refusal says so
    assert res.verification["sim_overshoot_pct"]["value"] <= 2.0
    assert not res.ok and any("sim_half_speed" in r for r in res.reasons), res.reasons
    # the same search on an encoder's measurement: its law, judged on the halls the drive has
    enc = prof.replace(sensors={"speed_source": "encoder", "encoder_lines": 500})
    law = run_design(enc, "mixed-pid", progress=False).law
    judged = verify_design(prof, dataclasses.replace(res, law=law, status="verified", reasons=[],
                                                     verification={}), drive=BuiltDrive())
    assert not judged.ok
    assert judged.verification["sim_overshoot_pct"]["value"] > 50.0, judged.verification["sim_overshoot_pct"]
    assert any("sim_overshoot_pct" in r for r in judged.reasons)


def test_hall_measurement_lags_and_quantises_like_the_firmware(micro, micro_zn):
    """Constant speed: the measurement is K / period in whole Timer5 ticks; from rest it reads 0
    until two edges were seen."""
    from picdrive.models.simulate import simulate_six_step
    from picdrive.gate import speed_measurement
    hall = speed_measurement(micro, micro_zn.law)["hall"]
    w = 2000.0
    sim = simulate_six_step(micro, micro_zn.law, t_end=0.02, ref_rpm=w * 60 / (2 * math.pi), x0=(0.0, w),
                            integrator0_v=micro.motor.kb_v_s_per_rad * w, measurement="hall", hall=hall)
    assert sim.y[0] == 0.0                                  # no two edges yet
    late = sim.y[sim.t > 0.01]
    assert late.size
    for v in late:                                          # every reading is K // (whole ticks)
        raw = round(v * 2 ** hall.qs)
        assert raw * 2.0 ** -hall.qs == v
        assert any(hall.k_raw // p == raw for p in (hall.k_raw // raw, hall.k_raw // raw + 1, hall.k_raw // (raw + 1) + 1))
    assert np.median(late) == pytest.approx(np.median(sim.omega[sim.t > 0.01]), rel=0.02)


# --------------------------------------------------------------------- phase boundaries
def test_sector_mean_never_reaches_across_a_phase_boundary(micro):
    from picdrive.analysis.steptest import sector_mean, sector_period_s
    ts = 1e-4
    rpm = 600.0
    n = int(round(sector_period_s(micro, rpm) / ts))
    assert n > 4
    y = np.where(np.arange(400) < 200, 1.0, -5.0)
    plain = sector_mean(micro, y, ts, rpm)
    split = sector_mean(micro, y, ts, rpm, breaks=(200,))
    assert np.any(plain[:200] != 1.0)                     # a centred window leaks the next phase in
    assert np.all(split[:200] == 1.0) and np.all(split[200:] == -5.0)


def test_industrial_48v_motor_with_a_1_n_m_load_is_verified():
    """The load step leaked into the last samples of the step phase: settling read inf and the
    +-10 % R check failed on a design the twin runs within 0.1 rpm (docs/motors.md)."""
    from picdrive.gate import run_design
    prof = _load(MOTORS / "industrial_310v_48v_bench.toml")
    res = run_design(prof, "zn", progress=False)
    assert res.ok, res.reasons
    assert res.verification["sim_settling_s"]["value"] < 0.3
    for fig in res.verification["sim_resistance_uncertainty"]["value"].values():
        assert math.isfinite(fig["settling_s"])


# --------------------------------------------------------------------- current inside the PWM period
@pytest.mark.parametrize("duty", [0.1, 0.5, 0.9])
@pytest.mark.parametrize("tau_over_t", [0.2, 0.8, 5.0])
def test_pwm_ripple_peak_is_the_switched_circuit_s(duty, tau_over_t):
    """Against a brute-force integration of the switched RL circuit (with a back-EMF) to its
    periodic steady state."""
    from picdrive.models.simulate import pwm_ripple_peak_a
    T, R, V, e = 50e-6, 2.9, 4.0, 0.0        # continuous conduction (a back-EMF shifts mean and peak alike)
    L = tau_over_t * T * R
    n = 4000
    dt = T / n
    i, peak = 0.0, 0.0
    for _ in range(int(12 * tau_over_t) + 8):
        peak, acc = 0.0, 0.0
        for k in range(n):
            v = V if k < duty * n else 0.0
            i += dt * (v - e - R * i) / L               # explicit Euler, dt = T/4000
            peak = max(peak, i)
            acc += i
    mean = acc / n
    want = peak - mean
    assert pwm_ripple_peak_a(V, R, L, duty, T) == pytest.approx(want, rel=2e-3, abs=1e-5)


def test_short_lr_winding_peak_current_includes_the_pwm_ripple(micro, micro_zn):
    """L/R = 40 us against a 50 us PWM period: the period average peaks near the 0.5 A limit,
    the current inside the period ~0.2 A higher; the check judges the latter."""
    v = micro_zn.verification["sim_peak_bus_current_a"]
    assert v["value"] > 0.65, v
    assert v["value"] < micro.inverter.overcurrent_trip_a
    assert "inside the PWM periods" in v["note"]


# --------------------------------------------------------------------- fuzzy-hinf on a fast winding
def test_fuzzy_hinf_says_why_no_certificate_exists(micro):
    """The continuous Theorem 1 on this winding (the default design at the loop rate has no such limit:
    tests/test_fuzzy_dhinf.py)."""
    from picdrive.gate import run_design
    res = run_design(micro, "fuzzy-hinf", progress=False, time_domain="continuous")
    assert not res.ok
    why = " ".join(res.reasons)
    assert "no fuzzy-hinf certificate exists at any gamma" in why
    assert "eps R/L = 2500 rad/s" in why and "1571 rad/s" in why
    assert "try a larger gamma" not in why


def test_the_stated_bound_is_where_the_lmis_become_feasible(micro):
    """The reason's argument, checked on the solver: a pole disk just outside eps R/L is feasible."""
    from picdrive.design import fuzzy_hinf
    from picdrive.models.tsfuzzy import model_for
    m = micro.motor
    opts = {"rho": 1.0, "integral_weight_rad_s": (m.viscous_friction_n_m_s + m.kt_n_m_per_a * m.kb_v_s_per_rad
                                                  / m.r_line_ohm) / m.inertia_kg_m2}
    ts = model_for(micro, "six-step", opts)
    bound = 0.1 * m.r_line_ohm / m.l_line_h
    assert fuzzy_hinf.no_certificate_reason(micro, ts, 0.99 * bound)
    assert fuzzy_hinf.no_certificate_reason(micro, ts, 1.2 * bound) is None
    sol = fuzzy_hinf.minimise_gamma(ts, delta=None, alpha=2.0, rho=1.0, pole_disk_rad_s=1.2 * bound)
    assert sol.feasible


# --------------------------------------------------------------------- the bridge's own limits
def test_plugging_brakes_a_forward_turning_rotor(micro, micro_zn):
    """A negative command on a forward-turning rotor selects the reverse table: braking torque."""
    from picdrive.models.simulate import simulate_six_step
    w0 = 700.0
    coast = simulate_six_step(micro, micro_zn.law, t_end=0.01, ref_rpm=0.0, x0=(0.0, w0), measurement="instant",
                              commutated=True, plant=None)
    assert np.any(coast.u < 0)
    assert coast.omega[-1] < 0.5 * w0


def test_short_sector_drive_cannot_hold_its_target_under_load():
    """maxon EC 45 flat, 8 pole pairs, 3000 rpm: the hall sector (0.42 ms) is shorter than L/R
    (0.45 ms) and the commutation transfers cost the torque the DC equivalent promised."""
    from picdrive.gate import run_design
    from picdrive.gate import bridge_hold_torque
    prof = _load(MOTORS / "maxon_ec45flat_339281.toml")
    te, need = bridge_hold_torque(prof, prof.speed_step_rpm())
    assert te < need
    duy = _load("duy2008")
    te2, need2 = bridge_hold_torque(duy, duy.speed_step_rpm())
    assert te2 > need2
    res = run_design(prof, "zn", progress=False)
    assert not res.ok
    assert any("bridge_hold_torque_n_m" in r for r in res.reasons)


def test_twin_comparator_sees_the_current_inside_the_pwm_period(micro):
    """The twin's plant averages each PWM period; its peak current (the overcurrent comparator's
    input) adds the switched current's rise above that average, as the verification does."""
    from picdrive_hil.plant import CPlant, plant_from_profile

    from picdrive.models.simulate import pwm_ripple_peak_a
    cp = CPlant(plant_from_profile(micro))
    cp.params.inertia_kg_m2 = 1e3                        # rotor held (no EMF): a pure switched RL pair
    h, d = 1.0 / micro.inverter.pwm_frequency_hz, 0.5
    for _ in range(400):
        cp.step([(d, 0.0), (0.0, 1.0), (0.0, 0.0)], 0.0, h)
    i_avg = cp.state.i_a[0]
    assert i_avg == pytest.approx(d * micro.inverter.bus_voltage_v / micro.motor.r_line_ohm, rel=1e-3)
    excess = pwm_ripple_peak_a(micro.inverter.bus_voltage_v, micro.motor.r_line_ohm, micro.motor.l_line_h, d, h)
    assert excess > 0.1
    assert cp.state.i_peak_a == pytest.approx(i_avg + excess, rel=1e-6)


def test_the_backup_is_judged_on_what_it_cut_not_on_ripple_past_the_limit():
    """A flywheel accelerating at the 10 A limit (T-Motor AK80-6, its ZN law): the window holds the mean
    current at the limit, so the sampled current crosses it by its ripple and the backup's cap leaves the
    top in some samples, yet never cuts the law's output: the window alone holds the current.  With the
    current limit halved in the firmware only (the law's window still at 10 A), the backup does cut it."""
    from pathlib import Path
    from picdrive.analysis.steptest import run_sim, sim_plan
    from picdrive.control_law import Rule, ScheduledLaw
    from picdrive.gate import BuiltDrive
    prof = load_profile(Path(__file__).parent / "motors" / "tmotor_ak80_6_flywheel.toml")
    law = ScheduledLaw(rules=(Rule(10.47017288457329, 2028.82192435831, 0.013508396044606847, 0.0),),
                       premise_rad_s=(0.0, 41.8879020478639), sample_time_s=1e-3, u_min_v=-22.08, u_max_v=22.08,
                       current_limit_a=10.0, kb_v_s_per_rad=prof.motor.kb_v_s_per_rad, r_ohm=prof.motor.r_line_ohm)
    drive = BuiltDrive()
    sim = run_sim(prof, law, sim_plan(prof), measurement=drive.speed_measurement(prof, law), disturbances=False,
                  three_phase=drive.three_phase_plant)
    assert np.sum(sim.cap_active) > 0 and not np.any(sim.cap_cut)
    assert np.max(sim.i_meas) > 10.0                              # it did cross the limit
    low = prof.replace(inverter={"current_limit_a": 5.0})
    sim = run_sim(low, law, sim_plan(prof), measurement=drive.speed_measurement(low, law), disturbances=False,
                  three_phase=drive.three_phase_plant)
    assert np.sum(sim.cap_cut) > 10
