"""Mixed H2/H-inf PID design (2008) on both bundled profiles: drive and paper variants, GA and DE."""

import numpy as np
import pytest

from picdrive.design import mixed_pid as mp
from picdrive.control_law import Rule, ScheduledLaw
from picdrive.design.ga import run_ga
from picdrive.analysis.h2hinf import j3_jury_dewey, tracking_error_polys
from picdrive.analysis.metrics import step_metrics
from picdrive.gate import BuiltDrive
from support.committed import assert_reproduces
from picdrive.models.tfmodel import closed_loop_tf, motor_tf, simulate_sampled

DRIVE = BuiltDrive()

PROFILES = ["duy2008", "assawinchaichote2016"]


@pytest.fixture(scope="module")
def drive_designs(profiles):
    return {n: mp.design(p, drive=DRIVE, progress=False) for n, p in profiles.items()}


@pytest.mark.parametrize("name", PROFILES)
def test_drive_design_verified_on_both_profiles(name, profiles, drive_designs):
    p, r = profiles[name], drive_designs[name]
    assert r.ok, r.reasons
    assert r.method == "mixed-pid" and r.variant == "drive" and r.profile_sha256 == p.sha256
    g = r.law.rules[0]
    lo, hi = r.certificate["search_box"]["lo"], r.certificate["search_box"]["hi"]
    assert np.all(np.array([g.kp, g.ki, g.kd]) >= lo) and np.all(np.array([g.kp, g.ki, g.kd]) <= hi)
    de = p.design
    assert de["kp_range"][0] <= g.kp <= de["kp_range"][1] and de["ki_range"][0] <= g.ki <= de["ki_range"][1]
    assert r.law.n_rules == 1 and r.law.setpoint_weight == 1.0 and g.kc == 0.0 and r.law.derivative_filter_hz is None
    u = p.inverter.bus_voltage_v * p.max_duty()
    assert r.law.u_max_v == pytest.approx(u) and r.law.u_min_v == pytest.approx(-u)
    assert r.law.sample_time_s == pytest.approx(1 / p.control.speed_loop_hz)
    c = r.certificate
    assert c["stable_sampled"] and c["spectral_radius_sampled"] < 1
    assert c["hinf_constraint"] <= 1.0 and c["sensitivity_peak_sampled"] <= 2.0 + 1e-9
    assert c["step_peak_current_a"] <= 0.9 * p.inverter.overcurrent_trip_a + 1e-9
    # the six-step step of the GA's constraint: no overshoot beyond 0.5 % (the bridge cannot brake)
    assert c["step_peak_speed_rad_s"] <= 1.005 * p.speed_step_rpm() * np.pi / 30 + 1e-9
    assert r.law.current_limit_a == p.inverter.current_limit_a and r.law.r_ohm == p.motor.r_line_ohm
    # our own checks and verify_design's both ran and passed
    v = r.verification
    for key in ("pid_sampled_spectral_radius", "pid_hinf_constraint_sampled", "pid_sensitivity_peak", "pid_tf_step",
                "pid_tf_load_step"):
        assert v[key]["ok"], key
    assert any(k.startswith("sim_") for k in v) and all(e.get("ok", True) for e in v.values() if isinstance(e, dict))


def test_drive_design_j3_recomputed_independently(profiles, drive_designs):
    """J3 of the result by direct simulation of law_step on the sampled plant (no saturation)."""
    from picdrive.control_law import LawState, law_step
    from picdrive.models.tfmodel import sampled_plant
    p, r = profiles["duy2008"], drive_designs["duy2008"]
    g = r.law.rules[0]
    sp = sampled_plant(motor_tf(p), r.law.sample_time_s)
    lin = ScheduledLaw(rules=(Rule(g.kp, g.ki, g.kd),), premise_rad_s=(0, 1), sample_time_s=sp.ts,
                       u_min_v=-1e12, u_max_v=1e12)
    st, x, J = LawState(), np.zeros(sp.n), 0.0
    for _ in range(8000):
        y = float(sp.Cd[0] @ x)
        J += (1.0 - y) ** 2 * sp.ts
        x = sp.Ad @ x + sp.Bd[:, 0] * law_step(lin, st, 1.0, y)
    assert r.certificate["j3_s"] == pytest.approx(J, rel=1e-6)
    assert r.certificate["j3_sampled_s"] == pytest.approx(J, rel=1e-6)


def test_ga_seeded_and_improving_on_the_real_problem(profiles):
    pb = mp.make_problem(profiles["duy2008"])
    a = run_ga(pb.cost, pb.lo, pb.hi, population=60, generations=8, seed=5, progress=False)
    b = run_ga(pb.cost, pb.lo, pb.hi, population=60, generations=8, seed=5, progress=False)
    np.testing.assert_array_equal(a.best, b.best)
    h = np.array(a.history_best)
    assert np.all(np.diff(h) <= 0) and h[-1] < h[0]
    assert a.best_feasible and bool(mp.evaluate(pb, a.best)["feasible"])


def test_search_box_is_cut_to_the_sampled_stability_limits(profiles):
    pb = mp.make_problem(profiles["duy2008"])
    lim = pb.limits
    assert pb.hi[0] == pytest.approx(min(200.0, lim["kp"])) and lim["kp"] < 200
    # just inside / outside the kp limit (P only, ki = 0: the integrator is decoupled -> check kp with tiny ki)
    ev_in = mp.evaluate(pb, np.array([[0.99 * lim["kp"], 1e-3, 0.0], [1.05 * lim["kp"], 1e-3, 0.0]]))
    assert ev_in["stable"].tolist() == [True, False]


def _corpus(name):
    import warnings
    from picdrive.paths import repo_root
    from picdrive.profile import load_profile
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_profile(repo_root() / "tests" / "motors" / f"{name}.toml")


def test_search_box_from_the_plant_where_the_profile_gives_no_range(profiles):
    """A profile without kp/ki/kd ranges is searched in the box of its sampled plant: kp <= Ku,
    ki <= Ku w180, kd <= its own stability limit, which holds every row of the ZN table's kp and ki
    with room to spare (the fixed default ki <= 10 V/rad did not hold this motor's classic ZN ki,
    11.9 V/rad).  A profile's own ranges are kept, cut to the per-term stability limits."""
    from picdrive.design import zn
    p = _corpus("nanotec_df45l024048a")
    assert not set(p.raw.get("design", {})) & {"kp_range", "ki_range", "kd_range"}
    pb = mp.make_problem(p)
    u = zn.ultimate_point(pb.sp)
    assert pb.box_source == {"kp": "plant", "ki": "plant", "kd": "plant"}
    np.testing.assert_allclose(pb.hi, [u["ku_v_per_rad_s"], u["ku_v_per_rad_s"] * u["w180_rad_s"], pb.limits["kd"]],
                               rtol=1e-9)
    np.testing.assert_allclose(pb.lo, 0.0)
    for row in zn.ULTIMATE_RULES:
        kp, ki, _, _ = zn.zn_gains(row, pb.sp, pb.plant)
        assert kp <= pb.hi[0] * (1 + 1e-12) and ki < 0.3 * pb.hi[1], row
    # the bound scales with the motor: a second motor's box is its own plant's
    q = _corpus("tmotor_ak80_6_flywheel")
    pq = mp.make_problem(q)
    uq = zn.ultimate_point(pq.sp)
    assert pq.hi[1] == pytest.approx(uq["ku_v_per_rad_s"] * uq["w180_rad_s"], rel=1e-9) and pq.hi[1] > 100 * pb.hi[1]
    # the bundled profiles give their ranges: kept
    d = mp.make_problem(profiles["duy2008"])
    assert d.box_source == {"kp": "profile", "ki": "profile", "kd": "profile"}
    assert d.hi[1] == pytest.approx(min(100.0, d.limits["ki"]))


def test_halls_only_profiles_are_screened_with_the_hall_measurement(profiles):
    """duy2008_halls measures its speed from the halls: the search simulates its step with the drive's
    hall-edge measurement (and the verification's load-torque disturbance), not the encoder's M/T."""
    from picdrive.models.simulate import simulate_six_step_batch
    p = profiles["duy2008_halls"]
    pb = mp.make_problem(p, drive=DRIVE)
    meter = DRIVE.speed_measurement(p, mp.pid_law(p, 0.4, 30.0, 1e-3))["hall"]
    assert pb.hall == meter
    assert mp.make_problem(profiles["duy2008"], drive=DRIVE).hall is None          # an encoder: M/T
    g = np.array([[0.4, 34.7, 9e-4], [0.2, 60.0, 0.0]])
    ev = mp.evaluate(pb, g, simulate_all=True)
    kw = dict(t_end_s=pb.step_sim_s, ref_rad_s=pb.step_rad_s, n_sub=4, plant=pb.plant6,
              torque_disturbance=pb.disturbance)
    hall = simulate_six_step_batch(p, g[:, 0], g[:, 1], g[:, 2], hall=meter, **kw)
    mt = simulate_six_step_batch(p, g[:, 0], g[:, 1], g[:, 2], **kw)
    np.testing.assert_array_equal(ev["step_peak_speed_rad_s"], hall["peak_speed_rad_s"])
    assert np.all(np.abs(hall["peak_speed_rad_s"] - mt["peak_speed_rad_s"]) > 1e-4 * pb.step_rad_s)


def test_a_failed_verification_tightens_the_screen_and_searches_again(profiles, monkeypatch):
    """The search's best is verified; when it fails for overshoot the next search runs with the
    screen's overshoot allowance scaled by what the verification saw (or the ki bound backed off),
    and the design returned is the first that verifies.  The verification is a stand-in here that
    fails the first design at 4 % overshoot."""
    calls = []

    def stand_in(profile, res, drive):
        calls.append(res.law.rules[0])
        if len(calls) == 1:
            res.verification["sim_overshoot_pct"] = {"value": 4.0, "limit": 2.0, "ok": False, "unit": "%"}
            res.fail("stand-in: overshoot 4 %")
        return res
    monkeypatch.setattr(mp, "run_verify", stand_in)
    p = profiles["duy2008"]
    r = mp.design(p, drive=DRIVE, progress=False, population=40, generations=4)
    tries = r.certificate["retune_tries"]
    assert r.ok and len(tries) == 2 and len(calls) == 2 and calls[0] != calls[1]
    assert tries[0]["status"] == "failed" and tries[0]["failed"] == ["sim_overshoot_pct"]
    step = tries[0]["retune"]
    assert tries[0]["screen"]["overshoot_max_pct"] == pytest.approx(0.5)
    if "overshoot_max_pct" in step:        # the screen saw some overshoot: scaled by 2 % / 4 %, x 0.9
        assert step["overshoot_max_pct"] == pytest.approx(0.9 * step["screened_overshoot_pct"] * 2.0 / 4.0)
        assert tries[1]["screen"]["overshoot_max_pct"] == pytest.approx(step["overshoot_max_pct"])
        assert r.certificate["step_peak_speed_rad_s"] <= pb_peak(p, step["overshoot_max_pct"])
    else:                                  # it saw none: the integral bound backs off
        assert step["ki_max"] == pytest.approx(0.7 * calls[0].ki) and calls[1].ki <= step["ki_max"]
    # retunes=0: the first search's best is the answer, failed
    calls.clear()
    r0 = mp.design(p, drive=DRIVE, progress=False, population=40, generations=4, retunes=0)
    assert not r0.ok and len(r0.certificate["retune_tries"]) == 1 and len(calls) == 1


def test_a_gain_too_small_to_act_is_zero(monkeypatch):
    """A search that ends on kd = 9e-11 V s^2/rad (2e-6 of its bound on the nanotec motor; a GA run
    ended there): nothing measurable, and below what the firmware's fixed point resolves on one speed
    LSB, which refuses the design.  It returns kd = 0; a gain above the floor (1e-3 of the bound) is
    kept."""
    from picdrive.errors import PicdriveError
    p = _corpus("nanotec_df45l024048a")
    pb = mp.make_problem(p, drive=DRIVE)
    tiny = np.array([0.0235432, 1.87895, 9e-11])
    assert bool(mp.evaluate(pb, tiny)["feasible"])
    with pytest.raises(PicdriveError, match="too small to act"):          # what the firmware says of it
        DRIVE.speed_measurement(p, mp.pid_law(p, *tiny))
    monkeypatch.setattr(mp, "_optimise", lambda *a, **k: (tiny.copy(), True, {"optimizer": "stand-in"}))
    r = mp.design(p, drive=DRIVE, progress=False)
    g = r.law.rules[0]
    assert r.ok, r.reasons
    assert (g.kp, g.ki, g.kd) == (tiny[0], tiny[1], 0.0)
    kept = np.array([0.0235432, 1.87895, 1e-6])
    np.testing.assert_array_equal(mp._snap_small_gains(pb, kept), kept)


def pb_peak(p, allow_pct):
    return p.speed_step_rpm() * np.pi / 30 * (1 + allow_pct / 100) * (1 + 1e-12)


def test_halls_only_corpus_motor_verifies():
    """nanotec DF45L024048-A (halls only): the default search used to stop at ki = 10 V/rad (the fixed
    default bound) with M/T scoring and overshoot 2.45 % in the verification; screened with the hall
    measurement and the verification's disturbance it verifies (a small GA keeps the test fast)."""
    p = _corpus("nanotec_df45l024048a")
    r = mp.design(p, drive=DRIVE, progress=False, population=60, generations=8)
    assert r.ok, r.reasons
    assert r.verification["sim_overshoot_pct"]["value"] <= 2.0
    assert r.certificate["search_box_source"]["ki"] == "plant"


def test_evaluate_bound_shortcut_agrees_with_exact(profiles):
    """Where (1 + ||S||)||xi|| <= 1 certifies eq 6, the exact value is indeed <= 1 (and below the bound)."""
    from picdrive.analysis.h2hinf import robust_constraint_z
    pb = mp.make_problem(profiles["assawinchaichote2016"])
    rng = np.random.default_rng(4)
    g = rng.uniform(pb.lo, pb.hi, size=(300, 3))
    ev = mp.evaluate(pb, g, simulate_all=True)
    exact, stable, _ = robust_constraint_z(pb.sp, g[:, 0], g[:, 1], g[:, 2], pb.d)
    sel = ev["stable"]
    assert sel.sum() > 50
    assert np.all(exact[sel] <= ev["hinf"][sel] * (1 + 1e-5))   # polynomial evaluation near z = 1: ~1e-6
    assert np.all((exact[sel] <= 1.0) | ev["hinf_exact"][sel])


def test_paper_variant_reaches_box_corner_and_fails_when_sampled(profiles):
    p = profiles["duy2008"]
    r = mp.design(p, drive=DRIVE, progress=False, variant="paper")
    g = r.law.rules[0]
    np.testing.assert_allclose([g.kp, g.ki, g.kd], [p.design[k][1] for k in ("kp_range", "ki_range", "kd_range")],
                               rtol=1e-6)                                      # the box corner
    P = motor_tf(p)
    ne, de_ = tracking_error_polys(P, 180.1755, 4.6997, 0.0353)
    j_paper = float(j3_jury_dewey(ne, de_))
    assert r.certificate["j3_s"] <= j_paper                 # GA J3 no worse than the paper's in the same box
    assert r.certificate["hinf_constraint"] <= 1.0
    assert not r.ok and any("unstable" in x for x in r.reasons)


def test_de_optimiser_agrees_with_ga(profiles, drive_designs):
    p = profiles["assawinchaichote2016"]
    r = mp.design(p, drive=DRIVE, progress=False, optimizer="de", de_maxiter=40)
    assert r.certificate["feasible"]
    j_ga = drive_designs["assawinchaichote2016"].certificate["j3_s"]
    # same problem: DE (more evaluations) is at least as good; the paper's GA (200 x 20) within 10 %
    # (measured, seed 1: 3.0 % above DE with the screen's load-torque disturbance, 8.6 % before it; over
    # seeds 1-4 the GA's J3 spans 0.0054-0.0064 s on this problem)
    assert r.certificate["j3_s"] <= j_ga * 1.01
    assert j_ga <= 1.10 * r.certificate["j3_s"]


def test_derivative_on_measurement_vs_error_in_the_law(profiles):
    """The law's derivative acts on the measurement: sampled very fast and unsaturated it follows
    closed_loop_tf(derivative='measurement'), not the paper's error form."""
    p = profiles["duy2008"]
    kp, ki, kd = 70.556, 10.0, 0.0212
    law = ScheduledLaw(rules=(Rule(kp, ki, kd),), premise_rad_s=(0, 1), sample_time_s=1e-6, u_min_v=-1e9, u_max_v=1e9)
    sim = simulate_sampled(p, law, t_end_s=0.004, ref_rad_s=1.0, delay_samples=0, measurement="instant")
    from scipy import signal
    P = motor_tf(p)
    gm = closed_loop_tf(P, kp, ki, kd, derivative="measurement")
    ge = closed_loop_tf(P, kp, ki, kd, derivative="error")
    _, ym = signal.step((gm.num, gm.den), T=sim["t_s"])
    _, ye = signal.step((ge.num, ge.den), T=sim["t_s"])
    assert np.max(np.abs(sim["speed_rad_s"] - ym)) < 0.01
    assert np.max(np.abs(sim["speed_rad_s"] - ye)) > 0.1
    me, mm = step_metrics(sim["t_s"], ye, 1.0), step_metrics(sim["t_s"], ym, 1.0)
    assert me.overshoot_pct > 15 and mm.overshoot_pct < 5 and mm.rise_time_s > 2 * me.rise_time_s


def test_bad_options_are_clear_errors(profiles):
    p = profiles["duy2008"]
    with pytest.raises(mp.MixedPidError, match="unknown mixed-pid option.*gamma"):
        mp.design(p, drive=DRIVE, progress=False, gamma=1.0)
    with pytest.raises(mp.MixedPidError, match="variant 'exact' is unknown"):
        mp.design(p, drive=DRIVE, progress=False, variant="exact")
    with pytest.raises(mp.MixedPidError, match="optimizer 'pso'"):
        mp.design(p, drive=DRIVE, progress=False, optimizer="pso")
    with pytest.raises(mp.MixedPidError, match=r"ms_max=0.5 is outside \[1.05, 100.0\]"):
        mp.design(p, drive=DRIVE, progress=False, ms_max=0.5)
    with pytest.raises(mp.MixedPidError, match="population='many'"):
        mp.design(p, drive=DRIVE, progress=False, population="many")
    bad = p.replace(design={"kp_range": [5.0, 10.0]})
    with pytest.raises(mp.MixedPidError, match="lies outside the gains the sampled loop"):
        mp.design(bad, drive=DRIVE, progress=False)


@pytest.mark.parametrize("name", PROFILES)
def test_the_committed_design_reproduces(name, profiles, drive_designs):
    """examples/<profile>.mixed-pid.design.json is what the code designs now (default options, seed 1)."""
    assert_reproduces(profiles[name], drive_designs[name], rel=1e-9)
