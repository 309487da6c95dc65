"""H2 cost (eq 22 vs Lyapunov), exact H-inf (eqs 7-10 vs grid vs Hamiltonian), stability tests."""
import numpy as np
import pytest
from scipy import integrate, signal

from picdrive.control_law import LawState, Rule, ScheduledLaw, law_step
from picdrive.analysis.h2hinf import h2_lyapunov, hinf_exact, hinf_exact_z, hinf_grid, hinf_statespace, j3_discrete, j3_jury_dewey, robust_constraint, routh_hurwitz, sampled_loop, sampled_loop_polys, schur_stable, sensitivity_peak_z, tracking_error_polys, robust_constraint_z, xi_tustin
from picdrive.profile import load_profile
from picdrive.models.tfmodel import TF, motor_tf, sampled_plant

P18 = TF([275577.36], [1, 417.7, 43567.5])


def _random_hurwitz(rng, n, size):
    """Random real Hurwitz polynomials of degree n (roots spread over decades), descending."""
    out = []
    for _ in range(size):
        roots = []
        while len(roots) < n:
            mag = 10 ** rng.uniform(-1, 4)
            if n - len(roots) >= 2 and rng.random() < 0.6:
                zeta = rng.uniform(0.02, 0.9)
                wd = mag * np.sqrt(1 - zeta ** 2)
                roots += [-zeta * mag + 1j * wd, -zeta * mag - 1j * wd]
            else:
                roots.append(-mag)
        out.append(np.real(np.poly(roots)) * rng.uniform(0.5, 3))
    return np.array(out)


def test_j3_jury_dewey_equals_lyapunov_random():
    rng = np.random.default_rng(0)
    a = _random_hurwitz(rng, 3, 300)
    b = rng.normal(size=(300, 3)) * np.abs(a[:, 1:]) ** 0.5
    jd = j3_jury_dewey(b, a)
    ly = h2_lyapunov(b, a)
    assert np.all(np.isfinite(jd)) and np.all(jd > 0)
    np.testing.assert_allclose(jd, ly, rtol=1e-8)


def test_h2_lyapunov_against_time_integral():
    num, den = [2.0, 3.0, 1.0], [1.0, 4.0, 6.0, 4.0]         # roots -2, -1 +- j
    t = np.linspace(0, 40, 160001)
    _, h = signal.impulse((num, den), T=t)
    direct = integrate.trapezoid(h ** 2, t)
    assert h2_lyapunov(num, den) == pytest.approx(direct, rel=1e-6)
    assert j3_jury_dewey(num, den) == pytest.approx(direct, rel=1e-6)
    # higher order (eq 25 is m = 5): Lyapunov works for any degree
    den5 = np.polymul(den, [1, 3, 5])
    _, h5 = signal.impulse(([1, 0, 2, 1], den5), T=t)
    assert h2_lyapunov([1, 0, 2, 1], den5) == pytest.approx(integrate.trapezoid(h5 ** 2, t), rel=1e-6)


def test_unstable_gives_inf():
    assert j3_jury_dewey([1, 1, 1], [1, 1, 1, 2]) == np.inf       # a1 a2 < a0 a3
    assert h2_lyapunov([1, 1, 1], [1, 1, 1, 2]) == np.inf


def test_routh_hurwitz_matches_roots():
    rng = np.random.default_rng(1)
    for n in range(1, 8):
        p = rng.normal(size=(400, n + 1))
        p[:, 0] = np.abs(p[:, 0]) + 0.1
        ref = np.array([np.all(np.roots(q).real < 0) for q in p])
        np.testing.assert_array_equal(routh_hurwitz(p), ref)
        hp = _random_hurwitz(rng, n, 50)
        assert routh_hurwitz(hp).all()
    assert not routh_hurwitz(np.array([1.0, 0.0, 1.0]))            # roots on the axis


def test_hinf_exact_equals_grid_and_hamiltonian_random():
    rng = np.random.default_rng(2)
    for n in (2, 3, 4, 5):
        dens = _random_hurwitz(rng, n, 25)
        nums = rng.normal(size=(25, n)) * np.abs(dens[:, 1:])          # strictly proper
        nums[::3, 0] = 0.0
        ex, wex = hinf_exact(nums, dens)
        w = np.logspace(-4, 6, 40001)
        for k in range(25):
            ss, _ = hinf_statespace(nums[k], dens[k])
            assert ex[k] == pytest.approx(ss, rel=1e-7)
            gr, _ = hinf_grid(nums[k], dens[k], w)
            assert gr <= ex[k] * (1 + 1e-9)                              # no grid point above the peak
            if np.isfinite(wex[k]):
                at = abs(np.polyval(nums[k], 1j * wex[k]) / np.polyval(dens[k], 1j * wex[k]))
                assert at == pytest.approx(ex[k], rel=1e-12)             # the peak is attained at w_peak


def test_hinf_exact_biproper_limit():
    # H = (2 s + 1)/(s + 1): |H| rises to 2 as w -> inf
    pk, w = hinf_exact(np.array([2.0, 1.0]), np.array([1.0, 1.0]))
    assert pk == pytest.approx(2.0) and w == np.inf


def test_robust_constraint_paper_gains():
    # ||P C xi/(1+PC)||_inf for d = 0.1: T ~ 1 at the resonance of xi, so ~ 0.316 (not binding)
    for g in [(180.1755, 4.6997, 0.0353), (70.556, 10, 0.0212)]:
        val, stable, w = robust_constraint(P18, *g, 0.1)
        assert stable and val == pytest.approx(0.316, abs=0.001) and w == pytest.approx(3.162, abs=0.01)
        char = np.polymul(np.polyadd(np.polymul([1, 417.7, 43567.5], [1, 0]),
                                     275577.36 * np.array([g[2], g[0], g[1]])), [1, 0.1, 10])
        num = 0.1 * 275577.36 * np.array([g[2], g[0], g[1]])
        assert hinf_statespace(num, char)[0] == pytest.approx(float(val), rel=1e-7)
    # an unstable gain set is reported as such
    val, stable, _ = robust_constraint(P18, 1.0, 1e9, 0.0, 0.1)
    assert not stable and val == np.inf


def test_tracking_error_polys_forms():
    num, den = tracking_error_polys(P18, 180.1755, 4.6997, 0.0353)
    assert np.allclose(num, [1, 417.7, 43567.5]) and den.shape == (4,)
    num_m, _ = tracking_error_polys(P18, 180.1755, 4.6997, 0.0353, derivative="measurement")
    assert np.allclose(num_m, [1, 417.7 + 275577.36 * 0.0353, 43567.5])


# --------------------------------------------------------------------------- sampled loop
@pytest.fixture(scope="module")
def sp():
    return sampled_plant(motor_tf(load_profile("duy2008")), 1e-3)


def test_sampled_loop_matches_polys_and_law(sp):
    kp = np.array([0.3, 0.5, 2.0]); ki = np.array([10.0, 30.0, 300.0]); kd = np.array([0.0, 5e-4, 5e-4])
    A, B, Cy = sampled_loop(sp, kp, ki, kd)
    char, _, _ = sampled_loop_polys(sp, kp, ki, kd)
    for k in range(3):
        np.testing.assert_allclose(np.sort_complex(np.linalg.eigvals(A[k])), np.sort_complex(np.roots(char[k])),
                                   rtol=1e-6, atol=1e-9)
    stable, rho = schur_stable(A)
    assert list(stable) == [True, True, False]
    J = j3_discrete(A, B, Cy, sp.ts)
    assert J[2] == np.inf
    for k in range(2):
        law = ScheduledLaw(rules=(Rule(kp[k], ki[k], kd[k]),), premise_rad_s=(0, 1), sample_time_s=sp.ts,
                           u_min_v=-1e12, u_max_v=1e12)
        st, x, s = LawState(), np.zeros(sp.n), 0.0
        for _ in range(5000):
            y = float(sp.Cd[0] @ x)
            s += (1 - y) ** 2 * sp.ts
            x = sp.Ad @ x + sp.Bd[:, 0] * law_step(law, st, 1.0, y)
        assert J[k] == pytest.approx(s, rel=1e-9)


def test_hinf_exact_z_equals_grid(sp):
    kp = np.array([0.3, 0.5, 0.7]); ki = np.array([10.0, 30.0, 60.0]); kd = np.array([0.0, 5e-4, 1e-3])
    ms, wms = sensitivity_peak_z(sp, kp, ki, kd)
    rc, stable, wrc = robust_constraint_z(sp, kp, ki, kd, 0.1)
    char, lnum, snum = sampled_loop_polys(sp, kp, ki, kd)
    xi = xi_tustin(0.1, sp.ts)
    th = np.concatenate([np.linspace(0, 0.02, 100001), np.linspace(0.02, np.pi, 200001)])
    z = np.exp(1j * th)
    for k in range(3):
        s = np.abs(np.polyval(snum[k], z) / np.polyval(char[k], z))
        assert s.max() == pytest.approx(ms[k], rel=1e-6) and s.max() <= ms[k] * (1 + 1e-9)
        t = np.abs(np.polyval(lnum[k], z) / np.polyval(char[k], z) * np.polyval(xi.num, z) / np.polyval(xi.den, z))
        assert t.max() == pytest.approx(rc[k], rel=1e-5) and t.max() <= rc[k] * (1 + 1e-9)   # sharp peak (Q ~ 32)
        assert wrc[k] == pytest.approx(np.sqrt(10), rel=1e-2)
    # the Tustin xi matches the continuous xi where it matters
    w = np.array([0.1, 1.0, np.sqrt(10), 10.0, 100.0])
    xd = np.abs(np.polyval(xi.num, np.exp(1j * w * sp.ts)) / np.polyval(xi.den, np.exp(1j * w * sp.ts)))
    xc = np.abs(0.1 / ((1j * w) ** 2 + 0.1j * w + 10))
    np.testing.assert_allclose(xd, xc, rtol=2e-3)


def test_hinf_exact_z_simple_first_order():
    # H(z) = 1/(z - a): peak 1/(1 - a) at theta = 0 for a > 0, 1/(1 + a) at pi for a < 0
    pk, th = hinf_exact_z(np.array([[0.0, 1.0], [0.0, 1.0]]), np.array([[1.0, -0.5], [1.0, 0.5]]))
    np.testing.assert_allclose(pk, [2.0, 2.0])
    np.testing.assert_allclose(th, [0.0, np.pi], atol=1e-9)
