"""Fixed-point plan, the Python model by hand, bit-exactness against the compiled C,
and the fixed-point loop against the float law in closed loop.

The laws here are TEST FIXTURES (hand-picked gains for the duy2008 motor), not
designs from picdrive.design: they exercise the formats, the shifts (both
signs), one to three rules, the derivative filter, current feedback and both
speed sources.
"""
import math

import pytest

from picdrive.firmware import codegen, fixedpoint as fx, pcpwm
from picdrive.control_law import LawState, Rule, ScheduledLaw, law_step
from picdrive.profile import load_profile
from picdrive.result import DesignResult, save_design
from support import core_c
from support.fixed_loop import closed_loop_compare

RPM = math.pi / 30
PROFILE = load_profile("duy2008")
HALL_PROFILE = PROFILE.replace(sensors={"encoder_lines": 0, "speed_source": "hall"})
#: a 60,000 rpm speed range: a speed count is about 2 rpm, so a plausible kp (300 V/(rad/s), under the
#: 421.7 that saturates the bridge from a 1 rpm error) needs the saturating left shift
FAST_PROFILE = PROFILE.replace(control={"speed_max_rpm": 60000.0})


def fixture_law(kind: str) -> ScheduledLaw:
    base = dict(premise_rad_s=(0.0, 2600 * RPM), sample_time_s=1e-3, u_min_v=-44.16, u_max_v=44.16)
    if kind == "fuzzy2":
        return ScheduledLaw(rules=(Rule(0.5, 20.0, 0.001), Rule(0.3, 10.0, 0.0005)), **base)
    if kind == "pid1-big":      # kp large enough for a negative (left, saturating) shift on FAST_PROFILE
        return ScheduledLaw(rules=(Rule(300.0, 40.0, 0.02),), **base)
    if kind == "fuzzy3-filter":
        return ScheduledLaw(rules=(Rule(0.4, 15.0, 0.002, 2.0), Rule(0.3, 10.0, 0.001, 1.0),
                                   Rule(0.2, 6.0, 0.0005, 0.5)), derivative_filter_hz=200.0,
                            setpoint_weight=0.6, integrator_limit_v=200.0, **base)
    if kind == "pi1":
        return ScheduledLaw(rules=(Rule(0.2, 5.0),), **base)
    if kind == "pi1-ff":        # reference feedforward (integrator preload), the motor's Kb + R B / Kt
        return ScheduledLaw(rules=(Rule(0.2, 5.0),), reference_ff_v_s_per_rad=0.158, **base)
    if kind == "pi1-ff-big":    # a feedforward gain whose shift is left (saturating)
        return ScheduledLaw(rules=(Rule(0.2, 5.0),), reference_ff_v_s_per_rad=5.0, **base)
    if kind == "fuzzy2-ff-neg":  # b > 1 with current feedback: a negative feedforward gain
        return ScheduledLaw(rules=(Rule(0.5, 20.0, 0.001, 1.0), Rule(0.3, 10.0, 0.0005, 0.5)), setpoint_weight=1.5,
                            reference_ff_v_s_per_rad=-0.09, **base)
    raise ValueError(kind)


def make_firmware(tmp_path, kind: str, profile=PROFILE):
    law = fixture_law(kind)
    d = DesignResult(method="zn", status="verified", profile_name=profile.name, profile_sha256=profile.sha256,
                     law=law, variant="test-fixture")
    dp = save_design(d, tmp_path / f"{kind}.design.json")
    fw = codegen.generate(profile, dp)
    out = codegen.write_firmware(fw, tmp_path / f"fw-{kind}", check=False)
    return fw, out


# ---------------------------------------------------------------------------
def test_plan_formats_and_quantisation_report():
    law = fixture_law("fuzzy2")
    plan = fx.plan_fixed_point(PROFILE, law, pcpwm.plan_pwm(PROFILE))
    # speed: 2600 rpm = 272 rad/s with 25 % headroom -> +-512 rad/s -> Q6
    assert plan.qs == 6 and 32768 * 2 ** -plan.qs >= 1.25 * 2600 * RPM
    # voltage: +-44.16 V with 2x headroom -> +-128 V -> Q8; integrator 16 bits finer
    assert plan.qu == 8 and plan.qi == 24
    assert plan.kp == (8192, 4915) and plan.q_kp == 14
    assert plan.shift_p == plan.q_kp + plan.qs - plan.qu
    for c in plan.coefs:
        assert c.rel_error < 1e-3, c
    text = "\n".join(plan.lines())
    assert "rule2_kp" in text and "error" in text and "encoder M/T" in text
    assert plan.loop_hz == 1000.0 and plan.t2_pre * (plan.pr2 + 1) * plan.t2_post * plan.loop_div == 10000


def test_refuses_what_cannot_be_represented():
    pwm = pcpwm.plan_pwm(PROFILE)
    base = dict(premise_rad_s=(0.0, 272.0), sample_time_s=1e-3, u_min_v=-44.0, u_max_v=44.0)
    with pytest.raises(fx.FixedPointError, match=r"rule 2 kp = 0.0001 .* cannot be represented.*error"):
        fx.plan_fixed_point(PROFILE, ScheduledLaw(rules=(Rule(100.0, 1.0), Rule(1e-4, 1.0)), **base), pwm)
    with pytest.raises(fx.FixedPointError, match="too small to act"):
        fx.plan_fixed_point(PROFILE, ScheduledLaw(rules=(Rule(1.0, 1e-14),), **base), pwm)
    with pytest.raises(fx.FixedPointError, match="too large"):
        fx.plan_fixed_point(PROFILE, ScheduledLaw(rules=(Rule(1e9, 1.0),), **base), pwm)
    with pytest.raises(fx.FixedPointError, match="setpoint weight b = 2.5"):
        fx.plan_fixed_point(PROFILE, ScheduledLaw(rules=(Rule(1.0, 1.0),), setpoint_weight=2.5, **base), pwm)
    with pytest.raises(fx.FixedPointError, match="re-run 'picdrive design'"):
        fx.plan_fixed_point(PROFILE, ScheduledLaw(rules=(Rule(1.0, 1.0),), **{**base, "sample_time_s": 5e-4}), pwm)


def test_model_against_a_hand_computed_sample_and_the_float_law():
    law = fixture_law("fuzzy2")
    plan = fx.plan_fixed_point(PROFILE, law, pcpwm.plan_pwm(PROFILE))
    p = fx.law_params_from_plan(plan)
    p.controller = 0                         # rule 1 only: kp 0.5, ki 20, kd 0.001
    st = fx.LawState()
    r = plan.to_speed_raw(10.0)              # 640 = 10 rad/s in Q6
    assert r == 640
    u = fx.law_step(plan, p, st, r, 0, 0, plan.u_min, plan.u_max)
    # P = 8192 * 640 >> 12 = 1280 (5 V); I = 10486 * 640 >> 1 = 3355520 (Q24), >> 16 = 51; D = 0 (first sample)
    assert st.integ == 3355520 and u == 1280 + 51
    f = law_step(ScheduledLaw(rules=(law.rules[0],), premise_rad_s=law.premise_rad_s, sample_time_s=1e-3,
                              u_min_v=-44.16, u_max_v=44.16), LawState(), 10.0, 0.0)
    assert abs(u / 256 - f) < 2 / 256       # 5.2 V
    # memberships at half the premise: mu1 = 0.5, gains blended
    p.controller = 1
    st = fx.LawState()
    y = (plan.premise_lo + plan.premise_hi) // 2
    fx.law_step(plan, p, st, y, y, 0, plan.u_min, plan.u_max)
    assert abs(st.mu1 - 2048) <= 1


def test_integrator_only_fills_the_output_headroom():
    law = fixture_law("pi1")
    plan = fx.plan_fixed_point(PROFILE, law, pcpwm.plan_pwm(PROFILE))
    p = fx.law_params_from_plan(plan)
    st = fx.LawState()
    r = plan.to_speed_raw(200.0)                 # P alone = 0.2 x 200 = 40 V of the 44.16 V
    for _ in range(2000):
        u = fx.law_step(plan, p, st, r, 0, 0, plan.u_min, plan.u_max)
    di = plan.qi - plan.qu
    assert u == plan.u_max
    # I stopped where P + I reaches u_max (within one step), not at u_max itself
    assert abs(fx.asr32(st.integ, di) - (plan.u_max - 40 * 256)) <= 2
    # and it is never discharged by force: a smaller error that still wants to push up leaves it
    before = st.integ
    fx.law_step(plan, p, st, plan.to_speed_raw(220.0), 0, 0, plan.u_min, plan.u_max)
    assert st.integ == before


def test_mt_speed_times_each_sample_by_tmr2():
    """Constant speed sampled late by a varying delay after the Timer2 match (the interrupt's entry
    latency): the M/T time step corrected by the change of TMR2 (x 2^t2_t5_shift Timer5 ticks per
    count: Timer2 1:4, Timer5 1:1 here) gives the exact count rate every sample; the time step
    taken as exactly Ts (TMR2 ignored) does not."""
    plan = fx.plan_fixed_point(PROFILE, fixture_law("pi1"), pcpwm.plan_pwm(PROFILE))
    assert (plan.t2_pre, plan.ps5, plan.t2_t5_shift) == (4, 1, 2)
    edge = 250                                       # a count every 250 Timer5 ticks (~125 rad/s)
    exact = plan.k_speed // edge                     # K counts / ticks, whole counts apart
    delays = [0, 40, 3, 55, 12, 0, 61, 20]           # TMR2 at each sample (entry latency / 4 Tcy)

    def run(timed):
        st, out = fx.CoreState(), []
        for k, t2 in enumerate(delays):
            t = k * plan.ts_ticks + (t2 << plan.t2_t5_shift)
            fx.speed_encoder(plan, st, (t // edge) & 0xFFFF, t % edge, t2 if timed else 0, 0)
            out.append(st.w_avg)
        return out[1:]

    timed = run(True)
    assert timed == [exact] * len(timed), (timed, exact)
    assert max(abs(w - exact) for w in run(False)) > exact // 100
    assert fx.t2_ticks(plan, -3) == -12 and fx.t2_ticks(plan, 255) == 1020


def test_integer_primitives():
    assert fx.asr32(-1, 1) == -1 and fx.asr32(-2, 1) == -1 and fx.asr32(5, 1) == 2
    assert fx.shl_sat32(1 << 30, 1) == fx.INT32_MAX and fx.shl_sat32(-(1 << 30), 1) == fx.INT32_MIN
    assert fx.mul_q15(-32768, 32768) == -32768 and fx.mul_q15(fx.INT32_MIN, 32768) == fx.INT32_MIN
    assert fx.premise_k(0, 17425, 2, 14) == (1 << 26) // 17425 and fx.premise_k(5, 5, 2, 14) == 0xFFFF


def _bit_exact(tmp_path, kind, n, profile=PROFILE, seed=0):
    fw, out = make_firmware(tmp_path, kind, profile)
    lib = core_c.build_core_lib(out, tmp_path / f"lib-{kind}")
    res = core_c.compare_with_c(fw.plan, lib, n, seed=seed)
    return fw, res


@pytest.mark.parametrize("kind,profile", [("fuzzy2", PROFILE), ("pid1-big", FAST_PROFILE),
                                          ("fuzzy3-filter", HALL_PROFILE), ("pi1-ff", PROFILE), ("pi1-ff-big", PROFILE),
                                          ("fuzzy2-ff-neg", HALL_PROFILE)])
def test_c_matches_python_model_bit_for_bit(tmp_path, kind, profile):
    fw, res = _bit_exact(tmp_path, kind, 4000, profile)
    if kind == "pid1-big":
        assert fw.plan.shift_p < 0            # the saturating left-shift path is exercised
    if kind == "fuzzy3-filter":
        assert fw.plan.dfilt_a > 0 and fw.plan.speed_source == "hall" and any(fw.plan.kc)
        assert fw.plan.qi < fw.plan.qu + 16          # +-200 V integrator: fewer fraction bits
    if "-ff" in kind:
        assert (fw.plan.kff < 0) == kind.endswith("-neg") and fw.plan.kff != 0
        if kind.endswith("-big"):
            assert fw.plan.shift_ff < 0              # the saturating left shift of the preload
    for name, r in res.items():
        assert r["mismatches"] == 0, (name, r["first"])
    assert res["total"]["vectors"] == 5 * 4000


def test_the_comparison_catches_a_one_lsb_change(tmp_path):
    fw, out = make_firmware(tmp_path, "fuzzy2")
    src = (out / "drive_core.c").read_text()
    bad = src.replace("return (int16_t)(uint16_t)((uint16_t)bg0 + (uint16_t)(int16_t)ACC);",
                      "return (int16_t)(uint16_t)((uint16_t)bg0 + 1u + (uint16_t)(int16_t)ACC);")
    assert bad != src
    (out / "drive_core.c").write_text(bad)
    lib = core_c.build_core_lib(out, tmp_path / "lib-bad")
    res = core_c.compare_with_c(fw.plan, lib, 2000, seed=3)
    assert res["law"]["mismatches"] > 0 and res["premise_k"]["mismatches"] == 0


@pytest.mark.slow
def test_c_matches_python_model_on_1e5_vectors(tmp_path):
    fw, res = _bit_exact(tmp_path, "fuzzy2", 100_000, seed=11)
    assert res["total"]["mismatches"] == 0, res["total"]["first"]


@pytest.mark.parametrize("kind", ["fuzzy2", "pi1", "pi1-ff"])
def test_fixed_point_loop_follows_the_float_law(kind):
    law = fixture_law(kind)
    plan = fx.plan_fixed_point(PROFILE, law, pcpwm.plan_pwm(PROFILE))
    # what the firmware measures (encoder M/T, bus shunt) against the float law on true values
    r = closed_loop_compare(PROFILE, law, plan, t_end_s=0.6)
    assert r["rms_dev"] <= 0.005, r["rms_dev"]
    # and the loop really ran: the float law reaches the setpoint, the load step happened
    assert abs(r["w_float"][-1] - r["setpoint_rad_s"]) < 0.01 * r["setpoint_rad_s"]
    assert r["w_fixed"].max() > 0.9 * r["setpoint_rad_s"]


def test_param_and_signal_scales():
    plan = fx.plan_fixed_point(PROFILE, fixture_law("fuzzy2"), pcpwm.plan_pwm(PROFILE))
    ps = fx.param_specs(plan, PROFILE)
    assert ps["rule1_kp"].to_eng(ps["rule1_kp"].default_raw) == pytest.approx(0.5)
    assert ps["rule1_ki"].to_eng(ps["rule1_ki"].default_raw) == pytest.approx(20.0, rel=1e-4)
    assert ps["rule2_kd"].to_eng(ps["rule2_kd"].default_raw) == pytest.approx(0.0005, rel=1e-4)
    assert ps["speed_setpoint"].to_raw(2400.0) == plan.to_speed_raw(2400 * RPM) or \
        abs(ps["speed_setpoint"].to_raw(2400.0) - plan.to_speed_raw(2400 * RPM)) <= 1
    assert ps["speed_setpoint"].to_raw(1e6) == ps["speed_setpoint"].max_raw     # clamped to the limit
    assert ps["u_max"].to_eng(ps["u_max"].max_raw) <= PROFILE.inverter.bus_voltage_v * PROFILE.max_duty()
    sg = fx.signal_specs(plan)
    assert sg["voltage"].scale == 2 ** -plan.qu and sg["mu1"].scale == 1 / 4096


@pytest.mark.parametrize("hz", [100.0, 1000.0, 2000.0, 20000.0, 152.6, 777.0])
def test_timer2_paces_the_speed_loop(hz):
    pre, post, pr2, div, ticks, achieved = fx._timer2(hz)
    assert pre in (1, 4, 16) and 1 <= post <= 16 and 0 <= pr2 <= 255
    assert ticks == pre * post * (pr2 + 1)
    assert achieved == pytest.approx(10e6 / (ticks * div))
    assert abs(achieved - hz) / hz <= 1e-4
    if 10e6 / hz == int(10e6 / hz) and hz >= 153:
        assert achieved == hz and div == 1


BUNDLED = [(prof, m) for prof in ("duy2008", "assawinchaichote2016") for m in ("fuzzy-hinf", "mixed-pid", "zn")]


@pytest.mark.parametrize("profile_name,method", BUNDLED)
def test_bundled_designs_fixed_point_arithmetic_against_the_float_law(profile_name, method):
    """The fixed-point law against law_step on the same speed sample (the instant one, as the
    design's verification uses): the arithmetic's effect only.  Sensor effects (the encoder's
    M/T measurement) are printed by bench/firmware.py."""
    from picdrive.paths import repo_root
    from picdrive.result import load_design
    path = repo_root() / "examples" / f"{profile_name}.{method}.design.json"
    prof = load_profile(profile_name)
    law = load_design(path, require_usable=True, profile=prof).law      # a missing or stale design fails
    plan = fx.plan_fixed_point(prof, law, pcpwm.plan_pwm(prof))
    r = closed_loop_compare(prof, law, plan, t_end_s=0.6, measurement="instant")
    assert r["rms_dev"] <= 0.005, r["rms_dev"]


@pytest.mark.parametrize("kind", ["fuzzy2", "fuzzy3-filter", "pi1"])
def test_law_parameters_are_the_param_specs_defaults(kind):
    """The law -> parameter mapping (what the console's 'load' pushes) names the parameters
    param_specs defines, and its values are their defaults before quantisation."""
    law = fixture_law(kind)
    plan = fx.plan_fixed_point(PROFILE, law, pcpwm.plan_pwm(PROFILE))
    ps = fx.param_specs(plan, PROFILE)
    vals = fx.law_parameters(law)
    assert len([k for k in vals if k.startswith("rule")]) == 4 * law.n_rules
    assert ("premise_low" in vals) == (law.n_rules > 1)
    for name, v in vals.items():
        s = ps[name]                                      # a name param_specs does not define fails here
        assert s.to_eng(s.default_raw) == pytest.approx(v, rel=1e-3, abs=s.scale), name
