"""The link module as the PIC18 compiler sees it (SDCC 4.2.0 pic16, installed by
scripts/pic_toolchain.sh), and the interrupt-safety rules it must keep there (issue 9, hazards
a, b, g).  Cycle and flash figures are printed by bench/link_pic18.py, not asserted here."""
import re

import pytest

from linksupport import build
from picdrive.link import protocol as P

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
    loop under a guard that may mask only the low priority: every field it writes is one byte."""
    c = build.render()["link_fw.c"]
    fields = dict((name, t) for t, name in re.findall(r"^\s+(?:volatile )?(u?int\d+_t) (\w+);", c, re.M))
    body = re.search(r"void link_rx_byte\(uint8_t b\)[^{]*\{(.*?)\n\}", c, re.S).group(1)
    written = set(re.findall(r"S\.(\w+)\s*(?:=[^=]|\+\+|--|\+=|-=)", body))
    written |= set(re.findall(r"(?:\+\+|--)S\.(\w+)", body))
    assert written, body
    assert {f: fields[f] for f in written} == {f: "uint8_t" for f in written}
    # and the ring: one byte per slot, an 8-bit index, a power-of-two size
    assert re.search(r"rx_ring\[h\] = b;", body) and P.RX_RING_BYTES & (P.RX_RING_BYTES - 1) == 0
