"""fuzzy-hinf at the speed-loop rate: the sampled model, the discrete bounded-real lemma, the synthesis.

Every certificate is re-checked here in numpy, independently of the solver and of the verification:
the closed loop rebuilt from the profile, its spectral radius at every rule and vertex, its H-inf
norm against the bound (picdrive.analysis.dlmi, picdrive.design.fuzzy_dhinf; docs/design-fuzzy.md).
"""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from picdrive.analysis.dlmi import (closed_loop_radius, dhinf_norm, dlmi_margins, law_gains, normalised,
                                    rescaled, sampled_model, sampled_stages)
from picdrive.analysis.sampled import six_step_closed_loop
from picdrive.control_law import Rule
from picdrive.design import fuzzy_hinf
from picdrive.design.fuzzy_dhinf import GAMMA_BACK_OFF, solve_discrete
from picdrive.gate import BuiltDrive
from picdrive.models.tsfuzzy import model_for
from picdrive.paths import repo_root
from picdrive.profile import load_profile

DRIVE = BuiltDrive()


def _profile(name):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_profile(name)


def test_the_design_model_is_the_verifications_sampled_loop():
    """The sampled model's closed loop under the law's gains has the eigenvalues of
    analysis.sampled.six_step_closed_loop (the verification's check), at R nominal and at its extremes:
    design and check close the same loop (delay, measurement, integrator)."""
    p = _profile("duy2008")
    ts = model_for(p, "six-step", {"emf_polytope": False})
    sm = sampled_model(p, ts)
    rng = np.random.default_rng(3)
    eps = p.design["resistance_uncertainty"]
    for _ in range(4):
        kp, ki, kc = rng.uniform(0.1, 3.0), rng.uniform(5.0, 200.0), rng.uniform(0.5, 30.0)
        F = np.array([-(kp + ki * sm.ts_s), -kc, ki])            # u = F [y, i, z]
        K = np.concatenate([F / sm.su * sm.S[:3], np.zeros(sm.n - 3)])[None]
        assert law_gains(sm, [K])[0] == pytest.approx((kp, ki, kc), rel=1e-12)
        for v, rs in enumerate((1.0, 1.0 - eps, 1.0 + eps)):
            assert sm.vertices[v].startswith(f"rule plant, R x {rs:g}")
            mine = np.sort_complex(np.linalg.eigvals(sm.A[0][v] + sm.B[0][v] @ K))
            theirs = np.linalg.eigvals(six_step_closed_loop(p, Rule(kp=kp, ki=ki, kd=0.0, kc=kc), sm.ts_s, None,
                                                            r_factor=rs))
            # the check's loop has two more states (derivative memory and filter, both at 0 with kd = 0)
            theirs = np.sort_complex(theirs[np.argsort(-np.abs(theirs))][:sm.n])
            assert np.max(np.abs(mine)) == pytest.approx(np.max(np.abs(theirs)), rel=1e-9)
            assert mine == pytest.approx(theirs, abs=1e-9)


def test_discrete_hinf_norm_against_a_frequency_sweep():
    rng = np.random.default_rng(5)
    for _ in range(3):
        A = rng.standard_normal((4, 4))
        A *= 0.9 / np.max(np.abs(np.linalg.eigvals(A)))
        B, C = rng.standard_normal((4, 2)), rng.standard_normal((3, 4))
        th = np.linspace(0.0, math.pi, 20001)
        sweep = max(np.linalg.svd(C @ np.linalg.solve(np.exp(1j * t) * np.eye(4) - A, B), compute_uv=False)[0]
                    for t in th)
        # the sweep is a lower bound; 2e4 points on the half circle resolve these peaks to 1e-4
        assert dhinf_norm(A, B, C) == pytest.approx(sweep, rel=1e-4)
        assert dhinf_norm(A, B, C) >= sweep * (1 - 1e-9)
    assert dhinf_norm(np.diag([1.01, 0.2]), np.ones((2, 1)), np.ones((1, 2))) == math.inf


@pytest.fixture(scope="module")
def dc_solution():
    """The synthesis on the 2016 motor's DC equivalent (2 equal rules, R and EMF vertices), as design() runs it."""
    p = _profile("assawinchaichote2016")
    ts = model_for(p, "six-step", {"integral_weight_rad_s": (p.motor.viscous_friction_n_m_s + p.motor.kt_n_m_per_a
                                                            * p.motor.kb_v_s_per_rad / p.motor.r_line_ohm)
                                   / p.motor.inertia_kg_m2})
    # design()'s second command weight, the full command priced as the full speed error (w_top / u_max)
    ew = ts.info["state_scale"][0] / (p.inverter.bus_voltage_v * p.max_duty())
    sm, stages = sampled_stages(p, ts, "six-step", (), ew)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        sol = solve_discrete(sm, start=stages)
    return p, ts, sm, sol, seen, ew


def test_the_certificate_holds_when_rebuilt_in_numpy(dc_solution):
    """The centred solution: the LMIs re-assembled are strictly satisfied; rebuilt independently from the
    profile (no solver object), every rule/vertex closed loop has spectral radius < 1 and H-inf norm within
    the certified gamma; gamma is 1.05 gamma_min; no solver text reaches the user."""
    p, ts, sm, sol, seen, _ = dc_solution
    assert [str(w.message) for w in seen] == []
    assert sol.feasible and sol.status == "optimal" and "centring" not in sol.extra
    # gamma backed off from the alternation's minimum: 1.05, else 1.1 or 1.2 x (the first centred solve that ends
    # optimal and strictly feasible)
    assert sol.extra["gamma_back_off"] in (GAMMA_BACK_OFF, 2 * GAMMA_BACK_OFF, 4 * GAMMA_BACK_OFF)
    assert sol.gamma == pytest.approx((1 + sol.extra["gamma_back_off"]) * sol.extra["gamma_min"], rel=1e-12)
    smn, nb, nc = normalised(rescaled(sm, sol.model.S / sm.S))
    marg = dlmi_margins(smn, sol.Q, sol.G, sol.Y, sol.extra["gamma_normalised"])
    assert max(marg.values()) < 0
    # K = [K_m, 0]: the law uses only [y, i, z]
    for k in sol.K:
        assert np.all(np.asarray(k)[0, sm.n_meas:] == 0.0)
    worst_rad, worst_h = 0.0, 0.0
    for v in range(smn.nv):
        for i in range(smn.r):
            for j in range(smn.r):
                Acl = smn.A[i][v] + smn.B[i][v] @ sol.K[j]
                worst_rad = max(worst_rad, float(np.max(np.abs(np.linalg.eigvals(Acl)))))
            Acl = smn.A[i][v] + smn.B[i][v] @ sol.K[i]
            Cz = smn.C[i] + smn.D[i] @ sol.K[i]                  # z = C x + D u, u = K x
            worst_h = max(worst_h, dhinf_norm(Acl, smn.Bw[i][v], Cz) * nb * nc)
    assert worst_rad < 1.0
    assert worst_h <= sol.gamma * (1 + 1e-6)
    rad, _ = closed_loop_radius(smn, sol.K)
    assert rad == pytest.approx(worst_rad, rel=1e-12)
    # the law's gains on the verification's own sampled loop: stable at every check point
    for kp, ki, kc in law_gains(sol.model, sol.K):
        for rs in (0.9, 1.0, 1.1):
            A = six_step_closed_loop(p, Rule(kp=kp, ki=ki, kd=0.0, kc=kc), sm.ts_s, None, r_factor=rs)
            assert np.max(np.abs(np.linalg.eigvals(A))) < 1.0


@pytest.mark.slow          # 60 s; the loop-rate design is not committed anywhere, so nothing pins its gains
def test_the_centred_gains_do_not_move_with_the_last_digits(dc_solution):
    """The model's A and B perturbed at 1e-9 relative move the loop-rate gains by 4.4 % relative (measured on
    this profile; 10 % before the centred rounds): the alternation stops at a local optimum that the last
    digits move, and the centred rounds only partly pin it.  This is far from the continuous design's 1e-4
    (tests/test_fuzzy_hinf.py) and is why no loop-rate design is committed under examples/ yet
    (docs/design-fuzzy.md, "Numerics"); the bound asserted, 0.1, is about twice the spread measured, so a
    regression that loses the centring (10 %) or a real change of the design (tens of percent) fails it."""
    import dataclasses
    p, ts, sm, sol, _, ew = dc_solution
    rng = np.random.default_rng(11)

    def jiggle(m):
        # the same perturbation for every rule: the rules stay equal, as the DC equivalent's are
        A = [a * (1 + 1e-9 * rng.standard_normal(a.shape)) for a in m.A[0]]
        B = [b * (1 + 1e-9 * rng.standard_normal(b.shape)) for b in m.B[0]]
        return dataclasses.replace(m, A=[A] * m.r, B=[B] * m.r)
    sm_p = jiggle(sm)
    _, stages = sampled_stages(p, ts, "six-step", (), ew)
    s1 = solve_discrete(sm_p, start=[jiggle(x) for x in stages])
    g0, g1 = (np.array(law_gains(s.model, s.K)) for s in (sol, s1))
    assert np.max(np.abs(g1 - g0) / np.abs(g0)) < 0.1


@pytest.mark.slow          # 150 s: the whole default chain; the suite keeps the synthesis's certificate test
def test_a_fast_winding_gets_a_verified_design():
    """maxon EC 13 305192: L/R 15.9 us against a 1 ms speed loop.  The continuous Theorem 1 has no certificate
    at any gamma there (the current mode cannot be held inside any pole disk the sampled law allows); at the
    loop rate the current mode is one sampled pole among others, and the design verifies."""
    p = _profile(str(repo_root() / "tests" / "motors" / "maxon_ec13_305192.toml"))
    cont = fuzzy_hinf.design(p, drive=DRIVE, progress=False, time_domain="continuous", plant_model="six-step",
                             simulate=False)
    assert not cont.ok and "no fuzzy-hinf certificate exists at any gamma" in cont.reasons[0]
    with pytest.warns(UserWarning, match="designed at the loop rate, not by the continuous Theorem 1"):
        r = fuzzy_hinf.design(p, drive=DRIVE, progress=False)      # the default: continuous, then the loop rate
    assert r.ok, r.reasons
    c, v = r.certificate, r.verification
    assert c["time_domain"] == "discrete" and r.options["time_domain"] == "discrete"
    assert "no fuzzy-hinf certificate exists at any gamma" in c["time_domain_fallback"]
    assert v["sampled_spectral_radius"]["value"] < 1.0 and v["discrete_spectral_radius"]["value"] < 1.0
    assert v["lmi_max_eig"]["value"] < 0 and v["hinf_norm"]["value"] <= c["certified_gain"] * (1 + 1e-6)
    assert v["sim_overshoot_pct"]["ok"] and v["sim_settling_s"]["ok"]


def test_a_failure_names_the_reason_with_numbers():
    """A pole disk no law can meet (|z| < 0.05 with the integrator and the mechanical mode): the design fails
    and says which requirement, the solver's status and how to get a design."""
    p = _profile("duy2008")
    # time_domain given: no fallback to the continuous design
    r = fuzzy_hinf.design(p, drive=DRIVE, progress=False, plant_model="six-step", simulate=False,
                          pole_disk_radius=0.05, effort_weight_rad_s_per_v=5.69, time_domain="discrete")
    assert not r.ok
    why = r.reasons[0]
    assert "no H-inf certificate for the sampled loop" in why and "1000 Hz" in why
    assert "|z| < 0.05" in why and "solver status" in why and "mixed-pid or zn" in why
    assert "verbose" not in why                           # no third-party advice picdrive cannot act on


def test_options_of_the_other_time_domain_are_refused():
    p = _profile("duy2008")
    with pytest.raises(fuzzy_hinf.FuzzyHinfError, match="pole_disk_radius"):
        fuzzy_hinf.design(p, drive=DRIVE, progress=False, pole_disk_rad_s=400.0, time_domain="discrete")
    with pytest.raises(fuzzy_hinf.FuzzyHinfError, match="continuous"):
        fuzzy_hinf.design(p, drive=DRIVE, progress=False, gamma=10.0, time_domain="discrete")
    with pytest.raises(fuzzy_hinf.FuzzyHinfError, match="pole_disk_rad_s"):
        fuzzy_hinf.design(p, drive=DRIVE, progress=False, pole_disk_radius=0.5, time_domain="continuous")
    with pytest.raises(fuzzy_hinf.FuzzyHinfError, match="time_domain"):
        fuzzy_hinf.design(p, drive=DRIVE, progress=False, time_domain="z")


def test_loop_bandwidth_counts_the_hold_the_command_delay_and_the_speed_measurement():
    """A quarter of the inverse delay: 1.5 samples of hold and command delay plus the measurement's lag --
    half a sample for the encoder's M/T speed, half a hall sector at half the step target from the halls."""
    enc = _profile("duy2008")                                    # 1 kHz, encoder
    assert fuzzy_hinf.loop_bandwidth_rad_s(enc) == pytest.approx(1.0 / (4 * (1.5e-3 + 0.5e-3)))
    hall = _profile(str(repo_root() / "tests" / "motors" / "nanotec_df45l024048a.toml"))
    assert hall.sensors.speed_source == "hall" and hall.motor.pole_pairs == 4
    sector = 60.0 / (0.5 * hall.speed_step_rpm() * 4 * 6)         # 1.67 ms at 1500 rpm
    assert fuzzy_hinf.loop_bandwidth_rad_s(hall) == pytest.approx(1.0 / (4 * (1.5e-3 + 0.5 * sector)))
    slow = hall.replace(control={"speed_loop_hz": 500.0})
    assert fuzzy_hinf.loop_bandwidth_rad_s(slow) < fuzzy_hinf.loop_bandwidth_rad_s(hall)


@pytest.mark.slow          # about 8 min: the default chain, continuous, then the loop rate at three weights
def test_a_fast_mechanism_on_hall_speed_gets_the_loop_bandwidth_as_its_integral_weight():
    """Nanotec DF45L024048-A, speed from the halls: its mechanical corner (1,314 rad/s) is ten times what a
    1 kHz loop measuring a hall sector's mean can follow; at that integral weight every design is an
    integrator-dominated law (kp near 0) that overshoots 17-54 %.  At the loop's bandwidth (107 rad/s) the
    loop-rate design overshoots 2.3 % under the injected disturbance; at half of it, it verifies."""
    p = _profile(str(repo_root() / "tests" / "motors" / "nanotec_df45l024048a.toml"))
    with pytest.warns(UserWarning, match="integral weight"):
        r = fuzzy_hinf.design(p, drive=DRIVE, progress=False)
    assert r.ok, r.reasons
    assert r.certificate["time_domain"] == "discrete"
    w = r.certificate["model_options"]["integral_weight_rad_s"]
    assert w <= fuzzy_hinf.loop_bandwidth_rad_s(p) * (1 + 1e-12)
    assert "mechanical corner" in r.certificate["integral_weight_note"]
    assert r.verification["sim_overshoot_pct"]["ok"] and r.verification["sim_half_speed"]["ok"]
