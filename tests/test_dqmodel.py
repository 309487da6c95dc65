"""The corrected dq model: steady state, energy balance, linearisation, six-step mapping."""
import math
import warnings

import numpy as np
import pytest

from picdrive.models.dqmodel import derivatives, dq_params, electrical_power_w, equilibrium, jacobian, max_speed_rad_s, six_step_gains, stored_energy_j, torque_n_m
from picdrive.profile import load_profile


@pytest.fixture(scope="module", params=["assawinchaichote2016", "duy2008"])
def prof(request):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_profile(request.param)


def test_table1_by_hand():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = dq_params(load_profile("assawinchaichote2016"))
    # Table 1: P = 2, L = 1.8 mH, R = 0.5, J = 0.003, B = 0.0008, lambda = 0.311
    x = np.array([10.0, 2.0, 0.5])
    f = derivatives(p, x, vq=20.0, vd=1.0, load_n_m=0.3)
    assert f[0] == pytest.approx((1.5 * 2 * 0.311 * 2.0 - 0.0008 * 10 - 0.3) / 0.003)
    assert f[1] == pytest.approx((20.0 - 0.5 * 2.0 - 2 * 10 * 0.0018 * 0.5 - 2 * 10 * 0.311) / 0.0018)
    # the corrected sign: -R/L_d i_d (the printed eq. 5 has +R/L_d)
    assert f[2] == pytest.approx((1.0 - 0.5 * 0.5 + 2 * 10 * 0.0018 * 2.0) / 0.0018)


def test_disturbances_enter_as_eq36(prof):
    p = dq_params(prof)
    x = np.array([5.0, 0.1, -0.2])
    f0 = derivatives(p, x, 1.0)
    f1 = derivatives(p, x, 1.0, w=(2.0, 3.0, 0.01))
    assert f1 - f0 == pytest.approx([-0.01 / p.j_kg_m2, 0.3, 0.2])


def test_equilibrium_is_a_fixed_point(prof):
    p = dq_params(prof)
    for w in (0.0, 30.0, 150.0):
        for load in (0.0, prof.control.load_torque_n_m):
            iq, id_, vq = equilibrium(p, w, load)
            f = derivatives(p, (w, iq, id_), vq, 0.0, load)
            assert np.abs(f) == pytest.approx(np.zeros(3), abs=1e-6)
            assert torque_n_m(p, iq, id_) == pytest.approx(p.b_n_m_s * w + load)


def test_energy_balance_salient_machine(prof):
    # d/dt (kinetic + magnetic) = electrical power - copper loss - friction - load power, also for Ld != Lq
    p = dq_params(prof).replace(ld_h=dq_params(prof).ld_h * 0.7)
    rng = np.random.default_rng(1)
    for _ in range(5):
        x = rng.normal(size=3) * [50, 2, 2]
        vq, vd, load = rng.normal(size=3) * [10, 10, 0.1]
        f = derivatives(p, x, vq, vd, load)
        dE = p.j_kg_m2 * x[0] * f[0] + 1.5 * (p.lq_h * x[1] * f[1] + p.ld_h * x[2] * f[2])
        loss = 1.5 * p.r_ohm * (x[1] ** 2 + x[2] ** 2) + p.b_n_m_s * x[0] ** 2 + load * x[0]
        assert dE == pytest.approx(electrical_power_w(p, x, vq, vd) - loss, rel=1e-9, abs=1e-9)


def test_jacobian_matches_finite_differences(prof):
    p = dq_params(prof).replace(ld_h=dq_params(prof).ld_h * 0.8)
    x = np.array([40.0, 1.2, -0.4])
    A, B = jacobian(p, x)
    h = 1e-6
    for k in range(3):
        dx = np.zeros(3); dx[k] = h
        col = (derivatives(p, x + dx, 3.0, 1.0) - derivatives(p, x - dx, 3.0, 1.0)) / (2 * h)
        assert A[:, k] == pytest.approx(col, rel=1e-6, abs=1e-6)
    assert (derivatives(p, x, 4.0, 1.0) - derivatives(p, x, 3.0, 1.0)) == pytest.approx(B[:, 0])


def test_six_step_mapping_power_and_speed(prof):
    m = prof.motor
    kv, ki = six_step_gains(m)
    # power balance u i_bus = 3/2 v_q i_q (lossless inverter, Kt = Kb)
    assert (1 / kv) * ki == pytest.approx(1.5 * m.kb_v_s_per_rad / m.kt_n_m_per_a)
    # no-load speed: u = Kb w  <=>  v_q = P lambda w
    p = dq_params(prof)
    w = 50.0
    assert kv * m.kb_v_s_per_rad * w == pytest.approx(p.pole_pairs * p.lambda_m_v_s * w)
    expect = {"trapezoidal": (0.5, 0.75), "sinusoidal": (math.pi / (3 * math.sqrt(3)), math.pi / (2 * math.sqrt(3)))}
    assert (kv, ki) == pytest.approx(expect[m.back_emf_shape])


def test_max_speed_consistent_with_equilibrium(prof):
    p = dq_params(prof)
    vmax = 20.0
    w = max_speed_rad_s(p, vmax, prof.control.load_torque_n_m)
    assert equilibrium(p, w, prof.control.load_torque_n_m)[2] == pytest.approx(vmax)
    assert stored_energy_j(p, (w, 0, 0)) == pytest.approx(0.5 * p.j_kg_m2 * w * w)
