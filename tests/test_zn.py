"""Ziegler-Nichols PID (ultimate point of the sampled loop, reaction curve) and the 2016 paper preset."""
import math

import numpy as np
import pytest

from picdrive.design import zn
from picdrive.design.mixed_pid import term_limits
from picdrive.gate import BuiltDrive
from support.committed import assert_reproduces
from picdrive.models.tfmodel import motor_tf, sampled_plant

DRIVE = BuiltDrive()

PROFILES = ["duy2008", "assawinchaichote2016"]


@pytest.mark.parametrize("name", PROFILES)
def test_ultimate_point_frequency_response_equals_stability_limit(name, profiles):
    p = profiles[name]
    sp = sampled_plant(motor_tf(p), 1 / p.control.speed_loop_hz)
    u = zn.ultimate_point(sp)
    assert u["ku_v_per_rad_s"] == pytest.approx(u["ku_bisection"], rel=1e-6)
    z = np.exp(1j * u["w180_rad_s"] * sp.ts)
    pz = np.polyval(sp.tf_z.num, z) / np.polyval(sp.tf_z.den, z)
    assert np.angle(pz) == pytest.approx(math.pi, abs=1e-6) or np.angle(pz) == pytest.approx(-math.pi, abs=1e-6)
    assert u["tu_s"] == pytest.approx(2 * math.pi / u["w180_rad_s"])
    # without hold and delay there is no ultimate gain: the continuous P loop of eq 1 is stable for all kp
    sp0 = sampled_plant(motor_tf(p), 1e-7, delay_samples=0, measurement="instant")
    assert term_limits(sp0)["kp"] > 100 * u["ku_v_per_rad_s"]


def test_classic_rule_by_hand(profiles):
    p = profiles["duy2008"]
    sp = sampled_plant(motor_tf(p), 1e-3)
    kp, ki, kd, f = zn.zn_gains("ultimate", sp, motor_tf(p))
    ku, tu = f["ku_v_per_rad_s"], f["tu_s"]
    assert (kp, ki, kd) == pytest.approx((0.6 * ku, 1.2 * ku / tu, 0.075 * ku * tu))
    kp2, ki2, kd2, _ = zn.zn_gains("no-overshoot", sp, motor_tf(p))
    assert (kp2, ki2, kd2) == pytest.approx((0.2 * ku, 0.4 * ku / tu, 0.2 * ku * tu / 3))


def test_zn_duy2008_verified(profiles):
    r = zn.design(profiles["duy2008"], drive=DRIVE, progress=False)
    assert r.ok, r.reasons
    assert r.method == "zn" and r.variant == "ultimate"
    assert r.certificate["sensitivity_peak_sampled"] > 2.0          # ZN is aggressive: Ms ~ 2.8
    assert r.verification["pid_tf_step"]["ok"]


def test_zn_auto_keeps_the_first_row_that_verifies(profiles):
    """rule=auto: classic, some-overshoot, no-overshoot in that order, the first that passes the
    six-step verification.  On duy2008 the milder rows overshoot *more* (their lower kp leaves the
    approach to the integrator) and the bridge cannot brake: they fail, the classic row passes."""
    p = profiles["duy2008"]
    auto = zn.design(p, drive=DRIVE, progress=False)
    assert auto.ok and auto.variant == "ultimate" and auto.options["rule"] == "auto"
    assert [t["rule"] for t in auto.certificate["rule_tries"]] == ["ultimate"]
    mild = zn.design(p, drive=DRIVE, progress=False, rule="no-overshoot")
    assert not mild.ok and mild.verification["sim_overshoot_pct"]["value"] > 2.0
    assert any("sim_overshoot_pct" in x for x in mild.reasons)
    # the law carries the firmware's current window, so the 2016 classic row no longer runs into the
    # current limit (it drew 19.9 A before the window): it verifies
    c = zn.design(profiles["assawinchaichote2016"], drive=DRIVE, progress=False)
    assert c.ok, c.reasons
    assert c.law.current_limit_a == profiles["assawinchaichote2016"].inverter.current_limit_a
    assert c.verification["sim_peak_bus_current_a"]["value"] < profiles["assawinchaichote2016"].inverter.overcurrent_trip_a


def test_auto_goes_on_to_the_backed_off_rows_and_names_the_row_kept(profiles, monkeypatch):
    """rule=auto does not stop at the table's first three rows: it tries the backed-off rows
    (classic with Ti x 2, Tyreus-Luyben, classic with Ti x 4) and Pessen's before refusing, keeps the
    first that verifies and records every row tried with its gains.  Here the verification is replaced
    by one that passes only the Tyreus-Luyben row, to check the order without the simulations."""
    def only_tyreus_luyben(profile, res, drive):
        if res.variant != "tyreus-luyben":
            res.fail(f"stand-in verification: {res.variant} fails")
        return res
    monkeypatch.setattr(zn, "run_verify", only_tyreus_luyben)
    p = profiles["duy2008"]
    r = zn.design(p, drive=DRIVE, progress=False)
    assert r.ok and r.variant == "tyreus-luyben" and r.certificate["rule"] == "tyreus-luyben"
    tries = r.certificate["rule_tries"]
    assert [t["rule"] for t in tries] == ["ultimate", "some-overshoot", "no-overshoot", "backed-off", "tyreus-luyben"]
    assert [t["status"] for t in tries] == ["failed"] * 4 + ["verified"]
    u = zn.ultimate_point(sampled_plant(motor_tf(p), 1 / p.control.speed_loop_hz))
    ku, tu = u["ku_v_per_rad_s"], u["tu_s"]
    assert tries[3]["gains"]["ki_v_per_rad"] == pytest.approx(0.5 * tries[0]["gains"]["ki_v_per_rad"])
    assert tries[3]["gains"]["kp_v_per_rad_s"] == pytest.approx(tries[0]["gains"]["kp_v_per_rad_s"])
    g = r.law.rules[0]
    assert (g.kp, g.ki, g.kd) == pytest.approx((ku / 2.2, ku / (2.2 * 2.2 * tu), ku * tu / (2.2 * 6.3)))
    # nothing verifies: refused, every row named with its first reason
    monkeypatch.setattr(zn, "run_verify", lambda profile, res, drive: (res.fail("stand-in: no"), res)[1])
    bad = zn.design(p, drive=DRIVE, progress=False)
    assert not bad.ok and [t["rule"] for t in bad.certificate["rule_tries"]] == list(zn.AUTO_ORDER)
    assert all(f"{row}: stand-in: no" in bad.reasons[-1] for row in zn.AUTO_ORDER)
    assert bad.variant == "ultimate" and bad.reasons[0] == "stand-in: no"   # the classic row's design first


def test_backed_off_row_verifies_where_the_classic_overshoots():
    """maxon EC 13 (305192, halls only): the classic row overshoots the 2 % band (the bridge cannot
    brake); the same kp and kd with the integral time doubled verify."""
    from picdrive.paths import repo_root
    from picdrive.profile import load_profile
    p = load_profile(repo_root() / "tests" / "motors" / "maxon_ec13_305192.toml")
    r = zn.design(p, drive=DRIVE, progress=False, rule="backed-off")
    assert r.ok, r.reasons
    kp, ki, kd, _ = zn.zn_gains("ultimate", sampled_plant(motor_tf(p), 1 / p.control.speed_loop_hz), motor_tf(p))
    g = r.law.rules[0]
    assert (g.kp, g.ki, g.kd) == pytest.approx((kp, 0.5 * ki, kd))
    assert r.verification["sim_overshoot_pct"]["value"] <= 2.0


def test_paper2016_preset_units_and_verdict(profiles):
    p = profiles["assawinchaichote2016"]
    kp, ki, kd, f = zn.paper2016_gains(p)
    # rpm -> rad/s (60/2pi) and v_q -> six-step u (3 sqrt(3)/pi for a sinusoidal machine)
    assert f == pytest.approx(60 / (2 * math.pi) * 3 * math.sqrt(3) / math.pi, rel=1e-9)
    assert (kp, ki, kd) == pytest.approx((0.43 * f, 2.30 * f, 0.28 * f))
    r = zn.design(p, drive=DRIVE, progress=False, preset="paper2016")
    assert r.variant == "paper2016" and r.law.rules[0].kp == pytest.approx(kp)
    assert not r.ok and any("unstable" in x for x in r.reasons)    # kd = 4.4 V s^2/rad at 1 kHz
    assert r.certificate["stable_continuous"]                       # fine in continuous time
    # trapezoidal machine: factor 2 instead of 3 sqrt(3)/pi
    assert zn.paper2016_gains(profiles["duy2008"])[3] == pytest.approx(60 / math.pi)


def test_paper2016_unit_study_no_unit_reproduces_table2(profiles):
    s = zn.paper2016_unit_study(profiles["assawinchaichote2016"], t_end_s=4.0)
    rpm, rad = s["rpm, derivative on error"], s["rad/s, derivative on error"]
    assert all(v["stable"] for v in s.values())
    # Table 2: 0.22 s, 4.16 %; rpm comes closest in settling, none matches
    assert abs(rpm["settling_s"] - 0.22) < abs(rad["settling_s"] - 0.22)
    assert all(abs(v["settling_s"] - 0.22) > 0.3 for v in s.values())


def test_reaction_curve(profiles):
    P = motor_tf(profiles["duy2008"])
    r = zn.reaction_curve(P)
    assert r["K"] == pytest.approx(P.dcgain()) and 0 < r["L_s"] < r["T_s"]
    with pytest.raises(zn.ZnError, match="overshoots"):
        zn.reaction_curve(motor_tf(profiles["assawinchaichote2016"]))


def test_bad_options(profiles):
    p = profiles["duy2008"]
    with pytest.raises(zn.ZnError, match="preset 'paper2017' is unknown"):
        zn.design(p, drive=DRIVE, progress=False, preset="paper2017")
    with pytest.raises(zn.ZnError, match="rule 'tyreus' is unknown"):
        zn.design(p, drive=DRIVE, progress=False, rule="tyreus")
    with pytest.raises(zn.ZnError, match="unknown zn option"):
        zn.design(p, drive=DRIVE, progress=False, seed=3)


@pytest.mark.parametrize("name", ["duy2008", "assawinchaichote2016"])
def test_the_committed_design_reproduces(name, profiles):
    """examples/<profile>.zn.design.json is what the code designs now (rule auto)."""
    assert_reproduces(profiles[name], zn.design(profiles[name], drive=DRIVE, progress=False), rel=1e-9)


def test_a_limit_of_the_drive_ends_the_search_at_the_first_row():
    """No ZN row can pass a check on the drive alone (the bridge cannot hold the target): the search
    stops at the classic row, whose refusal names the fix, instead of repeating it for every row."""
    from pathlib import Path
    from picdrive.gate import BuiltDrive
    from picdrive.profile import load_profile
    from picdrive.design import zn
    prof = load_profile(Path(__file__).parent / "motors" / "maxon_ec45flat_200142.toml")
    res = zn.design(prof, drive=BuiltDrive(), progress=False)
    assert not res.ok and [t["rule"] for t in res.certificate["rule_tries"]] == ["ultimate"]
    assert res.reasons[0].startswith("verification 'bridge_hold_torque_n_m' failed: ")
    assert "fix: control.reference_rpm at most" in res.reasons[0]
    assert not any(r.startswith("no row of the ZN table") for r in res.reasons)
