"""The C link module rendered from the protocol definition (:mod:`picdrive.link.protocol`).

:func:`render_c` fills the Jinja2 templates ``firmware_templates/link_fw.h.j2`` and
``link_fw.c.j2`` for one :class:`~picdrive.link.protocol.Table` (one build's parameter
scales and limits): the constants, the flash table read through one function
(:func:`_c_tables`) and the command dispatch.  The firmware generator
(:mod:`picdrive.firmware.codegen`) and the tests' fake board call it.
"""
from __future__ import annotations

import math
import struct

from .protocol import (ACK_BIT, BOARD_FRAMES, CAPTURE_BYTES_DEFAULT, CAPTURE_READ_HEADER_BYTES, COMMANDS,
                       COMMAND_BY_CODE, COMMAND_BY_NAME, CTYPES, CaptureState, Controller,
                       EEPROM_HEADER_BYTES, EEPROM_LAYOUT_VERSION, EEPROM_MAGIC, EepromResult, Entry, Event,
                       FEATURE_IDENT, FLAG_PERSISTED, FLAG_SIGNAL, FLAG_WRITABLE, Fault, MAX_BODY, MAX_FRAME, MAX_PAYLOAD,
                       MSG_EVENT, MSG_NACK, MSG_TELEMETRY, NAME_MAX, Nack, PARAM_GET_MAX, PROTOCOL_VERSION,
                       ProtocolError, REPLAY_BYTES, RX_BUFFER_BYTES, RX_SPILL_BYTES, STATE_BYTES, State,
                       TELEMETRY_HEADER_BYTES, Table, Trigger, ram_budget)

__all__ = ["render_c"]


# ---------------------------------------------------------------------------
# Rendering
# ---------------------------------------------------------------------------
def _env():
    import jinja2
    from ..paths import templates_dir
    return jinja2.Environment(
        loader=jinja2.FileSystemLoader(str(templates_dir())), undefined=jinja2.StrictUndefined,
        trim_blocks=True, lstrip_blocks=True, keep_trailing_newline=True, autoescape=False)


def _c_int(v: int) -> str:
    if v == -2**31:
        return "(-2147483647L - 1L)"
    return f"{v}L"


def _u32(name: str, v: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= 0xFFFFFFFF:
        raise ProtocolError(f"{name} = {v!r}: expected an unsigned 32-bit integer")
    return v


_C_ROW_BYTES = 20       # id, ctype, flags, unit, scale bits, min, max, default: the param_info reply head
_C_ROW16_BYTES = 14     # the same with min, max and default as 16 bits (widened by the entry's size code)
HELLO_BYTES = COMMAND_BY_NAME["hello"].reply_size + 1   # the fixed fields and the features byte
_C_HANDLERS = {"start": "h_app", "stop": "h_app", "brake": "h_app", "fault_clear": "h_app", "ident": "h_app",
               "heartbeat": "h_none"}
_C_IDLE_COMMANDS = ("eeprom_save", "eeprom_load")   # refused while the motor runs or brakes


def _c_bytes(data: bytes) -> str:
    return ", ".join(f"0x{b:02X}u" for b in data)


def _c_tables(table: Table, build_id: int, profile_hash: int, sample_hz: int, capture_words: int) -> dict:
    """The flash table of link_fw.c, one byte array read through one function: per entry the row
    (the param_info reply head, little-endian; min, max and default as 16 bits when every entry's
    store is at most 16 bits: ``row16``), store offset, size code and name length; the
    hello reply, the command specs, the names; with EEPROM the image header and the persisted
    entries.  Also the id runs (ids are contiguous within each run, so an index is a subtraction)."""
    ents = table.entries

    def size_code(e: Entry) -> int:     # bytes in the store (signals: 16 bits), bit 7: signed
        return e.ct.size | (0x80 if e.ctype.startswith("int") else 0)

    def le(macro: str, n: int) -> list[str]:   # the header's macros stay the authority
        return [f"(uint8_t)({macro} >> {8 * k}u)" if k else f"(uint8_t){macro}" for k in range(n)]

    def lines(items: list[str], per: int = 12) -> list[str]:
        return [", ".join(items[i:i + per]) + "," for i in range(0, len(items), per)]

    def fits16(e: Entry) -> bool:         # a store of at most 16 bits, its limits and default in its type
        lo, hi = (-32768, 32767) if e.ctype.startswith("int") else (0, 65535)
        return e.ct.size <= 2 and all(lo <= v <= hi for v in (e.min_raw, e.max_raw, e.default_raw))

    # 16-bit rows when every entry allows (the firmware widens each value to the reply's 32 bits by
    # the entry's size code: sign bit 7, as sign_extend does); else the reply head as it is
    row16 = all(fits16(e) for e in ents)
    fmt, row_bytes = ("<BBBBIhhh", _C_ROW16_BYTES) if row16 else ("<BBBBIiii", _C_ROW_BYTES)

    def row(e: Entry) -> bytes:
        vals = (e.min_raw, e.max_raw, e.default_raw)
        if row16:    # unsigned 16-bit values as the int16 of the same bits
            vals = tuple(v - 65536 if v > 32767 else v for v in vals)
        return struct.pack(fmt, e.id, e.ct.code, e.flags, e.unit_index, e.scale_bits, *vals)

    rows = [_c_bytes(row(e)) + f",   /* {e.name} */" for e in ents]
    hello = (["LINK_PROTO_MAJOR", "LINK_PROTO_MINOR"] + le("LINK_BUILD_ID", 4) + le("LINK_PROFILE_HASH", 4)
             + le("LINK_TABLE_HASH", 4) + ["LINK_N_ENTRIES", "LINK_MAX_PAYLOAD"] + le("LINK_HELLO_CAPTURE_WORDS", 2)
             + le("LINK_SAMPLE_HZ", 2) + ["LINK_FEATURES"])
    assert len(hello) == HELLO_BYTES
    cmd_spec = [f"0x{(0x7F if c.args_tail else c.args_size) | (0x80 if c.name in _C_IDLE_COMMANDS else 0):02X}u"
                for c in COMMANDS]
    names = [f"0x{b:02X}u" for e in ents for b in e.name.encode("ascii")]
    index = {e.name: i for i, e in enumerate(ents)}
    segs = [("ROM_ROWS", rows, len(ents) * row_bytes),
            ("ROM_OFF", lines(["NONE" if e.signal else f"(uint8_t)offsetof(link_params_t, {e.name})" for e in ents],
                              4), len(ents)),
            ("ROM_SIZE", lines([f"0x{size_code(e):02X}u" for e in ents]), len(ents)),
            ("ROM_NAME_LEN", lines([f"{len(e.name)}u" for e in ents]), len(ents)),
            ("ROM_HELLO", lines(hello, 4), HELLO_BYTES),
            ("ROM_CMD", lines(cmd_spec), len(cmd_spec)),
            ("ROM_NAMES", lines(names, 16), len(names)),
            ("ROM_EE_HEAD", lines([_c_bytes(EEPROM_MAGIC + bytes((EEPROM_LAYOUT_VERSION,)))] + le("LINK_TABLE_HASH", 4)
                                  + ["EE_DATA_BYTES"], 8), EEPROM_HEADER_BYTES),
            ("ROM_PERSIST", lines([f"{index[e.name]}u" for e in table.persisted]), len(table.persisted))]
    rom, off = [], 0
    for name, items, n in segs:
        rom.append((name, off, n, items))
        off += n
    runs: list[list[int]] = []             # [first id, count, first index]
    for i, e in enumerate(ents):
        if runs and runs[-1][0] + runs[-1][1] == e.id:
            runs[-1][1] += 1
        else:
            runs.append([e.id, 1, i])
    sig = [i for i, e in enumerate(ents) if e.signal]
    assert sig == list(range(sig[0], sig[0] + len(sig))), "signals must be contiguous in the table"
    assert all(r[0] >= r[2] for r in runs)
    return dict(row_bytes=row_bytes, row16=row16, rom_segments=rom, rom_size=off, id_runs=[tuple(r) for r in runs],
                sig_index=sig[0], handler_of=lambda c: _C_HANDLERS.get(c.name, "h_" + c.name))


def render_c(table: Table, build_id: int, profile_hash: int, *, sample_hz: float | None = None,
             capture_bytes: int = CAPTURE_BYTES_DEFAULT, critical_begin: str = "",
             critical_end: str = "", capture: bool = True, eeprom: bool = True,
             identify: bool = False, sfr_bits: dict | None = None) -> dict[str, str]:
    """Render the C link module for ``table``.

    Returns ``{"link_fw.h": text, "link_fw.c": text}``.  ``build_id`` and
    ``profile_hash`` (u32) are reported by hello.  ``sample_hz``: rate at
    which the firmware calls ``link_sample()`` (its speed loop), reported by
    hello so that the host can time telemetry (None: 0 = not stated).
    ``capture_bytes``: capture buffer size (even, 16..256: its indices are bytes).
    ``critical_begin``/``critical_end``: C statements that make a
    parameter-store update atomic against the interrupt that runs the speed
    loop (e.g. ``"INTCONbits.GIEH = 0;"``); empty when the speed loop reads
    the store from the main loop only.  Both can also be set with
    ``-DLINK_CRITICAL_BEGIN()=...`` at compile time.
    ``capture``/``eeprom``: generate the triggered capture (commands and buffer) and the EEPROM
    persistence, or leave them out to save flash (``LINK_WITH_CAPTURE``/``LINK_WITH_EEPROM``;
    a build without capture NACKs its commands UNKNOWN_COMMAND and reports 0 capture words in
    hello; one without EEPROM refuses eeprom_save and loads nothing).
    ``identify``: hello's features say the build has the identification mode (the application,
    ``app_command``, implements ``ident``; without it the command is NACKed UNKNOWN_COMMAND).
    ``sfr_bits``: the device's bit positions by register and bit name
    (``picdrive.firmware.p18f4431.bits()``), for the PIC18 assembly's bit operands; the
    firmware layer owns the device description, so its caller passes it in.
    """
    if not isinstance(table, Table):
        raise ProtocolError("render_c needs a protocol.Table from build_table()")
    _u32("build_id", build_id)
    _u32("profile_hash", profile_hash)
    if isinstance(capture_bytes, bool) or not isinstance(capture_bytes, int) or capture_bytes % 2 \
            or not 16 <= capture_bytes <= 256:
        raise ProtocolError(f"capture_bytes = {capture_bytes!r}: expected an even number of bytes in [16, 256]")
    hz = 0
    if sample_hz is not None:
        if not (isinstance(sample_hz, (int, float)) and math.isfinite(sample_hz) and 1 <= sample_hz <= 65535):
            raise ProtocolError(f"sample_hz = {sample_hz!r}: expected the speed-loop rate in Hz, 1..65535")
        hz = int(round(sample_hz))
    for k, (name, code, _doc) in enumerate(BOARD_FRAMES):
        assert code not in COMMAND_BY_CODE
    if sfr_bits is None:
        raise ProtocolError("render_c needs sfr_bits: picdrive.firmware.p18f4431.bits() (the assembly's bit names)")
    ctx = dict(
        table=table, entries=table.entries, params=table.params, signals=table.signals,
        persisted=table.persisted, commands=COMMANDS, version=PROTOCOL_VERSION,
        build_id=build_id, profile_hash=profile_hash, table_hash=table.hash, sample_hz=hz,
        capture_words=capture_bytes // 2, capture_bytes=capture_bytes, sig_all=(1 << len(table.signals)) - 1,
        max_payload=MAX_PAYLOAD, max_frame=MAX_FRAME, max_body=MAX_BODY,
        rx_bytes=RX_BUFFER_BYTES, rx_spill=RX_SPILL_BYTES, name_max=NAME_MAX, replay_bytes=REPLAY_BYTES,
        param_get_max=PARAM_GET_MAX,
        nacks=list(Nack), faults=list(Fault), states=list(State), events=list(Event),
        triggers=list(Trigger), capture_states=list(CaptureState), controllers=list(Controller),
        eeprom_results=list(EepromResult), ctypes=list(CTYPES.values()),
        msg_telemetry=MSG_TELEMETRY, msg_event=MSG_EVENT, msg_nack=MSG_NACK, ack_bit=ACK_BIT,
        flag_writable=FLAG_WRITABLE, flag_persisted=FLAG_PERSISTED, flag_signal=FLAG_SIGNAL,
        ee_magic=EEPROM_MAGIC, ee_version=EEPROM_LAYOUT_VERSION, ee_header=EEPROM_HEADER_BYTES,
        ee_image=table.eeprom_image_bytes, telem_header=TELEMETRY_HEADER_BYTES,
        capread_header=CAPTURE_READ_HEADER_BYTES, budget=ram_budget(table, capture_bytes), state_bytes=STATE_BYTES,
        critical_begin=critical_begin, critical_end=critical_end, c_int=_c_int, bit=sfr_bits,
        with_capture=bool(capture), with_eeprom=bool(eeprom), hello_bytes=HELLO_BYTES,
        features=FEATURE_IDENT if identify else 0,
        cmd=COMMAND_BY_NAME, hexu=lambda v: f"0x{v:08X}UL", **_c_tables(table, build_id, profile_hash, hz,
                                                                          capture_bytes // 2),
    )
    env = _env()
    return {name: env.get_template(name + ".j2").render(**ctx) for name in ("link_fw.h", "link_fw.c")}
