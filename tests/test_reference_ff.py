"""The reference feedforward (control_law.reference_ff_gain): the law's integrator preloaded by G_ff x each change of
the applied reference, in the float law, the fixed-point model and from the profile option.

The firmware's C and assembly against the model: tests/test_fixedpoint.py (kinds "pi1-ff",
"fuzzy2-ff-neg") and tests/test_target_bitexact.py (the duy2008 build with the feedforward)."""
import dataclasses
import math

import pytest

from picdrive.control_law import LawState, Rule, ScheduledLaw, law_step, reference_ff_gain
from picdrive.design.verify import choose_reference_ff, verify_design, with_reference_ff
from picdrive.firmware import fixedpoint as fx, pcpwm
from picdrive.paths import repo_root
from picdrive.profile import load_profile
from picdrive.result import load_design

RPM = math.pi / 30
BASE = dict(premise_rad_s=(0.0, 300.0), sample_time_s=1e-3, u_min_v=-1000.0, u_max_v=1000.0)


def test_the_preload_acts_on_reference_changes_only():
    """Two PI laws, with and without G_ff, wide limits (the headroom rule never binds): the integrators
    differ by G_ff x r after the reference steps (also when it steps back) and a speed disturbance at a
    constant reference moves both alike (load rejection unchanged)."""
    g = 0.15
    off = ScheduledLaw(rules=(Rule(0.4, 30.0),), **BASE)
    on = dataclasses.replace(off, reference_ff_v_s_per_rad=g)
    s0, s1 = LawState(), LawState()
    ys = [0.0, 10.0, 50.0, 120.0, 200.0, 180.0, 150.0, 160.0]          # a speed record with a dip
    rs = [200.0] * 5 + [200.0, 120.0, 120.0]
    for r, y in zip(rs, ys):
        law_step(off, s0, r, y)
        law_step(on, s1, r, y)
        assert s1.integ_v - s0.integ_v == pytest.approx(g * r, abs=1e-9)
    assert s1.r_prev == 120.0


def test_the_gain_gives_the_steady_state_voltage_at_y_equal_r():
    """G_ff = u_ss / w + Kp (1 - b) + Kc i_ss / w: with y = r = w and i = i_ss the law's output with the
    integrator at G_ff w (no integration: e = 0) is u_ss."""
    law = ScheduledLaw(rules=(Rule(0.5, 40.0, 0.0, 5.0),), setpoint_weight=1.27, **BASE)
    w, u_ss, i_ss = 250.0, 38.2, 0.19
    g = reference_ff_gain(law, w, u_ss, i_ss)
    st = LawState(y_prev=w)
    ff = dataclasses.replace(law, reference_ff_v_s_per_rad=g)
    assert law_step(ff, st, w, w, i_ss) == pytest.approx(u_ss, rel=1e-12)
    with pytest.raises(ValueError):
        reference_ff_gain(law, 0.0, u_ss, i_ss)


def test_the_fixed_point_preload_is_the_gain_times_the_change():
    prof = load_profile("duy2008")
    law = dataclasses.replace(ScheduledLaw(rules=(Rule(0.4, 30.0),), premise_rad_s=(0.0, 2600 * RPM),
                                           sample_time_s=1e-3, u_min_v=-44.16, u_max_v=44.16),
                              reference_ff_v_s_per_rad=0.158)
    plan = fx.plan_fixed_point(prof, law, pcpwm.plan_pwm(prof))
    assert plan.kff and any(c.name == "kff" for c in plan.coefs)
    for dr in (1, -1, 37, -1000, 20000):
        want = 0.158 * dr * 2.0 ** (plan.qi - plan.qs)
        assert fx.reference_ff(plan, dr) == pytest.approx(want, rel=2e-4, abs=2)
    assert fx.reference_ff(plan, 0) == 0
    assert fx.reference_ff(plan, 70000) == fx.reference_ff(plan, 32767)       # the change saturates to int16
    off = fx.plan_fixed_point(prof, dataclasses.replace(law, reference_ff_v_s_per_rad=0.0), pcpwm.plan_pwm(prof))
    assert off.kff == 0 and fx.reference_ff(off, 1000) == 0


def test_the_profile_option_sets_the_gain_at_verification():
    """control.reference_feedforward = "on": verify_design puts the DC-equivalent gain on the law (no
    built drive here: no averaged model) and the result's law carries it (the firmware's CORE_KFF)."""
    prof = load_profile("duy2008")
    assert prof.control.reference_feedforward == "off"
    on = prof.replace(control={"reference_feedforward": "on"})
    assert on.control.reference_feedforward == "on"
    res = load_design(str(repo_root() / "examples" / "duy2008.zn.design.json"))
    assert res.law.reference_ff_v_s_per_rad == 0.0
    m = prof.motor
    dc = m.kb_v_s_per_rad + m.r_line_ohm * m.viscous_friction_n_m_s / m.kt_n_m_per_a     # b = 1, kc = 0
    assert with_reference_ff(on, res.law).reference_ff_v_s_per_rad == pytest.approx(dc, rel=1e-12)
    verify_design(on, res, simulate=False)
    assert res.law.reference_ff_v_s_per_rad == pytest.approx(dc, rel=1e-12)
    verify_design(prof, res2 := load_design(str(repo_root() / "examples" / "duy2008.zn.design.json")),
                  simulate=False)
    assert res2.law.reference_ff_v_s_per_rad == 0.0


def test_a_bad_reference_feedforward_value_is_refused(tmp_path):
    """The profile field takes off / on / auto: anything else exits 2 naming the field and the choices."""
    import subprocess
    import sys
    text = (repo_root() / "examples" / "duy2008.toml").read_text(encoding="utf-8")
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("stall_timeout_ms = 500.0", "stall_timeout_ms = 500.0\nreference_feedforward = true"),
                   encoding="utf-8")
    r = subprocess.run([sys.executable, "-m", "picdrive", "design", "--profile", str(bad), "--method", "zn",
                        "-o", str(tmp_path / "out.design.json")], capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    assert "reference_feedforward" in r.stderr and "'auto'" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "out.design.json").exists()


@pytest.fixture(scope="module")
def drive():
    from picdrive.gate import BuiltDrive
    return BuiltDrive()


def test_auto_chooses_by_the_steps_to_the_band(drive):
    """'auto' keeps the feedforward when the worse of the two steps (no load, the profile's load) reaches
    the 1 % band sooner within 1 % overshoot: the duy2008 fuzzy-hinf law (54 -> 40 ms measured), not the
    duy2008 mixed-pid law (its step without load overshoots 1.7 % with it)."""
    prof = load_profile("duy2008").replace(control={"reference_feedforward": "auto"})
    fz = load_design(str(repo_root() / "examples" / "duy2008.fuzzy-hinf.design.json")).law
    law, chk = choose_reference_ff(prof, fz, drive, "auto")
    assert chk["value"] > 0 and law.reference_ff_v_s_per_rad == pytest.approx(chk["value"], rel=1e-5)
    assert chk["note"].startswith("with the feedforward")
    pid = load_design(str(repo_root() / "examples" / "duy2008.mixed-pid.design.json")).law
    law, chk = choose_reference_ff(prof, pid, drive, "auto")
    assert chk["value"] == 0 and law.reference_ff_v_s_per_rad == 0 and chk["note"].startswith("without")


def test_auto_is_an_add_on_that_must_pass_every_check(drive):
    """verify_design with 'auto': the duy2008 fuzzy-hinf law verifies without the feedforward; with it the
    steady-state saturation check fails, so the law keeps no feedforward, stays verified, and the
    record says why."""
    prof = load_profile("duy2008").replace(control={"reference_feedforward": "auto"})
    res = load_design(str(repo_root() / "examples" / "duy2008.fuzzy-hinf.design.json"))
    verify_design(prof, res, drive=drive)
    assert res.status == "verified"
    assert res.law.reference_ff_v_s_per_rad == 0.0
    chk = res.verification["reference_feedforward"]
    assert chk["value"] == 0.0 and chk["note"].startswith("left off: the law with it fails sim_saturated_steady_fraction")
