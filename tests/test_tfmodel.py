"""The 2008 transfer-function model (eq 1, 18, 19, 20, 21, 23-25, 6) and the sampled loop model."""
import math

import numpy as np
import pytest
from scipy import signal

from picdrive.profile import load_profile
from picdrive.models.tfmodel import TF, closed_loop_tf, load_gains, load_tf, motor_tf, perturbed_loop_tf, perturbed_plant, sampled_plant, speed_quantum_rad_s, tracking_error_tf, xi_tf

K18 = 275577.36       # eq 18 as printed


@pytest.fixture(scope="module")
def duy():
    return load_profile("duy2008")


def test_eq18_from_table2(duy):
    P = motor_tf(duy)
    # printed: 275577.36 / (s^2 + 417.7 s + 43567.5); computed from Table 2:
    # 0.1433/(0.052*1e-5) = 275576.92 and (21.2e-4 + 0.1433^2)/5.2e-7 = 43567.10
    assert P.den[0] == 1.0
    assert P.num[-1] == pytest.approx(K18, rel=2e-6)
    assert P.den[1] == pytest.approx(417.7, abs=0.01)
    assert P.den[2] == pytest.approx(43567.5, rel=1e-5)
    assert P.num[-1] == pytest.approx(0.1433 / (0.052 * 1e-5), rel=1e-12)


def test_eq1_by_hand_simple_motor():
    class M:
        l_line_h, r_line_ohm, inertia_kg_m2, viscous_friction_n_m_s = 1.0, 2.0, 1.0, 3.0
        kt_n_m_per_a = kb_v_s_per_rad = 1.0
    P = motor_tf(M())
    # (s + 2)(s + 3) + 1 = s^2 + 5 s + 7
    assert np.allclose(P.den, [1, 5, 7]) and np.allclose(P.num, [1])
    assert P.dcgain() == pytest.approx(1 / 7)
    assert P(1j * 2.0) == pytest.approx(1 / ((2j + 2) * (2j + 3) + 1))


def test_xi_bound_eq19():
    xi = xi_tf(0.1)
    w = np.logspace(-3, 3, 20001)
    mag = np.abs(xi(1j * w))
    assert mag[0] == pytest.approx(0.01, rel=1e-6)          # 0.1 |d| at w = 0, as eq 19 prints
    # but the peak, at the resonance sqrt(10), is ~3.16 |d|: eq 19's "<= 0.1|d|" does not hold
    assert mag.max() == pytest.approx(0.1 / (0.1 * math.sqrt(10 - 0.0025)), rel=1e-4)
    assert w[np.argmax(mag)] == pytest.approx(math.sqrt(10), rel=1e-3)


def test_eq23_perturbed_plant_coefficients(duy):
    P = TF([K18], [1, 417.7, 43567.5])                     # the paper's eq 18
    Pb = perturbed_plant(P, 0.1)
    assert np.allclose(Pb.num, K18 * np.array([1, 0.1, 10.1]))
    # printed: s^4 + 417.8 s^3 + 43619.27 s^2 + 8533.75 s + 435675
    assert np.allclose(Pb.den, [1, 417.8, 43619.27, 8533.75, 435675], rtol=1e-12)


def test_eq20_21_24_25_by_coefficients():
    P = TF([K18], [1, 417.7, 43567.5])
    kp, ki, kd, d = 180.1755, 4.6997, 0.0353, 0.1
    g = closed_loop_tf(P, kp, ki, kd)
    assert np.allclose(g.den, [1, 417.7 + K18 * kd, 43567.5 + K18 * kp, K18 * ki])     # a2, a1, a0
    assert np.allclose(g.num, K18 * np.array([kd, kp, ki]))
    e = tracking_error_tf(P, kp, ki, kd)
    assert np.allclose(e.num, [1, 417.7, 43567.5]) and np.allclose(e.den, g.den)        # eq 21 / 1000
    gb, eb = perturbed_loop_tf(P, d, kp, ki, kd)
    b = K18 * np.array([kd, 0.1 * kd + kp, (10 + d) * kd + 0.1 * kp + ki, (10 + d) * kp + 0.1 * ki, (10 + d) * ki])
    assert np.allclose(gb.num, b)
    c = [1, 417.8 + K18 * kd, 43619.27 + 27557.736 * kd + K18 * kp,
         8533.75 + K18 * (10 + d) * kd + 27557.736 * kp + K18 * ki,
         435675 + K18 * (10 + d) * kp + 27557.736 * ki, K18 * (10 + d) * ki]
    assert np.allclose(gb.den, c, rtol=1e-12)
    assert np.allclose(eb.num, [1, 417.8, 43619.27, 8533.75, 435675])                     # eq 25


def test_derivative_on_measurement_keeps_poles_drops_kd_zero():
    P = TF([K18], [1, 417.7, 43567.5])
    ge = closed_loop_tf(P, 70.556, 10, 0.0212)
    gm = closed_loop_tf(P, 70.556, 10, 0.0212, derivative="measurement")
    assert np.allclose(ge.den, gm.den)
    assert np.allclose(gm.num, K18 * np.array([70.556, 10]))
    with pytest.raises(ValueError, match="derivative"):
        closed_loop_tf(P, 1, 1, 1, derivative="both")


def test_load_gains_eq6(duy):
    k_pl, k_dl = load_gains(duy)
    assert k_pl == pytest.approx(1032, abs=0.5)          # printed k_pl = 1032
    assert k_dl == pytest.approx(2.53, abs=0.005)        # printed k_dl = 2.53
    # the physical load path has the same DC value up to the friction term
    lt = load_tf(duy)
    assert lt.dcgain() == pytest.approx(21.2 / 0.1433 / (21.2 * 1e-4 / 0.1433 + 0.1433), rel=1e-9)


@pytest.mark.parametrize("measurement", ["average", "instant"])
@pytest.mark.parametrize("delay", [0, 1])
def test_sampled_plant_dc_gain_and_step(duy, measurement, delay):
    P = motor_tf(duy)
    ts = 1e-3
    sp = sampled_plant(P, ts, delay_samples=delay, measurement=measurement)
    z = sp.tf_z
    assert np.polyval(z.num, 1.0) / np.polyval(z.den, 1.0) == pytest.approx(P.dcgain(), rel=1e-9)
    # simulate a unit voltage step; compare with the continuous step response
    t = np.linspace(0, 0.05, 50001)
    _, yc = signal.step((P.num, P.den), T=t)
    yint = np.concatenate([[0.0], np.cumsum(0.5 * (yc[1:] + yc[:-1]) * np.diff(t))])
    x = np.zeros(sp.n)
    ys = []
    for k in range(40):
        ys.append((sp.Cd @ x)[0])
        x = sp.Ad @ x + sp.Bd[:, 0] * 1.0
    ys = np.array(ys)
    shift = delay
    for k in range(1 + shift, 40):
        tk = (k - shift) * ts
        if measurement == "instant":
            expect = np.interp(tk, t, yc)
        else:     # mean over the last period
            expect = (np.interp(tk, t, yint) - np.interp(tk - ts, t, yint)) / ts
        assert ys[k] == pytest.approx(expect, rel=1e-5, abs=1e-9)
    assert np.all(ys[:1 + shift] == 0.0)


def test_speed_quantum(duy):
    # 500 lines x 4 counts at 1 kHz: 2 pi / (2000 * 1e-3) rad/s per count
    assert speed_quantum_rad_s(duy) == pytest.approx(2 * math.pi / 2.0)
    hall = duy.replace(sensors={"speed_source": "hall"})
    edges = 6 * duy.motor.pole_pairs                 # hall edges per mechanical turn
    assert speed_quantum_rad_s(hall) == pytest.approx(2 * math.pi / (edges * 1e-3))


def test_batch_simulation_equals_law_step_simulation(duy):
    """simulate_sampled_batch (eq 1, saturated step) is law_step written for arrays (a law without
    the current window: the batch has none; the six-step batch of picdrive.models.simulate has it)."""
    import dataclasses

    from picdrive.design.mixed_pid import pid_law as _pid_law

    def pid_law(*a):
        return dataclasses.replace(_pid_law(*a), current_limit_a=None)
    from picdrive.models.tfmodel import simulate_sampled, simulate_sampled_batch
    kp = np.array([0.1, 0.5, 3.0, 0.3]); ki = np.array([10.0, 40.0, 300.0, 0.0]); kd = np.array([0, 1e-3, 5e-3, 2e-3])
    ref = 2400 * math.pi / 30
    law0 = pid_law(duy, 1, 1, 0)
    for delay, meas in ((1, "average"), (0, "instant")):
        b = simulate_sampled_batch(duy, kp, ki, kd, ts=law0.sample_time_s, u_max_v=law0.u_max_v, t_end_s=0.15,
                                   ref_rad_s=ref, delay_samples=delay, measurement=meas)
        for j in range(kp.size):
            s = simulate_sampled(duy, pid_law(duy, kp[j], ki[j], kd[j]), t_end_s=0.15, ref_rad_s=ref,
                                 delay_samples=delay, measurement=meas)
            np.testing.assert_allclose(b["speed_rad_s"][:, j], s["speed_rad_s"], rtol=1e-10, atol=1e-9)
            np.testing.assert_allclose(b["current_a"][:, j], s["current_a"], rtol=1e-10, atol=1e-9)
        assert np.max(np.abs(b["current_a"][:, 2])) > 1.0      # the aggressive law saturates and draws current
