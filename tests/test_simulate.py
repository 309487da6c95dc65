"""Simulation helpers: plant integration, the sampled law, the 2016 disturbances."""
import math
import warnings

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from picdrive.control_law import Rule, ScheduledLaw
from picdrive.dqmodel import derivatives, dq_params, equilibrium
from picdrive.profile import load_profile
from picdrive.simulate import disturbances_2016, simulate_law, step_load


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
