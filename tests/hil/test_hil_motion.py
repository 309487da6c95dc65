"""Reversal, stop and brake through the link."""
import numpy as np

from picdrive.link import protocol as P

from hilbench import step_of


def test_reversal(open_bench):
    """+n -> -n: the drive passes through zero and settles at -n within twice
    the design's settling limit (a reversal is two steps)."""
    b = open_bench("duy2008", "mixed-pid")
    lim = b.limits()
    b.settle_at(lim.target_rpm, 0.5)
    b.stream()
    b.link.set_speed(-lim.target_rpm)
    data = b.collect(1.2)
    m, _ = step_of(data, -lim.target_rpm, b.profile)
    print(f"{b.label} reversal {lim.target_rpm:+.0f} -> {-lim.target_rpm:+.0f} rpm: {m.summary('rpm')}")
    st = b.link.status()
    assert st.fault == P.Fault.NONE and st.state == P.State.RUN
    assert np.min(data["speed"]) < -0.9 * lim.target_rpm
    assert m.settling_time_s <= 2 * lim.settle_s
    assert m.steady_state_error_pct <= lim.band_pct
    if b.is_twin:
        assert b.twin.state()["speed_rpm"] < 0 and b.twin.state()["shoot_through"] == 0


def _decay_time(data, level):
    below = np.nonzero(np.abs(data["speed"]) < level)[0]
    return float(data["t"][below[0]] - data["t"][0]) if below.size else np.inf


def test_stop_coasts_and_brake_stops_faster(open_bench):
    b = open_bench("duy2008", "mixed-pid")
    lim = b.limits()
    half = 0.5 * lim.target_rpm
    # coast
    b.settle_at(lim.target_rpm, 0.5)
    b.stream(("speed", "state"))
    b.link.stop()
    if b.is_twin:
        s = b.twin.state()
        assert not s["outputs_active"]                          # bridge off
    coast = b.collect(0.6)
    assert b.link.status().state == P.State.IDLE
    idle = coast["state"] == P.State.IDLE
    assert idle[-1]
    sp = coast["speed"][idle]
    assert np.all(np.diff(sp[sp > 0.05 * lim.target_rpm]) <= 2 * b.link.param("speed").scale)   # no drive torque
    t_coast = _decay_time(coast, half)
    # brake
    b.settle_at(lim.target_rpm, 0.6)
    b.stream(("speed", "state"))
    b.link.brake()
    brake = b.collect(0.6)
    assert b.link.status().state == P.State.BRAKE
    if b.is_twin:
        s = b.twin.state()
        assert s["gate_lo"] == (1, 1, 1) and s["gate_hi"] == (0, 0, 0)   # low sides on
    t_brake = _decay_time(brake, half)
    print(f"{b.label}: from {lim.target_rpm:.0f} rpm to half: coast {t_coast * 1e3:.1f} ms, "
          f"brake {t_brake * 1e3:.1f} ms")
    assert t_brake < t_coast
    assert abs(brake["speed"][-1]) < 0.05 * lim.target_rpm
