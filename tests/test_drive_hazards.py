"""The chip-only hazards of the drive firmware (docs/firmware.md), shown on the host build of
the committed firmware (firmware_build/duy2008) with a tracing register shim.

The twin's shim makes every SFR a byte of picsim_sfr[] and the model sees the
registers only between firmware calls.  Here every SFR access goes through
picsim_trace(): it returns a fresh slot holding the register's value and, at
the next access, commits what the firmware wrote into the previous slot and
logs it.  So the log holds every write in program order and every state the
registers pass through, which is what a PWM period boundary (OSYNC) or a pin
sees on the chip:

- (c) after a warm reset (LATB still 0x3F from before, PWM pins plain I/O), no
  state during fw_init drives both inputs of a leg;
- (d) over all 60 transitions between valid hall codes (both directions,
  one- and two-sector jumps), no intermediate (OVDCOND, OVDCONS) pair turns on
  both switches of a leg;
- (e) the speed loop captures POSCNT/Timer5 before any ADC access, with the
  high priority masked;
- (f) the bus current is converted by the PCPWM special event at mid on-time
  (SEVTCMP = PDC / 8, ADCON3.SSRC4), never by a software start;
- (g) fw_lock masks both priorities and nests;
- (h) an encoder speed above 1.2 x speed_max_rpm latches LINK_FAULT_OVERSPEED
  with the outputs off.

PICDRIVE_HAZARD_FW=<folder> runs the same tests on another generated folder
(used to show that each fails on the firmware before these fixes).
"""
import ctypes as C
import os
import re
import subprocess
from pathlib import Path

import pytest

from picdrive.firmware import codegen, p18f4431
from picdrive.link import protocol
from picdrive.paths import firmware_build_dir

FOLDER = Path(os.environ.get("PICDRIVE_HAZARD_FW", firmware_build_dir() / "duy2008"))

TRACE = r"""
#include <string.h>
#include "xc.h"
volatile uint8_t picsim_sfr[256];
uint8_t stub_ee[256];
/* the log: kind 1 = access, 2 = committed write (value) */
#define LOG_N 200000
uint8_t log_kind[LOG_N], log_idx[LOG_N], log_val[LOG_N];
int log_n;
static volatile uint8_t slot[32];
static uint8_t slot_idx[32], slot_snap[32], slot_used[32];
static unsigned slot_next;
static void log_add(uint8_t k, uint8_t i, uint8_t v)
{
    if (log_n < LOG_N) { log_kind[log_n] = k; log_idx[log_n] = i; log_val[log_n] = v; log_n++; }
}
void trace_flush(void)
{
    unsigned k;
    for (k = 0; k < 32u; k++) {
        if (slot_used[k] && slot[k] != slot_snap[k]) {
            picsim_sfr[slot_idx[k]] = slot[k];
            slot_snap[k] = slot[k];
            log_add(2, slot_idx[k], slot[k]);
        }
    }
}
volatile uint8_t *picsim_trace(uint8_t i)
{
    unsigned k;
    trace_flush();
    k = slot_next++ & 31u;
    slot_idx[k] = i;
    slot[k] = slot_snap[k] = picsim_sfr[i];
    slot_used[k] = 1;
    log_add(1, i, 0);
    return &slot[k];
}
uint16_t picsim_trace_addr(volatile uint8_t *p)
{
    trace_flush();
    return (uint16_t)(PICSIM_SFR_BASE + slot_idx[p - slot]);
}
void trace_reset(uint8_t latb)
{
    memset((void *)picsim_sfr, 0, sizeof picsim_sfr);
    memset(slot_used, 0, sizeof slot_used);
    log_n = 0;
    picsim_sfr[PICSIM_ADDR_TRISA - PICSIM_SFR_BASE] = 0xFF;
    picsim_sfr[PICSIM_ADDR_TRISB - PICSIM_SFR_BASE] = 0xFF;
    picsim_sfr[PICSIM_ADDR_TRISC - PICSIM_SFR_BASE] = 0xFF;
    picsim_sfr[PICSIM_ADDR_OVDCOND - PICSIM_SFR_BASE] = 0xFF;
    picsim_sfr[PICSIM_ADDR_LATB - PICSIM_SFR_BASE] = latb;     /* latches keep their value over a warm reset */
    memset(stub_ee, 0xFF, sizeof stub_ee);
}
void picsim_sfr_written(uint16_t addr)
{
    uint8_t i = (uint8_t)(addr - PICSIM_SFR_BASE);
    if (addr == PICSIM_ADDR_ADCON0 && (picsim_sfr[i] & PICSIM_ADCON0_GO_DONE_MASK)) {
        uint16_t v = ((picsim_sfr[i] >> 2) & 1) ? 512u : 0u;     /* AN1 nominal bus, AN0 no current */
        picsim_sfr[PICSIM_ADDR_ADRESH - PICSIM_SFR_BASE] = (uint8_t)(v >> 8);
        picsim_sfr[PICSIM_ADDR_ADRESL - PICSIM_SFR_BASE] = (uint8_t)v;
        picsim_sfr[i] = (uint8_t)(picsim_sfr[i] & ~PICSIM_ADCON0_GO_DONE_MASK);
    } else if (addr == PICSIM_ADDR_EECON1) {
        uint8_t c = picsim_sfr[i];
        uint8_t a = picsim_sfr[PICSIM_ADDR_EEADR - PICSIM_SFR_BASE];
        if (c & PICSIM_EECON1_RD_MASK) {
            picsim_sfr[PICSIM_ADDR_EEDATA - PICSIM_SFR_BASE] = stub_ee[a];
        }
        if ((c & PICSIM_EECON1_WR_MASK) && (c & PICSIM_EECON1_WREN_MASK)) {
            stub_ee[a] = picsim_sfr[PICSIM_ADDR_EEDATA - PICSIM_SFR_BASE];
        }
        picsim_sfr[i] = (uint8_t)(c & ~(PICSIM_EECON1_RD_MASK | PICSIM_EECON1_WR_MASK));
    }
}
void picsim_sfr_read(uint16_t addr) { (void)addr; }
"""

REG = p18f4431.registers()
BITS = p18f4431.bits()


def idx(name):
    return REG[name] - 0xF00


def traced_shim(text: str) -> str:
    """The host shim with every SFR access routed through picsim_trace()."""
    text = re.sub(r"\(picsim_sfr\[(0x[0-9A-F]{2})\]\)", r"(*picsim_trace(\1))", text)
    text = re.sub(r"&picsim_sfr\[(0x[0-9A-F]{2})\]", r"picsim_trace(\1)", text)
    text = text.replace("#define PICSIM_ADDR_OF(reg) ((uint16_t)(PICSIM_SFR_BASE + (uint16_t)(&(reg) - &picsim_sfr[0])))",
                        "volatile uint8_t *picsim_trace(uint8_t i);\nuint16_t picsim_trace_addr(volatile uint8_t *p);\n"
                        "#define PICSIM_ADDR_OF(reg) picsim_trace_addr(&(reg))")
    assert "picsim_trace_addr(&(reg))" in text and "picsim_sfr[0x" not in text
    return text


@pytest.fixture(scope="module")
def fw(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("hazards")
    hb = codegen.host_build(FOLDER)
    shim = tmp / "shim"
    shim.mkdir()
    (shim / "xc.h").write_text(traced_shim((FOLDER / "host" / "xc.h").read_text()))
    (tmp / "trace.c").write_text(TRACE)
    lib = tmp / "libhaz.so"
    subprocess.run(["gcc", "-std=c99", "-O1", "-shared", "-fPIC", f"-I{shim}", f"-I{FOLDER}", *hb["sources"],
                    str(tmp / "trace.c"), "-o", str(lib)], check=True, capture_output=True, text=True)
    return Board(C.CDLL(str(lib)))


class Board:
    def __init__(self, lib):
        self.lib = lib
        self.sfr = (C.c_uint8 * 256).in_dll(lib, "picsim_sfr")
        self.log_n = C.c_int.in_dll(lib, "log_n")
        self.kind = (C.c_uint8 * 200000).in_dll(lib, "log_kind")
        self.lidx = (C.c_uint8 * 200000).in_dll(lib, "log_idx")
        self.lval = (C.c_uint8 * 200000).in_dll(lib, "log_val")
        lib.app_command.argtypes = [C.c_uint8, C.c_void_p, C.c_uint8]
        lib.app_command.restype = C.c_uint8
        lib.app_signal.argtypes = [C.c_uint8]
        lib.app_signal.restype = C.c_int16
        lib.link_param_set.argtypes = [C.c_uint8, C.c_int32]
        lib.link_param_set.restype = C.c_uint8
        lib.trace_reset.argtypes = [C.c_uint8]

    def call(self, f, *a):
        r = getattr(self.lib, f)(*a)
        self.lib.trace_flush()
        return r

    def r(self, name):
        return self.sfr[idx(name)]

    def w(self, name, v):
        self.sfr[idx(name)] = v

    def setbit(self, reg, bit):
        self.w(reg, self.r(reg) | 1 << BITS[reg][bit])

    def bit(self, reg, bit):
        return self.r(reg) >> BITS[reg][bit] & 1

    def clear_log(self):
        self.log_n.value = 0

    def log(self):
        n = self.log_n.value
        return [(self.kind[k], self.lidx[k], self.lval[k]) for k in range(n)]

    def reset(self, latb=0x00):
        self.lib.trace_reset(latb)
        self.set_hall(0b101, irq=False)
        self.call("fw_init")

    def set_hall(self, code, irq=True):
        self.w("PORTC", (self.r("PORTC") & ~0x38 & 0xFF) | code << 3)
        if irq:
            self.setbit("INTCON", "INT0IF")
            self.call("fw_isr_high")

    def tick(self):
        self.setbit("PIR1", "TMR2IF")
        self.call("fw_isr_low")

    def cmd(self, name):
        return self.call("app_command", protocol.COMMAND_BY_NAME[name].code, None, 0)

    def param(self, pid, raw):
        return self.call("link_param_set", pid, raw)

    def sig(self, sig_index):
        return self.call("app_signal", sig_index)


def _fw_defines():
    text = (FOLDER / "drive_params.h").read_text() + (FOLDER / "link_fw.h").read_text()
    text = re.sub(r"/\*.*?\*/", " ", text, flags=re.S)
    return {m.group(1): m.group(2).strip() for m in re.finditer(r"#define (\w+) (.+)", text)}


def _int(v):
    return int(v.rstrip("uU"), 0)


DEF = _fw_defines()


def _link_id(name):
    return _int(DEF[f"LINK_ID_{name.upper()}"])


def _sig(name):
    return _int(DEF[f"LINK_SIG_{name.upper()}"])


def legs_shorted(regs):
    """Legs (0..2) whose high and low switch may both be on in this register state.

    PWM2k is the low side, PWM2k+1 the high side of leg k (FW_OVDCONS_BRAKE =
    PWM0/2/4 low sides).  A pin the PCPWM drives (PWMEN) is on when its
    override is off and OVDCONS forces it on, or when its override lets the
    duty through and the time base runs; a plain I/O pin is on when it is an
    output with its latch high."""
    pwmen = regs[idx("PWMCON0")] >> 4 & 7
    pten = regs[idx("PTCON1")] >> 7 & 1
    cond, cons = regs[idx("OVDCOND")], regs[idx("OVDCONS")]
    tris, lat = regs[idx("TRISB")], regs[idx("LATB")]
    on = []
    for n in range(6):
        if pwmen != 0:
            on.append(bool(cond >> n & 1 and pten) or bool(not cond >> n & 1 and cons >> n & 1))
        else:
            on.append(not tris >> n & 1 and bool(lat >> n & 1))
    return [k for k in range(3) if on[2 * k] and on[2 * k + 1]]


def replay(start, log):
    """Every register state the log passes through (after each committed write)."""
    regs = list(start)
    for kind, i, v in log:
        if kind == 2:
            regs[i] = v
            yield list(regs)


def test_warm_reset_never_drives_both_inputs_of_a_leg(fw):
    """(c): LATB holds 0x3F (all six driver inputs high) from before a warm reset."""
    fw.lib.trace_reset(0x3F)
    fw.set_hall(0b101, irq=False)
    start = list(fw.sfr)
    fw.call("fw_init")
    states = list(replay(start, fw.log()))
    assert len(states) > 20
    bad = [(k, legs_shorted(s)) for k, s in enumerate(states) if legs_shorted(s)]
    assert bad == [], f"states during fw_init with both switches of a leg on: {bad[:3]}"
    # and the outputs end up off and the PWM pins outputs
    assert fw.r("TRISB") & 0x3F == 0 and fw.r("OVDCOND") == 0 and fw.r("OVDCONS") == 0


def _valid_codes():
    mask = _int(DEF["FW_HALL_VALID_MASK"])
    return [c for c in range(8) if mask >> c & 1]


def _run_in(fw, direction):
    """RUN with the table of one direction applied (reverse: through the law's sign change)."""
    fw.reset()
    fw.param(_link_id("stall_timeout"), 60000)
    fw.param(_link_id("link_timeout"), 60000)
    assert fw.cmd("start") == 0
    sp = 10000 if direction == 0 else -10000             # +-1490 rpm
    assert fw.param(_link_id("speed_setpoint"), sp) == 0
    for _ in range(400):
        fw.tick()
        u = fw.sig(_sig("voltage"))
        if (u > 0) if direction == 0 else (u < 0):
            break
    fw.tick()
    assert fw.sig(_sig("state")) == protocol.State.RUN
    assert (fw.sig(_sig("duty")) > 0) == (direction == 0)


def test_every_hall_transition_changes_the_override_without_a_shorted_leg(fw):
    """(d): with OSYNC any pair of (OVDCOND, OVDCONS) values the firmware leaves
    between its writes may be applied at a PWM period boundary."""
    codes = _valid_codes()
    assert len(codes) == 6
    checked, bad = 0, []
    for direction in (0, 1):
        _run_in(fw, direction)
        for a in codes:
            for b in codes:
                if a == b:
                    continue
                fw.set_hall(a)
                assert fw.r("OVDCOND") | fw.r("OVDCONS") != 0, "the table is applied"
                start = list(fw.sfr)
                fw.clear_log()
                fw.set_hall(b)
                states = list(replay(start, fw.log()))
                shorted = [legs_shorted(s) for s in states if legs_shorted(s)]
                if shorted:
                    bad.append((direction, a, b, shorted[0]))
                checked += 1
    assert checked == 60
    assert bad == [], f"{len(bad)} of 60 transitions pass through a shorted leg, e.g. {bad[:4]}"


def test_speed_loop_captures_the_speed_sensor_first_with_the_high_priority_masked(fw):
    """(e)"""
    fw.reset()
    assert fw.cmd("start") == 0
    fw.tick()
    start = list(fw.sfr)
    fw.clear_log()
    fw.tick()
    log = fw.log()
    sensor = {idx("POSCNTL"), idx("POSCNTH"), idx("TMR5L"), idx("TMR5H")}
    first_sensor = next(k for k, (kind, i, _) in enumerate(log) if kind == 1 and i in sensor)
    first_adc = next(k for k, (kind, i, _) in enumerate(log) if kind == 1 and i in (idx("ADCON0"), idx("ADRESH"),
                                                                                    idx("ADRESL")))
    assert first_sensor < first_adc, "an ADC conversion runs before the speed sample"
    # GIEH is clear from before the first sensor read to after the last one of that capture
    regs = list(start)
    for kind, i, v in log[:first_sensor]:
        if kind == 2:
            regs[i] = v
    assert regs[idx("INTCON")] >> BITS["INTCON"]["GIEH"] & 1 == 0, "a hall/RX interrupt can delay the capture"


def test_fw_lock_masks_both_priorities_and_nests(fw):
    """(g)"""
    fw.reset()
    assert fw.bit("INTCON", "GIEH") == 1 and fw.bit("INTCON", "GIEL") == 1
    fw.call("fw_lock")
    assert fw.bit("INTCON", "GIEH") == 0 and fw.bit("INTCON", "GIEL") == 0
    fw.call("fw_lock")
    fw.call("fw_unlock")
    assert fw.bit("INTCON", "GIEH") == 0 and fw.bit("INTCON", "GIEL") == 0, "the inner unlock re-enabled"
    fw.call("fw_unlock")
    assert fw.bit("INTCON", "GIEH") == 1 and fw.bit("INTCON", "GIEL") == 1


def _spin(fw, counts_per_ms, samples):
    """Encoder counts per speed-loop sample (Timer5 restarted at each count: reads 0)."""
    pos = fw.r("POSCNTL") | fw.r("POSCNTH") << 8
    for _ in range(samples):
        pos = (pos + counts_per_ms) & 0xFFFF
        fw.w("POSCNTL", pos & 0xFF)
        fw.w("POSCNTH", pos >> 8)
        fw.w("TMR5L", 0)
        fw.w("TMR5H", 0)
        fw.tick()


def test_overspeed_latches_a_fault_with_the_outputs_off(fw):
    """(h): 1.2 x speed_max_rpm.  counts/ms = rpm x 4 lines / 60000."""
    from picdrive.profile import load_profile
    prof = load_profile("duy2008")
    cpr = 4 * prof.sensors.encoder_lines
    trip_rpm = 1.2 * prof.control.speed_max_rpm
    below = int(0.97 * trip_rpm * cpr / 60000)
    above = int(1.05 * trip_rpm * cpr / 60000) + 1
    fw.reset()
    fw.param(_link_id("stall_timeout"), 60000)
    fw.param(_link_id("link_timeout"), 60000)
    assert fw.cmd("start") == 0
    assert fw.param(_link_id("speed_setpoint"), 1000) == 0
    _spin(fw, below, 5)
    assert fw.sig(_sig("state")) == protocol.State.RUN, "tripped below the limit"
    _spin(fw, above, 3)
    assert fw.sig(_sig("state")) == protocol.State.FAULT
    assert fw.sig(_sig("fault")) == 8 == int(protocol.Fault.OVERSPEED)
    assert fw.r("OVDCOND") == 0 and fw.r("OVDCONS") == 0


def test_bus_current_is_converted_at_mid_on_time_by_the_special_event(fw):
    """(f): a software start of the current channel samples the shunt at whatever PWM phase the
    interrupt lands on (on-time current or zero); the special event samples it at mid on-time."""
    _run_in(fw, 0)
    start = list(fw.sfr)
    fw.clear_log()
    fw.tick()
    group = BITS["ADCON0"]["ACMOD0"]
    go = BITS["ADCON0"]["GO_DONE"] if "GO_DONE" in BITS["ADCON0"] else BITS["ADCON0"]["GO"]
    starts = [s[idx("ADCON0")] >> group & 3 for s in replay(start, fw.log())
              if s[idx("ADCON0")] >> go & 1]
    assert starts and 0 not in starts, f"software starts of group A (AN0, the bus current): {starts}"
    # after the sample: group A selected, the PCPWM special event starts its conversions ...
    assert fw.r("ADCON0") >> group & 3 == 0 and fw.r("ADCON0") >> BITS["ADCON0"]["ADON"] & 1
    assert fw.r("ADCON3") >> BITS["ADCON3"]["SSRC4"] & 1, "ADCON3.SSRC4: the special event starts the A/D"
    # ... once per PWM period, counting up, at mid on-time of the duty just written
    assert fw.r("PWMCON1") >> 3 & 0x1F == 0, "SEVOPS 1:1 and SEVTDIR = 0 (up)"
    pdc = fw.r("PDC0L") | fw.r("PDC0H") << 8
    sev = fw.r("SEVTCMPL") | fw.r("SEVTCMPH") << 8
    assert pdc > 0 and sev == pdc >> 3, (pdc, sev)
