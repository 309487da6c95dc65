"""The twin's PIC18F4431 peripheral model and event loop, driven by the twin's
own test firmware (tests/support/testfw/testfw.c, written against the
register-shim contract): UART byte timing, timer interrupts and priorities,
EEPROM unlock and write time, PCPWM override commutation against the plant
alone, QEI counts, FLTA latching, hall faults, deliberate firmware bugs the
twin must catch."""
import ctypes
import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from picdrive.profile import ProfileWarning, load_profile
from support import plant_reference as ref
from picdrive_hil.plant import plant_from_profile
from support.testfw import make_twin
from support.twin_uart import command
from picdrive_hil import twin as twin_module
from picdrive_hil.twin import Twin, TwinError

warnings.simplefilter("ignore", ProfileWarning)

PDC_FULL = 4 * (499 + 1)          # the test firmware's PTPER = 499


@pytest.fixture
def tw():
    t = make_twin("duy2008")
    yield t
    t.close()


def host_frame_s(tw):
    return 10.0 / tw.profile.uart.baud


def board_frame_s(tw):
    return 10.0 / tw.state()["board_baud"]


def wait_reply(tw, n, limit_s=0.05, dt=5e-6):
    """Run in small steps until n bytes came back; returns (bytes, time of the last byte)."""
    out = b""
    t_end = tw.t + limit_s
    while len(out) < n and tw.t < t_end:
        tw.run(dt)
        out += tw.uart_read()
    return out, tw.t


def test_uart_reply_takes_the_wire_time_of_both_frames(tw):
    tw.run(0.002)
    t0 = tw.t
    tw.uart_write(b"P")
    out, t1 = wait_reply(tw, 1)
    assert out == b"p"
    lo = host_frame_s(tw) + board_frame_s(tw)
    # + at most one event step of latency (PWM period) before the main loop sees the byte
    assert lo - 1e-6 <= t1 - t0 <= lo + tw.state()["pwm_period_s"] + 2e-5


def test_uart_burst_is_paced_by_the_baud_rate_without_loss(tw):
    tw.run(0.002)
    payload = bytes(range(33, 33 + 60))
    msg = b"".join(b"E" + bytes([c]) for c in payload)       # 120 bytes in, 60 echoed
    t0 = tw.t
    tw.uart_write(msg)
    assert tw.uart_pending() > 100                            # not delivered at once
    out, t1 = wait_reply(tw, len(payload), limit_s=0.1, dt=50e-6)
    assert out == payload
    # the input alone takes 120 host frames
    assert t1 - t0 >= len(msg) * host_frame_s(tw) - 1e-9
    assert tw.state()["uart_rx_overruns"] == 0


def test_timer2_interrupt_every_millisecond_at_low_priority(tw):
    tw.run(0.1)
    tw.uart_write(b"T")
    out, _ = wait_reply(tw, 2)
    ticks = int.from_bytes(out, "little")
    assert ticks == 100                                      # Timer2 1:16, PR2 124, 1:5 = 1 ms exactly
    s = tw.state()
    assert s["isr_low_calls"] >= 100


def test_eeprom_write_needs_the_unlock_and_takes_its_write_time(tw):
    tw.run(0.002)
    tw.uart_write(b"W\x05\x42")
    out, _ = wait_reply(tw, 1)
    assert out == b"w"
    tw.uart_write(b"W\x06\x43")                              # within the 4 ms write time: busy
    out, _ = wait_reply(tw, 1)
    assert out == b"b"
    assert tw.eeprom()[5] == 0xFF                            # not written yet
    tw.run(0.005)
    assert tw.eeprom()[5] == 0x42
    tw.uart_write(b"R\x05")
    out, _ = wait_reply(tw, 2)
    assert out == b"r\x42"
    # without the 0x55/0xAA sequence the chip does not start the write
    tw.uart_write(b"U\x07\x99")
    out, _ = wait_reply(tw, 1)
    tw.run(0.01)
    s = tw.state()
    assert out == b"u" and tw.eeprom()[7] == 0xFF
    assert s["eeprom_rejected"] == 1 and s["eeprom_writes"] == 1


def test_eeprom_image_survives_into_a_new_twin(tw):
    tw.run(0.002)
    tw.uart_write(b"W\x10\x5A")
    tw.run(0.01)
    img = tw.eeprom()
    t2 = make_twin("duy2008", eeprom=img)
    t2.uart_write(b"R\x10")
    out, _ = wait_reply(t2, 2)
    assert out == b"r\x5a"
    t2.close()


def drive(tw, duty):
    d = int(round(duty * PDC_FULL))
    tw.uart_write(bytes([ord("D"), d >> 8, d & 0xFF, ord("S")]))


def test_six_step_through_the_override_matches_the_plant_with_ideal_commutation(tw):
    """The firmware commutates from hall interrupts through OVDCOND/OVDCONS;
    the plant alone with the ideal table at the same duty must agree."""
    duty = 0.8
    tw.run(0.001)
    drive(tw, duty)
    while not tw.state()["outputs_active"]:                  # the 'S' byte has arrived
        tw.run(1e-6)
    t_start = tw.t
    rec = tw.record(0.25, 1e-3)
    m = plant_from_profile(tw.profile, load_mode="passive")
    legs = ref.sixstep_legs(ref.ideal_commutation_table(m), round(duty * PDC_FULL) / PDC_FULL)
    # plant alone, same start time, same inputs
    from test_plant import run_cplant
    te = rec["t_s"] - t_start
    te = te[te >= 0]
    c = run_cplant(m, legs, te, lambda t: 0.0)
    w_twin = rec["w_rad_s"][-len(te):]
    err = np.max(np.abs(w_twin - c[3])) / np.max(c[3])
    assert np.max(c[3]) > 100.0
    assert err < 0.01
    assert tw.state()["shoot_through"] == 0


def test_qei_position_counter_gives_the_speed(tw):
    tw.run(0.001)
    drive(tw, 0.7)
    tw.run(0.3)
    tw.uart_write(b"V")
    out, _ = wait_reply(tw, 2)
    counts_per_ms = int.from_bytes(out, "little", signed=True)
    w = tw.state()["speed_rad_s"]
    lines = tw.profile.sensors.encoder_lines
    expect = w * 4 * lines / (2 * math.pi) * 1e-3
    assert abs(counts_per_ms - expect) <= 1.5


def test_overcurrent_latches_flta_and_switches_the_bridge_off(tw):
    tw.run(0.001)
    drive(tw, 0.7)
    tw.run(0.05)
    assert tw.state()["outputs_active"]
    tw.inject("overcurrent", duration_s=20e-6)
    tw.run(1e-4)
    s = tw.state()
    assert s["pwm_fault_latched"] and not s["outputs_active"]        # hardware, at once
    tw.run(0.01)                                                     # comparator released, still latched
    assert not tw.state()["outputs_active"]
    tw.uart_write(b"F")
    out, _ = wait_reply(tw, 2)
    assert out == bytes([2, 1])                                      # firmware saw FLTAS
    tw.uart_write(b"C")
    tw.run(0.005)
    assert not tw.state()["pwm_fault_latched"]
    # clearing FLTAS while the comparator still asserts: the model sets it again
    tw.inject("overcurrent", duration_s=0.05)
    tw.run(1e-3)
    tw.uart_write(b"C")
    tw.run(0.005)
    assert tw.state()["pwm_fault_latched"]


def test_a_real_overcurrent_trips_the_comparator(tw):
    tw.run(0.001)
    tw.inject("lock_rotor", locked=True)
    drive(tw, 0.92)                                      # locked rotor: I = V / R_line = 2.1 A < 3 A trip
    tw.run(0.05)
    assert not tw.state()["flta_asserted"]
    tw.inject("bus_voltage", volts=96.0)                 # 4.5 A > 3 A
    tw.run(0.05)
    s = tw.state()
    assert s["pwm_fault_latched"] and not s["outputs_active"]
    assert max(abs(i) for i in s["i_abc_a"]) < tw.profile.inverter.overcurrent_trip_a * 1.2


def test_invalid_hall_code_interrupts_and_stops_the_drive(tw):
    tw.run(0.001)
    drive(tw, 0.7)
    tw.run(0.05)
    tw.inject("hall", code=0)
    tw.run(1e-3)
    assert not tw.state()["outputs_active"]
    tw.uart_write(b"F")
    out, _ = wait_reply(tw, 2)
    assert out[0] == 1
    tw.inject("hall", code=None)
    assert tw.state()["hall"] == tw.state()["hall_true"]


def test_shoot_through_is_counted(tw):
    tw.run(0.001)
    tw.uart_write(b"Z")
    tw.run(0.002)
    assert tw.state()["shoot_through"] > 0


def test_wrong_baud_rate_stops_the_twin_with_a_clear_error(tw):
    tw.run(0.001)
    tw.uart_write(b"B\x40")                     # SPBRG 64: 153.8 kbaud against the host's 115200
    tw.uart_write(b"P")
    with pytest.raises(TwinError, match="baud rate"):
        tw.run(0.01)


def test_passive_load_stops_the_rotor_at_zero(tw):
    tw.run(0.001)
    drive(tw, 0.7)
    tw.run(0.1)
    tw.set_load_torque(0.02)
    tw.uart_write(b"X")
    tw.run(0.2)
    assert tw.state()["speed_rad_s"] == 0.0


def test_record_is_sampled_exactly_and_load_profile_is_followed(tw):
    tw.run(0.001)
    drive(tw, 0.7)
    t0 = tw.t
    tw.set_load_profile([0.0, 0.05, 0.1], [0.0, 0.0, 0.01], relative=True)
    rec = tw.record(0.2, 1e-3)
    assert np.allclose(np.diff(rec["t_s"]), 1e-3, atol=1e-12)
    assert rec["t_s"][0] == pytest.approx(t0)
    tl = rec["torque_load_n_m"]
    k = np.searchsorted(rec["t_s"], t0 + 0.075)
    assert tl[k] == pytest.approx(0.005, rel=0.05)
    assert tl[-1] == pytest.approx(0.01)


def test_twins_in_one_process_are_independent():
    a, b = make_twin("duy2008"), make_twin("duy2008", perturb={"resistance": 1.1})
    drive(a, 0.8)
    a.run(0.1)
    b.run(0.1)
    assert a.state()["speed_rad_s"] > 50.0 and b.state()["speed_rad_s"] == 0.0
    assert b.model.r_phase_ohm == pytest.approx(1.1 * a.model.r_phase_ohm)
    a.close(), b.close()


def test_a_closed_twins_library_serves_the_next_twin_as_if_freshly_loaded():
    """A closed twin's loaded library goes to the next twin of the same build, its data written
    back as loaded: the same run gives the same bits as on a fresh copy; the closed twin refuses
    further calls."""
    a, b = make_twin("duy2008"), make_twin("duy2008")      # two copies loaded at once
    drive(b, 0.5)
    b.run(0.05)                                            # b's data far from its state as loaded
    libs = (a._lib, b._lib)
    loaded = b._loaded
    drive(a, 0.8)
    ref = a.record(0.03, 1e-4)
    a.close(), b.close()
    with pytest.raises(TwinError, match="closed"):
        b.state()
    # taken again, every byte of its writable data (the twin's, the firmware's) is as loaded
    again = twin_module._acquire(Path(loaded.path), False)
    assert again is loaded
    assert ctypes.string_at(loaded.data_at, len(loaded.pristine)) == loaded.pristine
    twin_module._release(again)
    c = make_twin("duy2008")
    assert c._lib is libs[1]                               # b's copy, restored
    drive(c, 0.8)
    got = c.record(0.03, 1e-4)
    c.close()
    assert ref["w_rad_s"][-1] > 10.0
    for k in ref:
        np.testing.assert_array_equal(got[k], ref[k], err_msg=k)


def test_twin_refuses_firmware_of_another_profile(tmp_path):
    from pathlib import Path
    fw = Path(__file__).resolve().parents[1] / "firmware_build" / "duy2008"
    assert (fw / "link_fw.h").exists(), "the committed firmware_build/duy2008 is missing"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ProfileWarning)
        other = load_profile("assawinchaichote2016")
    with pytest.raises(TwinError, match="another profile"):
        Twin(other, fw)


def _poscnt_diffs(tw, n):
    out, prev = [], None
    tw.run(0.0005)
    for _ in range(n):
        tw.run(1e-3)                                   # one noise period (1 / speed_loop_hz)
        p = tw.sfr("POSCNTL") | (tw.sfr("POSCNTH") << 8)
        if prev is not None:
            out.append(((p - prev + 32768) & 0xFFFF) - 32768)
        prev = p
    return np.array(out)


def test_speed_noise_is_seeded_and_has_the_requested_spread():
    """Encoder-angle jitter, redrawn every speed-loop period, whose count
    difference over one period has the requested speed standard deviation."""
    noise_rpm = 100.0
    runs = {}
    for seed in (1, 1, 2):
        t = make_twin("duy2008", speed_noise_rpm=noise_rpm, seed=seed)
        t.inject("lock_rotor", locked=True)
        runs.setdefault(seed, []).append(_poscnt_diffs(t, 400))
        t.close()
    a, b = runs[1]
    c = runs[2][0]
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    prof = load_profile("duy2008")
    counts_per_rad = 4 * prof.sensors.encoder_lines / (2 * math.pi)
    expect = noise_rpm * 2 * math.pi / 60 / prof.control.speed_loop_hz * counts_per_rad
    assert np.std(a) == pytest.approx(expect, rel=0.2)
    assert abs(np.mean(a)) < 3 * expect / math.sqrt(len(a)) + 0.5


def test_halls_through_input_capture_commutate_like_the_int_pins():
    """Halls on IC1..IC3 (RA2..RA4, capture on every state change): the same
    drive as through INT0..2, edge for edge."""
    speeds = {}
    for hall_input in ("int", "ic"):
        t = make_twin("duy2008", hall_input=hall_input)
        t.run(0.001)
        drive(t, 0.7)
        t.run(0.2)
        speeds[hall_input] = t.state()["speed_rad_s"]
        if hall_input == "ic":
            t.uart_write(b"H")
            out, _ = wait_reply(t, 2)
            edges = int.from_bytes(out, "little")
            # six hall edges per electrical revolution
            revs_e = t.state()["angle_rad"] * t.profile.motor.pole_pairs / (2 * math.pi)
            assert abs(edges - 6 * revs_e) <= 2
            assert t.sfr("CAP1BUFL") | t.sfr("CAP1BUFH") | t.sfr("CAP2BUFL") | t.sfr("CAP3BUFL")   # TMR5 captured
        t.close()
    assert speeds["int"] > 100.0
    assert speeds["ic"] == pytest.approx(speeds["int"], rel=0.01)


QEI_INDEX_FW = r"""
#include <xc.h>
#include <stdint.h>
/* the QEI alone: x4 update, position counter reset by the index pulse */
void fw_init(void) { ANSEL0 = 0; MAXCNTL = 0xFF; MAXCNTH = 0xFF; QEICON = (uint8_t)(5u << 2); }
void fw_poll(void) {}
void fw_isr_high(void) {}
void fw_isr_low(void) {}
"""


def test_qei_index_mode_counts_from_the_last_index_both_ways(tmp_path):
    """QEI in x4 index-reset mode against the true encoder count, the rotor turned
    several revolutions forward, then backward: POSCNT is the count since the last
    index pulse (forward: n mod 4 lines; backward: it wraps below the index,
    MAXCNT = 0xFFFF), IC2QEIF is set at the index and UP_DOWN follows the
    direction; the INDX pin (RA2) is high exactly on the index count."""
    from picdrive.firmware import p18f4431
    from picdrive_hil import build
    from picdrive_hil.twin import BoardConfig, shim_dir
    src = tmp_path / "qeifw.c"
    src.write_text(QEI_INDEX_FW)
    fw = build.Group((src,), (shim_dir(),), ("-std=c99", "-O2", "-Wall", "-Werror"))
    tw = Twin("duy2008", firmware=fw, board=BoardConfig(), speed_noise_rpm=0.0)
    bits = p18f4431.bits()
    cpr = 4 * tw.profile.sensors.encoder_lines

    def poscnt():
        return tw.sfr("POSCNTL") | (tw.sfr("POSCNTH") << 8)

    def turn(w, seconds):
        for _ in range(int(round(seconds / 1e-3))):
            tw.set_plant_state(w)        # held against friction (the bridge is off)
            tw.run(1e-3)
        tw.set_plant_state(0.0)          # standing: the next main-loop pass sees the final count
        tw.run(2e-3)
        return tw.state()["encoder_count"]

    tw.run(1e-3)
    n = turn(50.0, 0.4)                  # ~3.2 revolutions forward
    assert n > 3 * cpr
    assert poscnt() == n % cpr
    assert tw.sfr("PIR3") >> bits["PIR3"]["IC2QEIF"] & 1
    assert tw.sfr("QEICON") >> bits["QEICON"]["UP_DOWN"] & 1
    n = turn(-50.0, 0.25)                # ~2 revolutions back
    assert 0 < n < 2 * cpr and n % cpr != 0
    assert poscnt() == (n % cpr - cpr) & 0xFFFF
    assert not tw.sfr("QEICON") >> bits["QEICON"]["UP_DOWN"] & 1
    # the INDX pin: park the rotor on an index count and next to it
    for k, want in ((0, 1), (1, 0), (-1, 0), (0, 1)):
        tw.set_plant_state(0.0, (cpr + k + 0.5) * 2 * math.pi / cpr)
        tw.run(2e-3)
        assert tw.state()["encoder_count"] == cpr + k
        assert tw.sfr("PORTA") >> 2 & 1 == want
    tw.close()


PWM_UDIS_FW = r"""
#include <xc.h>
#include <stdint.h>
/* PCPWM at PTPER 499, PWM0..5 complementary, duty 800/2000; the hall pins (RC3..RC5)
   sequence the test: code 1 sets UDIS, 2 writes PDC0 = 1200, 3 clears UDIS */
void fw_init(void)
{
    PTPERL = (uint8_t)499u; PTPERH = (uint8_t)(499u >> 8);
    PDC0L = (uint8_t)800u; PDC0H = (uint8_t)(800u >> 8);
    OVDCOND = 0xFF;
    PWMCON0 = 0x40;
    PTCON0 = 0;
    PTCON1 = 0x80;
}
void fw_poll(void)
{
    uint8_t code = (uint8_t)((PORTC >> 3) & 7u);
    if (code == 1u) PWMCON1bits.UDIS = 1;
    if (code == 2u) { PDC0L = (uint8_t)1200u; PDC0H = (uint8_t)(1200u >> 8); }
    if (code == 3u) PWMCON1bits.UDIS = 0;
}
void fw_isr_high(void) {}
void fw_isr_low(void) {}
"""


def test_pcpwm_duty_buffer_waits_for_udis_cleared_in_a_later_call(tmp_path):
    """A duty written while UDIS is set (in another firmware call) reaches the
    output only at the first period boundary after UDIS is cleared; a duty written
    with UDIS clear at the next boundary."""
    from picdrive_hil import build
    from picdrive_hil.twin import BoardConfig, shim_dir
    src = tmp_path / "udisfw.c"
    src.write_text(PWM_UDIS_FW)
    fw = build.Group((src,), (shim_dir(),), ("-std=c99", "-O2", "-Wall", "-Werror"))
    tw = Twin("duy2008", firmware=fw, board=BoardConfig(), speed_noise_rpm=0.0)
    tw.inject("lock_rotor", locked=True)
    tw.inject("hall", code=0)
    tw.run(2e-3)
    assert tw.state()["duty"][0] == pytest.approx(0.4)
    tw.inject("hall", code=1)            # UDIS = 1
    tw.run(2e-3)
    tw.inject("hall", code=2)            # PDC0 = 1200, buffered
    tw.run(3e-3)
    assert tw.state()["duty"][0] == pytest.approx(0.4)
    tw.inject("hall", code=3)            # UDIS = 0: loads at the next period
    tw.run(2e-3)
    assert tw.state()["duty"][0] == pytest.approx(0.6)
    assert tw.sfr("PWMCON1") & 0x02 == 0
    tw.close()


def test_generated_firmware_with_halls_on_the_capture_pins_starts_and_runs(tmp_path):
    """The documented no-encoder option (halls on IC1..IC3 = RA2..RA4, also AN2..AN4): the
    firmware reads the halls right after making the pins digital (ANSEL0); that read must see
    the pins then, not the analog 0 of the start of its init call."""
    from picdrive.firmware import codegen
    from picdrive.link import protocol as P
    from test_codegen import fixture_design, profile_file
    prof = load_profile(profile_file(tmp_path, "halls-ic", encoder_lines="0", speed_source='"hall"'))
    fw = codegen.generate(prof, fixture_design(tmp_path, prof), hall_input="ic")
    out = codegen.write_firmware(fw, tmp_path / "fw", check=False)
    tw = Twin(prof, out)
    try:
        tw.run(0.01)
        assert tw.state()["hall"] in (1, 2, 3, 4, 5, 6)
        command(tw, "set_speed", 1, {"value": fw.table["speed_setpoint"].to_raw(1000.0)})
        command(tw, "start", 2)
        for seq in range(3, 13):                       # 0.2 s, heartbeats feed the board's watchdog
            command(tw, "heartbeat", seq)
            tw.run(0.02)
        st = command(tw, "status", 20)
        assert st["fault"] == P.Fault.NONE and st["state"] == P.State.RUN
        assert tw.state()["speed_rpm"] > 300.0
    finally:
        tw.close()
