"""The twin's compiled BLDC plant (hil/picdrive_hil/csrc/plant.c) against
independent references: the scipy model of the same equations
(tests/support/plant_reference.py, event-located continuous time), the dq model at
steady operating points, and the profile's six-step constants."""
from pathlib import Path
import math
import warnings

import numpy as np
import pytest

from picdrive.profile import ProfileWarning, load_profile
from support import plant_reference as ref
from picdrive_hil.plant import CPlant, PlantError, parse_perturb, plant_from_profile

warnings.simplefilter("ignore", ProfileWarning)

PROFILES = ("duy2008", "assawinchaichote2016")


def _profile(name):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ProfileWarning)
        return load_profile(name)


def run_cplant(model, legs_of_code, t_eval, load, h=50e-6, w0=0.0):
    """Step the C plant with the open-loop commutator, cutting steps at the
    hall edges the way the twin's event loop does."""
    cp = CPlant(model)
    cp.state.w_rad_s = w0
    out = np.zeros((5, len(t_eval)))
    P, off, sec = model.pole_pairs, math.radians(model.hall_offset_deg), math.pi / 3
    t = 0.0
    for k, tn in enumerate(t_eval):
        while t < tn - 1e-15:
            st = cp.state
            we, the = P * st.w_rad_s, P * st.theta_rad
            step = min(h, tn - t)
            if abs(we) > 1e-9:
                x = (the - off) / sec
                nxt = (math.floor(x) + 1 if we > 0 else math.ceil(x) - 1) * sec + off
                dt = (nxt - the) / we + 1e-12
                if 0 < dt < step:
                    step = dt
            code = cp.hall_code(st.theta_rad + math.copysign(1e-12, st.w_rad_s or 1.0))
            cp.step(legs_of_code(code), load(t + step / 2), step)
            t += step
        st = cp.state
        out[:, k] = [st.i_a[0], st.i_a[1], st.i_a[2], st.w_rad_s, st.theta_rad]
    return out


def rel_errors(c, r):
    w_err = np.max(np.abs(c[3] - r.w)) / np.max(np.abs(r.w))
    i_err = np.max(np.abs(c[:3] - r.i_abc)) / np.max(np.abs(r.i_abc))
    return w_err, i_err


@pytest.mark.parametrize("name, duty, complementary, t_end", [
    ("duy2008", 0.9, False, 0.3),
    ("duy2008", 0.6, True, 0.2),
    ("assawinchaichote2016", 0.9, False, 0.6),
])
def test_plant_matches_scipy_reference_six_step(name, duty, complementary, t_end):
    """Start from rest, six-step at a fixed duty, load-torque step half way:
    speed and phase currents within 1 % of the scipy model, same inputs."""
    p = _profile(name)
    m = plant_from_profile(p, load_mode="active").with_(bus_capacitance_f=0.0)   # the reference's bus is stiff
    dead = p.inverter.dead_time_ns * 1e-9 * p.inverter.pwm_frequency_hz
    legs = ref.sixstep_legs(ref.ideal_commutation_table(m), duty, dead, complementary)
    tl = p.control.load_torque_n_m
    load = lambda t: tl if t >= t_end / 2 else 0.0
    te = np.linspace(0, t_end, int(round(t_end / 1e-4)) + 1)
    r = ref.simulate_reference(m, legs, t_end, te, load=load, load_breaks=[t_end / 2])
    assert r.n_events > 50            # commutations, zero crossings: the modes really switch
    c = run_cplant(m, legs, te, load)
    w_err, i_err = rel_errors(c, r)
    print(f"{name} duty {duty} compl {complementary}: speed err {w_err:.3%}, current err {i_err:.3%}")
    assert w_err < 0.01 and i_err < 0.01


def test_plant_matches_scipy_reference_diode_rectification():
    """All switches off, rotor spun above the bus voltage's speed: the body
    diodes rectify the back-EMF into the bus and brake the rotor (the
    floating-phase logic with no switch at all)."""
    p = _profile("duy2008")
    m = plant_from_profile(p, load_mode="active").with_(bus_capacitance_f=0.0)   # the reference's bus is stiff
    w_bus = p.inverter.bus_voltage_v / m.kb_v_s_per_rad
    w0 = 1.6 * w_bus
    off = lambda code: [(0.0, 0.0)] * 3
    te = np.linspace(0, 0.05, 501)
    r = ref.simulate_reference(m, off, 0.05, te, w0=w0)
    c = run_cplant(m, off, te, lambda t: 0.0, w0=w0)
    w_err, i_err = rel_errors(c, r)
    assert np.max(np.abs(r.i_abc)) > 0.1           # the diodes really conduct
    assert r.w[-1] < w0 * 0.99                     # and brake the rotor
    assert w_err < 0.01 and i_err < 0.01


def test_floating_phase_decays_through_the_diodes_then_stays_open():
    """Commutation a+b- -> c+b-: the outgoing phase a, switched off entirely,
    keeps its current through its low-side body diode (node at 0 V) until the
    current reaches zero, then stays open (exactly zero, terminal floating
    between the rails) while c and b carry the current."""
    p = _profile("assawinchaichote2016")
    m = plant_from_profile(p, load_mode="active").with_(bus_capacitance_f=0.0)   # the rails exactly at the bus
    cp = CPlant(m)
    for _ in range(200):
        cp.step([(0.9, 0.0), (0.0, 1.0), (0.0, 0.0)], 0.0, 50e-6)
    assert cp.state.i_a[0] > 1.0
    seen_diode = seen_open = False
    for _ in range(200):
        was_open = seen_open
        cp.step([(0.0, 0.0), (0.0, 1.0), (0.9, 0.0)], 0.0, 50e-6)
        st = cp.state
        if st.i_a[0] > 0:
            assert not was_open                               # no chatter once open
            assert st.v_term[0] == pytest.approx(0.0, abs=1e-12)
            seen_diode = True
        elif st.i_a[0] == 0.0:
            assert 0.0 <= st.v_term[0] <= p.inverter.bus_voltage_v
            seen_open = True
        else:
            # the open terminal (v_n + e_a) reached the bus: the high-side diode conducts
            assert was_open and st.v_term[0] == pytest.approx(p.inverter.bus_voltage_v)
        assert sum(st.i_a) == pytest.approx(0.0, abs=1e-9)
    assert seen_diode and seen_open
    assert cp.state.i_a[2] > 1.0                              # c took over
    assert cp.state.w_rad_s * m.kb_v_s_per_rad < p.inverter.bus_voltage_v
    # everything off below the bus speed: all currents die and stay exactly zero
    for _ in range(400):
        cp.step([(0.0, 0.0)] * 3, 0.0, 50e-6)
    assert abs(m.kb_v_s_per_rad * cp.state.w_rad_s) < p.inverter.bus_voltage_v
    assert list(cp.state.i_a) == [0.0, 0.0, 0.0]


def test_emf_and_torque_constants_match_the_profile_six_step_equivalents():
    """Line-to-line EMF of the conducting pair, averaged over its 60-degree
    window, is the profile's Kb; the torque per line ampere is Kt."""
    for name in PROFILES:
        p = _profile(name)
        m = plant_from_profile(p)
        cp = CPlant(m)
        # window centred on the line-to-line peak of (a - b): 60 deg around 60 deg electrical
        th = np.linspace(math.radians(30), math.radians(90), 2001)
        eab = np.array([cp.emf_shape(x) - cp.emf_shape(x - 2 * math.pi / 3) for x in th])
        kb = m.pole_pairs * m.lambda_m_v_s * float(np.mean(eab))
        assert kb == pytest.approx(p.motor.kb_v_s_per_rad, rel=1e-4)
        assert m.kt_n_m_per_a == pytest.approx(p.motor.kt_n_m_per_a, rel=1e-9)
        assert m.r_line_ohm == pytest.approx(p.motor.r_line_ohm)


def test_hall_codes_follow_the_profile_placement():
    p = _profile("duy2008")
    m = plant_from_profile(p)
    cp = CPlant(m)
    P = m.pole_pairs
    th = np.linspace(0, 2 * math.pi, 3600, endpoint=False) / P
    codes = [cp.hall_code(x) for x in th]
    seq = [c for k, c in enumerate(codes) if k == 0 or c != codes[k - 1]]
    assert sorted(set(codes)) == [1, 2, 3, 4, 5, 6]           # 120-degree halls: 000/111 never valid
    for a, b in zip(seq, seq[1:]):
        assert bin(a ^ b).count("1") == 1                     # Gray sequence
    # hall A rises hall_offset_deg after e_a's rising zero crossing
    for off in (0.0, 30.0, -20.0):
        mo = m.with_(hall_offset_deg=off)
        c2 = CPlant(mo)
        eps = 1e-6
        x = math.radians(off) / P
        assert c2.hall_code(x - eps) & 1 == 0 and c2.hall_code(x + eps) & 1 == 1
        assert ref.hall_code(mo, x + eps) == c2.hall_code(x + eps)
    # 60-degree spacing: 000 and 111 are valid codes of that geometry
    c60 = CPlant(m.with_(hall_spacing_deg=60.0))
    assert {0, 7} <= {c60.hall_code(x) for x in th}


def test_passive_load_holds_a_standing_rotor_and_never_reverses_it():
    p = _profile("duy2008")
    m = plant_from_profile(p, load_mode="passive")
    cp = CPlant(m)
    off = [(0.0, 0.0)] * 3
    cp.step(off, 0.01, 0.1)
    assert cp.state.w_rad_s == 0.0
    cp.state.w_rad_s = 50.0
    for _ in range(4000):
        cp.step(off, 0.01, 50e-6)
    assert cp.state.w_rad_s == 0.0
    # active load: the same torque turns a free rotor backwards (2016 eq 5 as written)
    ca = CPlant(m.with_(load_mode="active"))
    for _ in range(100):
        ca.step(off, 0.01, 50e-6)
    assert ca.state.w_rad_s < 0.0


def _dq_steady_state(prof, vq, vd, tl):
    """Steady state of picdrive.models.dqmodel (the design's corrected 2016 eq 5) at
    voltages given in this test's Park convention (q axis on e_a's sine, d on
    its cosine); dqmodel's d axis points the other way: v_d, i_d change sign."""
    from scipy.optimize import brentq
    from picdrive.models import dqmodel
    p = dqmodel.dq_params(prof)
    f = lambda w: dqmodel.equilibrium(p, w, tl, vd=-vd)[2] - vq
    w = brentq(f, 1e-6, 10 * vq / (p.pole_pairs * p.lambda_m_v_s), xtol=1e-12)
    iq, id_, _ = dqmodel.equilibrium(p, w, tl, vd=-vd)
    return w, iq, -id_


@pytest.mark.parametrize("vq, vd, tl", [(20.0, 0.0, 0.5), (15.0, -5.0, 1.0)])
def test_plant_matches_the_dq_model_at_steady_operating_points(vq, vd, tl):
    """Sinusoidal PWM synchronous with the rotor (complementary legs, no dead
    time: average node voltage = V_bus x duty exactly) on the 2016 motor."""
    p = _profile("assawinchaichote2016")
    m = plant_from_profile(p, load_mode="active")
    w_ss, iq_ss, id_ss = _dq_steady_state(p, vq, vd, tl)
    cp = CPlant(m)
    cp.state.w_rad_s = 0.9 * w_ss
    vbus, P = m.bus_voltage_v, m.pole_pairs
    h = 50e-6
    iq_hist, id_hist = [], []
    for k in range(int(1.5 / h)):
        th = P * (cp.state.theta_rad + 0.5 * h * cp.state.w_rad_s)   # mid-step angle: no hold lag
        legs = []
        for ph in range(3):
            a = th - ph * 2 * math.pi / 3
            v = vq * math.sin(a) + vd * math.cos(a)          # phase voltage wanted
            d = 0.5 + v / vbus
            legs.append((d, 1.0 - d))
        cp.step(legs, tl, h)
        if k * h > 1.3:
            th = P * cp.state.theta_rad
            i = cp.state.i_a
            iq_hist.append(2 / 3 * sum(i[ph] * math.sin(th - ph * 2 * math.pi / 3) for ph in range(3)))
            id_hist.append(2 / 3 * sum(i[ph] * math.cos(th - ph * 2 * math.pi / 3) for ph in range(3)))
    assert cp.state.w_rad_s == pytest.approx(w_ss, rel=0.01)
    assert np.mean(iq_hist) == pytest.approx(iq_ss, rel=0.01)
    assert np.mean(id_hist) == pytest.approx(id_ss, abs=0.01 * math.hypot(iq_ss, id_ss))


def test_perturbations():
    p = _profile("duy2008")
    base = plant_from_profile(p)
    m = plant_from_profile(p, {"resistance": 1.1, "inertia": 0.9})
    assert m.r_phase_ohm == pytest.approx(1.1 * base.r_phase_ohm)
    assert m.inertia_kg_m2 == pytest.approx(0.9 * base.inertia_kg_m2)
    assert parse_perturb(["resistance=0.9"]) == {"resistance": 0.9}
    u = p.design["resistance_uncertainty"]
    assert parse_perturb(["resistance=+u"], p) == {"resistance": pytest.approx(1 + u)}
    assert parse_perturb(["resistance=-u"], p) == {"resistance": pytest.approx(1 - u)}
    with pytest.raises(PlantError, match="resistance_uncertainty"):
        parse_perturb(["resistance=+u"])
    with pytest.raises(PlantError, match="unknown perturbation 'resistnce'"):
        parse_perturb(["resistnce=1.1"])
    with pytest.raises(PlantError, match=r"\[0.1, 10\]"):
        parse_perturb({"resistance": 0.0})
    with pytest.raises(PlantError, match="KEY=FACTOR"):
        parse_perturb(["resistance"])


def test_sinusoidal_emf_sin_cos_from_an_anchor_is_within_a_few_ulp_of_libm():
    """The plant evaluates the sinusoidal EMF's sin/cos by turning an anchor (libm)
    by the small angle to go (Taylor series): within a few units in the last place,
    for unwrapped angles far from zero too, both directions, up to the reach."""
    from picdrive_hil import cmodel
    from picdrive_hil.build import plant_library
    import ctypes as C
    lib = cmodel.bind_plant(C.CDLL(str(plant_library())))
    out = (C.c_double * 2)()
    rng = np.random.default_rng(1)
    worst = 0.0
    for anchor in np.concatenate([rng.uniform(-7, 7, 200), rng.uniform(-3e4, 3e4, 200)]):
        for d in np.concatenate([rng.uniform(-0.1, 0.1, 20), [0.0, 0.0999999, -0.0999999]]):
            th = anchor + d
            lib.plant_sin_cos_probe(anchor, th, out)
            worst = max(worst, abs(out[0] - math.sin(th)), abs(out[1] - math.cos(th)))
    assert worst < 1e-15                           # a few ulp of values up to 1
    # out of reach: libm itself
    lib.plant_sin_cos_probe(0.0, 0.2, out)
    assert (out[0], out[1]) == (math.sin(0.2), math.cos(0.2))


def _spin_down_rectifying(m, w0, t_end=0.05, h=20e-6):
    """All switches off, the rotor spun at ``w0``: the body diodes rectify the back-EMF into the
    bus.  Returns the plant, the bus voltage trace and the energy the bridge returned, J."""
    cp = CPlant(m)
    cp.state.w_rad_s = w0
    v, back, burnt = [], 0.0, 0.0
    for _ in range(int(round(t_end / h))):
        v0 = cp.state.v_bus_v
        cp.step([(0.0, 0.0)] * 3, 0.0, h)
        back += -0.5 * (v0 + cp.state.v_bus_v) * cp.state.i_bus_a * h
        burnt += cp.state.v_bus_v * cp.state.i_brake_a * h
        v.append(cp.state.v_bus_v)
    return cp, np.array(v), back, burnt


def test_the_bus_capacitor_takes_what_the_supply_cannot():
    """A rotor spun at 1.6 x the bus speed with the bridge off charges the 470 uF capacitor through the
    diodes (a supply that cannot sink): the bus rises towards the line EMF's peak, the energy the
    bridge returned is the capacitor's 1/2 C (V^2 - Vs^2) to 1 %, and the rotor keeps the rest.
    A supply that sinks the current holds the bus at its voltage; a stiff bus is the old model."""
    p = _profile("duy2008")
    m = plant_from_profile(p, load_mode="active")
    vs, c = p.inverter.bus_voltage_v, p.inverter.bus_capacitance_f
    assert c == 470e-6 and p.inverter.supply_sink_a == 0.0          # the defaults
    w0 = 1.6 * vs / m.kb_v_s_per_rad
    cp, v, back, _ = _spin_down_rectifying(m, w0)
    # it rises while the line EMF is above it, then holds its charge (nothing takes it back)
    assert 1.15 * vs < v.max() < m.kb_v_s_per_rad * w0 and v[-1] == v.max()
    assert m.kb_v_s_per_rad * cp.state.w_rad_s < v[-1]
    assert back == pytest.approx(0.5 * c * (v[-1] ** 2 - vs ** 2), rel=0.01)
    _, v_sink, _, _ = _spin_down_rectifying(m.with_(supply_sink_a=1000.0), w0)
    assert np.max(v_sink) == pytest.approx(vs, abs=1e-9)
    _, v_stiff, _, _ = _spin_down_rectifying(m.with_(bus_capacitance_f=0.0), w0)
    assert np.all(v_stiff == vs)


def test_a_brake_chopper_holds_the_bus_at_its_threshold():
    """The same rotor with a 10 ohm brake resistor switched in above 1.05 x the bus: the bus stops at
    the chopper's threshold, and what the bridge returned is in the capacitor and the resistor."""
    p = _profile("duy2008")
    vs, c = p.inverter.bus_voltage_v, p.inverter.bus_capacitance_f
    m = plant_from_profile(p, load_mode="active").with_(brake_resistor_ohm=10.0, brake_chopper_v=1.05 * vs)
    cp, v, back, burnt = _spin_down_rectifying(m, 1.6 * vs / m.kb_v_s_per_rad)
    assert np.max(v) == pytest.approx(1.05 * vs, rel=1e-9)
    assert burnt > 0.1 * back
    assert back == pytest.approx(0.5 * c * (v[-1] ** 2 - vs ** 2) + burnt, rel=0.01)


def test_a_brake_chopper_that_cannot_protect_the_switches_is_refused():
    from picdrive.profile import ProfileError, loads_profile
    base = (Path(__file__).resolve().parents[1] / "examples" / "duy2008.toml").read_text()
    for extra, msg in [("brake_resistor_ohm = 10.0\nbrake_chopper_v = 95.0\n", "must be below 90 % of the switch rating"),
                       ("brake_resistor_ohm = 10.0\nbrake_chopper_v = 40.0\n", "must be above inverter.bus_voltage_v"),
                       ("brake_chopper_v = 60.0\n", "has no effect without inverter.brake_resistor_ohm")]:
        with pytest.raises(ProfileError, match=msg):
            loads_profile(base.replace("[inverter]\n", "[inverter]\n" + extra))
    p = loads_profile(base.replace("[inverter]\n", "[inverter]\nbrake_resistor_ohm = 10.0\n"))
    assert p.inverter.brake_chopper_v == pytest.approx(1.1 * p.inverter.bus_voltage_v)
