"""Intel HEX (INHX32) images for the PIC18F4431, strictly validated: the one HEX reader of
picdrive (the firmware build's call-graph analysis, picdrive.firmware.target, and the
processor twin, picdrive_hil, both read through it).

A HEX from gputils, SDCC or XC8 addresses bytes: program flash 0x0000-0x3FFF
(16 KB), user ID 0x200000-0x200007, configuration bytes 0x300000-0x30000D
(CONFIG1L..CONFIG7H) and data EEPROM 0xF00000-0xF000FF.  Every record is
checked (``:``, hex digits, length, checksum, type); a byte defined twice, a
byte outside those regions, data after the end record or a missing end record
is refused with the line number, the address and what to do.  Record types
03/05 (start address) are checked and ignored: a PIC18 starts at 0x0000.

The configuration bytes the simulator depends on: CONFIG4L bit 0 (STVREN,
stack full/underflow reset) is honoured; bit 6 is XINST on the PIC18 parts
that have the extended instruction set -- the 18F4431 has none, so a HEX that
sets it was built for another device (or with the extended set on) and is
refused.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from picdrive.errors import PicdriveError

FLASH_BYTES = 0x4000
IDLOC_BASE, IDLOC_N = 0x200000, 8
CONFIG_BASE, CONFIG_N = 0x300000, 14
EEPROM_BASE, EEPROM_N = 0xF00000, 256
DEVID_BASE = 0x3FFFFE

# unprogrammed configuration bytes of the 18F4431 (DS39616 Table 23-1), CONFIG1L..CONFIG7H
CONFIG_DEFAULT = bytes([0xFF, 0xCF, 0x0F, 0x3F, 0x3C, 0x9D, 0x85, 0xFF,
                        0x0F, 0xC0, 0x0F, 0xE0, 0x0F, 0x40])
CONFIG_NAMES = ("CONFIG1L", "CONFIG1H", "CONFIG2L", "CONFIG2H", "CONFIG3L", "CONFIG3H", "CONFIG4L",
                "CONFIG4H", "CONFIG5L", "CONFIG5H", "CONFIG6L", "CONFIG6H", "CONFIG7L", "CONFIG7H")
CONFIG4L_STVREN = 0x01
CONFIG4L_XINST = 0x40


class HexError(PicdriveError):
    """The HEX file is malformed or is not a PIC18F4431 image."""


@dataclass
class HexImage:
    """What a HEX programs: flash bytes (erased = 0xFF), config, ID, EEPROM."""

    flash: bytearray = field(default_factory=lambda: bytearray(b"\xff" * FLASH_BYTES))
    config: bytearray = field(default_factory=lambda: bytearray(CONFIG_DEFAULT))
    idloc: bytearray = field(default_factory=lambda: bytearray(b"\xff" * IDLOC_N))
    eeprom: bytearray = field(default_factory=lambda: bytearray(b"\xff" * EEPROM_N))
    flash_used: int = 0          # bytes of flash the HEX defines
    flash_top: int = 0           # highest flash address defined + 1
    config_given: set[int] = field(default_factory=set)

    @property
    def stvren(self) -> bool:
        return bool(self.config[6] & CONFIG4L_STVREN)


def _where(name: str, lineno: int) -> str:
    return f"{name}:{lineno}"


def parse_hex(text: str, name: str = "<hex>", *, flash_bytes: int = FLASH_BYTES) -> HexImage:
    """Parse and validate the text of a HEX file; returns its image or raises HexError.
    ``flash_bytes``: the program memory (the 18F4431's 16 KB; larger only for the processor
    twin's explicit enlarged-memory option)."""
    img = HexImage(flash=bytearray(b"\xff" * flash_bytes))
    base = 0
    seen: dict[int, int] = {}          # byte address -> line that defined it
    ended = False
    nrec = 0
    beyond: list[tuple[int, str]] = []  # program addresses past the flash, judged once the file is read
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line:
            continue
        at = _where(name, lineno)
        if ended:
            raise HexError(f"{at}: record after the end-of-file record (type 01); "
                           "remove what follows it or re-export the HEX")
        if not line.startswith(":"):
            raise HexError(f"{at}: a record must start with ':' (got {line[:12]!r}); "
                           "this is not an Intel HEX file")
        body = line[1:]
        if len(body) % 2 or len(body) < 10:
            raise HexError(f"{at}: record of odd or too short length ({len(body)} hex digits); "
                           "the file is truncated or corrupted: rebuild it")
        try:
            rec = bytes.fromhex(body)
        except ValueError:
            raise HexError(f"{at}: non-hex character in the record; the file is corrupted: rebuild it") from None
        n, addr16, rtype = rec[0], (rec[1] << 8) | rec[2], rec[3]
        data = rec[4:-1]
        if len(data) != n:
            raise HexError(f"{at}: byte count {n} but {len(data)} data bytes; "
                           "the record is truncated: rebuild the HEX")
        if sum(rec) & 0xFF:
            want = (-sum(rec[:-1])) & 0xFF
            raise HexError(f"{at}: checksum 0x{rec[-1]:02X} wrong (should be 0x{want:02X}); "
                           "the file is corrupted: rebuild or re-download it")
        nrec += 1
        if rtype == 0x00:
            for i, b in enumerate(data):
                a = base + addr16 + i
                if a in seen:
                    raise HexError(f"{at}: address 0x{a:06X} already defined on line {seen[a]} "
                                   "(overlapping records); the HEX was merged badly: rebuild it")
                seen[a] = lineno
                if flash_bytes == FLASH_BYTES and FLASH_BYTES <= a < IDLOC_BASE:
                    beyond.append((a, at))
                    continue
                _place(img, a, b, at, flash_bytes)
        elif rtype == 0x01:
            if n:
                raise HexError(f"{at}: end-of-file record with {n} data bytes (must have none)")
            ended = True
        elif rtype == 0x02:
            if n != 2:
                raise HexError(f"{at}: extended segment address record needs 2 data bytes, has {n}")
            base = ((data[0] << 8) | data[1]) << 4
        elif rtype == 0x04:
            if n != 2:
                raise HexError(f"{at}: extended linear address record needs 2 data bytes, has {n}")
            base = ((data[0] << 8) | data[1]) << 16
        elif rtype in (0x03, 0x05):
            if n != 4:
                raise HexError(f"{at}: start address record (type {rtype:02X}) needs 4 data bytes, has {n}")
            # ignored: a PIC18 starts at its reset vector 0x0000
        else:
            raise HexError(f"{at}: unknown record type {rtype:02X} (Intel HEX has 00-05); "
                           "this is not an INHX32 file: export Intel HEX from the toolchain")
    if not nrec:
        raise HexError(f"{name}: no HEX records in the file; give the .hex your compiler wrote")
    if not ended:
        raise HexError(f"{name}: no end-of-file record (:00000001FF); the file is truncated: rebuild it")
    if beyond:
        _refuse_beyond_flash(beyond, seen, img)
    cfg4l = img.config[6]
    if CONFIG_BASE + 6 in img.config_given and cfg4l & CONFIG4L_XINST:
        raise HexError(f"{name}: CONFIG4L (0x300006) = 0x{cfg4l:02X} sets bit 6, XINST (extended instruction "
                       "set): the PIC18F4431 has no extended set; build with XINST = OFF for the 18F4431")
    return img


def _place(img: HexImage, a: int, b: int, at: str, flash_bytes: int = FLASH_BYTES) -> None:
    if a < flash_bytes:
        img.flash[a] = b
        img.flash_used += 1
        img.flash_top = max(img.flash_top, a + 1)
    elif a < 0x200000 and flash_bytes != FLASH_BYTES:
        raise HexError(f"{at}: program address 0x{a:06X} is beyond the enlarged program memory "
                       f"(0x0000-0x{flash_bytes - 1:05X})")
    elif IDLOC_BASE <= a < IDLOC_BASE + IDLOC_N:
        img.idloc[a - IDLOC_BASE] = b
    elif CONFIG_BASE <= a < CONFIG_BASE + CONFIG_N:
        img.config[a - CONFIG_BASE] = b
        img.config_given.add(a)
    elif EEPROM_BASE <= a < EEPROM_BASE + EEPROM_N:
        img.eeprom[a - EEPROM_BASE] = b
    elif DEVID_BASE <= a <= DEVID_BASE + 1:
        raise HexError(f"{at}: address 0x{a:06X} is the device ID (read-only); remove it from the HEX")
    elif CONFIG_BASE <= a < CONFIG_BASE + 0x100:
        raise HexError(f"{at}: configuration address 0x{a:06X} does not exist on the 18F4431 "
                       "(CONFIG1L..CONFIG7H are 0x300000-0x30000D): this HEX is for another device")
    elif EEPROM_BASE <= a < EEPROM_BASE + 0x10000:
        raise HexError(f"{at}: EEPROM address 0x{a:06X} is beyond the 18F4431's 256 bytes "
                       "(0xF00000-0xF000FF): this HEX is for another device")
    else:
        raise HexError(f"{at}: address 0x{a:06X} is outside every PIC18F4431 memory (flash 0x0000-0x3FFF, "
                       "ID 0x200000-7, config 0x300000-D, EEPROM 0xF00000-FF); is this a HEX for this chip?")


PIC16_WORDS = {0x2000: "its user ID locations (words 0x2000-0x2003)",
               0x2007: "its configuration word (word 0x2007)", 0x2008: "its second configuration word (0x2008)",
               0x2100: "its data EEPROM (words 0x2100-0x21FF)"}
"""Where a mid-range PIC (PIC12/PIC16, 14-bit words, byte address = 2 x word) HEX puts what is
not program: byte addresses 0x4000-0x43FF, just past the 18F4431's flash."""


def _pic16_region(a: int) -> str | None:
    w = a // 2
    if 0x2000 <= w <= 0x2003:
        return PIC16_WORDS[0x2000]
    if w in (0x2007, 0x2008):
        return PIC16_WORDS[w]
    if 0x2100 <= w <= 0x21FF:
        return PIC16_WORDS[0x2100]
    return None


def _refuse_beyond_flash(beyond: list[tuple[int, str]], seen: dict[int, int], img: HexImage) -> None:
    """Program addresses past the 16 KB flash: a mid-range PIC's HEX (its configuration word
    there, everything else past the flash in its ID/EEPROM words, nothing above 64 KB, 14-bit
    instruction words) or a larger PIC18's."""
    a, at = beyond[0]
    config = [(x, w) for x, w in beyond if x // 2 in (0x2007, 0x2008)]
    pic16 = (config and all(_pic16_region(x) for x, _ in beyond) and max(seen) < 0x10000
             and all(img.flash[i] <= 0x3F for i in seen if i < FLASH_BYTES and i % 2))
    if pic16:
        x, xat = config[0]
        raise HexError(f"{xat}: address 0x{x:06X} is where a mid-range PIC (PIC12/PIC16, 14-bit instructions) "
                       f"HEX puts {_pic16_region(x)}, and every instruction word is 14-bit: this HEX is for a "
                       "PIC16, not the PIC18F4431; build the firmware for the 18F4431 ('picdrive firmware' "
                       "writes its HEX)")
    raise HexError(f"{at}: program address 0x{a:06X} is beyond the 18F4431's 16 KB flash "
                   "(0x0000-0x3FFF): this HEX is for a PIC18 with more flash (e.g. 18F4520/18F4550); "
                   "link it for the 18F4431 (its linker script, 18f4431_g.lkr)")


def load_hex(path: str | Path, *, flash_bytes: int = FLASH_BYTES) -> HexImage:
    """Read and validate a HEX file (HexError on any problem, also a missing/unreadable file)."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as e:
        raise HexError(f"cannot read HEX file {p}: {e.strerror}; give the path of the .hex") from None
    try:
        text = raw.decode("ascii")
    except UnicodeDecodeError:
        raise HexError(f"{p}: not a text file (non-ASCII bytes); give the Intel HEX, not the binary/ELF/COF") from None
    return parse_hex(text, str(p), flash_bytes=flash_bytes)
