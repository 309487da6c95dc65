"""TS fuzzy models: memberships shared with the law, exactness, vertices = linearisations."""
import warnings

import numpy as np
import pytest

from picdrive.control_law import Rule, ScheduledLaw, memberships
from picdrive.models.dqmodel import derivatives, dq_params, jacobian
from picdrive.profile import load_profile
from picdrive.models.tsfuzzy import operating_region, paper_model, rule_centres, tracking_model


@pytest.fixture(scope="module", params=["assawinchaichote2016", "duy2008"])
def prof(request):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_profile(request.param)


def test_vertices_are_linearisations_at_premise_points(prof):
    ts = paper_model(prof)
    p = dq_params(prof)
    for i, c in enumerate(rule_centres(ts.premise_rad_s, ts.r)):
        A, B = jacobian(p, (c, 0.0, 0.0))
        assert ts.A[i] == pytest.approx(A)
        assert ts.B[i] == pytest.approx(B)
    assert ts.premise_rad_s[1] == pytest.approx(prof.design["premise_rpm"][1] * 2 * np.pi / 60)


def test_memberships_are_the_laws(prof):
    for r in (1, 2, 3):
        ts = paper_model(prof, rules=r)
        law = ScheduledLaw(rules=tuple(Rule(1, 1) for _ in range(r)), premise_rad_s=ts.premise_rad_s,
                           sample_time_s=1e-3, u_min_v=-1, u_max_v=1)
        for s in np.linspace(-50, 400, 17):
            assert ts.mu(s) == pytest.approx(memberships(law, s))


def test_ts_model_is_exact_inside_premise(prof):
    # L_d = L_q: sum mu_i A_i x equals the nonlinear model (sector nonlinearity, not an approximation)
    ts = paper_model(prof, rules=3)
    p = dq_params(prof)
    rng = np.random.default_rng(0)
    for _ in range(10):
        x = np.array([rng.uniform(*ts.premise_rad_s), rng.normal() * 3, rng.normal() * 3])
        u = rng.normal(size=2) * 10
        A, B = ts.blended(x[0])
        assert A @ x + B @ u == pytest.approx(derivatives(p, x, u[0], u[1]), rel=1e-9)


def test_uncertainty_structure_is_paper_h1(prof):
    ts = paper_model(prof)
    p = dq_params(prof)
    assert ts.H1[0] == pytest.approx(np.diag([0, -0.1 * p.r_ohm / p.lq_h, -0.1 * p.r_ohm / p.ld_h]))
    # F = +I in dA = F H1 is R + 10 %
    A_hi = jacobian(p.replace(r_ohm=1.1 * p.r_ohm), (ts.premise_rad_s[1], 0, 0))[0]
    assert ts.A[-1] + ts.H1[-1] == pytest.approx(A_hi)


def test_tracking_model_deviation_is_exact(prof):
    ts = tracking_model(prof)
    p = dq_params(prof)
    reg = operating_region(prof)
    from picdrive.models.dqmodel import equilibrium
    w0 = reg["omega_top_rad_s"]
    iq0, id0, vq0 = equilibrium(p, w0, reg["load_n_m"])
    dx = np.array([3.0, 0.05, -0.02])
    x = np.array([w0, iq0, id0]) + dx
    du = 0.7
    f = derivatives(p, x, vq0 + p.kv_vq_per_u * du, 0.0, reg["load_n_m"])
    # exact decomposition: scheduled by the *actual* speed, unscheduled by the equilibrium currents
    A = ts.blended(x[0])[0][:3, :3] + (jacobian(p, (0, iq0, id0))[0] - jacobian(p, (0, 0, 0))[0])
    assert A @ dx + ts.B[0][:3, 0] * du == pytest.approx(f, rel=1e-9, abs=1e-9)
    # the equilibrium currents lie inside the polytope box
    assert 0 <= iq0 <= reg["iq_max_a"] + 1e-12 and 0 <= id0 <= reg["id_max_a"] + 1e-12
