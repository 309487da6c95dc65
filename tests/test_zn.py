"""Ziegler-Nichols PID (ultimate point of the sampled loop, reaction curve) and the 2016 paper preset."""
import math

import numpy as np
import pytest

from picdrive.design import zn
from picdrive.design.mixed_pid import term_limits
from picdrive.models.tfmodel import motor_tf, sampled_plant

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
    r = zn.design(profiles["duy2008"], progress=False)
    assert r.ok, r.reasons
    assert r.method == "zn" and r.variant == "ultimate"
    assert r.certificate["sensitivity_peak_sampled"] > 2.0          # ZN is aggressive: Ms ~ 2.8
    assert r.verification["pid_tf_step"]["ok"]


def test_zn_auto_keeps_the_first_row_that_verifies(profiles):
    """rule=auto: classic, some-overshoot, no-overshoot in that order, the first that passes the
    six-step verification.  On duy2008 the milder rows overshoot *more* (their lower kp leaves the
    approach to the integrator) and the bridge cannot brake: they fail, the classic row passes."""
    p = profiles["duy2008"]
    auto = zn.design(p, progress=False)
    assert auto.ok and auto.variant == "ultimate" and auto.options["rule"] == "auto"
    assert [t["rule"] for t in auto.certificate["rule_tries"]] == ["ultimate"]
    mild = zn.design(p, progress=False, rule="no-overshoot")
    assert not mild.ok and mild.verification["sim_overshoot_pct"]["value"] > 2.0
    assert any("sim_overshoot_pct" in x for x in mild.reasons)
    # the law carries the firmware's current window, so the 2016 classic row no longer runs into the
    # current limit (it drew 19.9 A before the window): it verifies
    c = zn.design(profiles["assawinchaichote2016"], progress=False)
    assert c.ok, c.reasons
    assert c.law.current_limit_a == profiles["assawinchaichote2016"].inverter.current_limit_a
    assert c.verification["sim_peak_bus_current_a"]["value"] < profiles["assawinchaichote2016"].inverter.overcurrent_trip_a


def test_paper2016_preset_units_and_verdict(profiles):
    p = profiles["assawinchaichote2016"]
    kp, ki, kd, f = zn.paper2016_gains(p)
    # rpm -> rad/s (60/2pi) and v_q -> six-step u (3 sqrt(3)/pi for a sinusoidal machine)
    assert f == pytest.approx(60 / (2 * math.pi) * 3 * math.sqrt(3) / math.pi, rel=1e-9)
    assert (kp, ki, kd) == pytest.approx((0.43 * f, 2.30 * f, 0.28 * f))
    r = zn.design(p, progress=False, preset="paper2016")
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
        zn.design(p, progress=False, preset="paper2017")
    with pytest.raises(zn.ZnError, match="rule 'tyreus' is unknown"):
        zn.design(p, progress=False, rule="tyreus")
    with pytest.raises(zn.ZnError, match="unknown zn option"):
        zn.design(p, progress=False, seed=3)
