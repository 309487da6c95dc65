"""The PIC18F4431 build of a generated firmware: SDCC's pic16 port + gputils' linker.

``build_hex(folder, out_dir)`` compiles the firmware folder's C (the sources
in ``TARGET_SOURCES``, with the device header and SFR placement rendered by
``picdrive.p18f4431.render_sdcc_device``) with SDCC for the 18F4431 and links
it with gplink into the 18F4431's memory (gputils' ``18f4431_g.lkr``).  The
returned ``Build`` carries the HEX and the figures read from the linker's map
and from the linked code itself:

* flash bytes (program sections, without the configuration words),
* static RAM bytes (data sections below the SFRs, without the software stack),
* the worst-case software stack (bytes pushed through FSR1) and hardware
  return-stack depth, from the call graph of the linked program: main, plus
  the low-priority interrupt, plus the high-priority interrupt nesting on top,
* per-function sizes, and which functions each interrupt reaches.

The call graph is decoded from the linked HEX, with function boundaries from
the map, rather than from SDCC's ``.asm`` listing: the runtime library's
helpers (``__mullong``, ``__gptrget3``...) exist only as objects, and the HEX is
what runs.  SDCC's ``.asm`` is still read for what the HEX cannot show: which
functions have their address taken (an indirect call could reach them; then
the stack is reported as not bounded instead of guessed).

The software stack is then linked at exactly the computed worst case (a
second link), so the RAM the map shows is the RAM the firmware needs.

Budgets are defined once here: ``BUDGETS``.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

from ..board import FCY_HZ
from ..errors import PicdriveError
from .ihex import FLASH_BYTES      # the PIC18F4431's program memory

__all__ = ["TargetError", "Toolchain", "Budgets", "BUDGETS", "FCY_HZ", "RAM_BYTES", "FLASH_BYTES",
           "TARGET_SOURCES", "toolchain", "build_hex", "Build", "Function", "call_graph",
           "budget_lines", "over_budget", "build_measured", "enlarged_lkr", "shared_static_helpers", "unsaved_table_pointer",
           "EEPROM_GPTR_STUBS", "TEST_BUILD_CORE"]

ENLARGED_FLASH_BYTES = 0x20000   # enlarged_lkr's program memory (measurement links only)
RAM_BYTES = 768              # PIC18F4431 data memory (0x000-0x2FF)
HW_STACK_LEVELS = 31         # PIC18 return-address stack
STACK_MODEL_BYTES = 256      # SDCC's small stack model: the software stack lives in one bank
TARGET_SOURCES = ("drive.c", "drive_core.c", "link_fw.c", "main_sdcc.c")
TOOLCHAIN_SCRIPT = "scripts/pic_toolchain.sh"
#: SDCC options of every build (the HEX, the timing and the bit-exact builds): bank selection
#: and data-flow optimisation, no frame pointer where a function needs none (SDCC 4.2 does not
#: know --optimize-goto: it warns and ignores it, so it is not here)
#: SDCC's generic-pointer helpers reach data EEPROM through these symbols, which its (non-free)
#: device library provides.  picdrive's code never forms a pointer into EEPROM, so they are
#: unreachable: should one be reached anyway, reset (outputs off).  One copy for every SDCC
#: build: main_sdcc.c (codegen renders it in), the bit-exact test's and bench/link_pic18.py's harnesses.
EEPROM_GPTR_STUBS = """/* Contract: never reached (no pointer into EEPROM is formed); if reached, RESET: the chip
 * restarts with its outputs off. */
void eeprom_gptr_unused(void) __naked
{
    __asm
""" + "".join(f"    global ___eeprom_gptr{op}{n}\n" for op in ("get", "put") for n in (1, 2, 3, 4)) + \
    "".join(f"___eeprom_gptr{op}{n}:\n" for op in ("get", "put") for n in (1, 2, 3, 4)) + """    reset
    __endasm;
}
"""
#: drive_core.c as the bit-exact test builds it: with the C entry points the firmware itself
#: reaches only through the assembly (core_law, core_duty, core_speed_encoder on SDCC)
TEST_BUILD_CORE = '#define CORE_TEST_BUILD 1\n#include "drive_core.c"\n'
SDCC_FLAGS = ("-mpic16", "-p18f4431", "--std-c99", "--no-warn-non-free", "--obanksel=9", "--optimize-cmp",
              "--optimize-df", "--fomit-frame-pointer")


@dataclass(frozen=True)
class Budgets:
    """What a firmware may use on the 18F4431."""

    flash_bytes: int = 14_336             # 16 KB less 2 KB headroom
    ram_stack_bytes: int = 700            # static RAM + worst-case software stack, of 768
    speed_loop_fraction: float = 0.40     # speed-loop interrupt, of its period
    speed_loop_hz: int = 1_000            # ... at this rate (4,000 cycles at 10 MIPS)
    hall_isr_cycles: int = 200            # 20 us at 10 MIPS
    uart_rx_cycles: int = 100             # 10 us per received byte

    @property
    def speed_loop_cycles(self) -> int:
        return int(self.speed_loop_fraction * FCY_HZ / self.speed_loop_hz)


BUDGETS = Budgets()


class TargetError(PicdriveError):
    """The PIC18 build cannot be made (the message says why and what to do)."""


# ---------------------------------------------------------------------------
# Toolchain
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Toolchain:
    sdcc: Path
    lib_dir: Path          # share/sdcc/lib/pic16 (crt0iz.o, libsdcc.lib)
    gplink: str
    gpasm: str
    lkr: Path              # gputils' 18f4431_g.lkr

    @property
    def crt0(self) -> Path:
        """SDCC's start-up that initialises data and clears the rest of RAM at every reset (what C
        promises for statics; the generated fw_init relies on it: FW_BSS_ZEROED)."""
        return self.lib_dir / "crt0iz.o"

    @property
    def libsdcc(self) -> Path:
        return self.lib_dir / "libsdcc.lib"


def toolchain() -> Toolchain:
    """Find SDCC's pic16 port (``$PICDRIVE_TOOLCHAIN`` or scripts/pic_toolchain.sh's cache) and gputils."""
    root = Path(os.environ.get("PICDRIVE_TOOLCHAIN") or Path.home() / ".cache" / "picdrive" / "toolchain")
    prefix = root / "sdcc-4.2.0-pic16"
    sdcc = prefix / "bin" / "sdcc"
    lib = prefix / "share" / "sdcc" / "lib" / "pic16"
    missing = [str(p) for p in (sdcc, lib / "crt0iz.o", lib / "libsdcc.lib") if not p.is_file()]
    if missing:
        raise TargetError(f"the PIC18 compiler is not installed ({missing[0]} missing): run {TOOLCHAIN_SCRIPT} "
                          "(or set PICDRIVE_TOOLCHAIN to the folder it installed into)")
    gplink, gpasm = shutil.which("gplink"), shutil.which("gpasm")
    lkr = Path("/usr/share/gputils/lkr/18f4431_g.lkr")
    if not gplink or not gpasm or not lkr.is_file():
        raise TargetError("gputils (gpasm, gplink, 18f4431_g.lkr) is not installed: run scripts/setup.sh "
                          "(apt-get install gputils)")
    return Toolchain(sdcc, lib, gplink, gpasm, lkr)


# ---------------------------------------------------------------------------
# The map file
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Section:
    name: str
    kind: str        # code, romdata, udata, idata
    address: int
    location: str    # program, data
    size: int


@dataclass(frozen=True)
class Symbol:
    name: str
    address: int
    location: str
    storage: str     # extern, static
    file: str


_SECTION = re.compile(r"^\s*(\S+)\s+(code|romdata|udata|idata|udata_ovr|udata_acs|idata_acs|udata_shr)\s+"
                      r"0x([0-9a-f]+)\s+(program|data)\s+0x([0-9a-f]+)\s*$")
_SYMBOL = re.compile(r"^\s*(\S+)\s+0x([0-9a-f]+)\s+(program|data)\s+(extern|static)\s*(\S*)\s*$")


def parse_map(text: str) -> tuple[list[Section], list[Symbol]]:
    """Sections and symbols of a gplink ``.map`` (symbols from the by-address listing)."""
    sections, symbols = [], []
    part = None
    for line in text.splitlines():
        if "Section Info" in line:
            part = "sec"
        elif "Program Memory Usage" in line:
            part = None
        elif "Sorted by Address" in line:
            part = "sym"
        elif "Sorted by Name" in line:
            part = None
        elif part == "sec":
            m = _SECTION.match(line)
            if m:
                sections.append(Section(m[1], m[2], int(m[3], 16), m[4], int(m[5], 16)))
        elif part == "sym":
            m = _SYMBOL.match(line)
            if m:
                symbols.append(Symbol(m[1], int(m[2], 16), m[3], m[4], m[5]))
    return sections, symbols


def read_hex(path, flash_bytes: int = FLASH_BYTES) -> bytearray:
    """The program memory a linked HEX defines (erased bytes 0xFF), read and checked by
    :func:`picdrive.firmware.ihex.load_hex` (record checksums, overlaps, the 18F4431's memories;
    ``flash_bytes``: more for a measurement link, ``ENLARGED_FLASH_BYTES``)."""
    from .ihex import load_hex
    return load_hex(path, flash_bytes=flash_bytes).flash


# ---------------------------------------------------------------------------
# Call graph from the linked code
# ---------------------------------------------------------------------------
def _sfr(name: str) -> int:
    from .p18f4431 import registers
    return registers()[name]


POSTDEC1, POSTINC1, PREINC1, FSR1L = (_sfr(n) for n in ("POSTDEC1", "POSTINC1", "PREINC1", "FSR1L"))
TABLE_REGS = {_sfr(n): n for n in ("TABLAT", "TBLPTRL", "TBLPTRH", "TBLPTRU")}
ACCESS_SPLIT = 0x60          # 18F4431: access-bank addresses >= 0x60 are SFRs 0xF60..


@dataclass
class Function:
    """One function of the linked program."""

    name: str
    address: int
    size: int                      # bytes of code
    file: str                      # source module (.asm) it came from
    calls: set = field(default_factory=set)        # CALL/RCALL targets (function names)
    jumps: set = field(default_factory=set)        # GOTO/BRA into other functions (tail calls)
    frame: int = 0                 # most bytes this function has pushed at once (software stack)
    call_depths: dict = field(default_factory=dict)  # callee -> bytes pushed at the call
    table_read: bool = False       # executes TBLRD
    saves: set = field(default_factory=set)        # table registers pushed (MOVFF reg, POSTDEC1)
    static_data: bool = False      # a runtime-library helper keeping its operands in static RAM (not reentrant)
    indirect: int | None = None    # software-stack depth at its deepest indirect call (PUSH ... MOVWF PCL)


def _file_reg(word: int) -> int:
    """The data address a byte-oriented instruction addresses, as an access-bank address when a=0."""
    f, a = word & 0xFF, (word >> 8) & 1
    if a == 0:
        return 0xF00 + f if f >= ACCESS_SPLIT else f
    return -1   # banked: not an SFR this analysis follows


BRANCHES = {0xE0: "BZ", 0xE1: "BNZ", 0xE2: "BC", 0xE3: "BNC", 0xE4: "BOV", 0xE5: "BNOV", 0xE6: "BN", 0xE7: "BNN"}
_NAMED = {0x0012: ("return", 0), 0x0013: ("return", 1), 0x0010: ("retfie", 0), 0x0011: ("retfie", 1),
          0x0005: ("push", None), 0x0006: ("pop", None), 0x00FF: ("reset", None), 0x0003: ("sleep", None)}


def decode_insn(mem: bytes, pc: int) -> tuple[str, object, int, int, int]:
    """The PIC18 instruction at ``pc`` of program memory ``mem`` (beyond it reads as erased):
    ``(kind, operands, size in bytes, first word, second word)``.  The one Python decoder of
    picdrive (the call graph here; the processor twin's stop messages, picdrive_hil.pil): control
    flow by kind and target, the register moves the stack and table-pointer analyses follow, any
    other instruction as "other" with the register it reads or writes (or -1)."""
    def byte(a):
        return mem[a] if 0 <= a < len(mem) else 0xFF
    w = byte(pc) | (byte(pc + 1) << 8)
    w2 = byte(pc + 2) | (byte(pc + 3) << 8)
    hi = w >> 8
    if (w & 0xFE00) == 0xEC00 or hi == 0xEF:                # CALL (FAST: bit 8) / GOTO
        return ("call" if hi in (0xEC, 0xED) else "goto"), ((w & 0xFF) | ((w2 & 0xFFF) << 8)) * 2, 4, w, w2
    if (w & 0xF000) == 0xC000:                               # MOVFF src, dst
        return "movff", (w & 0xFFF, w2 & 0xFFF), 4, w, w2
    if (w & 0xFFC0) == 0xEE00:                               # LFSR
        return "lfsr", ((w >> 4) & 3, ((w & 0xF) << 8) | (w2 & 0xFF)), 4, w, w2
    if (w & 0xF000) == 0xD000:                               # RCALL / BRA
        n = w & 0x7FF
        n = n - 0x800 if n & 0x400 else n
        return ("rcall" if w & 0x0800 else "bra"), pc + 2 + 2 * n, 2, w, w2
    if hi in BRANCHES:                                       # conditional branch: (name, target)
        n = w & 0xFF
        return "bcc", (BRANCHES[hi], pc + 2 + 2 * (n - 0x100 if n & 0x80 else n)), 2, w, w2
    if 0x0008 <= w <= 0x000B:
        return "tblrd", None, 2, w, w2
    if w in _NAMED:
        kind, op = _NAMED[w]
        return kind, op, 2, w, w2
    if hi == 0x0C:
        return "retlw", w & 0xFF, 2, w, w2
    if hi == 0x0E:
        return "movlw", w & 0xFF, 2, w, w2
    if (w & 0xFE00) == 0x6E00:
        return "movwf", _file_reg(w), 2, w, w2
    if (w & 0xFC00) == 0x5000:
        return "movf", _file_reg(w), 2, w, w2
    if (w & 0xFC00) == 0x2400:
        return "addwf", (_file_reg(w), (w >> 9) & 1), 2, w, w2
    if (w & 0xFC00) == 0x5C00:
        return "subwf", (_file_reg(w), (w >> 9) & 1), 2, w, w2
    if (w & 0xFC00) in (0x6800, 0x6A00) or (w & 0xF000) in (0x7000, 0x8000, 0x9000):
        return "write", _file_reg(w), 2, w, w2                # SETF/CLRF, BTG/BSF/BCF: writes a register
    return "other", _file_reg(w) if 0x1000 <= w < 0x7000 else -1, 2, w, w2


def _decode(mem: bytes, start: int, end: int):
    """Yield (address, kind, operands) for the instructions in [start, end) (decode_insn)."""
    pc = start
    while pc < end:
        kind, op, size, _w, _w2 = decode_insn(mem, pc)
        yield pc, kind, op
        pc += size


_IVAL = re.compile(r"Starting pCode block for Ival\s*\n(?:\s*\S*\s+code\s*\n)?(_\w+):")


def const_tables(asm_text: str) -> set[str]:
    """Names of the const data tables SDCC places in program memory (not functions)."""
    return set(_IVAL.findall(asm_text))


def call_graph(mem: bytes, sections: list[Section], symbols: list[Symbol],
               tables: set[str] = frozenset()) -> dict[str, Function]:
    """Functions of the linked program with their calls, frames and table-pointer use.

    ``tables``: symbols in program memory that are data (``const_tables``), left out.
    """
    ends = {}
    starts: dict[int, tuple[str, str]] = {}
    code = [s for s in sections if s.location == "program" and s.kind == "code"]
    by_addr: dict[int, list[Symbol]] = {}
    for s in symbols:
        if s.location == "program":
            by_addr.setdefault(s.address, []).append(s)
    for sec in code:
        ends[sec.address] = sec.address + sec.size
        # the function's own (extern) name before a local label at the same address (a loop at entry)
        syms = sorted(by_addr.get(sec.address, []), key=lambda s: s.storage != "extern")
        name = syms[0].name if syms else sec.name
        file = syms[0].file if syms else ""
        starts[sec.address] = (name, file)
    for addr, syms in by_addr.items():
        for s in syms:
            if s.storage == "extern" and not s.name.startswith("_lab_") and addr not in starts:
                if any(c.address <= addr < c.address + c.size for c in code):
                    starts[addr] = (s.name, s.file)
    sec_end = {}
    for sec in code:
        for a in starts:
            if sec.address <= a < sec.address + sec.size:
                sec_end[a] = sec.address + sec.size
    order = sorted(starts)
    funcs: dict[str, Function] = {}
    addr_name = {}
    for i, a in enumerate(order):
        end = sec_end[a]
        if i + 1 < len(order) and order[i + 1] < end:
            end = order[i + 1]
        name, file = starts[a]
        if name in tables:
            continue
        funcs[name] = Function(name, a, end - a, file)
        addr_name[a] = name
    data_files = {s.file for s in symbols if s.location == "data" and s.address < 0xF00
                  and not s.name.startswith("r0x") and s.file}
    for f in funcs.values():
        f.static_data = f.file in data_files
        depth, w = 0, None
        for pc, kind, op in _decode(mem, f.address, f.address + f.size):
            if kind in ("call", "rcall", "goto", "bra"):
                if op in addr_name and op != f.address:
                    callee = addr_name[op]
                    if kind in ("call", "rcall"):
                        f.calls.add(callee)
                        f.call_depths[callee] = max(f.call_depths.get(callee, 0), depth)
                    else:
                        f.jumps.add(callee)
                        f.call_depths[callee] = max(f.call_depths.get(callee, 0), depth)
                elif not f.address <= op < f.address + f.size and kind in ("call", "rcall"):
                    f.calls.add(f"?0x{op:05x}")
            elif kind == "movlw":
                w = op
            elif kind == "movff":
                src, dst = op
                if dst == POSTDEC1:
                    depth += 1
                    if src in TABLE_REGS:
                        f.saves.add(TABLE_REGS[src])
                if src in (POSTINC1, PREINC1):
                    depth -= 1
            elif kind in ("movwf", "write") and op == POSTDEC1:
                depth += 1
            elif kind in ("movf", "other") and op in (POSTINC1, PREINC1):
                depth -= 1
            elif kind in ("addwf", "subwf") and op[0] == FSR1L and op[1] == 1 and w is not None:
                depth += -w if kind == "addwf" else w
            elif kind == "tblrd":
                f.table_read = True
            elif kind == "push":     # SDCC's indirect call pushes its return address, then writes PCL
                f.indirect = max(f.indirect or 0, depth)
            if kind != "movlw":
                w = None
            f.frame = max(f.frame, depth)
    return funcs


# ---------------------------------------------------------------------------
# Build
# ---------------------------------------------------------------------------
@dataclass
class Build:
    """A linked PIC18F4431 build and its figures."""

    hex_path: Path
    flash_bytes: int
    ram_bytes: int                 # static RAM (data sections, without the software stack)
    stack_bytes: int | None        # worst-case software stack: main + low ISR + high ISR (None: unbounded)
    hw_stack_levels: int | None    # worst-case return-address stack depth
    functions: dict                # name -> Function
    sizes: dict                    # function name -> bytes
    roots: dict                    # 'main', 'isr_low', 'isr_high' -> entry function name
    stack_by_root: dict            # root -> (software bytes, hardware levels)
    notes: list = field(default_factory=list)   # what could not be determined, and why
    on_chip: bool = True           # linked into the 18F4431's memory (False: an enlarged measurement script)

    @property
    def ram_stack_bytes(self) -> int | None:
        return None if self.stack_bytes is None else self.ram_bytes + self.stack_bytes

    def reachable(self, root: str) -> set[str]:
        """Function names reachable from a root ('main', 'isr_low', 'isr_high') or a function name."""
        start = self.roots.get(root, root)
        seen, todo = set(), [start]
        while todo:
            n = todo.pop()
            if n in seen or n not in self.functions:
                continue
            seen.add(n)
            f = self.functions[n]
            todo += list(f.calls | f.jumps)
        return seen


def _run(cmd, cwd, what):
    r = subprocess.run([str(c) for c in cmd], cwd=cwd, capture_output=True, text=True)
    if r.returncode != 0:
        err = "\n".join(l for l in (r.stdout + r.stderr).splitlines() if "1301" not in l and l.strip())
        lines = err.strip().splitlines()
        more = f"\n... ({len(lines) - 20} more lines)" if len(lines) > 20 else ""
        raise TargetError(f"{what} failed:\n" + "\n".join(lines[:20]) + more)
    return r


def _stack_asm(size: int) -> str:
    """The software stack section, ``size`` bytes; FSR1 starts at its last byte and grows down."""
    size = max(1, size)
    return ("; software stack for SDCC's pic16 code (picdrive.target: sized to the worst case)\n"
            "\tglobal _stack, _stack_end\n"
            "stack_section udata\n"
            + (f"_stack\tres D'{size - 1}'\n" if size > 1 else "_stack\n")
            + "_stack_end\tres D'1'\n\tend\n")


def _worst(funcs: dict[str, Function], root: str, memo: dict, path: tuple = ()) -> tuple[int, int]:
    """(software stack bytes, return-stack levels) of the deepest path from ``root``; raises on recursion."""
    if root in memo:
        return memo[root]
    if root in path:
        raise RecursionError(" -> ".join((*path, root)))
    f = funcs.get(root)
    if f is None:
        raise KeyError(root)
    sw, hw = f.frame, 0
    for callee, at in f.call_depths.items():
        csw, chw = _worst(funcs, callee, memo, (*path, root))
        sw = max(sw, at + csw)
        hw = max(hw, chw + (1 if callee in f.calls else 0))
    memo[root] = (sw, hw)
    return memo[root]


def _vector_target(mem, addr, addr_name) -> str | None:
    for _pc, kind, op in _decode(mem, addr, addr + 4):
        if kind in ("goto", "call", "bra") and op in addr_name:
            return addr_name[op]
    return None


def _write_device_table(tc: Toolchain, work: Path) -> None:
    """SDCC's device table with the 18F4431's access split at 0x80, into the build folder
    (SDCC reads pic16devices.txt from its include path, ``-I.`` first).  SDCC's own entry
    says 0x60 (right: 0xF60-0xF7F, the PCPWM/QEI/capture SFRs, are in the access bank) and
    then emits their accesses with no BANKSEL; gpasm 1.4 assembles any SFR below 0xF80 as
    BANKED, so on the chip those writes went to the GPR bank BSR selected and the PCPWM was
    never configured (found by the processor twin).  With 0x80 SDCC emits a
    BANKSEL (MOVLB 0xF) before them, which is what gpasm encodes."""
    src = tc.sdcc.parent.parent / "share" / "sdcc" / "include" / "pic16" / "pic16devices.txt"
    if not src.is_file():
        return
    lines, in_dev = [], False
    for line in src.read_text().splitlines():
        f = line.split()
        if f and f[0] == "name":
            in_dev = len(f) > 1 and f[1] == "18f4431"
        elif in_dev and f and f[0] == "split":
            line = "split       0x80"
        lines.append(line)
    (work / "pic16devices.txt").write_text("\n".join(lines) + "\n")


def build_hex(folder, out_dir, *, name: str = "firmware", linker_script=None, sources=TARGET_SOURCES,
              extra_c: dict | None = None, device: tuple[str, str] | None = None) -> Build:
    """Compile and link a generated firmware folder for the PIC18F4431; returns the ``Build``.

    ``out_dir`` receives the objects, ``<name>.hex``, ``.map`` and ``.cod``.
    ``linker_script`` replaces gputils' 18f4431_g.lkr (measurement builds
    only: a bigger memory for a firmware that does not fit, or a timing build).
    ``extra_c`` adds C files ({file name: text}) to the build (a harness);
    ``device`` replaces the rendered (xc.h, xc_sfr.c) (picdrive.gpsim's timing build).
    """
    from .p18f4431 import render_sdcc_device
    tc = toolchain()
    folder, out = Path(folder), Path(out_dir)
    missing = [s for s in sources if not (folder / s).is_file()]
    if missing:
        raise TargetError(f"{folder} has no {', '.join(missing)}: regenerate it with 'picdrive firmware'")
    out.mkdir(parents=True, exist_ok=True)
    work = out / "obj"
    if work.exists():
        shutil.rmtree(work)
    work.mkdir()
    for p in folder.iterdir():
        if p.is_file() and p.suffix in (".c", ".h"):
            shutil.copyfile(p, work / p.name)
    hdr, sfr = device or render_sdcc_device()
    _write_device_table(tc, work)
    (work / "xc.h").write_text(hdr)
    (work / "xc_sfr.c").write_text(sfr)
    for fn, text in (extra_c or {}).items():
        (work / fn).write_text(text)
    cfiles = [*sources, *(extra_c or {}), "xc_sfr.c"]
    for c in cfiles:
        _run([tc.sdcc, *SDCC_FLAGS, "-I.", "-c", c], work, f"sdcc {c}")
    objs = [tc.crt0, *[Path(c).with_suffix(".o").name for c in cfiles], "stack.o", tc.libsdcc]
    lkr = Path(linker_script) if linker_script else tc.lkr
    asm_text = "".join((work / Path(c).with_suffix(".asm").name).read_text() for c in cfiles)

    def link(stack: int):
        (work / "stack.asm").write_text(_stack_asm(stack))
        _run([tc.gpasm, "-p", "p18f4431", "-c", "stack.asm"], work, "gpasm stack.asm")
        _run([tc.gplink, "-m", "-w", "-s", lkr.resolve(), "-o", f"{name}.hex", *objs], work,
             "gplink (the firmware does not fit the PIC18F4431)" if linker_script is None else "gplink")
        sections, symbols = parse_map((work / f"{name}.map").read_text())
        return sections, symbols, read_hex(work / f"{name}.hex",
                                           FLASH_BYTES if linker_script is None else ENLARGED_FLASH_BYTES)

    sections, symbols, mem = link(1)
    tables = const_tables(asm_text)
    funcs = call_graph(mem, sections, symbols, tables)
    own = {Path(c).with_suffix(".asm").name for c in cfiles}
    for f in funcs.values():
        f.static_data = f.static_data and f.file not in own
    addr_name = {f.address: n for n, f in funcs.items()}
    roots = {"main": "_main"}
    for root, vec in (("isr_high", 0x08), ("isr_low", 0x18)):
        t = _vector_target(mem, vec, addr_name)
        if t:
            roots[root] = t
    notes = []
    taken = sorted(n for n in funcs if re.search(rf"\b(LOW|HIGH|UPPER)\s*\(\s*{re.escape(n)}\s*\)", asm_text)
                   and n not in tables)
    # an indirect call may reach any function whose address the C takes (SDCC's .asm: LOW/HIGH/UPPER(_f))
    callers = [f for f in funcs.values() if f.indirect is not None]
    for f in callers:
        for n in taken:
            f.calls.add(n)
            f.call_depths[n] = max(f.call_depths.get(n, 0), f.indirect)
    if callers and taken:
        notes.append(f"stack: {len(callers)} function(s) call through pointers; counted as calling each of the "
                     f"{len(taken)} functions whose address is taken")
    stack_by_root, stack, hw = {}, None, None
    try:
        memo = {}
        for r, fn in roots.items():
            stack_by_root[r] = _worst(funcs, fn, memo)
        unknown = sorted(c for f in funcs.values() for c in f.calls if c.startswith("?"))
        if callers and not taken:
            notes.append("stack: indirect calls, but no function address found in the .asm: not bounded")
        elif unknown:
            notes.append("stack: calls to addresses outside any function: " + ", ".join(unknown))
        else:
            # the high-priority interrupt may nest on the low one, both on main's deepest point
            stack = sum(v[0] for v in stack_by_root.values())
            hw = stack_by_root["main"][1] + sum(1 + stack_by_root[r][1] for r in ("isr_low", "isr_high")
                                                if r in stack_by_root)
    except RecursionError as e:
        notes.append(f"stack: recursion ({e}): not bounded")
    if stack is not None:
        if stack > STACK_MODEL_BYTES:
            notes.append(f"stack: the worst case, {stack} B, exceeds the {STACK_MODEL_BYTES} B one bank that "
                         "SDCC's small stack model (8-bit FSR1L frame pointer) addresses; linked with "
                         f"{STACK_MODEL_BYTES} B")
        sections, symbols, mem = link(min(stack, STACK_MODEL_BYTES))
    for ext in ("hex", "map", "cod"):
        shutil.copyfile(work / f"{name}.{ext}", out / f"{name}.{ext}")
    flash = sum(s.size for s in sections if s.location == "program" and s.address < 0x200000)
    ram = sum(s.size for s in sections if s.location == "data" and s.address < 0xF00
              and s.name != "stack_section")
    sizes = {n: f.size for n, f in funcs.items()}
    return Build(out / f"{name}.hex", flash, ram, stack, hw, funcs, sizes, roots, stack_by_root, notes,
                 on_chip=linker_script is None)


def enlarged_lkr() -> str:
    """18f4431_g.lkr with 128 KB of flash and 1.5 KB of RAM: measures a firmware that does not fit.

    A HEX linked with it is for measurement only (it cannot be flashed).
    """
    return "\n".join([
        "LIBPATH .",
        f"CODEPAGE   NAME=page       START=0x0               END=0x{ENLARGED_FLASH_BYTES - 1:X}",
        "CODEPAGE   NAME=idlocs     START=0x200000          END=0x200007       PROTECTED",
        "CODEPAGE   NAME=config     START=0x300000          END=0x30000D       PROTECTED",
        "CODEPAGE   NAME=devid      START=0x3FFFFE          END=0x3FFFFF       PROTECTED",
        "CODEPAGE   NAME=eedata     START=0xF00000          END=0xF000FF       PROTECTED",
        "ACCESSBANK NAME=accessram  START=0x0               END=0x5F",
        "ACCESSBANK NAME=accesssfr  START=0xF60             END=0xFFF          PROTECTED",
        "DATABANK   NAME=gpr0       START=0x60              END=0xFF",
        *[f"DATABANK   NAME=gpr{b}       START=0x{b:X}00           END=0x{b:X}FF" for b in range(1, 6)],
        ""])


def build_measured(folder, out_dir, name: str = "firmware") -> Build:
    """``build_hex`` into the 18F4431; if it does not fit, again with ``enlarged_lkr`` (``on_chip`` False)."""
    try:
        return build_hex(folder, out_dir, name=name)
    except TargetError as e:
        if "No target memory available" not in str(e):
            raise
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "enlarged.lkr").write_text(enlarged_lkr())
    return build_hex(folder, out_dir, name=name, linker_script=out / "enlarged.lkr")


# ---------------------------------------------------------------------------
# Budgets
# ---------------------------------------------------------------------------
def over_budget(build: Build, cycles: dict | None = None, budgets: Budgets | None = None) -> list[str]:
    """What exceeds its budget (empty: the firmware fits); ``cycles`` from picdrive.firmware.gpsim;
    ``budgets`` default: ``BUDGETS`` as it is at the call."""
    budgets = BUDGETS if budgets is None else budgets
    bad = []
    if not build.on_chip:
        bad.append("does not link into the 18F4431's memory")
    if build.flash_bytes > budgets.flash_bytes:
        bad.append(f"flash {build.flash_bytes} B > {budgets.flash_bytes} B")
    if build.ram_stack_bytes is None:
        bad.append("worst-case stack not bounded: " + "; ".join(build.notes))
    elif build.ram_stack_bytes > budgets.ram_stack_bytes:
        bad.append(f"static RAM + stack {build.ram_stack_bytes} B > {budgets.ram_stack_bytes} B")
    for key, limit in _cycle_budgets(budgets).items():
        if cycles is not None and cycles.get(key) is not None and cycles[key] > limit:
            bad.append(f"{key} {cycles[key]} cycles > {limit}")
    return bad


def _cycle_budgets(b: Budgets) -> dict[str, int]:
    return {"speed_loop_isr": b.speed_loop_cycles, "hall_isr": b.hall_isr_cycles, "uart_rx_byte": b.uart_rx_cycles}


def budget_lines(build: Build, cycles: dict | None = None, budgets: Budgets | None = None) -> list[str]:
    """The figures of a build against their budgets, one per line."""
    budgets = BUDGETS if budgets is None else budgets
    st = "not bounded" if build.stack_bytes is None else f"{build.stack_bytes} B"
    rs = "?" if build.ram_stack_bytes is None else f"{build.ram_stack_bytes} B"
    lines = [f"flash            {build.flash_bytes:6d} B   (budget {budgets.flash_bytes} B of {FLASH_BYTES})"
             + ("" if build.on_chip else "  -- does NOT fit: measured with an enlarged linker script"),
             f"RAM + stack      {rs:>8s}   (static {build.ram_bytes} B + stack {st}; budget "
             f"{budgets.ram_stack_bytes} B of {RAM_BYTES})",
             f"return stack     {build.hw_stack_levels if build.hw_stack_levels is not None else '?':>6} levels "
             f"(of {HW_STACK_LEVELS})"]
    for key, limit in _cycle_budgets(budgets).items():
        v = (cycles or {}).get(key)
        lines.append(f"{key:16s} {('?' if v is None else v):>6} cycles (budget {limit})")
    return lines + [f"note: {n}" for n in build.notes]


# ---------------------------------------------------------------------------
# Hazards only the compiled output shows
# ---------------------------------------------------------------------------
TABLE_SAVE = ("TBLPTRU", "TBLPTRH", "TBLPTRL", "TABLAT")


def unsaved_table_pointer(build: Build) -> dict[str, list[str]]:
    """Interrupts that (transitively) execute TBLRD without saving the table pointer.

    Returns {root: [functions that read tables]} for each interrupt whose entry
    does not push all of TBLPTRU/H/L and TABLAT; empty when none.
    """
    bad = {}
    for root in ("isr_high", "isr_low"):
        if root not in build.roots:
            continue
        readers = sorted(n for n in build.reachable(root) if build.functions[n].table_read)
        entry = build.functions[build.roots[root]]
        if readers and not set(TABLE_SAVE) <= entry.saves:
            bad[root] = readers
    return bad


def shared_static_helpers(build: Build) -> dict[str, set[str]]:
    """Runtime-library helpers with static operands reachable from an interrupt and from the main loop.

    Returns {helper: {roots it is reachable from}} for each helper reached
    from main and from at least one interrupt (an interrupt landing inside
    the main loop's call would overwrite its operands).
    """
    reach = {r: build.reachable(r) for r in build.roots}
    out = {}
    for n, f in build.functions.items():
        if not f.static_data:
            continue
        roots = {r for r, s in reach.items() if n in s}
        if "main" in roots and roots - {"main"}:
            out[n] = roots
    return out
