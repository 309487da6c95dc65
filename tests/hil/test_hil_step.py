"""Speed steps through the link: 0 -> Profile.speed_step_rpm() for each
bundled profile and each design method, the load-torque step, R +-10 %.
Rise, settling, overshoot and steady-state error are reported in the test
summary; the limits come from the profile and the design's verification."""
import numpy as np
import pytest

from picdrive import protocol as P

from hilbench import METHODS, PROFILES, step_of

RECORD_S = 1.0

# Cases the suite finds failing against the committed designs and firmware (reported to the
# design and firmware owners; docs/twin.md).  Full diagnosis:
# * duy2008 fuzzy-hinf: the design's integrator_limit_v (1154 V) is sized for the 1453 rpm its dq
#   model allows; at 2400 rpm u = -kp w - kc i + I needs I ~ 1190 V, so the drive holds ~2041 rpm.
# * assawinchaichote2016 (all designs): the speed overshoots (~410 rpm for 380.5) and the
#   high-side-PWM / low-side-on drive cannot brake (the current cannot reverse while the back-EMF
#   is below the bus): friction alone brings it down, it undershoots, the loop pushes again: a
#   limit cycle of about 377..414 rpm, period ~0.4 s, that never settles in the 2 % band.  (Before
#   firmware f344104 the step also tripped the 15 A FLTA comparator within ~6 ms.)
# Deterministic failures are strict (they turn red when fixed); the 2016 ones depend on the rotor
# position at the start (real-time pacing), so they are not.
KNOWN = {
    ("duy2008", "fuzzy-hinf"): ("integrator_limit_v sized for 1453 rpm: holds ~2041 rpm of 2400", True),
    ("assawinchaichote2016", "fuzzy-hinf"): ("overshoot six-step cannot brake: ~377..414 rpm limit cycle", False),
    ("assawinchaichote2016", "mixed-pid"): ("overshoot six-step cannot brake: ~377..414 rpm limit cycle", False),
    ("assawinchaichote2016", "zn"): ("overshoot six-step cannot brake: ~377..414 rpm limit cycle", False),
}


def known(profile_name, method):
    k = KNOWN.get((profile_name, method))
    return [pytest.mark.xfail(reason=f"{profile_name} {method}: {k[0]} (docs/twin.md)", strict=k[1])] if k else []


def matrix(profiles=PROFILES, methods=METHODS):
    return [pytest.param(p, m, marks=known(p, m), id=f"{p}-{m}") for p in profiles for m in methods]


def _step(b, case: str):
    lim = b.limits()
    b.stream()
    b.link.set_speed(lim.target_rpm)
    b.link.start()
    data = b.collect(RECORD_S)
    m, k = step_of(data, lim.target_rpm)
    b.report.append({"case": case, "target_rpm": lim.target_rpm, "rise_s": m.rise_time_s,
                     "settle_s": m.settling_time_s, "overshoot_pct": m.overshoot_pct,
                     "sse_pct": m.steady_state_error_pct})
    print(f"{case}: {m.summary('rpm')}")
    st = b.link.status()
    assert st.fault == P.Fault.NONE and st.state == P.State.RUN, st
    assert b.link.telemetry_stats.dropped == 0
    assert m.settling_time_s <= lim.settle_s, f"settling {m.settling_time_s:.3f} s > {lim.settle_s} s"
    assert m.overshoot_pct <= lim.overshoot_pct, f"overshoot {m.overshoot_pct:.2f} % > {lim.overshoot_pct:.2f} %"
    assert m.steady_state_error_pct <= lim.band_pct, \
        f"steady error {m.steady_state_error_pct:.3f} % > {lim.band_pct:.2f} %"
    if b.is_twin:
        # the board's speed measurement agrees with the true rotor speed
        true_rpm = b.twin.state()["speed_rpm"]
        assert abs(true_rpm - m.final_value) <= 0.01 * abs(lim.target_rpm)
        assert b.twin.state()["shoot_through"] == 0
    return m, data


@pytest.mark.parametrize("profile_name, method", matrix())
def test_speed_step(open_bench, profile_name, method):
    b = open_bench(profile_name, method)
    _step(b, b.label)


@pytest.mark.parametrize("profile_name, method", matrix())
@pytest.mark.parametrize("sign", ["-u", "+u"])
def test_speed_step_with_resistance_off_by_its_uncertainty(open_bench, profile_name, method, sign):
    """The profile's design.resistance_uncertainty (the 2016 paper's R +-10 %): same firmware, same limits."""
    b = open_bench(profile_name, method, perturb=[f"resistance={sign}"])
    u = b.profile.design["resistance_uncertainty"]
    factor = 1 + u if sign == "+u" else 1 - u
    assert b.twin.model.r_phase_ohm == pytest.approx(factor * b.profile.motor.r_phase_ohm)
    _step(b, b.label)


# At 2400 rpm the 0.015 N m load needs more than the bridge gives: the twin holds ~2306 rpm at the
# duty limit.  Profile.max_reachable_rpm (2533 rpm) is the DC equivalent (2008 eq 1), which ignores
# commutation (a hall sector lasts 1.04 ms < L/R = 2.45 ms) and hall_offset_deg = 0 puts the
# commutation 30 electrical degrees off the EMF.
HEADROOM = "duy2008 at 2400 rpm under 0.015 N m: bridge holds ~2306 rpm, not the DC equivalent's 2533 (docs/twin.md)"


def load_cases():
    out = []
    for p, m, marks in [(p, m, known(p, m)) for p in PROFILES for m in METHODS]:
        # duy2008 fuzzy-hinf's integrator limit allows 1200 rpm: only the full target is known to fail
        half = [] if (p, m) == ("duy2008", "fuzzy-hinf") else marks
        out.append(pytest.param(p, m, 0.5, marks=half, id=f"{p}-{m}-half"))
        full = marks or ([pytest.mark.xfail(reason=HEADROOM, strict=True)] if p == "duy2008" else [])
        out.append(pytest.param(p, m, 1.0, marks=full, id=f"{p}-{m}-target"))
    return out


@pytest.mark.parametrize("profile_name, method, fraction", load_cases())
def test_load_torque_step_is_rejected(open_bench, profile_name, method, fraction):
    """The profile's load-torque step (control.load_torque_n_m) at steady speed:
    at half the step target (the loop's rejection, away from the voltage
    limit) and at the step target itself (the profile's headroom claim)."""
    b = open_bench(profile_name, method)
    b.need_twin("a load-torque step")
    lim = b.limits(fraction * b.profile.speed_step_rpm())
    b.settle_at(lim.target_rpm, 0.8)
    b.stream()
    b.collect(0.05)
    b.link.flush_samples()
    t_load = b.twin.t
    b.twin.set_load_torque(b.profile.control.load_torque_n_m)
    data = b.collect(RECORD_S)
    y, t = data["speed"], data["t"]
    dip = lim.target_rpm - float(np.min(y))
    band = lim.band_pct / 100 * lim.target_rpm
    out = np.nonzero(np.abs(y - lim.target_rpm) > band)[0]
    recovery = 0.0 if out.size == 0 else float(t[out[-1]] - t[0])
    tail = y[-len(y) // 10:]
    print(f"{b.label}: load {b.profile.control.load_torque_n_m} N m at {lim.target_rpm:.0f} rpm (t={t_load:.3f} s): "
          f"dip {dip:.1f} rpm, back in the {lim.band_pct:.1f} % band after {recovery * 1e3:.1f} ms, "
          f"final {np.mean(tail):.2f} rpm")
    why = (f"dip {dip:.1f} rpm, recovery {recovery:.3f} s (limit {lim.load_recovery_s} s), final "
           f"{np.mean(tail):.2f} rpm, {len(y)} samples, twin lag events {b.server.lag_events}")
    assert b.twin.state()["torque_load_n_m"] == pytest.approx(b.profile.control.load_torque_n_m)
    assert b.link.status().fault == P.Fault.NONE
    assert dip < lim.target_rpm, why                                # never stalls
    assert out.size == 0 or out[-1] < len(y) - 1, why               # recovered inside the record
    assert recovery <= lim.load_recovery_s, why
    assert abs(np.mean(tail) - lim.target_rpm) <= band, why
