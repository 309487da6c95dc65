"""The link module as the PIC18 compiler sees it (SDCC 4.2.0 pic16, installed by
scripts/pic_toolchain.sh), and the interrupt-safety rules it must keep there (issue 9, hazards
a, b, g).  Cycle and flash figures are printed by bench/link_pic18.py, not asserted here."""
import re

import pytest

from linksupport import build
from picdrive import protocol as P

ISR_ENTRIES = ("_link_rx_byte", "_link_tick_ms", "_link_sample")


@pytest.fixture(scope="module")
def asm(tmp_path_factory):
    return build.sdcc_asm(build.render(), tmp_path_factory.mktemp("sdcc"))


def _bodies(asm: str) -> dict[str, str]:
    out, cur = {}, None
    for line in asm.splitlines():
        m = re.match(r"^(_\w+):", line)
        if m and not re.match(r"^_\d+_DS_", line):
            cur = m.group(1)
            out[cur] = ""
        elif cur is not None:
            out[cur] += line + "\n"
    return out


def test_interrupt_paths_call_no_compiler_helper(asm):
    """Hazard b: the compiler's multiply/divide/generic-pointer helpers keep their operands in
    static RAM; one reachable from an interrupt and from the main loop can be corrupted.  The
    functions the interrupts call reach no helper at all (only the application's callbacks)."""
    graph = build.asm_call_graph(asm)
    isr = build.reachable(graph, ISR_ENTRIES)
    assert set(ISR_ENTRIES) <= isr
    helpers = sorted(f for f in isr if f.startswith("__"))
    assert helpers == [], f"runtime-library helpers reachable from an interrupt: {helpers}"
    assert "_capture_sample" in isr and "_app_signal" in isr   # the graph follows the calls
    # and the main loop's products are gone too: no multiply or divide helper anywhere
    assert not re.search(r"CALL\s+__(mul|div|mod)\w+", asm)


def test_interrupt_paths_read_no_flash_table(asm):
    """Hazard a: the interrupt prologue does not save TBLPTR/TABLAT; the functions the
    interrupts call read no flash (no TBLRD, no generic-pointer read)."""
    graph, bodies = build.asm_call_graph(asm), _bodies(asm)
    for f in build.reachable(graph, ISR_ENTRIES):
        if f in bodies:
            assert "TBLRD" not in bodies[f] and "TBLPTR" not in bodies[f], f


def test_rx_interrupt_shares_single_bytes_only():
    """Hazard g: state written by link_rx_byte (high-priority interrupt) is read by the main
    loop under a guard that may mask only the low priority: every variable it writes is one
    byte (the frame buffer's fill count, the ready flag, the lost-byte count) or a byte of the
    frame buffer, indexed by a byte."""
    c = build.render()["link_fw.c"]
    decl = re.search(r"^static volatile uint8_t ([\w, ]+);", c, re.M).group(1)
    bytes_ = {v.strip() for v in decl.split(",")}
    body = re.search(r"void link_rx_byte\(uint8_t b\)[^{]*\{(.*?)\n\}", c, re.S).group(1)
    written = set(re.findall(r"\b(\w+)\s*(?:=[^=]|\+\+|--|\+=|-=)", body)) - {"rx_buf"}
    written |= set(re.findall(r"(?:\+\+|--)(\w+)", body))
    assert written == {"rx_n", "rx_ready", "rx_ovf"} and written <= bytes_, (written, bytes_)
    assert "S." not in body                                  # nothing of the main loop's state
    assert re.search(r"rx_buf\[rx_n\] = b;", body) and P.RX_BUFFER_BYTES < 256
