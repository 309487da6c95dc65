"""Drive profile: loading, derived quantities and every kind of validation error."""
import math
from pathlib import Path
import warnings

import pytest

from picdrive.profile import ProfileError, ProfileWarning, bundled_profiles, load_profile, loads_profile

MIN = """
[drive]
name = "t"
[motor]
pole_pairs = 2
resistance_ohm = 0.5
inductance_h = 0.002
inertia_kg_m2 = 0.001
viscous_friction_n_m_s = 0.0001
flux_linkage_v_s = 0.02
rated_current_a = 5
[inverter]
bus_voltage_v = 24
current_limit_a = 5
overcurrent_trip_a = 8
[sensors]
encoder_lines = 500
[control]
speed_max_rpm = 2500
reference_rpm = 2000
"""


def test_bundled_profiles_load():
    names = set(bundled_profiles())
    assert {"duy2008", "assawinchaichote2016"} <= names
    with warnings.catch_warnings():
        warnings.simplefilter("error")        # the main example must not warn
        p = load_profile("duy2008")
    assert p.name == "duy2008"
    assert len(p.sha256) == 64


def test_duy2008_line_to_line_basis_gives_paper_tf_constants():
    m = load_profile("duy2008").motor
    # eq. 1 with Table 2: (Ls+R)(Js+D)+KtKb, L and R terminal values
    assert m.r_line_ohm == pytest.approx(21.2)
    assert m.l_line_h == pytest.approx(0.052)
    assert m.r_phase_ohm == pytest.approx(10.6)
    assert m.kt_n_m_per_a == pytest.approx(0.1433)


def test_paper2016_motor_warns_unreachable_speed():
    with pytest.warns(ProfileWarning, match=r"speed_max_rpm = 3000 rpm cannot be reached"):
        p = load_profile("assawinchaichote2016")
    # sinusoidal six-step DC equivalent: Kb = 3 sqrt(3)/pi * P * lambda_m
    assert p.motor.kb_v_s_per_rad == pytest.approx(3 * math.sqrt(3) / math.pi * 2 * 0.311)
    assert p.speed_step_rpm() < p.control.reference_rpm


def test_reachable_speed_by_hand():
    p = loads_profile(MIN)
    m = p.motor
    kb = 2 * 2 * 0.02                      # trapezoidal default
    v = 24 * (1 - (2000 + 2 * 1000) / 50000)
    w = v / (kb + 2 * 0.5 * 0.0001 / kb)
    assert p.max_reachable_rpm() == pytest.approx(w * 60 / (2 * math.pi))
    assert m.kt_n_m_per_a == pytest.approx(kb)
    assert p.max_duty() == pytest.approx(0.92)


def test_load_torque_lowers_reachable_speed():
    p = loads_profile(MIN)
    assert p.max_reachable_rpm(0.1) < p.max_reachable_rpm(0.0)


def test_replace_revalidates():
    p = loads_profile(MIN)
    q = p.replace(motor={"resistance_ohm": 0.55})
    assert q.motor.resistance_ohm == 0.55 and p.motor.resistance_ohm == 0.5
    assert q.sha256 != p.sha256
    with pytest.raises(ProfileError, match="motor.resistance_ohm"):
        p.replace(motor={"resistance_ohm": -1.0})


def _mutate(text, old, new):
    assert old in text
    return text.replace(old, new)


@pytest.mark.parametrize("old,new,match", [
    ("resistance_ohm = 0.5", "", r"'motor.resistance_ohm' is missing.*\[0.0001, 1000\]"),
    ("resistance_ohm = 0.5", 'resistance_ohm = "half"', r"'motor.resistance_ohm' = 'half'.*without quotes"),
    ("resistance_ohm = 0.5", "resistance_ohm = -0.5", r"'motor.resistance_ohm' = -0.5: outside the accepted range"),
    ("resistance_ohm = 0.5", "resistance_ohm = nan", r"'motor.resistance_ohm' = nan: expected a finite value"),
    ("pole_pairs = 2", "pole_pairs = 2.5", r"'motor.pole_pairs' = 2.5: expected an integer"),
    ("pole_pairs = 2", "pole_pairs = 0", r"'motor.pole_pairs' = 0: outside"),
    ("inertia_kg_m2 = 0.001", "inertia_kg_m2 = 0", r"motor.inertia_kg_m2"),
    ("inductance_h = 0.002", "", r"'motor.inductance_h' is missing"),
    ("inductance_h = 0.002", "inductance_h = 0.002\nld_h = 0.001", r"exclusive"),
    ("flux_linkage_v_s = 0.02", "", r"'motor.flux_linkage_v_s' is missing"),
    ("bus_voltage_v = 24", "bus_voltage_v = 150", r"'inverter.bus_voltage_v' = 150.*switch rating"),
    ("current_limit_a = 5", "current_limit_a = 9", r"'inverter.current_limit_a' = 9.*overcurrent_trip_a"),
    ("encoder_lines = 500", "encoder_lines = 0", r"'sensors.speed_source' = 'encoder'.*no encoder"),
    ("reference_rpm = 2000", "reference_rpm = 4000", r"'control.reference_rpm' = 4000.*speed_max_rpm"),
    ("[sensors]", "[sensors]\nhall_spacing_deg = 90", r"'sensors.hall_spacing_deg' = 90: expected 60 or 120"),
    ("[sensors]", "[sensors]\nspeed_source = \"tacho\"", r"expected one of 'encoder', 'hall'"),
    ("[drive]\nname = \"t\"", "[drive]\nname = \"Bad Name\"", r"'drive.name' = 'Bad Name'"),
    ("resistance_ohm = 0.5", "resistance_ohm = 0.5\nresistence_ohm = 1", r"did you mean 'resistance_ohm'"),
    ("[control]", "[controll]\nx=1\n[control]", r"unknown section"),
    ("[inverter]", "[inverter]\npwm_frequency_hz = 200000", r"inverter.pwm_frequency_hz"),
    ("[inverter]", "[inverter]\npwm_frequency_hz = 40000\ndead_time_ns = 6000", r"'inverter.dead_time_ns' = 6000.*lower the PWM frequency"),
    ("[control]", "[control]\nspeed_loop_hz = 30000", r"control.speed_loop_hz"),
])
def test_validation_errors_name_field_value_and_range(old, new, match):
    with pytest.raises(ProfileError, match=match):
        loads_profile(_mutate(MIN, old, new))


def test_range_fields_checked():
    bad = MIN + "\n[design]\nkp_range = [5, 1]\n"
    with pytest.raises(ProfileError, match=r"'design.kp_range'.*low < high"):
        loads_profile(bad)
    bad = MIN + "\n[design]\nkp_range = [5]\n"
    with pytest.raises(ProfileError, match=r"two numbers"):
        loads_profile(bad)


def test_invalid_toml_and_missing_file(tmp_path):
    with pytest.raises(ProfileError, match="not valid TOML"):
        loads_profile("[motor\n")
    with pytest.raises(ProfileError, match="no profile file 'nope.toml'.*bundled profiles: .*duy2008"):
        load_profile("nope.toml")
    f = tmp_path / "p.toml"
    f.write_text(MIN.replace("pole_pairs = 2", "pole_pairs = -3"))
    with pytest.raises(ProfileError, match=str(f).replace("\\", "\\\\") + r".*motor.pole_pairs"):
        load_profile(f)


def test_hash_ignores_formatting():
    a = loads_profile(MIN)
    b = loads_profile("# a comment\n" + MIN.replace("pole_pairs = 2", "pole_pairs   =   2"))
    assert a.sha256 == b.sha256


def test_profile_doc_is_current():
    from picdrive.paths import repo_root
    from picdrive.profile import schema_markdown
    doc = (repo_root() / "docs" / "profile.md").read_text()
    assert doc == schema_markdown(), "docs/profile.md is stale: regenerate it with picdrive.profile.schema_markdown()"


def test_the_bus_divider_is_the_profiles_and_must_show_the_overvoltage_trip():
    from picdrive.firmware.codegen import bus_sense
    from picdrive.profile import ProfileError
    base = (Path(__file__).resolve().parents[1] / "examples" / "duy2008.toml").read_text()
    assumed = bus_sense(loads_profile(base))
    assert assumed["source"] == "assumed" and assumed["bus_sense_v_per_v"] == pytest.approx(2.5 / 48)
    given = bus_sense(loads_profile(base.replace("[inverter]\n", "[inverter]\nbus_sense_v_per_v = 0.05\n")))
    assert given["source"] == "inverter.bus_sense_v_per_v"
    assert given["ov"] == int(math.ceil(60.0 * 0.05 * 1024 / 5.0))          # 60 V trip x 0.05 V/V
    with pytest.raises(ProfileError, match=r"puts the overvoltage trip \(60.0 V\) at 6.00 V on AN1, beyond the "
                                           r"ADC's 5 V: the firmware could not see it; a divider of at most 0.08167"):
        loads_profile(base.replace("[inverter]\n", "[inverter]\nbus_sense_v_per_v = 0.1\n"))


def test_the_bus_guard_levels_are_fractions_of_the_switch_rating_above_the_supply():
    from picdrive.profile import BUS_GUARD_LEVELS, BUS_SUPPLY_MARGIN, bus_guard
    p = load_profile("duy2008")                       # 48 V bus, 100 V switches
    g = bus_guard(p.inverter)
    assert (g.taper_start_v, g.taper_end_v, g.trip_v) == pytest.approx((52.8, 57.6, 60.0))
    assert BUS_SUPPLY_MARGIN * 48 <= g.taper_start_v < g.taper_end_v < g.trip_v <= 0.9 * 100
    assert g.uv < g.taper_start < g.taper_end < g.trip < 1023 and g.problem == ""
    # a 310 V bus on 500 V switches: the switch fractions bind
    hv = bus_guard(p.replace(inverter={"bus_voltage_v": 310.0, "switch_vds_max_v": 500.0}).inverter)
    assert (hv.taper_start_v, hv.taper_end_v, hv.trip_v) == pytest.approx(
        tuple(min(BUS_GUARD_LEVELS[k][0] * 310, BUS_GUARD_LEVELS[k][1] * 500) for k in ("taper_start", "taper_end", "trip")))
    assert hv.taper_start_v == pytest.approx(341.0) and hv.trip_v == pytest.approx(387.5)


def test_a_bus_too_close_to_the_switch_rating_leaves_no_guard_window():
    from picdrive.profile import ProfileError, bus_guard
    p = load_profile("duy2008").replace(inverter={"bus_voltage_v": 80.0})      # 80 V on 100 V switches
    with pytest.raises(ProfileError, match=r"'inverter.bus_voltage_v' = 80 V and 'inverter.switch_vds_max_v' = "
                                           r"100 V leave no regeneration window: braking would taper from 80.0 V "
                                           r"\(0.80 x the switch rating\), less than 1.05 x the bus \(84.0 V\); use "
                                           r"switches rated at least 105 V or a lower bus"):
        bus_guard(p.inverter)
    assert bus_guard(p.inverter, strict=False).problem.startswith("profile fields")
