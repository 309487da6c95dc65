"""p18f4431.inc parser and the generated host register shim (seam 4)."""
import re
import shutil
import subprocess

import pytest

from picdrive.firmware import p18f4431 as inc
from picdrive.errors import PicdriveError

INC = inc.INC_PATH
pytestmark = pytest.mark.skipif(not INC.exists(), reason="gputils' p18f4431.inc not installed")


def test_registers_against_the_file_and_datasheet():
    regs = inc.registers()
    # independent re-read of the Register Files block, line by line
    text = INC.read_text(encoding="latin-1")
    block = text.split(";----- Register Files")[1].split(";----- DFLTCON Bits")[0]
    raw = dict(re.findall(r"^(\w+)\s+EQU\s+H'0?([0-9A-F]{3,4})'", block, re.M))
    assert {k: int(v, 16) for k, v in raw.items()} == regs
    # a few addresses checked by hand against the PIC18F4431 data sheet register map
    assert regs["TXREG"] == 0xFAD and regs["RCREG"] == 0xFAE and regs["PIR1"] == 0xF9E
    assert regs["OVDCOND"] == 0xF6B and regs["OVDCONS"] == 0xF6A and regs["DTCON"] == 0xF6D
    assert regs["PTPERL"] == 0xF7B and regs["PDC0L"] == 0xF79 and regs["POSCNTL"] == 0xF66
    assert regs["TRISA"] == regs["DDRA"] == 0xF92
    assert all(0xF60 <= a <= 0xFFF for a in regs.values())


def test_bits_and_config():
    b = inc.bits()
    assert b["PIR1"]["RCIF"] == 5 and b["PIR1"]["TXIF"] == 4
    assert b["INTCON"]["GIEH"] == b["INTCON"]["GIE"] == b["INTCON"]["GIE_GIEH"] == 7
    assert b["QEICON"]["VELM"] == 7 and b["QEICON"]["QEIM2"] == 4 and b["QEICON"]["UP_DOWN"] == 5
    assert b["PIR3"]["IC1IF"] == 1 and b["INTCON3"]["INT2IF"] == 1 and b["RCON"]["IPEN"] == 7
    assert b["EECON1"]["WR"] == 1 and b["EECON1"]["RD"] == 0
    assert len(b) >= 70
    cfg = inc.config_settings()
    assert "HSPLL" in cfg["OSC"] and set(cfg["WDTEN"]) == {"OFF", "ON"}
    assert set(cfg["FLTAMX"]) == {"RD4", "RC1"} and "OFF" in cfg["LVP"]


def test_multibyte_aliases_left_out_of_the_shim():
    s = inc.shim_registers()
    for n in ("TMR5", "ADRES", "PROD", "PC", "TMR0", "CCPR1"):
        assert n in inc.registers() and n not in s
    for n in ("TMR5L", "TMR5H", "ADRESL", "ADRESH", "TXREG", "VELRL"):
        assert n in s


def test_shim_deterministic_and_complete():
    a, b = inc.render_host_shim(), inc.render_host_shim()
    assert a == b
    for n, addr in inc.shim_registers().items():
        if n in inc.PIN_READ_REGISTERS:        # a port access notifies the model: the pins now
            assert f"#define {n} (*(picsim_sfr_read(0x{addr:03X}u), &picsim_sfr[0x{addr - 0xF00:02X}]))" in a
        else:
            assert f"#define {n} (picsim_sfr[0x{addr - 0xF00:02X}])" in a
    assert "#define PIR1bits (*(volatile PIR1bits_t *)&picsim_sfr[0x9E])" in a
    assert "#define PORTCbits (*(volatile PORTCbits_t *)(picsim_sfr_read(0xF82u), &picsim_sfr[0x82]))" in a
    assert "void picsim_sfr_written(uint16_t addr);" in a and "#define __interrupt(x)" in a


def _bit_check_program() -> str:
    """A C program that sets every bit of every bit struct through REGbits.BIT
    and checks the byte picsim_sfr[] holds exactly that mask."""
    lines = ["#include <stdio.h>", "#include <xc.h>", "volatile uint8_t picsim_sfr[256];",
             "static uint16_t wr, rd;",
             "void picsim_sfr_written(uint16_t a) { wr = a; }",
             "void picsim_sfr_read(uint16_t a) { rd = a; }",
             "int main(void) {", "  int bad = 0;"]
    regs = inc.shim_registers()
    for reg, bb in sorted(inc.bits().items()):
        if reg not in regs:
            continue
        for name, pos in sorted(bb.items()):
            lines += [f"  {reg} = 0; {reg}bits.{name} = 1;",
                      f"  if ({reg} != 0x{1 << pos:02X}u) {{ printf(\"{reg}.{name} %02x\\n\", {reg}); bad++; }}",
                      f"  {reg} = 0xFF; {reg}bits.{name} = 0;",
                      f"  if ({reg} != 0x{0xFF ^ (1 << pos):02X}u) {{ printf(\"{reg}.{name}\\n\"); bad++; }}",
                      f"  {reg} = 0;"]
    lines += ["  TXREG = 0x41; PICSIM_WRITE(TXREG);",
              "  PICSIM_READ(RCREG);",
              "  if (wr != 0xFADu || rd != 0xFAEu) { printf(\"notify %x %x\\n\", wr, rd); bad++; }",
              "  if (sizeof(PIR1bits_t) != 1u) { printf(\"size\\n\"); bad++; }",
              "  printf(\"bad=%d\\n\", bad);", "  return bad != 0;", "}"]
    return "\n".join(lines) + "\n"


def test_shim_bit_layout_runs_on_gcc(tmp_path):
    (tmp_path / "xc.h").write_text(inc.render_host_shim())
    (tmp_path / "t.c").write_text(_bit_check_program())
    exe = tmp_path / "t"
    subprocess.run(["gcc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-I", str(tmp_path),
                    str(tmp_path / "t.c"), "-o", str(exe)], check=True, capture_output=True, text=True)
    r = subprocess.run([str(exe)], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout
    assert "bad=0" in r.stdout


@pytest.mark.skipif(shutil.which("avr-gcc") is None, reason="avr-gcc not installed")
def test_shim_compiles_with_16bit_int(tmp_path):
    (tmp_path / "xc.h").write_text(inc.render_host_shim())
    (tmp_path / "t.c").write_text(
        "#include <xc.h>\nvoid f(uint8_t x);\nvoid f(uint8_t x) { TXREG = x; PICSIM_WRITE(TXREG);"
        " PIR1bits.RCIF = 0; INTCONbits.GIEH = 1; }\n")
    subprocess.run(["avr-gcc", "-mmcu=atmega328p", "-std=c99", "-Wall", "-Wextra", "-Werror",
                    "-Wconversion", "-pedantic", "-I", str(tmp_path), "-c", str(tmp_path / "t.c"),
                    "-o", str(tmp_path / "t.o")], check=True, capture_output=True, text=True)


def test_missing_inc_is_a_clear_error(tmp_path, monkeypatch):
    with pytest.raises(inc.IncError, match="gputils"):
        inc.parse_inc(tmp_path / "nope.inc")
    monkeypatch.setenv(inc.INC_ENV, str(tmp_path / "nope.inc"))
    with pytest.raises(PicdriveError, match="PICDRIVE_P18F4431_INC"):
        inc.registers()
    bad = tmp_path / "bad.inc"
    bad.write_text("; nothing here\n")
    with pytest.raises(inc.IncError, match="not a Microchip"):
        inc.parse_inc(bad)


def test_names_used():
    src = """
    #define MY_CONST 3
    enum { ST_IDLE, ST_RUN = 2 };
    static struct { int a; } S;
    /* TXSTA in a comment does not count, nor "PORTZ" in a string */
    void f(void) { TXREG = MY_CONST; PIR1bits.RCIF = 0; OVDCOND = ST_RUN; FOOBAR = 1; S.a = 1; }
    int g(void) { return OVDCONX; }
    """
    sfrs, bit_uses, unknown = inc.names_used([src])
    assert sfrs == {"TXREG", "PIR1", "OVDCOND"}
    assert bit_uses == {("PIR1", "RCIF")}
    assert unknown == {"FOOBAR", "OVDCONX"}     # a typo of an SFR name is caught
