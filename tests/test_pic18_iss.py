"""The PIC18 instruction-set simulator (picdrive_hil.pic18, csrc/pic18cpu.c).

1. Differential test against gpsim (p18f4520 runs the same PIC18 core): the corpus of
   tests/support/pic18diff.py -- every ALU/literal instruction on edge operands, STATUS as a
   destination, banked/access operands, skips over 1- and 2-word instructions, branches, all
   FSR forms, table reads, PCL, the stack, CALL/RETURN FAST, interrupts of both priorities,
   compiled-code arithmetic, seeded random sequences -- compared at every checkpoint (GPRs,
   WREG, STATUS, BSR, FSR0-2, PROD, TABLAT, TBLPTR, STKPTR, TOS, PCLATH/U, PC, cycles).
2. What gpsim cannot check, against the data sheet (DS39616): default timing, stack
   full/underflow with and without STVREN, config-space table reads, runtime faults.
3. The Intel HEX loader's bad-input cases.
"""
from __future__ import annotations

import pytest

from picdrive.firmware import ihex
from picdrive_hil.pic18 import Pic18
from support import pic18diff as D


# ---------------------------------------------------------------- differential (gpsim)

@pytest.fixture(scope="module")
def diff_results(tmp_path_factory):
    D.tools()   # gpasm and gpsim must be installed (scripts/setup.sh): a missing tool fails
    wd = tmp_path_factory.mktemp("pic18diff")
    return D.differential_many(D.corpus(), wd)


def test_gpsim_agrees_at_every_checkpoint(diff_results):
    bad = [f"{r.program}: {d}" for r in diff_results for d in r.diffs]
    assert not bad, "simulator and gpsim differ:\n" + "\n".join(bad[:30])


def test_corpus_size(diff_results):
    insns = sum(r.insns for r in diff_results)
    checks = sum(len(r.iss) for r in diff_results)
    assert insns >= 100_000, insns
    assert checks >= 2000, checks
    # every program ran to its end (the last checkpoint is 'done') in both
    for r in diff_results:
        assert r.iss and r.iss[-1].pc == D.DONE, r.program
        assert r.gpsim and r.gpsim[-1].pc == D.DONE, r.program


# ---------------------------------------------------------------- data sheet checks

def _cpu(words, config=None):
    c = Pic18()
    c.load_words(words)
    if config is not None:
        c.set_config(config)
    c.power_on()
    return c


def test_flag_mutation_is_caught(tmp_path):
    """The differential test sees a wrong flag: a core built with DC of additions inverted
    disagrees with gpsim on the compiled-arithmetic program."""
    from picdrive_hil import build
    src = (build.CSRC / "pic18cpu.c").read_text()
    bad = src.replace("if (((a & 0xF) + (b & 0xF) + cin) & 0x10) s |= S_DC;",
                      "if (!(((a & 0xF) + (b & 0xF) + cin) & 0x10)) s |= S_DC;")
    assert bad != src
    mdir = tmp_path / "mut"
    mdir.mkdir()
    (mdir / "pic18cpu.c").write_text(bad)
    (mdir / "pic18cpu.h").write_text((build.CSRC / "pic18cpu.h").read_text())
    lib = build.build_library([build.Group((mdir / "pic18cpu.c",), (mdir,),
                                           build.twin_cflags() + ("-DPIC18_GPSIM_COMPAT",),
                                           (mdir / "pic18cpu.h",))], name="libpic18mut")
    (tmp_path / "w").mkdir()
    res = D.differential(D.prog_arith(iterations=20), tmp_path / "w", lib=lib)
    assert res.diffs, "a broken DC computation went unnoticed"


def test_run_limits():
    c = _cpu([0x0000] * 8 + [0xD7F7])                # 8 nops ; bra 0 (2 cycles)
    assert c.run_to_cycle(5) == "ok" and c.cycles == 5 and c.pc == 10
    assert c.run(until=0x10) == "break" and c.pc == 0x10 and c.cycles == 8
    assert c.step(2) == "ok" and c.pc == 0x02 and c.insns == 10


def test_peripheral_hooks_and_irq_lines():
    """The API the twin's peripheral model will use: SFR reads/writes at their cycle, the
    core's registers stay the core's, request lines gated by GIEH."""
    # 0x00 goto 0x20 | 0x08: incf 0x10 ; retfie | 0x20: movlw 0x5A ; movwf PORTB ; movf PORTA,W ;
    # movwf 0x11 ; bsf INTCON,GIEH ; movff PORTB, 0x12 ; nop ; nop
    words = ([0xEF10, 0xF000, 0xFFFF, 0xFFFF, 0x2A10, 0x0010] + [0x0000] * 10 +
             [0x0E5A, 0x6E81, 0x5080, 0x6E11, 0x8EF2, 0xCF81, 0xF012, 0x0000, 0x0000])
    c = _cpu(words)
    log = []
    intcon = {"v": 0x33}

    def rd(a):
        log.append(("r", a, c.cycles))
        return 0xA7 if a == 0xF80 else intcon["v"] if a == 0xFF2 else 0x33

    c.attach(rd, lambda a, v: log.append(("w", a, v, c.cycles)), owned={0xF80, 0xF81, 0xFF2})
    c.run(insns=7)
    # a hook sees the cycle count at the end of the cycle of the access: goto 0-1, movlw 2,
    # movwf PORTB 3 (-> 4), movf PORTA 4 (-> 5), movwf 5, bsf INTCON 6 (-> 7), movff 7-8
    assert ("w", 0xF81, 0x5A, 4) in log
    assert ("r", 0xF80, 5) in log and c.read(0x11) == 0xA7
    assert ("r", 0xFF2, 7) in log and ("w", 0xFF2, 0xB3, 7) in log   # BSF: read-modify-write
    assert ("r", 0xF81, 8) in log and c.read(0x12) == 0x33   # MOVFF reads in its first cycle
    c.set_irq(high=True)          # the model's INTCON still reads GIEH = 0: no entry
    c.run(insns=1)
    assert c.read(0x10) == 0 and c.pc == 0x30 and c.cycles == 10
    intcon["v"] = 0x80            # GIEH set in the model
    c.set_irq(high=True)
    c.run(insns=1)                # vectoring (2 cycles), then incf 0x10 at 0x0008
    assert c.read(0x10) == 1 and c.pc == 0x0A and c.cycles == 13
    assert ("w", 0xFF2, 0x00, 10) in log and c.stack() == [0x30]   # GIEH cleared through the model


def test_default_timing_is_the_datasheets():
    # TBLRD*+ is 2 cycles (Table 25-2), MOVFF 2, a skip over a 2-word instruction 3
    c = _cpu([0x0009, 0x0000])                       # tblrd*+ ; nop
    c.run(insns=1)
    assert c.cycles == 2
    c = _cpu([0x6A20, 0x6620, 0xC020, 0xF021, 0x0000])   # clrf 0x20; tstfsz 0x20 (skips movff)
    c.run(insns=2)
    assert c.cycles == 1 + 3 and c.pc == 8


def test_interrupt_vectoring_takes_two_cycles():
    # bsf INTCON,INT0IE ; bsf INTCON,GIEH ; bsf INTCON,INT0IF ; nop  -> vector 0x0008 after 2 cycles
    words = [0xEF10, 0xF000] + [0xFFFF] * 2 + [0x0000] * 12 + [0x88F2, 0x8EF2, 0x82F2, 0x0000]
    c = _cpu(words)
    c.run(until=0x08)
    assert c.pc == 0x08
    assert c.cycles == 2 + 3 + 2                      # goto, 3 bsf, vectoring
    assert c.stack() == [0x26]                        # the nop after the flag is not executed
    assert c.reg("INTCON") & 0x80 == 0                # GIEH cleared


def _recurse_words():
    # 0x00: rcall 0x00 (infinite recursion)
    return [0xDFFF]


def test_stack_overflow_with_stvren_resets():
    c = _cpu(_recurse_words())
    st = c.run(insns=100)
    assert st == "stack_overflow"
    assert c.stop.address == 0x0000 and c.stop.word == 0xDFFF
    assert c.pc == 0 and c.stkptr == 0x80             # reset: SP 0, STKFUL kept (5.1.2.4)
    assert "stack overflow" in c.stop.message and "0x000000" in c.stop.message


def test_stack_overflow_without_stvren_sets_stkful_and_stops():
    cfg = bytearray(ihex.CONFIG_DEFAULT)
    cfg[6] &= ~1                                      # STVREN off
    c = _cpu(_recurse_words(), bytes(cfg))
    assert c.run(insns=100) == "stack_overflow"
    assert c.stkptr == 0x80 | 31                      # 31st push: STKFUL, SP 31
    assert c.run(insns=1) == "stack_overflow"         # pushes beyond are lost, SP stays 31
    assert c.stkptr == 0x80 | 31


def test_stack_underflow():
    c = _cpu([0x0000, 0x0012])                        # nop ; return (empty stack)
    assert c.run(insns=10) == "stack_underflow"
    assert c.stkptr & 0x40 and c.pc == 0


def test_pc_outside_flash_and_illegal_opcode_stop_the_core():
    c = _cpu([0xEF00, 0xF020])                        # goto 0x4000 (beyond 16 KB)
    assert c.run(insns=5) == "pc_outside_flash"
    assert c.stop.fatal and c.stop.address == 0x4000 and "0x004000" in c.stop.message
    assert c.run(insns=5) == "pc_outside_flash"       # stays stopped until reset
    c = _cpu([0x0000, 0xE801])                        # nop ; ADDFSR (extended set)
    assert c.run(insns=5) == "illegal_opcode"
    assert (c.stop.address, c.stop.word) == (2, 0xE801) and "0xE801" in c.stop.message
    c = _cpu([0x0000] * 0x1FFF + [0x0000])            # falls off the end of flash
    assert c.run(insns=10_000) == "pc_outside_flash" and c.stop.address == 0x4000


def test_table_reads_of_config_and_device_id():
    # TBLPTR = 0x300006 (CONFIG4L) ; tblrd* ; TBLPTR = 0x3FFFFF ; tblrd*  ; tblrd*+ wraps to 0
    words = [0x0E30, 0x6EF8, 0x0E00, 0x6EF7, 0x0E06, 0x6EF6, 0x0008,
             0x0E3F, 0x6EF8, 0x0EFF, 0x6EF7, 0x6EF6, 0x0008, 0x0009]
    c = _cpu(words)
    c.run(insns=7)
    assert c.reg("TABLAT") == ihex.CONFIG_DEFAULT[6]
    c.run(insns=6)
    assert c.reg("TABLAT") == 0x05                    # DEVID2 of the 18F4431 family
    c.run(insns=1)
    assert c.tblptr == 0                              # 22-bit pointer wraps


def test_status_as_destination_keeps_the_flag_logic():
    # movlw 0x0F ; movwf STATUS ; movlw 0xE0 ; addwf STATUS,F  -> flags from 0x0F+0xE0, not the sum
    c = _cpu([0x0E0F, 0x6ED8, 0x0EE0, 0x26D8])
    c.run(insns=4)
    assert c.reg("STATUS") == 0x10                    # N only: 0xEF; the result itself not written


def test_indf_through_indf_reads_zero():
    # lfsr 0,0xFEF ; movlw 5 ; movf INDF0,W  -> W = 0, Z set; movwf INDF0 does nothing
    c = _cpu([0xEE0F, 0xF0EF, 0x0E05, 0x50EF, 0x6EEF])
    c.run(insns=4)
    assert c.w == 0 and c.reg("STATUS") & 0x04
    c.run(insns=1)
    assert c.reg("FSR0L") == 0xEF


# ---------------------------------------------------------------- HEX loader

GOOD = ":020000040000FA\n:0400000012EF00F00B\n:00000001FF\n"


def _rec(addr: int, data: bytes, rtype: int = 0) -> str:
    body = bytes([len(data), addr >> 8, addr & 0xFF, rtype]) + data
    return ":" + (body + bytes([(-sum(body)) & 0xFF])).hex().upper()


def test_hex_good():
    img = ihex.parse_hex(GOOD)
    assert img.flash[:4] == bytes([0x12, 0xEF, 0x00, 0xF0]) and img.flash_used == 4


@pytest.mark.parametrize("text, needle", [
    (":0400000012EF00F00C\n:00000001FF\n", "checksum"),
    ("0400000012EF00F00B\n:00000001FF\n", "start with ':'"),
    (":0400000012EF00F0\n:00000001FF\n", "byte count"),
    (":0400000\n:00000001FF\n", "odd or too short"),
    (":0400000012EF00ZZ0B\n:00000001FF\n", "non-hex"),
    (":0400000012EF00F00B\n", "no end-of-file"),
    (":00000001FF\n" + _rec(0, b"\x00\x00") + "\n", "after the end-of-file"),
    (_rec(0, b"\x01\x02") + "\n" + _rec(1, b"\x03") + "\n:00000001FF\n", "overlapping"),
    (_rec(0x4000 - 2, b"\x00\x00\x00\x00") + "\n:00000001FF\n", "beyond the 18F4431's 16 KB"),
    (_rec(0, b"\x00\x30", 4) + "\n" + _rec(0x0020, b"\xff") + "\n:00000001FF\n", "does not exist on the 18F4431"),
    (_rec(0, b"\x00\xf0", 4) + "\n" + _rec(0x0100, b"\xff") + "\n:00000001FF\n", "EEPROM address"),
    (_rec(0, b"\x00\x30", 4) + "\n" + _rec(0x0006, b"\xc5") + "\n:00000001FF\n", "XINST"),
    (_rec(0, b"\x00\x3f", 4) + "\n" + _rec(0xFFFE, b"\x00") + "\n:00000001FF\n", "device ID"),
    (_rec(0, b"\x00\x00\x00", 3) + "\n:00000001FF\n", "start address record"),
    (_rec(0, b"\x00", 6) + "\n:00000001FF\n", "unknown record type"),
    ("", "no HEX records"),
])
def test_hex_bad_input(text, needle):
    with pytest.raises(ihex.HexError) as e:
        ihex.parse_hex(text, "f.hex")
    assert needle in str(e.value), str(e.value)
    assert "\n" not in str(e.value)


def test_hex_accepted_regions_and_start_records():
    text = "\n".join([_rec(0, b"\x00\x00\x00\x00", 5), _rec(0, b"\x00\x30", 4), _rec(6, b"\x84"),
                      _rec(0, b"\x00\xf0", 4), _rec(0x10, b"\xab"), _rec(0, b"\x00\x20", 4),
                      _rec(0, b"\x11"), _rec(0, b"\x00\x00", 2), _rec(0x3FFE, b"\x12\x00"), ":00000001FF"])
    img = ihex.parse_hex(text)
    assert not img.stvren and img.config[6] == 0x84
    assert img.eeprom[0x10] == 0xAB and img.idloc[0] == 0x11 and img.flash[0x3FFE] == 0x12


def test_hex_file_errors(tmp_path):
    with pytest.raises(ihex.HexError, match="cannot read"):
        ihex.load_hex(tmp_path / "missing.hex")
    p = tmp_path / "bin.hex"
    p.write_bytes(b"\x7fELF\x00\xff")
    with pytest.raises(ihex.HexError, match="not a text file"):
        ihex.load_hex(p)
