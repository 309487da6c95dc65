"""Faults: the link watchdog, an invalid hall code, an overcurrent, a stall.
Each latches its fault code with the outputs off, and only the fault-clear
command releases it."""
import time

from picdrive.link import protocol as P
from picdrive.link.client import Link


def _running(b):
    lim = b.limits()
    b.settle_at(lim.target_rpm, 0.4)
    st = b.link.status()
    assert st.state == P.State.RUN and st.fault == P.Fault.NONE, st
    return lim


def _expect_fault(b, fault, timeout=1.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        st = b.link.status()
        if st.state == P.State.FAULT:
            break
        time.sleep(0.01)
    assert st.state == P.State.FAULT and st.fault == fault, st
    if b.is_twin:
        assert not b.twin.state()["outputs_active"]


def test_link_loss_stops_the_drive_within_the_watchdog_timeout(open_bench):
    b = open_bench("duy2008", "mixed-pid")
    _running(b)
    timeout_s = b.link.get("link_timeout") / 1000.0
    url = b.link.url
    t_close = b.twin.t if b.is_twin else None
    b.link.close()                                     # no frame from now on
    if b.is_twin:
        t_off = None
        end = time.monotonic() + 3 * timeout_s + 1.0
        while time.monotonic() < end:
            s = b.twin.state()
            if not s["outputs_active"]:
                t_off = s["t_s"]
                break
            time.sleep(0.002)
        assert t_off is not None, "the watchdog never switched the outputs off"
        # the last frame left the host at most one keep-alive period (timeout / 4) before the close
        print(f"{b.label}: outputs off {1e3 * (t_off - t_close):.1f} ms after the link went silent "
              f"(link_timeout {timeout_s * 1e3:.0f} ms)")
        assert timeout_s * 0.75 - 0.01 <= t_off - t_close <= timeout_s + 0.005
    else:
        time.sleep(timeout_s + 0.3)
    b.link = Link.open(url, expect_profile_hash=int(b.profile.sha256[:8], 16))
    st = b.link.status()
    assert st.state == P.State.FAULT and st.fault == P.Fault.LINK_LOST, st
    b.link.fault_clear()
    assert b.link.status().state == P.State.IDLE


def test_invalid_hall_code_latches_a_fault_with_outputs_off(open_bench):
    b = open_bench("duy2008", "mixed-pid")
    b.need_twin("forcing the hall inputs to 000")
    _running(b)
    b.twin.inject("hall", code=0)
    _expect_fault(b, P.Fault.HALL_INVALID)
    b.twin.inject("hall", code=None)
    time.sleep(0.05)
    assert b.link.status().state == P.State.FAULT           # latched until cleared
    b.link.fault_clear()
    assert b.link.status().state == P.State.IDLE


def test_overcurrent_latches_a_fault_with_outputs_off(open_bench):
    b = open_bench("duy2008", "mixed-pid")
    b.need_twin("an overcurrent on the FLTA comparator")
    _running(b)
    b.twin.inject("overcurrent", duration_s=2e-3)
    _expect_fault(b, P.Fault.OVERCURRENT)
    assert b.twin.state()["pwm_fault_latched"]              # FLTAS: hardware shutdown
    time.sleep(0.05)
    assert b.link.status().state == P.State.FAULT
    b.link.fault_clear()
    st = b.link.status()
    assert st.state == P.State.IDLE and st.fault == P.Fault.NONE
    assert not b.twin.state()["pwm_fault_latched"]


def test_stall_latches_a_fault(open_bench):
    b = open_bench("duy2008", "mixed-pid")
    b.need_twin("a locked rotor")
    _running(b)
    stall_s = b.link.get("stall_timeout") / 1000.0
    b.twin.inject("lock_rotor", locked=True)
    t0 = b.twin.t
    _expect_fault(b, P.Fault.STALL, timeout=stall_s + 1.0)
    print(f"{b.label}: stall fault {1e3 * (b.twin.t - t0):.0f} ms after the rotor locked "
          f"(stall_timeout {stall_s * 1e3:.0f} ms)")
    b.twin.inject("lock_rotor", locked=False)
