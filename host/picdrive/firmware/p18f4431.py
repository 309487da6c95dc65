"""Microchip's ``p18f4431.inc``: register and bit names, and the host register shim.

The firmware is written against XC8's ``<xc.h>``: special-function registers
by name (``PDC0L``, ``OVDCOND``, ``TXREG``) and bit structs
(``PIR1bits.RCIF``), with the names of Microchip's MPASM include file
``p18f4431.inc`` (Debian package ``gputils``, folder
``/usr/share/gputils/header/``).  This module parses that file and renders,
from it and nothing typed by hand, the **host register shim** ``xc.h`` that
lets the same C compile with gcc (architecture.md, seam 4):

* every SFR is a byte of ``extern volatile uint8_t picsim_sfr[256]``, indexed
  by ``address - 0xF00``: ``#define TXREG (picsim_sfr[0xAD])``;
* ``REGbits`` is a union of bit structs overlaying the same byte, with the
  bit names of the ``.inc`` (``#define PIR1bits (*(volatile PIR1bits_t
  *)&picsim_sfr[0x9E])``; the unions are ``may_alias`` so that optimising
  compilers keep byte and bit accesses to the same register coherent); a register whose ``.inc`` section lists several
  names for one bit (``GIE``/``GIEH``/``GIE_GIEH``) gets them all;
* the port registers ``PORTA``..``PORTE`` (and their bit structs) call
  ``picsim_sfr_read(addr)`` at every access, so that a read sees the pins'
  levels at that moment (e.g. just after the firmware changed ``ANSEL0``),
  not the levels of the start of the firmware call;
* ``PICSIM_WRITE(REG)`` / ``PICSIM_READ(REG)`` call
  ``picsim_sfr_written(addr)`` / ``picsim_sfr_read(addr)`` with the full
  data-memory address (``0xFAD`` for TXREG); on XC8 the firmware defines them
  as nothing;
* ``__interrupt(x)``, ``NOP()``, ``CLRWDT()``, ``di()``, ``ei()`` compile to
  nothing (the interrupt entry points are called by the twin directly);
* ``PICSIM_ADDR_<REG>`` (full address) and ``PICSIM_<REG>_<BIT>_MASK``
  constants for the twin's peripheral model.

Names that the ``.inc`` gives to the low byte of a multi-byte register
(``TMR5`` = ``TMR5L``, ``ADRES`` = ``ADRESL``, ``PC`` = ``PCL``...) are XC8
16- or 24-bit objects, not bytes; the shim leaves them out so that a
firmware that uses them fails to compile on the host instead of silently
reading one byte.  The firmware uses the ``L``/``H`` bytes.
"""
from __future__ import annotations

import functools
import hashlib
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import PicdriveError

__all__ = ["IncError", "IncData", "INC_PATH", "SFR_BASE", "parse_inc", "registers", "bits",
           "config_settings", "shim_registers", "render_host_shim", "render_sdcc_device", "write_host_shim", "names_used"]

#: default location of the include file (Debian/Ubuntu package gputils)
INC_PATH = Path("/usr/share/gputils/header/p18f4431.inc")
#: environment variable that overrides :data:`INC_PATH`
INC_ENV = "PICDRIVE_P18F4431_INC"
#: data-memory address of picsim_sfr[0]
SFR_BASE = 0xF00


class IncError(PicdriveError):
    """``p18f4431.inc`` is missing or not in the expected form."""


@dataclass(frozen=True)
class IncData:
    """What the ``.inc`` defines.

    ``registers``: name -> data-memory address (aliases included, e.g. both
    ``TRISA`` and ``DDRA``).  ``bit_groups``: register -> list of groups, each
    a list of ``(bit_name, position)`` as the ``.inc`` lists them (one group
    per blank-line-separated block of the register's ``Bits`` section).
    ``config``: setting -> {value: description} from the ``CONFIG``
    directive listing (the names XC8's ``#pragma config`` takes).
    ``config_bytes``: ``_CONFIG1H`` etc. -> address.
    """

    path: str
    sha256: str
    registers: dict[str, int]
    bit_groups: dict[str, list[list[tuple[str, int]]]]
    config: dict[str, dict[str, str]]
    config_bytes: dict[str, int] = field(default_factory=dict)


_EQU = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)\s+EQU\s+H'([0-9A-Fa-f]+)'")
_SECTION = re.compile(r"^;-----\s+(.*?)\s+-{3,}\s*$")
_CFG_LINE = re.compile(r"^;\s+([A-Z0-9]+)\s*=\s*([A-Z0-9]+)\s+(.*?)\s*$")


def _inc_path(path: str | os.PathLike | None) -> Path:
    if path is not None:
        return Path(path)
    env = os.environ.get(INC_ENV)
    return Path(env) if env else INC_PATH


@functools.lru_cache(maxsize=4)
def _parse_cached(path: str, mtime_ns: int) -> IncData:
    text = Path(path).read_text(encoding="latin-1")
    registers: dict[str, int] = {}
    bit_groups: dict[str, list[list[tuple[str, int]]]] = {}
    config: dict[str, dict[str, str]] = {}
    config_bytes: dict[str, int] = {}
    section: str | None = None
    current: list[tuple[str, int]] | None = None
    in_config_listing = False
    for raw in text.splitlines():
        line = raw.rstrip()
        m = _SECTION.match(line)
        if m:
            title = m.group(1)
            current = None
            if title == "Register Files":
                section = "registers"
            elif title.endswith(" Bits"):
                section = "bits:" + title[:-5].strip()
                bit_groups.setdefault(section[5:], [])
            else:
                section = "other"
            in_config_listing = False
            continue
        if "superseded by the CONFIG directive" in line:
            in_config_listing = True
            section = "other"
            continue
        if in_config_listing:
            m = _CFG_LINE.match(line)
            if m:
                config.setdefault(m.group(1), {})[m.group(2)] = m.group(3)
            elif line.startswith(";====") and config:
                in_config_listing = False
            continue
        if not line.strip():
            current = None
            continue
        if line.lstrip().startswith(";"):
            continue
        m = _EQU.match(line.strip())
        if not m:
            continue
        name, value = m.group(1), int(m.group(2), 16)
        if name.startswith("_CONFIG"):
            config_bytes[name] = value
            continue
        if section == "registers":
            registers[name] = value
        elif section and section.startswith("bits:"):
            reg = section[5:]
            if value > 7:
                raise IncError(f"{path}: bit {name} of {reg} has position {value}, expected 0..7")
            if current is None:
                current = []
                bit_groups[reg].append(current)
            current.append((name, value))
    if not registers:
        raise IncError(f"{path} has no 'Register Files' section: not a Microchip MPASM include file")
    for reg in bit_groups:
        if reg not in registers:
            raise IncError(f"{path}: bits section for {reg!r}, which is not a register in the file")
    return IncData(path=path, sha256=hashlib.sha256(text.encode("latin-1")).hexdigest(),
                   registers=registers, bit_groups={k: v for k, v in bit_groups.items() if v},
                   config=config, config_bytes=config_bytes)


def parse_inc(path: str | os.PathLike | None = None) -> IncData:
    """Parse ``p18f4431.inc`` (default :data:`INC_PATH`, or ``$PICDRIVE_P18F4431_INC``)."""
    p = _inc_path(path)
    try:
        st = p.stat()
    except OSError:
        raise IncError(f"Microchip's register header {p} is missing: install gputils "
                       f"('apt-get install gputils', or run scripts/setup.sh), or point "
                       f"${INC_ENV} at a copy of p18f4431.inc") from None
    return _parse_cached(str(p), st.st_mtime_ns)


def registers(path=None) -> dict[str, int]:
    """SFR name -> data-memory address (0xF60..0xFFF), aliases included."""
    return dict(parse_inc(path).registers)


def bits(path=None) -> dict[str, dict[str, int]]:
    """Register -> {bit name: position} for every register with a ``Bits`` section."""
    out: dict[str, dict[str, int]] = {}
    for reg, groups in parse_inc(path).bit_groups.items():
        d: dict[str, int] = {}
        for group in groups:
            for name, pos in group:
                if name in d and d[name] != pos:
                    raise IncError(f"bit {reg}.{name} listed at positions {d[name]} and {pos}")
                d[name] = pos
        out[reg] = d
    return out


def config_settings(path=None) -> dict[str, dict[str, str]]:
    """``#pragma config`` setting -> {value: description} (``OSC`` -> ``HSPLL``...)."""
    return {k: dict(v) for k, v in parse_inc(path).config.items()}


def shim_registers(path=None) -> dict[str, int]:
    """The byte-wide SFR names the shim defines.

    Leaves out names for the low byte of a multi-byte register (``X`` when
    ``XL`` is at the same address: ``TMR5``, ``ADRES``, ``PROD``, ``PC``...),
    which XC8 declares as 16/24-bit objects.
    """
    regs = parse_inc(path).registers
    return {n: a for n, a in regs.items()
            if not (n + "L" in regs and regs[n + "L"] == a)}


def _bit_structs(groups: list[list[tuple[str, int]]]) -> list[list[tuple[str, int]]]:
    """Split the ``.inc`` groups into structs with one name per position and
    no name repeated across the union (anonymous members must be unique)."""
    seen: dict[str, int] = {}
    structs: list[list[tuple[str, int]]] = []
    for group in groups:
        pending = []
        for name, pos in group:
            if name in seen:
                continue
            seen[name] = pos
            pending.append((name, pos))
        while pending:
            used: set[int] = set()
            this, rest = [], []
            for name, pos in pending:
                (rest if pos in used else this).append((name, pos))
                used.add(pos)
            structs.append(sorted(this, key=lambda t: t[1]))
            pending = rest
    return structs


def _struct_members(fields: list[tuple[str, int]], ctype: str) -> str:
    """One byte's bit-field members, padding the gaps: ``ctype NAME:1;`` per named bit."""
    parts, pos = [], 0
    for name, p in fields:
        if p > pos:
            parts.append(f"{ctype} :{p - pos};")
        parts.append(f"{ctype} {name}:1;")
        pos = p + 1
    if pos < 8:
        parts.append(f"{ctype} :{8 - pos};")
    return " ".join(parts)


def _struct_c(fields: list[tuple[str, int]]) -> str:
    return "    __extension__ struct { " + _struct_members(fields, "uint8_t") + " };"


PIN_READ_REGISTERS = ("PORTA", "PORTB", "PORTC", "PORTD", "PORTE")
"""Registers whose every access notifies ``picsim_sfr_read``: a port read returns the pins'
levels at that instant (the model refreshes the byte), as on the chip."""


def render_host_shim(path=None) -> str:
    """The host ``xc.h``: SFRs in ``picsim_sfr[256]``, bit structs, notifications.

    Deterministic: the same ``.inc`` gives the same bytes.
    """
    inc = parse_inc(path)
    regs = shim_registers(path)
    skipped = sorted(set(inc.registers) - set(regs))
    for n, a in regs.items():
        if not SFR_BASE <= a <= SFR_BASE + 0xFF:
            raise IncError(f"register {n} at 0x{a:X} is outside the SFR page 0xF00..0xFFF")
    by_addr = sorted(regs.items(), key=lambda t: (t[1], t[0]))
    L: list[str] = []
    w = L.append
    w("/* xc.h -- host register shim for the PIC18F4431 firmware.")
    w(" *")
    w(" * GENERATED by picdrive.p18f4431.render_host_shim() from Microchip's")
    w(f" * p18f4431.inc (sha256 {inc.sha256[:16]}...).  Do not edit: regenerate.")
    w(" *")
    w(" * Every SFR is one byte of picsim_sfr[], indexed by (address - 0xF00).  The")
    w(" * storage and the two notification functions are provided by the twin's")
    w(" * peripheral model (or a test stub).  PICSIM_WRITE(REG) after a write and")
    w(" * PICSIM_READ(REG) before a read tell the model about accesses that have a")
    w(" * side effect on the chip; the address passed is the full data-memory")
    w(" * address (0xF00 + index).  On XC8 these macros are defined empty by the")
    w(" * firmware.  The port registers (PORTA..PORTE) notify picsim_sfr_read at")
    w(" * every access by themselves, so that a pin read sees the pin's level then.")
    w(" *")
    w(" * Not defined here (XC8 declares them 16/24-bit; use the L/H bytes):")
    for i in range(0, len(skipped), 8):
        w(" *   " + " ".join(skipped[i:i + 8]))
    w(" */")
    w("#ifndef PICDRIVE_XC_SHIM_H")
    w("#define PICDRIVE_XC_SHIM_H")
    w("")
    w("#include <stdint.h>")
    w("")
    w("#define PICSIM_HOST 1")
    w("#define PICSIM_SFR_BASE 0x0F00u")
    w("")
    w("extern volatile uint8_t picsim_sfr[256];")
    w("void picsim_sfr_written(uint16_t addr);")
    w("void picsim_sfr_read(uint16_t addr);")
    w("")
    w("#define PICSIM_ADDR_OF(reg) ((uint16_t)(PICSIM_SFR_BASE + (uint16_t)(&(reg) - &picsim_sfr[0])))")
    w("#define PICSIM_WRITE(reg) picsim_sfr_written(PICSIM_ADDR_OF(reg))")
    w("#define PICSIM_READ(reg) picsim_sfr_read(PICSIM_ADDR_OF(reg))")
    w("")
    w("#define __interrupt(x)")
    w("#define NOP() ((void)0)")
    w("#define CLRWDT() ((void)0)")
    w("#define di() ((void)0)")
    w("#define ei() ((void)0)")
    w("")
    w("/* ---- special-function registers ---- */")
    for n, a in by_addr:
        if n in PIN_READ_REGISTERS:
            w(f"#define {n} (*(picsim_sfr_read(0x{a:03X}u), &picsim_sfr[0x{a - SFR_BASE:02X}]))")
        else:
            w(f"#define {n} (picsim_sfr[0x{a - SFR_BASE:02X}])")
    w("")
    w("/* ---- full data-memory addresses (for the peripheral model) ---- */")
    for n, a in by_addr:
        w(f"#define PICSIM_ADDR_{n} 0x{a:03X}u")
    w("")
    w("/* ---- bit structs: REGbits.BIT, names as in p18f4431.inc ---- */")
    for reg in sorted(inc.bit_groups, key=lambda r: (inc.registers[r], r)):
        if reg not in regs:
            continue
        a = inc.registers[reg]
        w("typedef union __attribute__((__may_alias__)) {")
        w("    uint8_t picsim_byte;   /* whole register (host shim only; not in XC8) */")
        for fields in _bit_structs(inc.bit_groups[reg]):
            w(_struct_c(fields))
        w(f"}} {reg}bits_t;")
        if reg in PIN_READ_REGISTERS:
            w(f"#define {reg}bits (*(volatile {reg}bits_t *)(picsim_sfr_read(0x{a:03X}u), "
              f"&picsim_sfr[0x{a - SFR_BASE:02X}]))")
        else:
            w(f"#define {reg}bits (*(volatile {reg}bits_t *)&picsim_sfr[0x{a - SFR_BASE:02X}])")
    w("")
    w("/* ---- bit masks (for the peripheral model) ---- */")
    b = bits(path)
    for reg in sorted(b, key=lambda r: (inc.registers[r], r)):
        if reg not in regs:
            continue
        for name, pos in sorted(b[reg].items(), key=lambda t: (t[1], t[0])):
            w(f"#define PICSIM_{reg}_{name}_MASK 0x{1 << pos:02X}u")
    w("")
    w("#endif /* PICDRIVE_XC_SHIM_H */")
    return "\n".join(L) + "\n"


def _struct_sdcc(fields: list[tuple[str, int]]) -> str:
    return "    struct { " + _struct_members(fields, "unsigned") + " };"


def render_sdcc_device(path=None) -> tuple[str, str]:
    """The target ``xc.h`` for SDCC's pic16 port and the C file that places the SFRs.

    SDCC ships no free PIC18F4431 header (Debian's source package removes
    Microchip's), so the device support is rendered from the same ``.inc`` as
    the host shim: ``extern __at(addr) volatile uint8_t REG;`` and
    ``REGbits`` unions, declared in the header and defined once in the
    returned C file (the start-up code and SDCC's runtime library refer to
    ``_TBLPTRU``, ``_POSTINC0``... by symbol, so every SFR is defined).
    ``PICSIM_WRITE`` / ``PICSIM_READ`` compile to nothing; ``NOP()``,
    ``di()`` / ``ei()`` map to the instructions and ``GIEH``.

    Returns ``(header, c_source)``; deterministic for a given ``.inc``.
    """
    inc = parse_inc(path)
    regs = shim_registers(path)
    by_addr = sorted(regs.items(), key=lambda t: (t[1], t[0]))
    head = [
        "/* xc.h -- PIC18F4431 device support for SDCC's pic16 port.",
        " *",
        " * GENERATED by picdrive.p18f4431.render_sdcc_device() from Microchip's",
        f" * p18f4431.inc (sha256 {inc.sha256[:16]}...).  Do not edit: regenerate.",
        " * The SFRs are placed by xc_sfr.c; names as in the .inc, byte-wide only",
        " * (use the L/H bytes of 16-bit registers, as with the host shim).",
        " */",
        "#ifndef PICDRIVE_XC_SDCC_H",
        "#define PICDRIVE_XC_SDCC_H",
        "",
        "#include <stdint.h>",
        "",
        "#define PICSIM_WRITE(reg) ((void)0)",
        "#define PICSIM_READ(reg) ((void)0)",
        "#define NOP() do { __asm nop __endasm; } while (0)",
        "#define CLRWDT() do { __asm clrwdt __endasm; } while (0)",
        "#define di() (INTCONbits.GIEH = 0)",
        "#define ei() (INTCONbits.GIEH = 1)",
        "",
    ]
    body = ["/* xc_sfr.c -- PIC18F4431 SFR placement for SDCC (see xc.h).",
            " *",
            " * GENERATED by picdrive.p18f4431.render_sdcc_device().  Do not edit: regenerate.",
            " */",
            '#include "xc.h"', ""]
    for n, a in by_addr:
        head.append(f"extern __at(0x{a:03X}) volatile uint8_t {n};")
        body.append(f"__at(0x{a:03X}) volatile uint8_t {n};")
    head.append("")
    body.append("")
    for reg in sorted(inc.bit_groups, key=lambda r: (inc.registers[r], r)):
        if reg not in regs:
            continue
        a = inc.registers[reg]
        head.append("typedef union {")
        for fields in _bit_structs(inc.bit_groups[reg]):
            head.append(_struct_sdcc(fields))
        head.append(f"}} __{reg}bits_t;")
        head.append(f"extern __at(0x{a:03X}) volatile __{reg}bits_t {reg}bits;")
        body.append(f"__at(0x{a:03X}) volatile __{reg}bits_t {reg}bits;")
    head += ["", "#endif /* PICDRIVE_XC_SDCC_H */"]
    return "\n".join(head) + "\n", "\n".join(body) + "\n"


def write_host_shim(folder, path=None) -> Path:
    """Write ``xc.h`` into ``folder`` (atomically); returns its path."""
    from ..fileio import atomic_write_text
    return atomic_write_text(Path(folder) / "xc.h", render_host_shim(path))


# ---------------------------------------------------------------------------
# Which SFR and bit names does a C source use?
# ---------------------------------------------------------------------------
_BITS_USE = re.compile(r"\b([A-Z][A-Z0-9_]*)bits\s*\.\s*([A-Za-z_][A-Za-z0-9_]*)")
_IDENT = re.compile(r"\b[A-Z][A-Z0-9_]*\b")
_DEFINE = re.compile(r"^\s*#\s*define\s+([A-Za-z_][A-Za-z0-9_]*)", re.M)
_COMMENT = re.compile(r"/\*.*?\*/|//[^\n]*", re.S)
_STRING = re.compile(r'"(?:\\.|[^"\\])*"|\'(?:\\.|[^\'\\])*\'')
_PRAGMA = re.compile(r"^\s*#\s*(pragma|include|error|warning)[^\n]*", re.M)


def names_used(c_sources: list[str], path=None) -> tuple[set[str], set[tuple[str, str]], set[str]]:
    """SFR names, ``(register, bit)`` pairs, and other upper-case identifiers used by C sources.

    Comments, strings, ``#pragma``/``#include`` lines and ``__asm``...``__endasm`` blocks are ignored.  Returns
    ``(sfrs, bit_uses, unknown)`` where ``unknown`` are upper-case
    identifiers that are neither SFRs of the ``.inc`` nor ``#define``'d in the
    sources themselves nor standard C macros: a test asserts it is empty.
    """
    regs = parse_inc(path).registers
    text = "\n".join(c_sources)
    text = _COMMENT.sub(" ", text)
    text = _STRING.sub(" ", text)
    text = re.sub(r"\b__asm\b.*?\b__endasm\b", " ", text, flags=re.S)   # inline assembly: mnemonics
    defined = set(_DEFINE.findall(text))
    text = _PRAGMA.sub(" ", text)
    bit_uses = {(r, b) for r, b in _BITS_USE.findall(text)}
    stripped = _BITS_USE.sub(" ", text)
    # enum constants and upper-case variables are declared in the sources too
    declared = set()
    for prev, name in re.findall(r"(\}|\b[A-Za-z_]\w*)\s*\**\s+([A-Z][A-Z0-9_]*)\s*(?:;|=|\[)", text):
        if prev not in ("return", "case", "goto", "else", "sizeof", "do"):
            declared.add(name)
    for body in re.findall(r"\benum\b[^{;]*\{([^}]*)\}", text):
        declared |= set(re.findall(r"\b([A-Za-z_][A-Za-z0-9_]*)\s*(?:=[^,]*)?(?:,|$)", body.strip()))
    std = {"NULL", "UINT32_C", "INT32_C", "UINT16_C", "INT16_C", "INT8_MIN", "INT8_MAX", "UINT8_MAX", "INT16_MIN", "INT16_MAX", "UINT16_MAX",
           "INT32_MIN", "INT32_MAX", "UINT32_MAX", "__FILE__", "__LINE__"}
    sfrs, unknown = set(), set()
    for ident in _IDENT.findall(stripped):
        if ident in regs:
            sfrs.add(ident)
        elif ident not in defined and ident not in declared and ident not in std:
            unknown.add(ident)
    sfrs |= {r for r, _ in bit_uses if r in regs}
    return sfrs, bit_uses, unknown
