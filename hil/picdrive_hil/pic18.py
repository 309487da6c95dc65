"""The PIC18 instruction-set simulator (csrc/pic18cpu.c) from Python.

    cpu = Pic18.from_hex("firmware.hex")     # validated (ihex.HexError on a bad file)
    cpu.run(cycles=10_000)                   # or insns=, until=(0x0123, ...)
    cpu.pc, cpu.cycles, cpu.w, cpu.status, cpu.read(0x020)
    cpu.stop                                 # why it stopped: Stop(name, address, word, message)

The C library is built with the twin's helpers (build.py: content-hash cache,
the twin's flags) and loaded from a private copy, so each Pic18 is
independent.  Times are instruction cycles (Tcy = 4 / Fosc).
"""
from __future__ import annotations

import ctypes as C
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

from picdrive.firmware import ihex, p18f4431

from . import build

SOURCES = ("pic18cpu.c",)
HEADERS = ("pic18cpu.h",)
RAM_END = 0x300
FLASH_BYTES = ihex.FLASH_BYTES

STATUS_NAMES = {0: "ok", 1: "break", 2: "sleep", 3: "stack_overflow", 4: "stack_underflow",
                5: "reset_instruction", 16: "pc_outside_flash", 17: "illegal_opcode"}
FATAL = 16

# core register addresses, from p18f4431.inc
SFR = {n: p18f4431.registers()[n] for n in (
    "TOSU", "TOSH", "TOSL", "STKPTR", "PCLATU", "PCLATH", "PCL", "TBLPTRU", "TBLPTRH", "TBLPTRL", "TABLAT",
    "PRODH", "PRODL", "INTCON", "INTCON2", "INTCON3", "FSR0H", "FSR0L", "WREG", "FSR1H", "FSR1L", "BSR",
    "FSR2H", "FSR2L", "STATUS", "RCON")}
# pic18_snapshot's layout (then RAM 0x000-0x2FF)
SNAPSHOT_REGS = ("WREG", "STATUS", "BSR", "FSR0L", "FSR0H", "FSR1L", "FSR1H", "FSR2L", "FSR2H",
                 "PRODL", "PRODH", "TABLAT", "TBLPTRL", "TBLPTRH", "TBLPTRU", "STKPTR", "PCLATH", "PCLATU")


@dataclass(frozen=True)
class Stop:
    """Why the core stopped: ``name`` (STATUS_NAMES), the instruction's address and first word."""

    code: int
    address: int
    word: int

    @property
    def name(self) -> str:
        return STATUS_NAMES.get(self.code, f"status{self.code}")

    @property
    def fatal(self) -> bool:
        return self.code >= FATAL

    @property
    def message(self) -> str:
        a, w = self.address, self.word
        if self.code == 16:
            return f"PC left the flash: jump/fall-through to 0x{a:06X} (the 18F4431 has 0x0000-0x3FFF); core stopped"
        if self.code == 17:
            return (f"illegal or unimplemented opcode 0x{w:04X} at 0x{a:06X} (extended-set or undefined "
                    "instruction, or data executed as code); core stopped")
        if self.code == 3:
            return f"stack overflow (31st return-stack push) by the instruction at 0x{a:06X} (0x{w:04X})"
        if self.code == 4:
            return f"stack underflow (pop of an empty return stack) by the instruction at 0x{a:06X} (0x{w:04X})"
        if self.code == 5:
            return f"RESET instruction at 0x{a:06X}"
        return self.name


def library(gpsim_compat: bool = False) -> Path:
    """Build (cached) the simulator's shared library; returns its path.  `gpsim_compat`:
    the build that reproduces gpsim 0.31's known departures from the datasheet
    (docs/twin.md, "Processor core"), for the differential test only."""
    flags = build.twin_cflags() + build.core_cflags() + (("-DPIC18_GPSIM_COMPAT",) if gpsim_compat else ())
    g = build.Group(tuple(build.CSRC / s for s in SOURCES), (), flags,
                    tuple(build.CSRC / h for h in HEADERS))
    return build.build_library([g], name="libpic18gpsim" if gpsim_compat else "libpic18")


SFR_READ_FN = C.CFUNCTYPE(C.c_uint8, C.c_void_p, C.c_uint16)
SFR_WRITE_FN = C.CFUNCTYPE(None, C.c_void_p, C.c_uint16, C.c_uint8)


def _bind(lib: C.CDLL) -> C.CDLL:
    P, u8p = C.c_void_p, C.POINTER(C.c_uint8)
    sig = {
        "pic18_sizeof": (C.c_uint, []),
        "pic18_init": (None, [P]),
        "pic18_power_on": (None, [P]),
        "pic18_reset": (None, [P]),
        "pic18_load_flash": (None, [P, C.c_uint32, u8p, C.c_uint32]),
        "pic18_set_config": (None, [P, u8p]),
        "pic18_set_eeprom": (None, [P, u8p]),
        "pic18_set_idloc": (None, [P, u8p]),
        "pic18_run_bp": (C.c_int, [P, C.c_uint64, C.c_uint64, C.POINTER(C.c_uint32), C.c_int]),
        "pic18_peek": (C.c_uint8, [P, C.c_uint16]),
        "pic18_poke": (None, [P, C.c_uint16, C.c_uint8]),
        "pic18_info": (None, [P, C.POINTER(C.c_uint64)]),
        "pic18_stack_entry": (C.c_uint32, [P, C.c_uint]),
        "pic18_set_pc": (None, [P, C.c_uint32]),
        "pic18_set_irq": (None, [P, C.c_uint]),
        "pic18_set_timing": (None, [P, C.c_uint, C.c_uint]),
        "pic18_shadow": (None, [P, u8p]),
        "pic18_snapshot": (None, [P, u8p]),
        "pic18_flash_erase_row": (None, [P, C.c_uint32]),
        "pic18_flash_write_block": (None, [P, C.c_uint32]),
        "pic18_attach": (None, [P, P, SFR_READ_FN, SFR_WRITE_FN, u8p]),
    }
    for name, (res, args) in sig.items():
        f = getattr(lib, name)
        f.restype, f.argtypes = res, args
    return lib


_LIBS: dict[str, C.CDLL] = {}


def _lib(path: str | Path | None = None) -> C.CDLL:
    # the core has no globals: one loaded copy serves every Pic18
    key = str(path or library())
    if key not in _LIBS:
        _LIBS[key] = _bind(C.CDLL(key))
    return _LIBS[key]


def _u8(b: bytes | bytearray):
    return (C.c_uint8 * len(b)).from_buffer_copy(bytes(b))


class Pic18:
    """One PIC18F4431 core, powered on, flash erased (or loaded from a HEX image).
    `lib`: another build of the simulator's library (mutation checks)."""

    def __init__(self, image: ihex.HexImage | None = None, *, lib: str | Path | None = None):
        self._lib = _lib(lib)
        self._mem = C.create_string_buffer(self._lib.pic18_sizeof())
        self._p = C.cast(self._mem, C.c_void_p)
        self._info = (C.c_uint64 * 10)()
        self._lib.pic18_init(self._p)
        self.image = image
        if image is not None:
            self.load_image(image)

    @classmethod
    def from_hex(cls, path: str | Path) -> "Pic18":
        return cls(ihex.load_hex(path))

    def load_image(self, image: ihex.HexImage) -> None:
        """Program flash, config, ID and EEPROM from a validated image; power-on reset."""
        L, p = self._lib, self._p
        L.pic18_load_flash(p, 0, _u8(image.flash), len(image.flash))
        L.pic18_set_config(p, _u8(image.config))
        L.pic18_set_idloc(p, _u8(image.idloc))
        L.pic18_set_eeprom(p, _u8(image.eeprom))
        L.pic18_power_on(p)
        self.image = image

    def load_words(self, words: Iterable[int], addr: int = 0) -> None:
        """Program instruction words at a byte address (tests)."""
        b = bytearray()
        for w in words:
            b += bytes((w & 0xFF, (w >> 8) & 0xFF))
        self._lib.pic18_load_flash(self._p, addr, _u8(b), len(b))

    def set_config(self, config: bytes) -> None:
        if len(config) != ihex.CONFIG_N:
            raise ValueError("14 configuration bytes (CONFIG1L..CONFIG7H)")
        self._lib.pic18_set_config(self._p, _u8(config))

    # --- running
    def power_on(self) -> None:
        self._lib.pic18_power_on(self._p)

    def reset(self) -> None:
        """MCLR reset (a fatal stop is cleared)."""
        self._lib.pic18_reset(self._p)

    def run(self, cycles: int | None = None, insns: int | None = None,
            until: int | Iterable[int] | None = None) -> str:
        """Run until `cycles` more instruction cycles, `insns` more instructions, PC in
        `until` (checked before each instruction after the first), or a stop; returns the
        status name ("ok" when a limit was reached)."""
        big = (1 << 64) - 1
        bps = [] if until is None else ([until] if isinstance(until, int) else list(until))
        arr = (C.c_uint32 * max(1, len(bps)))(*bps)
        st = self._lib.pic18_run_bp(self._p, big if cycles is None else int(cycles),
                                    big if insns is None else int(insns), arr, len(bps))
        return STATUS_NAMES.get(st, str(st))

    def step(self, n: int = 1) -> str:
        return self.run(insns=n)

    def run_to_cycle(self, cycle: int, until: int | Iterable[int] | None = None) -> str:
        """Run until the cycle counter reaches `cycle` (absolute; the instruction that crosses
        it completes), PC in `until`, or a stop."""
        return self.run(cycles=max(0, cycle - self.cycles), until=until)

    def attach(self, read, write, owned: Iterable[int]) -> None:
        """A peripheral model in Python (tests; the twin's model attaches in C): `read(addr)`
        -> byte and `write(addr, value)` are called for the SFRs in `owned` (0xF60-0xFFF) at
        the cycle of the access (`self.cycles` inside the call); interrupts then come only
        from set_irq()."""
        mask = bytearray(256)
        for a in owned:
            if not 0xF60 <= a <= 0xFFF:
                raise ValueError(f"SFR address 0x{a:03X} outside 0xF60-0xFFF")
            mask[a & 0xFF] = 1
        self._cb = (SFR_READ_FN(lambda ctx, a: read(a) & 0xFF),
                    SFR_WRITE_FN(lambda ctx, a, v: write(a, v)))   # kept alive with the core
        self._lib.pic18_attach(self._p, None, self._cb[0], self._cb[1], _u8(mask))

    def set_irq(self, high: bool = False, low: bool = False) -> None:
        """The interrupt-request lines a peripheral model drives (switches off the built-in
        INTCON/PIR evaluation, which only the model-less core uses)."""
        self._lib.pic18_set_irq(self._p, (1 if high else 0) | (2 if low else 0))

    def set_timing(self, irq_vector_cycles: int = 2, table_cycles: int = 2) -> None:
        """Cycles of the interrupt vectoring and of TBLRD/TBLWT: the datasheet's 2 and 2
        by default (other values only to compare with gpsim, which takes 1 and 1)."""
        self._lib.pic18_set_timing(self._p, irq_vector_cycles, table_cycles)

    # --- state
    def _i(self, k: int) -> int:
        self._lib.pic18_info(self._p, self._info)
        return int(self._info[k])

    @property
    def pc(self) -> int:
        return self._i(0)

    @pc.setter
    def pc(self, v: int) -> None:
        self._lib.pic18_set_pc(self._p, v)

    @property
    def cycles(self) -> int:
        return self._i(1)

    @property
    def insns(self) -> int:
        return self._i(2)

    @property
    def status(self) -> str:
        return STATUS_NAMES.get(self._i(3), str(self._i(3)))

    @property
    def stop(self) -> Stop:
        self._lib.pic18_info(self._p, self._info)
        return Stop(int(self._info[3]), int(self._info[4]), int(self._info[5]))

    @property
    def stack_high(self) -> int:
        return self._i(7)

    @property
    def tblptr(self) -> int:
        return self._i(8)

    def read(self, addr: int) -> int:
        """A data-space byte (no FSR side effects)."""
        return int(self._lib.pic18_peek(self._p, addr))

    def write(self, addr: int, value: int) -> None:
        self._lib.pic18_poke(self._p, addr, value & 0xFF)

    def reg(self, name: str) -> int:
        return self.read(SFR[name])

    @property
    def w(self) -> int:
        return self.read(SFR["WREG"])

    @property
    def stkptr(self) -> int:
        return self._i(6)

    def stack(self) -> list[int]:
        """Return addresses, level 1 (bottom) .. SP (top)."""
        return [int(self._lib.pic18_stack_entry(self._p, k)) for k in range(1, (self.stkptr & 0x1F) + 1)]

    def shadow(self) -> tuple[int, int, int]:
        out = (C.c_uint8 * 3)()
        self._lib.pic18_shadow(self._p, out)
        return tuple(out)  # type: ignore[return-value]

    def snapshot(self) -> dict:
        """Core registers (SNAPSHOT_REGS), PC, cycles, stack, RAM 0x000-0x2FF: what the
        differential test compares."""
        out = (C.c_uint8 * (18 + RAM_END))()
        self._lib.pic18_snapshot(self._p, out)
        b = bytes(out)
        d = {k: b[i] for i, k in enumerate(SNAPSHOT_REGS)}
        d["PC"] = self.pc
        d["cycles"] = self.cycles
        d["stack"] = self.stack()
        d["ram"] = b[18:]
        return d
