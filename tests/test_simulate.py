"""Simulation helpers: plant integration, the sampled law, the 2016 disturbances."""
import math
import warnings

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from picdrive.control_law import Rule, ScheduledLaw
from picdrive.models.dqmodel import derivatives, dq_params, equilibrium
from picdrive.profile import load_profile
from picdrive.models.simulate import disturbances_2016, simulate_law, step_load


@pytest.fixture(scope="module")
def prof():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_profile("assawinchaichote2016")


def test_constant_voltage_matches_solve_ivp_and_equilibrium(prof):
    p = dq_params(prof)
    u = 20.0
    law = ScheduledLaw(rules=(Rule(kp=0.0, ki=0.0),), premise_rad_s=(0, 1), sample_time_s=1e-3,
                       u_min_v=u - 1e-9, u_max_v=u)        # a "law" that always outputs u
    sim = simulate_law(prof, law, t_end=0.2, ref_rpm=0.0, load=0.2)
    ref = solve_ivp(lambda t, x: derivatives(p, x, p.kv_vq_per_u * u, 0.0, 0.2), (0, 0.2), [0, 0, 0],
                    t_eval=sim.t, rtol=1e-10, atol=1e-12)
    assert sim.omega == pytest.approx(ref.y[0], abs=1e-5 * max(1, np.max(ref.y[0])))
    # steady state = the model's equilibrium at that voltage
    w_end = sim.omega[-1]
    assert equilibrium(p, w_end, 0.2)[2] == pytest.approx(p.kv_vq_per_u * u, rel=1e-4)


def test_sampled_law_holds_u_between_samples(prof):
    law = ScheduledLaw(rules=(Rule(kp=0.1, ki=5.0),), premise_rad_s=(0, 1), sample_time_s=2e-3,
                       u_min_v=-44.0, u_max_v=44.0)
    sim = simulate_law(prof, law, t_end=0.05, ref_rpm=100.0)
    assert np.diff(sim.t) == pytest.approx(np.full(sim.t.size - 1, 2e-3))
    assert sim.u[0] == pytest.approx(0.1 * 100 * 2 * math.pi / 60 + 5.0 * 2e-3 * 100 * 2 * math.pi / 60)


def test_disturbances_finite_energy_and_deterministic():
    t = np.linspace(0, 0.5, 5001)
    w = disturbances_2016(t, amplitude=(1, 1, 0.1))
    assert np.all(w[t >= 0.2] == 0) and np.all(np.abs(w[:, :2]) <= 1) and np.all(np.abs(w[:, 2]) <= 0.1)
    assert np.array_equal(w, disturbances_2016(t, amplitude=(1, 1, 0.1)))
    assert np.std(w[t < 0.2, 0]) > 0.4      # noise, not a constant
    assert step_load(0.3, 2.0)(0.29) == 0.0 and step_load(0.3, 2.0)(0.3) == 2.0


# ---------------------------------------------------------------------------
# the six-step drive model (verification's plant)
# ---------------------------------------------------------------------------
from picdrive.models.simulate import commutated_emf, simulate_six_step, simulate_six_step_batch  # noqa: E402


@pytest.fixture(scope="module")
def duy():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_profile("duy2008")


def _const_law(u, ts=1e-3):
    """A 'law' whose output is always u (its window collapses to u)."""
    return ScheduledLaw(rules=(Rule(kp=0.0, ki=0.0),), premise_rad_s=(0, 1), sample_time_s=ts,
                        u_min_v=min(u, 0.0) - 1e-9 if u <= 0 else u - 1e-9, u_max_v=u if u > 0 else u + 1e-9)


def test_six_step_constant_voltage_reaches_the_dc_equivalent_speed(duy):
    u = 30.0
    s = simulate_six_step(duy, _const_law(u), t_end=0.4, ref_rpm=0.0)
    m = duy.motor
    w_ss = u / (m.kb_v_s_per_rad + m.r_line_ohm * m.viscous_friction_n_m_s / m.kt_n_m_per_a)
    assert s.omega[-1] == pytest.approx(w_ss, rel=1e-4)
    assert s.i[-1] == pytest.approx(m.viscous_friction_n_m_s * w_ss / m.kt_n_m_per_a, rel=1e-3)


def test_current_cannot_reverse_below_the_back_emf(duy):
    """u >= 0 below the EMF: the current decays to zero and stays there (no braking); the
    speed falls by friction alone: J w' = -B w."""
    m = duy.motor
    w0 = 200.0
    s = simulate_six_step(duy, _const_law(10.0), t_end=0.1, ref_rpm=0.0, x0=(0.5, w0), integrator0_v=10.0)
    assert np.min(s.i_fine) >= 0.0
    k = np.nonzero(s.i_fine == 0.0)[0][0]
    assert s.t_fine[k] < 0.02                                  # the current died within a few L/R
    w_k, t_k = s.omega_fine[k], s.t_fine[k]
    expect = w_k * np.exp(-m.viscous_friction_n_m_s / m.inertia_kg_m2 * (s.t_fine[-1] - t_k))
    assert s.omega_fine[-1] == pytest.approx(expect, rel=1e-3)


def test_negative_output_plugs_after_one_sample_with_all_switches_off(duy):
    s = simulate_six_step(duy, _const_law(-10.0), t_end=0.03, ref_rpm=0.0, x0=(0.5, 200.0), integrator0_v=10.0)
    assert s.direction[0] == 0 and np.all(s.direction[1:] == -1)      # one sample all off, then the reverse table
    assert np.min(s.i_fine) < -0.3                                      # braking current
    free = simulate_six_step(duy, _const_law(10.0), t_end=0.03, ref_rpm=0.0, x0=(0.5, 200.0), integrator0_v=10.0)
    assert s.omega[-1] < free.omega[-1] - 20.0


def test_commutated_emf_mean_is_kb_and_advance_ripples(duy):
    aligned = duy.replace(sensors={"hall_offset_deg": 30.0})
    kf, kr = commutated_emf(aligned)
    kb = duy.motor.kb_v_s_per_rad
    assert np.allclose(kf, kb) and np.allclose(kr, -kb)                  # trapezoid, aligned: flat tops only
    kf0, _ = commutated_emf(duy.replace(sensors={"hall_offset_deg": 0.0}))
    assert kf0.min() == pytest.approx(0.5 * kb, rel=1e-2) and kf0.max() == pytest.approx(kb)   # 30 deg early
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sine = load_profile("assawinchaichote2016").replace(sensors={"hall_offset_deg": 30.0})
    ks, _ = commutated_emf(sine)
    assert ks.mean() == pytest.approx(sine.motor.kb_v_s_per_rad, rel=1e-4)
    assert ks.min() / ks.max() == pytest.approx(np.sqrt(3) / 2, rel=2e-3)       # table bins: 0.25 deg


def test_batch_equals_scalar_simulation(duy):
    from picdrive.design.mixed_pid import pid_law
    kp = np.array([0.12, 0.53, 0.2]); ki = np.array([10.0, 74.0, 400.0]); kd = np.array([0.0, 9e-4, 0.0])
    ref = 2400 * math.pi / 30
    n_sub = int(round(1e-3 * duy.inverter.pwm_frequency_hz)) - 1
    b = simulate_six_step_batch(duy, kp, ki, kd, t_end_s=0.2, ref_rad_s=ref, n_sub=n_sub)
    for j in range(kp.size):
        s = simulate_six_step(duy, pid_law(duy, kp[j], ki[j], kd[j]), t_end=0.2, ref_rpm=2400.0)
        np.testing.assert_allclose(b["speed_rad_s"][:, j], s.omega, rtol=1e-5, atol=1e-6)
        assert b["peak_speed_rad_s"][j] == pytest.approx(np.max(s.omega_fine), rel=1e-5)
        assert b["peak_current_a"][j] == pytest.approx(np.max(np.abs(s.i_fine)), rel=1e-4)
    assert not np.any(s.cap_active)


def test_batch_with_the_hall_meter_equals_scalar_simulation():
    """The batch with ``hall=`` measures the speed as simulate_six_step's "hall" does (the hall-edge
    period in Timer5 ticks of the firmware's plan) and takes the same signed torque disturbance:
    the same trajectories on a halls-only drive."""
    from picdrive.design.mixed_pid import pid_law
    from picdrive.gate import speed_measurement
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = load_profile("duy2008_halls")
    kp = np.array([0.12, 0.4, 0.2]); ki = np.array([10.0, 34.7, 80.0]); kd = np.array([0.0, 9e-4, 0.0])
    meter = speed_measurement(p, pid_law(p, 0.4, 34.7, 9e-4))["hall"]
    ref = p.speed_step_rpm() * math.pi / 30
    n_sub = int(round(1e-3 * p.inverter.pwm_frequency_hz)) - 1
    w3 = lambda t: 0.05 * math.sin(300.0 * t)            # a signed torque against the motor, N m
    b = simulate_six_step_batch(p, kp, ki, kd, t_end_s=0.15, ref_rad_s=ref, n_sub=n_sub, hall=meter,
                                torque_disturbance=w3)
    mt = simulate_six_step_batch(p, kp, ki, kd, t_end_s=0.15, ref_rad_s=ref, n_sub=n_sub, torque_disturbance=w3)
    for j in range(kp.size):
        s = simulate_six_step(p, pid_law(p, kp[j], ki[j], kd[j]), t_end=0.15, ref_rpm=ref * 30 / math.pi,
                              measurement="hall", hall=meter, torque_disturbance=w3)
        np.testing.assert_allclose(b["speed_rad_s"][:, j], s.omega, rtol=1e-5, atol=1e-6)
        assert b["peak_speed_rad_s"][j] == pytest.approx(np.max(s.omega_fine), rel=1e-5)
        # and the hall's lag is not the encoder's: the M/T batch differs
        assert np.max(np.abs(mt["speed_rad_s"][:, j] - s.omega)) > 1e-3 * ref


def test_firmware_measurement_is_mt_average_plus_half_a_sample(duy):
    """y[k] = w_avg[k] + (w_avg[k] - w_avg[k-1]) / 2, w_avg[k] the mean speed over the last sample
    (from the PWM-period trajectory), no extrapolation at the first counts."""
    from picdrive.design.mixed_pid import pid_law
    s = simulate_six_step(duy, pid_law(duy, 0.3, 30.0, 0.0), t_end=0.05, ref_rpm=1500.0)
    n_sub = s.t_fine.size // (s.t.size)
    w = np.concatenate([[0.0], s.omega_fine])
    seg = 0.5 * (w[1:] + w[:-1])                          # trapezoid over each PWM period
    w_avg = seg[: n_sub * (s.t.size - 1)].reshape(-1, n_sub).mean(axis=1)   # sample k+1's average
    y_expect = w_avg[1:] + 0.5 * (w_avg[1:] - w_avg[:-1])
    np.testing.assert_allclose(s.y[2:], y_expect, rtol=1e-9, atol=1e-9)
    assert s.y[0] == 0.0 and s.y[1] == pytest.approx(w_avg[0])
