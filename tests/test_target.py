"""The firmware on the PIC18F4431: every bundled design builds, links and keeps its budgets.

Built with SDCC's pic16 port and gputils (picdrive.firmware.target), timed on the PIC18
core in gpsim (picdrive.firmware.gpsim).  Budgets: picdrive.firmware.target.BUDGETS.
Also inspects the compiled output for hazards the host twin cannot show:
the interrupt prologue must save the table pointer when an interrupt reads
tables, and no runtime-library helper with static operands may be shared by
an interrupt and the main loop.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest

from picdrive import outputs
from picdrive.firmware import codegen, gpsim, target
from picdrive.paths import firmware_build_dir, repo_root
from picdrive.profile import load_profile

EXAMPLES = repo_root() / "examples"
DESIGNS = sorted(EXAMPLES.glob("*.design.json"))


def _generate(design: Path, out: Path) -> tuple[Path, str]:
    profile = load_profile(json.loads(design.read_text())["profile"]["name"])
    fw = codegen.generate(profile, design)
    codegen.write_firmware(fw, out)
    return out, fw.name


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """{design file name: (Build, {mode: Cycles})} for every bundled design."""
    out = {}
    for d in DESIGNS:
        t = tmp_path_factory.mktemp(d.name.replace(".", "_"))
        folder, name = _generate(d, t / "fw")
        b = target.build_measured(folder, t / "hex", name=name)
        out[d.name] = (b, gpsim.measure_modes(folder, t / "timing"))
    return out


def test_every_bundled_design_is_measured_and_a_halls_only_one_among_them():
    """Three designs for each bundled profile, all measured below; one profile takes the speed from
    the halls, so the hall-speed interrupt path is held to the budgets too."""
    import tomllib
    profiles = sorted(EXAMPLES.glob("*.toml"))
    assert {d.name for d in DESIGNS} == {f"{p.stem}.{m}.design.json" for p in profiles
                                         for m in ("fuzzy-hinf", "mixed-pid", "zn")}
    assert any(tomllib.loads(p.read_text())["sensors"]["speed_source"] == "hall" for p in profiles)


def _figures(b, modes) -> dict[str, int]:
    worst = {k: max(c.worst[k] for c in modes.values()) for k in ("speed_loop_isr", "hall_isr", "uart_rx_byte")}
    return {"flash_bytes": b.flash_bytes, "ram_stack_bytes": b.ram_stack_bytes, **worst}


@pytest.mark.parametrize("design", [d.name for d in DESIGNS])
def test_design_keeps_the_budgets_on_the_18f4431(built, design):
    """The chip's budgets (picdrive.firmware.target.BUDGETS): flash, static RAM + worst-case stack, the speed-loop interrupt with 4 signals and
    a capture armed (the worst over the three telemetry modes), the hall interrupt and the UART receive."""
    b, modes = built[design]
    got = _figures(b, modes)
    figures = "\n".join(target.budget_lines(b, got))
    assert b.on_chip, f"{design} does not link into the 18F4431:\n{figures}"
    assert target.over_budget(b, got) == [], f"{design} is over the PIC18F4431's budgets:\n{figures}"
    # a timing figure at or below the interrupt entry alone is a broken measurement (the harness's
    # timer-read overhead once came out 256 high and made the hall and UART figures negative)
    for k in ("speed_loop_isr", "hall_isr", "uart_rx_byte"):
        assert got[k] > gpsim.ENTRY_CYCLES + 10, (k, got[k])


def test_picdrive_firmware_writes_the_hex_of_a_design_that_fits(tmp_path):
    """One design through the generator's HEX path (each build costs a gpsim run)."""
    design = EXAMPLES / "duy2008.fuzzy-hinf.design.json"
    profile = load_profile(json.loads(design.read_text())["profile"]["name"])
    fw = codegen.generate(profile, design)
    report: list[str] = []
    codegen.write_firmware(fw, tmp_path / "fw", hex_build=True, report=report)
    hex_path = tmp_path / "fw" / f"{fw.name}.hex"
    assert hex_path.is_file()
    assert any("flash" in line for line in report), report
    # the marker lists the HEX, so writing the same folder again (a re-design) replaces it...
    listed = json.loads((tmp_path / "fw" / outputs.MARKER).read_text())["files"]
    assert listed[hex_path.name] == hashlib.sha256(hex_path.read_bytes()).hexdigest()
    codegen.write_firmware(fw, tmp_path / "fw", hex_build=True)
    assert hex_path.is_file()
    # ...and a HEX changed since (the user's own build put there) is not overwritten
    hex_path.write_text(hex_path.read_text() + ":00000001FF\n")
    before = hex_path.read_bytes()
    with pytest.raises(outputs.OutputError, match=rf"{hex_path.name} \(changed since picdrive wrote it\)"):
        codegen.write_firmware(fw, tmp_path / "fw", hex_build=True)
    assert hex_path.read_bytes() == before


def test_a_design_over_budget_is_refused_and_nothing_is_written(tmp_path, monkeypatch):
    """The refusal path: the same design against a flash budget it cannot meet."""
    monkeypatch.setattr(target, "BUDGETS", target.Budgets(flash_bytes=4_096))
    design = EXAMPLES / "duy2008.mixed-pid.design.json"
    profile = load_profile(json.loads(design.read_text())["profile"]["name"])
    fw = codegen.generate(profile, design)
    with pytest.raises(codegen.CodegenError, match=r"does not fit the PIC18F4431's budgets \(flash \d+ B > 4096 B"):
        codegen.write_firmware(fw, tmp_path / "fw", hex_build=True)
    assert not (tmp_path / "fw").exists()


@pytest.mark.parametrize("design", [d.name for d in DESIGNS])
def test_drive_build_links_none_of_the_identification_mode(built, design):
    """The drive firmware (without --identify): no identification table or variable in the map."""
    b, _ = built[design]
    symbols = target.parse_map(b.hex_path.with_suffix(".map").read_text())[1]
    names = {sym.name for sym in symbols}
    assert "_comm_ovd" in names                      # the map lists the drive's tables
    assert not {n for n in names if n.startswith("_ident_")}


@pytest.mark.parametrize("stem", ["duy2008.fuzzy-hinf", "duy2008_halls.fuzzy-hinf"])
def test_identification_build_keeps_the_budgets(tmp_path, stem):
    """picdrive firmware --identify of the largest designs (most flash; most RAM: the halls-only
    one) fits the chip's budgets, with the mode linked in."""
    design = EXAMPLES / f"{stem}.design.json"
    profile = load_profile(json.loads(design.read_text())["profile"]["name"])
    fw = codegen.generate(profile, design, identify=True)
    codegen.write_firmware(fw, tmp_path / "fw")
    b = target.build_measured(tmp_path / "fw", tmp_path / "hex", name=fw.name)
    symbols = target.parse_map(b.hex_path.with_suffix(".map").read_text())[1]
    names = {sym.name for sym in symbols}
    assert {"_ident_ovd", "_ident_pos", "_ident_m"} <= names
    got = _figures(b, gpsim.measure_modes(tmp_path / "fw", tmp_path / "timing"))
    assert b.on_chip and target.over_budget(b, got) == [], "\n".join(target.budget_lines(b, got))


@pytest.mark.parametrize("design", [d.name for d in DESIGNS])
def test_interrupts_save_the_table_pointer_when_they_read_tables(built, design):
    b, _ = built[design]
    assert target.unsaved_table_pointer(b) == {}


@pytest.mark.parametrize("design", [d.name for d in DESIGNS])
def test_no_static_operand_helper_is_shared_by_an_interrupt_and_the_main_loop(built, design):
    b, _ = built[design]
    assert target.shared_static_helpers(b) == {}
    # and the speed loop calls none at all
    low = b.reachable("isr_low")
    assert not sorted(n for n in low if b.functions[n].static_data)


def test_committed_hex_is_what_the_toolchain_builds(tmp_path):
    """A HEX is committed exactly when the build fits the chip, and it is a fresh, deterministic build."""
    committed = firmware_build_dir() / "duy2008"
    a = target.build_measured(committed, tmp_path / "a", name="duy2008")
    b = target.build_measured(committed, tmp_path / "b", name="duy2008")
    assert a.hex_path.read_bytes() == b.hex_path.read_bytes()          # deterministic
    if a.on_chip:
        assert (committed / "duy2008.hex").is_file(), "firmware_build/duy2008/duy2008.hex is not committed"
        assert (committed / "duy2008.hex").read_bytes() == a.hex_path.read_bytes()
    else:                                                              # no unflashable HEX is shipped
        assert not (committed / "duy2008.hex").exists()


def test_the_build_reads_its_hex_through_the_checked_reader(tmp_path):
    """The call-graph analysis reads the linked HEX with picdrive.firmware.ihex (the twin's
    reader): the committed HEX's flash as the reader gives it, and a record whose checksum is
    wrong is refused instead of decoded."""
    from picdrive.firmware import ihex
    committed = firmware_build_dir() / "duy2008" / "duy2008.hex"
    mem = target.read_hex(committed)
    assert mem == ihex.load_hex(committed).flash and len(mem) == target.FLASH_BYTES
    lines = committed.read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if ln[7:9] == "00")
    lines[k] = lines[k][:-2] + f"{(int(lines[k][-2:], 16) + 1) & 0xFF:02X}"
    bad = tmp_path / "bad.hex"
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(ihex.HexError, match="checksum"):
        target.read_hex(bad)


# ---------------------------------------------------------------------------
# The checks themselves: each finds the hazard it is for
# ---------------------------------------------------------------------------
PLAIN_MAIN = """#include <xc.h>
#include "drive.h"
void isr_high(void) __interrupt(1) { fw_isr_high(); }
void isr_low(void) __interrupt(2) { fw_isr_low(); }
"""

TABLE_ISR = """#include <stdint.h>
static const uint8_t tab[4] = {1, 2, 3, 4};
volatile uint8_t idx, out;
int32_t a32, b32;
int16_t x16, y16;
void fw_init(void) { }
void fw_poll(void) { a32 = (int32_t)x16 * y16; }
void fw_isr_high(void) { out = tab[idx & 3u]; }
void fw_isr_low(void) { b32 = (int32_t)y16 * x16; }
"""


#: the shape of drive.c's isr_high (the template's vector jumps to it): the entry pushes the table
#: pointer and latch on the software stack around the handler that reads a table
SAVING_ISR_HIGH = """
void isr_high(void) __naked
{
    __asm
    movwf   _POSTDEC1, A
    movff   _STATUS, _POSTDEC1
    movff   _BSR, _POSTDEC1
    movff   _TBLPTRU, _POSTDEC1
    movff   _TBLPTRH, _POSTDEC1
    movff   _TBLPTRL, _POSTDEC1
    movff   _TABLAT, _POSTDEC1
    call    _fw_isr_high
    movff   _PREINC1, _TABLAT
    movff   _PREINC1, _TBLPTRL
    movff   _PREINC1, _TBLPTRH
    movff   _PREINC1, _TBLPTRU
    movff   _PREINC1, _BSR
    movff   _PREINC1, _STATUS
    movff   _PREINC1, _WREG
    retfie  0
    __endasm;
}
"""


def _mini(tmp_path, main_text, isr_high=SAVING_ISR_HIGH):
    src = tmp_path / "src"
    src.mkdir()
    (src / "drive.h").write_text("void fw_init(void);\nvoid fw_poll(void);\nvoid fw_isr_high(void);\n"
                                 "void fw_isr_low(void);\n")
    (src / "drive.c").write_text("#include <xc.h>\n" + TABLE_ISR + isr_high)
    tpl = (repo_root() / "firmware_templates" / "main_sdcc.c.j2").read_text()
    (src / "main_sdcc.c").write_text(main_text(tpl))
    return target.build_hex(src, tmp_path / "out", name="mini", sources=("drive.c", "main_sdcc.c"))


def _rendered_main(tpl: str) -> str:
    import jinja2
    return jinja2.Environment(trim_blocks=True, lstrip_blocks=True).from_string(tpl).render(
        gen_note="test", config=[("WDTEN", "OFF", "no watchdog")], eeprom_gptr_stubs=target.EEPROM_GPTR_STUBS)


def test_table_pointer_check_finds_an_unsaved_table_read(tmp_path):
    # vectors as a new user writes them for SDCC: the compiler's own prologue only
    b = _mini(tmp_path, lambda tpl: PLAIN_MAIN + _eeprom_stubs(tpl)
              + "void main(void) { fw_init(); for (;;) fw_poll(); }\n", isr_high="")
    assert "isr_high" in target.unsaved_table_pointer(b)
    assert any(b.functions[n].table_read for n in b.reachable("isr_high"))


def test_an_entry_that_saves_the_table_pointer_passes_the_check(tmp_path):
    # the template's vectors: the high one jumps to drive.c's isr_high (here SAVING_ISR_HIGH), the low
    # one saves the table pointer around fw_isr_low itself
    b = _mini(tmp_path, _rendered_main)
    assert any(b.functions[n].table_read for n in b.reachable("isr_high"))
    assert target.unsaved_table_pointer(b) == {}
    assert set(target.TABLE_SAVE) <= b.functions[b.roots["isr_high"]].saves


def test_shared_helper_check_finds_a_multiply_in_both(tmp_path):
    b = _mini(tmp_path, _rendered_main)
    shared = target.shared_static_helpers(b)
    assert "__mullong" in shared and shared["__mullong"] >= {"main", "isr_low"}


def _eeprom_stubs(tpl: str) -> str:
    body = _rendered_main(tpl)
    i = body.index("void eeprom_gptr_unused")
    return body[i:body.index("void main")]


def test_stack_figure_counts_pushes_along_the_deepest_path(tmp_path):
    b = _mini(tmp_path, _rendered_main)
    # every root has a bounded figure, and the total is the three nested
    assert b.stack_bytes == sum(v[0] for v in b.stack_by_root.values())
    assert b.stack_by_root["isr_low"][0] >= b.functions[b.roots["isr_low"]].frame > 10
    assert b.hw_stack_levels >= 3
