"""Faults: the link watchdog, an invalid hall code, an overcurrent, a stall.
Each latches its fault code with the outputs off, and only the fault-clear
command releases it."""
import threading
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
    if b.is_twin:
        # when did the board receive the host's last byte?  Sample the twin's clock with what the
        # endpoint has read from the host and what the board has not yet received, while the link
        # closes and until the endpoint has seen the client go (it drops what was not received)
        samples = []
        stop = threading.Event()

        def watch():
            while not stop.is_set():
                st = b.server.status()
                samples.append((b.twin.t, st["bytes_in"], st["input_waiting"] + b.twin.uart_pending(),
                                st["client_connected"], st["dropped_on_disconnect"]))
                time.sleep(0.0005)
        dropped0 = b.server.status()["dropped_on_disconnect"]
        th = threading.Thread(target=watch, daemon=True)
        th.start()
        while not samples:
            time.sleep(0.001)
        b.link.status()                                # a frame the watch sees arrive
        b.link.close()                                 # no frame from now on
        end = time.monotonic() + 3.0
        while (not samples or samples[-1][3]) and time.monotonic() < end:
            time.sleep(0.001)
        stop.set()
        th.join()
        assert not samples[-1][3], "the endpoint never saw the client go"
        final_in = samples[-1][1]
        i = next(k for k, sm in enumerate(samples) if sm[1] == final_in and sm[2] == 0)
        assert i > 0, "the last host byte was delivered before the first sample"
        t_lo, t_hi = samples[i - 1][0], samples[i][0]      # the last byte arrived in (t_lo, t_hi]
        t_off = None
        end = time.monotonic() + 3 * timeout_s + 1.0
        while time.monotonic() < end:
            s = b.twin.state()
            if not s["outputs_active"]:
                t_off = s["outputs_off_t_s"]          # the instant they went off, on the twin's clock
                assert t_off is not None and t_off > t_lo, (t_off, t_lo)
                break
            time.sleep(0.002)
        assert t_off is not None, "the watchdog never switched the outputs off"
        print(f"{b.label}: outputs off {1e3 * (t_off - t_hi):.1f}..{1e3 * (t_off - t_lo):.1f} ms after the "
              f"board received the host's last byte (link_timeout {timeout_s * 1e3:.0f} ms)")
        # within the timeout, give or take the 1 ms watchdog tick and the 1 ms poll of the link
        # module, all on the twin's clock
        assert t_off - t_hi <= timeout_s + 0.002
        if samples[-1][4] == dropped0:                 # nothing dropped: the last byte was a whole frame
            assert t_off - t_lo >= timeout_s - 0.002
    else:
        b.link.close()
        time.sleep(timeout_s + 0.3)
    b.link = Link.open(url, expect_profile_hash=b.profile.hash32)
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
