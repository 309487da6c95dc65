"""The generated firmware run on the host against the register shim and a small
peripheral stub (no plant): initialisation values, six-step commutation from
the hall interrupt, the speed loop writing duty, direction reversal through an
all-off sample, brake, every fault path, the serial link (hello over the
EUSART registers) and EEPROM persistence.

The design is the bundled duy2008 fuzzy-hinf design when it is present and
verified; otherwise a test-fixture law (labelled in the generated header).
"""
import ctypes as C
import struct
import subprocess

import pytest

from picdrive.link import codec, protocol
from picdrive.firmware import codegen
from picdrive.profile import load_profile
from picdrive.result import load_design
from picdrive.paths import repo_root

STUB = r"""
#include <string.h>
#include "xc.h"
volatile uint8_t picsim_sfr[256];
uint8_t stub_ee[256];
uint16_t stub_adc[2];
uint8_t stub_tx[4096];
int stub_tx_n;
int stub_written[256], stub_read[256];
static uint8_t idx(uint16_t a) { return (uint8_t)(a - PICSIM_SFR_BASE); }
void stub_reset(void)
{
    memset((void *)picsim_sfr, 0, sizeof picsim_sfr);
    memset(stub_written, 0, sizeof stub_written);
    memset(stub_read, 0, sizeof stub_read);
    stub_tx_n = 0;
}
void stub_ee_blank(void) { memset(stub_ee, 0xFF, sizeof stub_ee); }
void picsim_sfr_written(uint16_t addr)
{
    uint8_t i = idx(addr);
    stub_written[i]++;
    if (addr == PICSIM_ADDR_TXREG) {
        if (stub_tx_n < 4096) stub_tx[stub_tx_n++] = picsim_sfr[i];
    } else if (addr == PICSIM_ADDR_ADCON0 && (picsim_sfr[i] & PICSIM_ADCON0_GO_DONE_MASK)) {
        int ch = (picsim_sfr[i] >> 2) & 3;          /* ACMOD: group A (AN0) or B (AN1) */
        uint16_t v = stub_adc[ch & 1];
        picsim_sfr[idx(PICSIM_ADDR_ADRESH)] = (uint8_t)(v >> 8);
        picsim_sfr[idx(PICSIM_ADDR_ADRESL)] = (uint8_t)v;
        picsim_sfr[i] = (uint8_t)(picsim_sfr[i] & ~PICSIM_ADCON0_GO_DONE_MASK);
    } else if (addr == PICSIM_ADDR_EECON1) {
        uint8_t c = picsim_sfr[i];
        uint8_t a = picsim_sfr[idx(PICSIM_ADDR_EEADR)];
        if (c & PICSIM_EECON1_RD_MASK) {
            picsim_sfr[idx(PICSIM_ADDR_EEDATA)] = stub_ee[a];
            picsim_sfr[i] = (uint8_t)(c & ~PICSIM_EECON1_RD_MASK);
        }
        if (c & PICSIM_EECON1_WR_MASK) {
            if (c & PICSIM_EECON1_WREN_MASK) stub_ee[a] = picsim_sfr[idx(PICSIM_ADDR_EEDATA)];
            picsim_sfr[i] = (uint8_t)(picsim_sfr[i] & ~PICSIM_EECON1_WR_MASK);
        }
    }
}
void picsim_sfr_read(uint16_t addr) { stub_read[idx(addr)]++; }
"""

RPM = 3.141592653589793 / 30


@pytest.fixture(scope="module")
def fw(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("fwhost")
    prof = load_profile("duy2008")
    design = repo_root() / "examples" / "duy2008.fuzzy-hinf.design.json"
    load_design(design, require_usable=True, profile=prof)      # the committed design; stale or missing fails
    f = codegen.generate(prof, design)
    out = codegen.write_firmware(f, tmp / "fw", check=False)
    (out / "host" / "stub.c").write_text(STUB)
    hb = codegen.host_build(out)
    lib = tmp / "libfw.so"
    subprocess.run(["gcc", "-std=c99", "-O1", "-shared", "-fPIC", *[f"-I{d}" for d in hb["include_dirs"]],
                    *hb["sources"], str(out / "host" / "stub.c"), "-o", str(lib)],
                   check=True, capture_output=True, text=True)
    d = C.CDLL(str(lib))
    d.app_command.argtypes = [C.c_uint8, C.c_void_p, C.c_uint8]
    d.app_command.restype = C.c_uint8
    d.app_signal.argtypes = [C.c_uint8]
    d.app_signal.restype = C.c_int16
    d.link_param_set.argtypes = [C.c_uint8, C.c_int32]
    d.link_param_set.restype = C.c_uint8
    d.link_param_get.argtypes = [C.c_uint8]
    d.link_param_get.restype = C.c_int32
    d.link_eeprom_save.restype = C.c_uint8
    d.link_eeprom_load.restype = C.c_uint8
    d.link_rx_byte.argtypes = [C.c_uint8]
    return Board(d, f, prof)


class Board:
    def __init__(self, lib, fwobj, prof):
        self.lib, self.fw, self.prof = lib, fwobj, prof
        self.sfr = (C.c_uint8 * 256).in_dll(lib, "picsim_sfr")
        self.adc = (C.c_uint16 * 2).in_dll(lib, "stub_adc")
        self.regs = __import__("picdrive.firmware.p18f4431", fromlist=["x"]).registers()
        self.bits = __import__("picdrive.firmware.p18f4431", fromlist=["x"]).bits()
        self.table = fwobj.table
        self.plan = fwobj.plan

    # registers
    def r(self, name):
        return self.sfr[self.regs[name] - 0xF00]

    def w(self, name, v):
        self.sfr[self.regs[name] - 0xF00] = v

    def setbit(self, reg, bit, v=1):
        m = 1 << self.bits[reg][bit]
        self.w(reg, (self.r(reg) | m) if v else (self.r(reg) & ~m & 0xFF))

    def bit(self, reg, bit):
        return self.r(reg) >> self.bits[reg][bit] & 1

    # board actions
    def reset(self):
        self.lib.stub_reset()
        self.lib.stub_ee_blank()
        self.adc[0] = 0
        self.adc[1] = 512                 # nominal bus: 2.5 V at the ADC
        self.set_hall(0b101, irq=False)
        self.lib.fw_init()

    def set_hall(self, code, irq=True):
        pc = self.r("PORTC") & ~0x38 & 0xFF
        self.w("PORTC", pc | (code << 3))
        if irq:
            self.setbit("INTCON", "INT0IF")
            self.lib.fw_isr_high()

    def tick(self, n=1):
        for _ in range(n):
            if self.r("ADCON3") & 0x10:          # SSRC4: the PCPWM special event converted AN0 meanwhile
                self.w("ADRESH", self.adc[0] >> 8)
                self.w("ADRESL", self.adc[0] & 0xFF)
            self.setbit("PIR1", "TMR2IF")
            self.lib.fw_isr_low()
            self.lib.fw_poll()                   # the main loop runs between interrupts

    def cmd(self, name):
        return self.lib.app_command(protocol.COMMAND_BY_NAME[name].code, None, 0)

    def sig(self, name):
        return self.lib.app_signal(self.table.signal_index(name))

    def param(self, name, raw):
        return self.lib.link_param_set(self.table[name].id, raw)

    def outputs(self):
        return self.r("OVDCOND"), self.r("OVDCONS")

    def duty(self):
        return [self.r(f"PDC{k}L") | self.r(f"PDC{k}H") << 8 for k in range(3)]


def test_init_programs_the_peripherals(fw):
    fw.reset()
    per = fw.fw.pwm.period
    assert fw.r("PTPERL") | fw.r("PTPERH") << 8 == per.ptper
    # the fields by their data-sheet meaning (DS39616 section 18), not the byte codegen writes
    pwmen = sum(fw.bit("PWMCON0", f"PWMEN{k}") << k for k in range(3))
    pmod = sum(fw.bit("PWMCON0", f"PMOD{k}") << k for k in range(4))
    assert pwmen == 0b100                       # PWM0-PWM5 are PWM outputs
    assert pmod == 0b0111                       # pairs 0-2 independent (six-step by override), pair 3 unused
    assert fw.bit("PWMCON1", "OSYNC") == 1 and fw.bit("PWMCON1", "UDIS") == 0   # overrides at the period
    assert fw.r("DTCON") == fw.fw.pwm.dead.dtcon
    assert fw.bit("PTCON1", "PTEN") == 1
    assert fw.bit("FLTCONFIG", "FLTAEN") == 1 and fw.bit("FLTCONFIG", "FLTCON") == 1   # FLTA drives all outputs off
    assert fw.bit("FLTCONFIG", "FLTAMOD") == 0  # latched until cleared (cycle-by-cycle would let it restart)
    assert fw.outputs() == (0, 0) and fw.duty() == [0, 0, 0]
    assert fw.r("PR2") == fw.plan.pr2 and fw.bit("T2CON", "TMR2ON") == 1
    assert fw.bit("RCON", "IPEN") == 1 and fw.bit("INTCON", "GIEH") == 1 and fw.bit("INTCON", "GIEL") == 1
    assert fw.bit("INTCON", "INT0IE") == 1 and fw.bit("INTCON3", "INT1IP") == 1
    assert fw.bit("PIE1", "RCIE") == 1 and fw.bit("IPR1", "RCIP") == 1 and fw.bit("IPR1", "TMR2IP") == 0
    assert fw.r("QEICON") & 0x9C == 0x18        # VELM = 0, QEIM = 110
    brg, _ = codegen.uart_brg(fw.prof.uart.baud)
    assert fw.r("SPBRG") | fw.r("SPBRGH") << 8 == brg and fw.bit("BAUDCON", "BRG16") == 1
    assert fw.sig("state") == protocol.State.IDLE and fw.sig("fault") == 0
    # hall A is high now (code 101): the edge interrupt waits for the falling edge
    assert fw.bit("INTCON2", "INTEDG0") == 0 and fw.bit("INTCON2", "INTEDG1") == 1


def test_run_commutates_and_drives_duty(fw):
    fw.reset()
    t = fw.fw.pwm.table
    assert fw.cmd("start") == 0 and fw.sig("state") == protocol.State.RUN
    fw.param("speed_setpoint", fw.table["speed_setpoint"].to_raw(1000.0))
    fw.tick(3)
    d = fw.duty()
    assert d[0] > 0 and d[0] == d[1] == d[2] and d[0] <= fw.fw.pwm.pdc_max
    assert fw.sig("voltage") > 0 and fw.sig("duty") == d[0]
    for code in (0b001, 0b011, 0b010, 0b110, 0b100, 0b101):      # forward rotation
        fw.set_hall(code)
        assert fw.outputs() == (t.ovdcond[0][code], t.ovdcons[0][code]), code
        assert fw.sig("hall") == code
    # the edge detector follows the pins
    assert fw.bit("INTCON2", "INTEDG0") == 0      # A high in 101
    fw.tick()
    assert fw.outputs() == (t.ovdcond[0][0b101], t.ovdcons[0][0b101])


def test_reversal_passes_through_an_all_off_sample(fw):
    fw.reset()
    fw.param("stall_timeout", 60000)
    fw.param("link_timeout", 60000)
    t = fw.fw.pwm.table
    fw.cmd("start")
    fw.param("speed_setpoint", fw.table["speed_setpoint"].to_raw(500.0))
    fw.tick(2)
    assert fw.sig("voltage") > 0
    assert fw.outputs() == (t.ovdcond[0][0b101], t.ovdcons[0][0b101])
    fw.param("speed_setpoint", fw.table["speed_setpoint"].to_raw(-500.0))
    for _ in range(20000):                  # the law's own pace (a b = 0 law unwinds its integrator)
        fw.tick()
        if fw.sig("voltage") < 0:
            break
    assert fw.sig("voltage") < 0 and fw.sig("state") == protocol.State.RUN
    assert fw.outputs() == (0, 0)                                  # dead time: everything off
    fw.set_hall(0b101)
    assert fw.outputs() == (0, 0)                                  # the hall ISR honours the hold too
    fw.tick()
    assert fw.outputs() == (t.ovdcond[1][0b101], t.ovdcons[1][0b101]) and fw.sig("duty") < 0


def test_brake_after_one_off_sample(fw):
    fw.reset()
    fw.cmd("start")
    fw.param("speed_setpoint", fw.table["speed_setpoint"].to_raw(500.0))
    fw.tick(2)
    assert fw.outputs() != (0, 0)
    assert fw.cmd("brake") == 0 and fw.outputs() == (0, 0)
    fw.tick()
    assert fw.outputs() == (0, 0)
    fw.tick()
    assert fw.outputs() == (0, 0x15) and fw.sig("state") == protocol.State.BRAKE
    assert fw.cmd("stop") == 0 and fw.outputs() == (0, 0) and fw.sig("state") == protocol.State.IDLE


def _assert_fault(fw, code):
    assert fw.sig("state") == protocol.State.FAULT and fw.sig("fault") == code
    assert fw.outputs() == (0, 0)


def test_invalid_hall_faults_latches_and_clears_only_by_command(fw):
    fw.reset()
    fw.cmd("start")
    fw.param("speed_setpoint", fw.table["speed_setpoint"].to_raw(500.0))
    fw.tick(2)
    fw.set_hall(0b000)
    assert fw.outputs() == (0, 0)                 # at once, in the hall ISR
    fw.tick(2)
    _assert_fault(fw, protocol.Fault.HALL_INVALID)
    assert fw.cmd("start") == protocol.Nack.FAULT_ACTIVE
    fw.set_hall(0b101)
    fw.tick(5)
    _assert_fault(fw, protocol.Fault.HALL_INVALID)  # still latched with a good code back
    assert fw.cmd("fault_clear") == 0
    assert fw.sig("state") == protocol.State.IDLE and fw.sig("fault") == 0
    assert fw.cmd("start") == 0


def test_flta_overcurrent(fw):
    fw.reset()
    fw.cmd("start")
    fw.tick()
    fw.setbit("FLTCONFIG", "FLTAS")
    fw.tick()
    _assert_fault(fw, protocol.Fault.OVERCURRENT)
    assert fw.cmd("fault_clear") == 0 and fw.bit("FLTCONFIG", "FLTAS") == 0


def test_adc_backup_overcurrent_and_bus_limits(fw):
    fw.reset()
    fw.cmd("start")
    fw.adc[0] = fw.plan.itrip if fw.plan.itrip < 1024 else 1023
    fw.tick()
    if fw.plan.itrip < 1024:
        _assert_fault(fw, protocol.Fault.OVERCURRENT)
    fw.reset()
    fw.cmd("start")
    fw.adc[1] = 100                               # bus collapsed
    fw.tick(9)
    assert fw.sig("state") == protocol.State.RUN   # debounced
    fw.tick(1)
    _assert_fault(fw, protocol.Fault.UNDERVOLTAGE)
    fw.reset()
    fw.adc[1] = 1000                              # pumped-up bus, even when idle
    fw.tick(10)
    _assert_fault(fw, protocol.Fault.OVERVOLTAGE)


def test_stall_and_link_loss(fw):
    fw.reset()
    fw.param("link_timeout", 60000)
    fw.param("stall_timeout", 200)
    fw.cmd("start")
    fw.param("speed_setpoint", fw.table["speed_setpoint"].to_raw(500.0))
    fw.tick(150)
    fw.set_hall(0b001)                            # the rotor moves: the stall timer restarts
    fw.tick(150)
    assert fw.sig("state") == protocol.State.RUN
    fw.tick(60)
    _assert_fault(fw, protocol.Fault.STALL)
    # resting in RUN at setpoint 0 longer than the stall timeout is no stall: a later
    # non-zero setpoint gets the full timeout (found from the console on the twin)
    fw.reset()
    fw.param("link_timeout", 60000)
    fw.param("stall_timeout", 200)
    fw.cmd("start")
    fw.param("speed_setpoint", 0)
    fw.tick(500)
    assert fw.sig("state") == protocol.State.RUN, fw.sig("fault")
    fw.param("speed_setpoint", fw.table["speed_setpoint"].to_raw(500.0))
    fw.tick(150)
    assert fw.sig("state") == protocol.State.RUN, fw.sig("fault")
    fw.tick(60)
    _assert_fault(fw, protocol.Fault.STALL)
    fw.reset()
    fw.param("stall_timeout", 60000)
    fw.param("link_timeout", 100)
    fw.cmd("start")
    fw.tick(95)
    assert fw.sig("state") == protocol.State.RUN
    fw.tick(10)
    _assert_fault(fw, protocol.Fault.LINK_LOST)


def test_hello_over_the_uart_registers(fw):
    fw.reset()
    frame = codec.encode_command("hello", 7)
    for b in frame:
        fw.w("RCREG", b)
        fw.setbit("PIR1", "RCIF")
        fw.lib.fw_isr_high()
    for _ in range(50):
        fw.lib.fw_poll()
        for _ in range(64):
            if not fw.bit("PIE1", "TXIE"):
                break
            fw.setbit("PIR1", "TXIF")
            fw.lib.fw_isr_high()                 # TXIP: the transmit interrupt is high priority
    n = C.c_int.in_dll(fw.lib, "stub_tx_n").value
    tx = bytes((C.c_uint8 * 4096).in_dll(fw.lib, "stub_tx")[:n])
    ack = protocol.ack_type(protocol.COMMAND_BY_NAME["hello"].code)
    dec = codec.StreamDecoder()
    replies = [f for f in dec.feed(tx) if f.type == ack and f.seq == 7]
    assert len(replies) == 1 and dec.crc_errors == 0 and dec.pending == 0, tx.hex()
    payload = replies[0].payload
    major, minor, build_id, profile_hash, table_hash = struct.unpack_from("<BBIII", payload)
    assert (major, minor) == protocol.PROTOCOL_VERSION
    assert build_id == fw.fw.build_id and table_hash == fw.table.hash
    assert profile_hash == fw.prof.hash32


def test_eeprom_persistence_through_the_registers(fw):
    fw.reset()
    kp = fw.table["rule1_kp"]
    assert fw.lib.link_eeprom_save() == 0
    fw.param("rule1_kp", kp.default_raw // 2)
    assert fw.lib.link_param_get(kp.id) == kp.default_raw // 2
    assert fw.lib.link_eeprom_load() == protocol.EepromResult.OK
    assert fw.lib.link_param_get(kp.id) == kp.default_raw
    # a reset boots from the saved image (fw_init loads it)
    fw.param("rule1_kp", 123)
    assert fw.lib.link_eeprom_save() == 0
    fw.lib.stub_reset()
    fw.adc[1] = 512
    fw.lib.fw_init()
    assert fw.lib.link_param_get(kp.id) == 123


def test_current_limit_window_at_standstill(fw):
    """At rest the output may not exceed R_line x I_lim: the current cannot pass the limit."""
    fw.reset()
    fw.param("stall_timeout", 60000)
    fw.param("link_timeout", 60000)
    fw.cmd("start")
    fw.param("speed_setpoint", fw.table["speed_setpoint"].to_raw(2400.0))
    fw.tick(50)
    r_ilim_v = fw.prof.motor.r_line_ohm * fw.table["current_limit"].scale * fw.lib.link_param_get(
        fw.table["current_limit"].id)
    v = fw.sig("voltage") * fw.table["voltage"].scale
    assert 0 < v <= r_ilim_v + 0.05, (v, r_ilim_v)
    # with a larger limit the window opens (up to the bridge's limit)
    fw.param("current_limit", 1023)
    fw.tick(20)
    assert fw.sig("voltage") * fw.table["voltage"].scale > min(r_ilim_v + 1.0, 40.0)
