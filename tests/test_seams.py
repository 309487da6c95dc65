"""The seam modules: control law reference, step metrics, design-result file."""
import json
import math

import numpy as np
import pytest

from picdrive.control_law import LawState, Rule, ScheduledLaw, law_step, memberships
from picdrive.analysis.metrics import step_metrics
from picdrive.result import DesignError, DesignResult, load_design, save_design


def law(rules=(Rule(1.0, 10.0),), **kw):
    base = dict(rules=tuple(rules), premise_rad_s=(0.0, 300.0), sample_time_s=1e-3,
                u_min_v=-10.0, u_max_v=10.0)
    base.update(kw)
    return ScheduledLaw(**base)


def test_memberships_partition_and_linear_two_rules():
    lw = law(rules=(Rule(1, 0), Rule(2, 0)))
    for s in np.linspace(-400, 400, 41):
        mu = memberships(lw, s)
        assert mu.sum() == pytest.approx(1.0) and (mu >= 0).all()
    # the 2016 paper's M1 = (N2 - x)/(N2 - N1), M2 = (x - N1)/(N2 - N1)
    assert memberships(lw, 75.0) == pytest.approx([0.75, 0.25])
    assert memberships(lw, -75.0) == pytest.approx([0.75, 0.25])       # premise |y|
    assert memberships(lw, 1e6) == pytest.approx([0.0, 1.0])           # clamped
    assert lw.gains_at(150.0).kp == pytest.approx(1.5)


def test_memberships_three_rules_triangles():
    lw = law(rules=(Rule(0, 0), Rule(1, 0), Rule(2, 0)))
    assert memberships(lw, 150.0) == pytest.approx([0, 1, 0])
    assert memberships(lw, 225.0) == pytest.approx([0, 0.5, 0.5])


def test_law_pi_by_hand():
    lw = law()
    st = LawState()
    u1 = law_step(lw, st, r=2.0, y=0.0)
    # P = 1*2, I = 10*1e-3*2 = 0.02
    assert u1 == pytest.approx(2.02)
    u2 = law_step(lw, st, r=2.0, y=1.0)
    assert u2 == pytest.approx(1.0 + 0.02 + 0.01)


def test_law_saturation_and_conditional_integration():
    lw = law(rules=(Rule(100.0, 1000.0),))
    st = LawState()
    for _ in range(100):
        u = law_step(lw, st, r=1.0, y=0.0)
    assert u == 10.0
    assert st.integ_v == 0.0      # P alone saturates: no headroom, integrator stays put
    u = law_step(lw, st, r=0.0, y=0.05)   # error reversed: integrates again
    assert st.integ_v < 0.0


def test_law_integrates_only_into_headroom_and_never_discharges_by_force():
    lw = law(rules=(Rule(4.0, 1000.0),))
    st = LawState()
    law_step(lw, st, r=2.0, y=0.0)        # P = 8, headroom 2: I' = 2 -> 2
    assert st.integ_v == pytest.approx(2.0)
    law_step(lw, st, r=2.5, y=0.0)        # P = 10: no headroom left, I keeps 2 (not pulled to 0)
    assert st.integ_v == pytest.approx(2.0)


def test_law_state_feedback_integrator_holds_equilibrium_beyond_output_range():
    # b = 0: at equilibrium y* = r, I* = u* + kp y*, which is far above u_max = 10 V
    kp, ki, r = 2.0, 50.0, 4.0
    lw = law(rules=(Rule(kp, ki),), setpoint_weight=0.0, integrator_limit_v=100.0)
    st = LawState()
    y = 0.0
    for _ in range(20000):                # first-order plant dy/dt = -y + 0.5 u
        u = law_step(lw, st, r=r, y=y)
        y += 1e-3 * (-y + 0.5 * u)
    assert y == pytest.approx(r, rel=1e-3)
    u_star = r / 0.5                      # 8 V, inside the output range
    assert st.integ_v == pytest.approx(u_star + kp * r, rel=1e-3)    # 16 V
    assert st.integ_v > lw.u_max_v


def test_law_current_clamp_bounds_steady_current_at_every_speed():
    kb, r, imax = 0.1, 2.0, 1.5
    lw = law(rules=(Rule(50.0, 500.0),), u_min_v=-40.0, u_max_v=40.0, current_limit_a=imax,
             kb_v_s_per_rad=kb, r_ohm=r)
    assert lw.output_limits(0.0) == pytest.approx((-3.0, 3.0))
    assert lw.output_limits(300.0) == pytest.approx((27.0, 33.0))
    assert lw.output_limits(1000.0) == pytest.approx((40.0, 40.0))     # inside [u_min, u_max]
    assert lw.output_limits(-1000.0) == pytest.approx((-40.0, -40.0))
    for y in (0.0, 50.0, 200.0, -100.0):
        st = LawState()
        for _ in range(20):
            u = law_step(lw, st, r=250.0, y=y)
            assert abs((u - kb * y) / r) <= imax + 1e-12
    with pytest.raises(ValueError, match="current-limited law"):
        law(current_limit_a=1.0)


def test_law_without_current_limit_is_unchanged():
    lw = law()
    assert lw.output_limits(123.0) == (lw.u_min_v, lw.u_max_v)


def test_law_integrator_limit():
    lw = law(rules=(Rule(0.0, 1000.0),), integrator_limit_v=3.0, u_max_v=10.0)
    st = LawState()
    for _ in range(50):
        law_step(lw, st, r=1.0, y=0.0)
    assert st.integ_v == 3.0
    with pytest.raises(ValueError, match="integrator_limit_v"):
        law(integrator_limit_v=0.0)


def test_law_derivative_on_measurement_and_state_feedback_form():
    lw = law(rules=(Rule(0.0, 0.0, kd=0.01, kc=2.0),), setpoint_weight=0.0)
    st = LawState()
    assert law_step(lw, st, r=5.0, y=0.0, i=1.0) == pytest.approx(-2.0)   # no kick from r
    assert law_step(lw, st, r=5.0, y=0.1, i=0.0) == pytest.approx(-0.01 * 0.1 / 1e-3)


def test_step_metrics_first_order_by_hand():
    tau = 0.1
    t = np.linspace(0, 2, 20001)
    y = 100 * (1 - np.exp(-t / tau))
    m = step_metrics(t, y, 100.0)
    assert m.rise_time_s == pytest.approx(tau * math.log(9), rel=1e-3)
    assert m.settling_time_s == pytest.approx(tau * math.log(50), rel=1e-3)
    assert m.overshoot_pct == 0.0
    assert m.steady_state_error == pytest.approx(0.0, abs=1e-6)


def test_step_metrics_second_order_overshoot():
    zeta, wn = 0.5, 10.0
    t = np.linspace(0, 5, 50001)
    wd = wn * math.sqrt(1 - zeta**2)
    y = 1 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta / math.sqrt(1 - zeta**2) * np.sin(wd * t))
    m = step_metrics(t, y, 1.0)
    assert m.overshoot_pct == pytest.approx(100 * math.exp(-zeta * math.pi / math.sqrt(1 - zeta**2)), rel=1e-3)


def test_step_metrics_downward_step_and_never_settles():
    t = np.linspace(0, 1, 1001)
    y = 2000 - 1000 * (1 - np.exp(-t / 0.05))
    m = step_metrics(t, y, 1000.0)
    assert m.overshoot_pct == 0.0 and m.settling_time_s < 1
    m2 = step_metrics(t, 500 * t, 1000.0)
    assert m2.settling_time_s == math.inf
    with pytest.raises(ValueError, match="no step"):
        step_metrics(t, y, 2000.0)


def _result(**kw):
    base = dict(method="zn", status="verified", profile_name="t", profile_sha256="ab" * 32, law=law())
    base.update(kw)
    return DesignResult(**base)


def test_result_roundtrip_and_jsonable(tmp_path):
    r = _result(certificate={"P": np.eye(2), "eig": np.array([-1 + 2j]), "n": np.inf})
    p = save_design(r, tmp_path / "x.design.json")
    d = json.loads(p.read_text())
    assert d["certificate"]["eig"] == [[-1.0, 2.0]] and d["certificate"]["n"] == "inf"
    r2 = load_design(p, require_usable=True)
    assert r2.law == r.law and r2.ok


def test_result_refuses_failed_lawless_and_foreign(tmp_path):
    f = _result(); f.fail("closed loop unstable at vertex 2")
    p = save_design(f, tmp_path / "f.json")
    with pytest.raises(DesignError, match="failed its verification.*unstable at vertex 2"):
        load_design(p, require_usable=True)
    p = save_design(_result(law=None, variant="paper"), tmp_path / "n.json")
    with pytest.raises(DesignError, match="no law the six-step firmware can run"):
        load_design(p, require_usable=True)

    class Prof:
        sha256 = "cd" * 32
    p = save_design(_result(), tmp_path / "o.json")
    with pytest.raises(DesignError, match="re-run 'picdrive design' on this profile"):
        load_design(p, require_usable=True, profile=Prof())
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(DesignError, match="not valid JSON"):
        load_design(tmp_path / "bad.json")


def test_atomic_write_gives_ordinary_permissions(tmp_path):
    import os
    import stat

    from picdrive.fileio import atomic_write_text
    old = os.umask(0o022)
    try:
        p = atomic_write_text(tmp_path / "a.json", "{}")
    finally:
        os.umask(old)
    assert stat.S_IMODE(p.stat().st_mode) == 0o644
    assert not list(tmp_path.glob(".a.json.*"))


def test_publish_dir_replaces_whole_with_ordinary_mode(tmp_path):
    import os
    import stat

    from picdrive.fileio import new_temp_dir, publish_dir
    out = tmp_path / "fw"
    out.mkdir()
    (out / "old.c").write_text("old")
    tmp = new_temp_dir(out)
    (tmp / "new.c").write_text("new")
    old = os.umask(0o022)
    try:
        publish_dir(tmp, out)
    finally:
        os.umask(old)
    assert sorted(p.name for p in out.iterdir()) == ["new.c"]
    assert stat.S_IMODE(out.stat().st_mode) == 0o755
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fw"]       # no temp or backup left
