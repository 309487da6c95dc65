"""The serial protocol between host and board: defined once, here.

Everything both ends must agree on lives in this module as plain data:

* the frame (COBS with the :data:`DELIMITER` 0x00, :data:`MAX_PAYLOAD`, CRC-16/CCITT-FALSE);
* the message types (:data:`COMMANDS` and the board-initiated frames), each
  with its argument and reply layout (little-endian ``struct`` codes);
* the NACK, fault, state, event, trigger and controller codes (``IntEnum``);
* the parameter table: writable parameters and read-only telemetry signals in
  one id space (:data:`PARAMS`, :data:`RULE_GAINS`, :data:`SIGNALS`).

:func:`build_table` resolves the static definition for one build (``r``
rules, per-parameter overrides of raw scale, limits, default and C type from
the firmware's fixed-point plan) into a :class:`Table`, whose
:attr:`Table.hash` (CRC-32 of a canonical encoding) goes into ``hello``.
:func:`picdrive.link.protocol_c.render_c` renders the C link module
(``link_fw.h``/``link_fw.c``, from the Jinja2 templates in
``firmware_templates/``) for that table; :mod:`picdrive.link.codec` encodes and
decodes frames with the same tables; and
:func:`picdrive.link.protocol_doc.render_markdown` writes ``docs/protocol.md``.

Raw values and scales: a parameter's engineering value is ``raw * scale``
(unit in :attr:`Entry.unit`).  The scale is a float32 constant that the
firmware only stores and reports (as its IEEE-754 bit pattern) and never
computes with.  Limits and defaults are raw integers, enforced by the
firmware.

Regenerate the document with ``python -m picdrive.link.protocol_doc docs/protocol.md``.
"""
from __future__ import annotations

import dataclasses
import enum
import math
import struct
import zlib
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Iterable, Mapping

from ..errors import PicdriveError

__all__ = [
    "ProtocolError", "PROTOCOL_VERSION", "DELIMITER", "MAX_PAYLOAD", "MAX_BODY", "BODY_OVERHEAD",
    "MAX_FRAME", "FRAME_OVERHEAD", "HOST_GAP_MS", "RX_BUFFER_BYTES", "REPLAY_BYTES", "CAPTURE_BYTES_DEFAULT", "PARAM_GET_MAX",
    "NAME_MAX", "EEPROM_BYTES", "EEPROM_LAYOUT_VERSION", "EEPROM_MAGIC", "EEPROM_HEADER_BYTES",
    "CTYPES", "CType", "UNITS", "FLAG_WRITABLE", "FLAG_PERSISTED", "FLAG_SIGNAL",
    "Nack", "Fault", "State", "Event", "Trigger", "CaptureState", "Controller", "EepromResult",
    "NACK_REASONS", "Field", "Command", "COMMANDS", "COMMAND_BY_NAME", "COMMAND_BY_CODE",
    "MSG_TELEMETRY", "MSG_EVENT", "MSG_NACK", "ACK_BIT", "ack_type",
    "ParamDef", "PARAMS", "RULE_GAINS", "SIGNALS", "SIGNAL_BASE_ID", "RULE_BASE_ID",
    "ParamOverride", "Entry", "Table", "static_defs", "build_table", "ram_budget", "DEFAULT_TELEMETRY_SIGNALS", "DEFAULT_SAMPLES_PER_FRAME",
    "TELEMETRY_HEADER_BYTES", "CAPTURE_READ_HEADER_BYTES", "STATE_BYTES", "float32_bits", "float32_from_bits",
]


class ProtocolError(PicdriveError, ValueError):
    """A protocol table, override or frame that cannot be built or sent.

    The message names the parameter or field, the value and what is accepted.
    """


# ---------------------------------------------------------------------------
# Frame
# ---------------------------------------------------------------------------
PROTOCOL_VERSION = (2, 1)
"""(major, minor).  A host refuses a board with another major version.  2.0: COBS framing with
a 0x00 delimiter (1.x: start byte 0xA5 without stuffing).  2.1: hello ends with the features byte
(2.0 builds send none)."""

FEATURE_IDENT = 0x01
"""hello ``features`` bit: the build has the identification mode (the ``ident`` command, state
IDENT; generated with ``picdrive firmware --identify``)."""

DELIMITER = 0x00
"""Frame delimiter.  Frames are COBS-encoded, so it never occurs inside a frame: a receiver
resynchronises exactly at the next delimiter, and no frame can hide inside another's payload."""

MAX_PAYLOAD = 40
"""Largest payload (LEN) in bytes.  Sized for the PIC18F4431's 768 B of RAM:
the largest payloads are ``param_info`` replies (20 B + a name of up to
:data:`NAME_MAX` characters), ``capture_read`` chunks and four-sample
telemetry frames of four signals (34 B)."""

BODY_OVERHEAD = 5
"""LEN, TYPE, SEQ, CRC high, CRC low: the frame body is the payload plus these."""

MAX_BODY = MAX_PAYLOAD + BODY_OVERHEAD

FRAME_OVERHEAD = BODY_OVERHEAD + 2
"""Bytes on the wire beyond the payload: the body's five, the COBS code byte (one block: a body
is shorter than 254 bytes) and the delimiter.  The host sends one more delimiter before each
command."""

MAX_FRAME = MAX_PAYLOAD + FRAME_OVERHEAD

HOST_GAP_MS = 100
"""The host abandons a partly received frame after this long without bytes (USB-serial adapters
and the OS deliver bytes in bursts: an FTDI chip holds them up to its 16 ms latency timer).  The
board needs no timer: the host's delimiter before each command ends any partial frame."""

RX_BUFFER_BYTES = MAX_BODY + 1
"""Receive buffer of the C module: one frame as it arrives (COBS code byte + body, without the
delimiter).  The RX interrupt only stores bytes and marks the frame complete at its delimiter;
link_poll decodes it in place and hands the buffer back.  Bytes arriving while the main loop
holds the buffer (checks a frame, answers it) wait in the spill ring (RX_SPILL_BYTES) and go
through the same framing when it is handed back."""

RX_SPILL_BYTES = 16
"""Spill ring of the C module (a power of two; one slot stays free): the bytes that arrive while
the main loop holds the receive buffer, 15 bytes or 1.3 ms at 115,200 baud, against the main
loop's hold of a frame it rejects (a maximum frame's COBS decoding and CRC, about 1,800 cycles, with
a speed-loop interrupt of up to 4,000 in between: 6.5 byte times).  A byte that finds it full is
lost and counted (status rx_overflows), and the frame it belonged to is dropped."""

REPLAY_BYTES = 8
"""Replies up to this size are stored for duplicate-SEQ replay; every command
with side effects has a reply no longer than this (checked below)."""

CAPTURE_BYTES_DEFAULT = 128
"""Default size of the capture buffer in the C module, bytes (64 samples of
one signal, 32 of two...).  ``render_c(..., capture_bytes=N)`` changes it."""

PARAM_GET_MAX = 10
"""Most parameter ids one ``param_get`` may ask for (10 x 4 B of reply)."""

NAME_MAX = 15
"""Longest parameter or signal name, characters (ASCII)."""

EEPROM_BYTES = 256
EEPROM_LAYOUT_VERSION = 1
EEPROM_MAGIC = b"PD"
EEPROM_HEADER_BYTES = 8
"""EEPROM image: 'P' 'D', layout version, table hash (u32 LE), data length,
then the persisted parameters in table order (little-endian, C-type width),
then CRC-16/CCITT-FALSE of everything before it, high byte first."""

STATE_BYTES = 108
"""Scalar state of the C module (struct S, the value and limit registers V and X, the receive bytes rx_n, rx_ready, rx_ovf, the spill ring's indices and the copy and sample pointers in link_fw.c), bytes, as avr-nm measures it;
checked by tests/test_protocol.py."""

TELEMETRY_HEADER_BYTES = 2            # u16 counter of the frame's first sample
CAPTURE_READ_HEADER_BYTES = 7         # state u8, total u16, trigger index u16, start u16

DEFAULT_TELEMETRY_SIGNALS = ("speed", "setpoint", "voltage", "current")
DEFAULT_SAMPLES_PER_FRAME = 4
"""The default telemetry frame: four signals, four samples (34 B payload,
41 B on the wire) -- 1 kHz of four signals fits into 115200 baud."""


# ---------------------------------------------------------------------------
# Types, units, flags
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class CType:
    name: str
    code: int        # on the wire (param_info)
    size: int        # bytes
    lo: int
    hi: int

    @property
    def c(self) -> str:
        return f"{self.name}_t"


CTYPES: dict[str, CType] = {t.name: t for t in (
    CType("uint8", 1, 1, 0, 255),
    CType("int8", 2, 1, -128, 127),
    CType("uint16", 3, 2, 0, 65535),
    CType("int16", 4, 2, -32768, 32767),
    CType("int32", 5, 4, -2**31, 2**31 - 1),
)}
CTYPE_BY_CODE = {t.code: t for t in CTYPES.values()}
SIGNAL_CTYPES = ("int16", "uint16")   # telemetry values travel as 16 bits

UNITS: tuple[str, ...] = (
    "1", "rpm", "rpm/s", "V", "A", "V/(rad/s)", "V/rad", "V s^2/rad", "V/A",
    "ms", "counts", "code", "enum",
)
"""Units by index (param_info carries the index).  Append only."""

FLAG_WRITABLE = 0x01
FLAG_PERSISTED = 0x02
FLAG_SIGNAL = 0x04


# ---------------------------------------------------------------------------
# Codes shared by both ends
# ---------------------------------------------------------------------------
class Nack(enum.IntEnum):
    """Error codes carried by a NACK."""
    UNKNOWN_COMMAND = 1
    BAD_CRC = 2
    MALFORMED = 3
    OUT_OF_RANGE = 4
    READ_ONLY = 5
    WRONG_STATE = 6
    BUSY = 7
    UNKNOWN_PARAM = 8
    FAULT_ACTIVE = 9
    EEPROM_ERROR = 10


NACK_REASONS: dict[Nack, str] = {
    Nack.UNKNOWN_COMMAND: "the board does not know this command (firmware of another protocol version?)",
    Nack.BAD_CRC: "the board received a frame with a bad CRC (line noise or wrong baud rate); the command was not executed",
    Nack.MALFORMED: "the argument length does not fit the command",
    Nack.OUT_OF_RANGE: "a value is outside the range the board accepts",
    Nack.READ_ONLY: "the entry is read-only (a telemetry signal or a fixed parameter)",
    Nack.WRONG_STATE: "not allowed in the board's present state (stop the motor first, or nothing captured yet)",
    Nack.BUSY: "the board is busy with this resource (capture still recording)",
    Nack.UNKNOWN_PARAM: "no parameter with this id in the board's table",
    Nack.FAULT_ACTIVE: "a fault is latched; clear it with fault_clear first",
    Nack.EEPROM_ERROR: "EEPROM image missing, of another build, or corrupt (bad CRC / out-of-range value), or write verify failed",
}


class Fault(enum.IntEnum):
    """Fault codes the firmware latches (status, fault events)."""
    NONE = 0
    HALL_INVALID = 1       # hall code 000 or 111
    OVERCURRENT = 2        # FLTA comparator trip
    STALL = 3              # commanded, no motion for stall_timeout
    LINK_LOST = 4          # watchdog: no valid frame for link_timeout while running
    UNDERVOLTAGE = 5       # bus under-voltage
    OVERVOLTAGE = 6        # bus over-voltage
    EEPROM_CRC = 7         # EEPROM image corrupt at boot
    OVERSPEED = 8          # |speed| above the profile-derived trip (1.2 x speed_max_rpm)


class State(enum.IntEnum):
    """Drive state (signal ``state``).  The watchdog is armed in RUN and IDENT."""
    IDLE = 0               # outputs off
    RUN = 1                # speed loop closed
    BRAKE = 2              # low sides on, braking
    FAULT = 3              # outputs off, fault latched
    IDENT = 4              # identification: the `ident` command's vector at its duty, trips armed


class Event(enum.IntEnum):
    """Board-initiated event frames (payload: event, code)."""
    BOOT = 1               # code: reset cause (firmware-defined, 0 = unknown)
    FAULT = 2              # code: Fault
    WATCHDOG = 3           # code: Fault.LINK_LOST


class Trigger(enum.IntEnum):
    """Capture triggers."""
    IMMEDIATE = 0          # first sample after arming (pre_trigger must be 0)
    SETPOINT_CHANGE = 1    # speed_setpoint written (set_speed / param_set)
    SPEED_RISING = 2       # speed crosses threshold upward (raw, signed)
    SPEED_FALLING = 3      # speed crosses threshold downward


class CaptureState(enum.IntEnum):
    IDLE = 0
    ARMED = 1              # recording pre-trigger history, waiting for the trigger
    TRIGGERED = 2          # recording post-trigger samples
    DONE = 3               # record complete, readable


class Controller(enum.IntEnum):
    """Values of the ``controller`` parameter."""
    PID = 0                # rule 1 only
    FUZZY = 1              # memberships blend all rules


class EepromResult(enum.IntEnum):
    """Return values of the C ``link_eeprom_load()`` (boot-time load)."""
    OK = 0
    BLANK = 1              # no image (magic absent): defaults kept
    OTHER_BUILD = 2        # image of another table (hash/length differ): defaults kept
    CORRUPT = 3            # bad CRC or a value out of range: defaults kept, firmware latches EEPROM_CRC


# ---------------------------------------------------------------------------
# Messages
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Field:
    name: str
    fmt: str          # struct code, little-endian: B b H h I i
    doc: str = ""


@dataclass(frozen=True)
class Command:
    """One host command.  ``args``/``reply`` are fixed fields; ``args_tail`` /
    ``reply_tail`` a repeated field (``fmt`` per item; ``'s'`` = ASCII text)."""
    name: str
    code: int
    doc: str
    args: tuple[Field, ...] = ()
    reply: tuple[Field, ...] = ()
    args_tail: Field | None = None
    reply_tail: Field | None = None
    side_effects: bool = True
    app: bool = False             # forwarded to app_command()

    @property
    def args_size(self) -> int:
        return struct.calcsize("<" + "".join(f.fmt for f in self.args))

    @property
    def reply_size(self) -> int:
        return struct.calcsize("<" + "".join(f.fmt for f in self.reply))

    @property
    def c_name(self) -> str:
        return "LINK_CMD_" + self.name.upper()


MSG_TELEMETRY = 0x60
MSG_EVENT = 0x61
MSG_NACK = 0x7F
ACK_BIT = 0x80


def ack_type(cmd_code: int) -> int:
    """TYPE of the ACK to a command: the command code with bit 7 set."""
    return cmd_code | ACK_BIT


_F = Field
COMMANDS: tuple[Command, ...] = (
    Command("hello", 0x01, "Handshake: versions and identities of the build.",
            reply=(_F("proto_major", "B"), _F("proto_minor", "B"), _F("build_id", "I", "firmware build id"),
                   _F("profile_hash", "I", "first 4 bytes of the profile's SHA-256, big-endian"),
                   _F("table_hash", "I", "CRC-32 of the canonical parameter table"),
                   _F("n_entries", "B", "entries in the table (param_info index range)"),
                   _F("max_payload", "B"), _F("capture_words", "H", "capture buffer, 16-bit words"),
                   _F("sample_hz", "H", "link_sample() rate (speed loop), Hz; 0 = not stated")),
            reply_tail=_F("features", "B", "one byte from protocol 2.1 on (none before): bit 0 the "
                                           "identification mode (ident)"),
            side_effects=False),
    Command("param_info", 0x02, "Describe table entry number `index` (0..n_entries-1, in id order).",
            args=(_F("index", "B"),),
            reply=(_F("id", "B"), _F("ctype", "B", "C type code"), _F("flags", "B", "1 writable, 2 persisted, 4 signal"),
                   _F("unit", "B", "index into UNITS"), _F("scale_bits", "I", "float32 bit pattern"),
                   _F("min", "i", "raw"), _F("max", "i", "raw"), _F("default", "i", "raw")),
            reply_tail=_F("name", "s", f"ASCII, up to {NAME_MAX} characters"),
            side_effects=False),
    Command("param_get", 0x03, f"Read 1..{PARAM_GET_MAX} entries (parameters or signals), raw.",
            args_tail=_F("ids", "B", "entry ids"), reply_tail=_F("values", "i", "raw values, same order"),
            side_effects=False),
    Command("param_set", 0x04, "Write a parameter (raw).  Range-checked; a rejected set changes nothing.",
            args=(_F("id", "B"), _F("value", "i", "raw")), reply=(_F("id", "B"), _F("value", "i", "raw, as stored"))),
    Command("set_speed", 0x05, "Write speed_setpoint (raw, signed: the sign is the direction).",
            args=(_F("value", "i", "raw"),), reply=(_F("value", "i", "raw, as stored"),)),
    Command("start", 0x06, "Close the speed loop (state RUN).  Arms the link watchdog.", app=True),
    Command("stop", 0x07, "Outputs off (state IDLE).", app=True),
    Command("brake", 0x08, "Brake (state BRAKE).", app=True),
    Command("select_controller", 0x09, "Write the controller parameter (0 pid, 1 fuzzy).",
            args=(_F("controller", "B"),), reply=(_F("controller", "B"),)),
    Command("telem_config", 0x0A,
            "Configure telemetry: signal mask (bit i = signal i), decimation (0 = off), samples per frame.  "
            "Restarts the sample counter; the new generation is the SEQ of the telemetry frames that follow.",
            args=(_F("mask", "H"), _F("decimation", "H"), _F("samples_per_frame", "B")),
            reply=(_F("generation", "B"), _F("payload_len", "B", "LEN of each telemetry frame"))),
    Command("capture_arm", 0x0B,
            "Arm a capture of n_samples samples of the masked signals, pre_trigger of them before the trigger, "
            "every decimation-th sample.",
            args=(_F("mask", "H"), _F("n_samples", "H"), _F("pre_trigger", "H"), _F("decimation", "H"),
                  _F("trigger", "B", "Trigger"), _F("threshold", "h", "raw speed, for SPEED_* triggers"))),
    Command("capture_read", 0x0C,
            "Read a finished capture from sample `start` on (oldest first), as many samples as fit.",
            args=(_F("start", "H"), _F("count", "B", "most samples wanted")),
            reply=(_F("state", "B", "CaptureState"), _F("total", "H", "samples recorded"),
                   _F("trigger_index", "H", "index of the trigger sample"), _F("start", "H")),
            reply_tail=_F("values", "h", "sample-major, signals in mask order"),
            side_effects=False),
    Command("eeprom_save", 0x0D, "Save the persisted parameters (motor stopped)."),
    Command("eeprom_load", 0x0E, "Load the persisted parameters (motor stopped); a bad image changes nothing."),
    Command("fault_clear", 0x0F, "Clear a latched fault (state FAULT -> IDLE).", app=True),
    Command("status", 0x10, "Drive and link status.",
            reply=(_F("state", "B", "State"), _F("fault", "B", "Fault"), _F("capture_state", "B", "CaptureState"),
                   _F("telem_generation", "B"), _F("crc_errors", "H", "received frames with a bad CRC"),
                   _F("rx_overflows", "H", "bytes lost to a full receive spill ring (the main loop held the frame buffer too long)"),
                   _F("telem_dropped", "H", "telemetry samples not sent (link busy)"),
                   _F("uptime_ms", "I")),
            side_effects=False),
    Command("heartbeat", 0x11, "Keep the link watchdog fed; no effect otherwise.", side_effects=False),
    Command("ident", 0x12,
            "Identification drive (state IDENT, from IDLE or IDENT; arms the link watchdog): apply "
            "identification vector `vector` at `duty`.  0..11: the current at -30 + 30 vector electrical "
            "degrees (even: two phases, odd: three; picdrive.commutation.IDENT_VECTORS), held, or stepped "
            "by one (30 deg) every |step_ms| ms, forward for step_ms > 0; 12..23: hall-driven, selection "
            "vector - 12 (picdrive.commutation.ident_hall_vector).  The overcurrent trip, the current limit "
            "(a fault above it), the hall, overspeed and bus checks and the link watchdog act as in RUN.  "
            "Refused: vector > 23 or duty above the build's limit (OUT_OF_RANGE), running or braking "
            "(WRONG_STATE), a fault latched (FAULT_ACTIVE).  A new vector applies at once: the host "
            "changes between vectors that are not neighbours (30 deg apart, or 60 between two-phase ones) "
            "through stop, so that no leg goes from its high side to its low side without an off period.  "
            "Only in the identification build (picdrive firmware --identify; hello's features bit 0): "
            "any other build answers UNKNOWN_COMMAND.",
            args=(_F("vector", "B"), _F("duty", "H", "PDC counts"),
                  _F("step_ms", "b", "0 = hold; ms per 30-degree step, the sign the direction")),
            app=True),
)
COMMAND_BY_NAME = {c.name: c for c in COMMANDS}
COMMAND_BY_CODE = {c.code: c for c in COMMANDS}

BOARD_FRAMES = (
    ("telemetry", MSG_TELEMETRY, "SEQ = telemetry generation; payload: u16 counter of the first sample, then "
                                 "samples (sample-major, int16 per signal in mask order)"),
    ("event", MSG_EVENT, "SEQ = event counter; payload: u8 Event, u8 code"),
    ("nack", MSG_NACK, "SEQ = the command's SEQ; payload: u8 command TYPE, u8 Nack code"),
)


# ---------------------------------------------------------------------------
# Parameter table: static definition
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class ParamDef:
    """Static definition of one table entry (defaults; overridable per build)."""
    id: int
    name: str
    unit: str
    ctype: str
    scale: float
    min_raw: int
    max_raw: int
    default_raw: int
    writable: bool
    persisted: bool
    doc: str
    signal: bool = False
    values: tuple[str, ...] = ()      # enum value names (raw = index)


SIGNAL_BASE_ID = 0x20
RULE_BASE_ID = 0x40
_RULE_KINDS = ("kp", "ki", "kd", "kc")

# Default scales are placeholders that make a table usable on its own (tests,
# docs); the firmware's fixed-point plan overrides those of the gains, speeds
# and voltages.
_V = 1.0 / 128.0         # V per count: +-256 V in int16
_A = 1.0 / 1024.0        # A per count: +-32 A in int16
_GAIN = 1.0 / 256.0
_Q14 = 1.0 / 16384.0

PARAMS: tuple[ParamDef, ...] = (
    ParamDef(0x00, "speed_setpoint", "rpm", "int16", 1.0, -30000, 30000, 0, True, False,
             "commanded speed, mechanical; the sign is the direction"),
    ParamDef(0x01, "controller", "enum", "uint8", 1.0, 0, 1, 1, True, True,
             "0 = pid (rule 1 only), 1 = fuzzy (memberships blend all rules)", values=("pid", "fuzzy")),
    ParamDef(0x02, "premise_low", "rpm", "int16", 1.0, 0, 30000, 0, True, True,
             "N1 of the fuzzy premise (|speed|)"),
    ParamDef(0x03, "premise_high", "rpm", "int16", 1.0, 0, 30000, 3000, True, True,
             "N2 of the fuzzy premise (|speed|)"),
    ParamDef(0x04, "setpoint_weight", "1", "int16", _Q14, 0, 16384, 16384, True, True,
             "b of the 2-DOF PID (P acts on b r - y)"),
    ParamDef(0x05, "u_min", "V", "int16", _V, -32767, 32767, -32767, True, True,
             "lower output limit of the control law"),
    ParamDef(0x06, "u_max", "V", "int16", _V, -32767, 32767, 32767, True, True,
             "upper output limit of the control law"),
    ParamDef(0x07, "current_limit", "A", "int16", _A, 0, 32767, 2048, True, True,
             "firmware current limit"),
    ParamDef(0x08, "accel_limit", "rpm/s", "uint16", 1.0, 0, 65535, 0, True, True,
             "setpoint ramp; 0 = off"),
    ParamDef(0x09, "link_timeout", "ms", "uint16", 1.0, 20, 60000, 500, True, True,
             "link-loss watchdog while running"),
    ParamDef(0x0A, "stall_timeout", "ms", "uint16", 1.0, 10, 60000, 500, True, True,
             "commanded with no motion for this long = stall fault"),
)

RULE_GAINS: tuple[tuple[str, str, str], ...] = (
    ("kp", "V/(rad/s)", "proportional gain of rule {j} (on b r - y)"),
    ("ki", "V/rad", "integral gain of rule {j}"),
    ("kd", "V s^2/rad", "derivative gain of rule {j} (on measurement)"),
    ("kc", "V/A", "current-feedback gain of rule {j}"),
)
"""Per rule j = 1..r: ids RULE_BASE_ID + 4 (j-1) + k, names rule{j}_{kind}."""

SIGNALS: tuple[ParamDef, ...] = tuple(
    ParamDef(SIGNAL_BASE_ID + i, name, unit, "int16", scale, -32768, 32767, 0, False, False, doc, signal=True,
             values=values)
    for i, (name, unit, scale, doc, values) in enumerate((
        ("speed", "rpm", 1.0, "measured speed, mechanical", ()),
        ("setpoint", "rpm", 1.0, "setpoint after the ramp", ()),
        ("voltage", "V", _V, "the law's output u", ()),
        ("current", "A", _A, "measured bus current", ()),
        ("integrator", "V", _V, "integral term I", ()),
        ("duty", "counts", 1.0, "PDC duty, raw counts (sign = direction)", ()),
        ("hall", "code", 1.0, "hall code 0..7", ()),
        ("state", "enum", 1.0, "drive state", tuple(s.name.lower() for s in State)),
        ("fault", "code", 1.0, "latched fault", tuple(f.name.lower() for f in Fault)),
        ("mu1", "1", _Q14, "membership of rule 1, 0..1", ()),
        ("position", "counts", 1.0, "encoder position (wraps at 16 bits)", ()),
        ("bus_voltage", "V", 1.0, "DC bus voltage measured on AN1 (scaled from the divider)", ()),
    )))


def static_defs(rules: int) -> tuple[ParamDef, ...]:
    """The static definition for ``rules`` rules, in id order."""
    if not isinstance(rules, int) or isinstance(rules, bool) or not 1 <= rules <= 8:
        raise ProtocolError(f"rules = {rules!r}: expected an integer in [1, 8] (design.rules of the profile)")
    gains = []
    for j in range(1, rules + 1):
        for k, (kind, unit, doc) in enumerate(RULE_GAINS):
            gains.append(ParamDef(RULE_BASE_ID + 4 * (j - 1) + k, f"rule{j}_{kind}", unit, "int16", _GAIN,
                                  -32768, 32767, 0, True, True, doc.format(j=j)))
    return tuple(sorted(PARAMS + SIGNALS + tuple(gains), key=lambda d: d.id))


# ---------------------------------------------------------------------------
# Resolved table
# ---------------------------------------------------------------------------
def float32_bits(x: float) -> int:
    return struct.unpack("<I", struct.pack("<f", x))[0]


def float32_from_bits(b: int) -> float:
    return struct.unpack("<f", struct.pack("<I", b))[0]


@dataclass(frozen=True)
class ParamOverride:
    """Per-build change of one entry: raw scale (float, stored as float32),
    raw limits and default, C type.  ``None`` keeps the static value."""
    scale: float | None = None
    min_raw: int | None = None
    max_raw: int | None = None
    default_raw: int | None = None
    ctype: str | None = None


@dataclass(frozen=True)
class Entry:
    """One resolved table entry."""
    id: int
    name: str
    unit: str
    ctype: str
    scale: float          # exactly representable as float32
    min_raw: int
    max_raw: int
    default_raw: int
    writable: bool
    persisted: bool
    signal: bool
    doc: str = ""
    values: tuple[str, ...] = ()

    @property
    def flags(self) -> int:
        return ((FLAG_WRITABLE if self.writable else 0) | (FLAG_PERSISTED if self.persisted else 0)
                | (FLAG_SIGNAL if self.signal else 0))

    @property
    def scale_bits(self) -> int:
        return float32_bits(self.scale)

    @property
    def ct(self) -> CType:
        return CTYPES[self.ctype]

    @property
    def unit_index(self) -> int:
        return UNITS.index(self.unit)

    @property
    def c_id(self) -> str:
        return "LINK_ID_" + self.name.upper()

    @property
    def min_value(self) -> float:
        return self.min_raw * self.scale

    @property
    def max_value(self) -> float:
        return self.max_raw * self.scale

    @property
    def default_value(self) -> float:
        return self.default_raw * self.scale

    def to_raw(self, value: float) -> int:
        """Nearest raw integer to an engineering value (no range check)."""
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ProtocolError(f"{self.name} = {value!r}: expected a finite number in {self.unit}")
        return int(round(value / self.scale))

    def canonical(self) -> bytes:
        return struct.pack("<BBBBIiii", self.id, self.ct.code, self.flags, self.unit_index, self.scale_bits,
                           self.min_raw, self.max_raw, self.default_raw) + self.name.encode("ascii") + b"\0"


@dataclass(frozen=True)
class Table:
    """The resolved parameter table of one build (entries in id order)."""
    entries: tuple[Entry, ...]
    rules: int

    def __post_init__(self):
        ids = [e.id for e in self.entries]
        if ids != sorted(set(ids)):
            raise ProtocolError("table entries must have unique ids in increasing order")
        if len(self.entries) > 255:
            raise ProtocolError(f"{len(self.entries)} table entries: at most 255 fit the protocol")

    @cached_property
    def by_name(self) -> dict[str, Entry]:
        return {e.name: e for e in self.entries}

    @cached_property
    def by_id(self) -> dict[int, Entry]:
        return {e.id: e for e in self.entries}

    def __getitem__(self, name: str) -> Entry:
        try:
            return self.by_name[name]
        except KeyError:
            raise ProtocolError(f"no table entry named {name!r}; known: {', '.join(self.by_name)}") from None

    def __contains__(self, name: object) -> bool:
        return name in self.by_name

    def __iter__(self):
        return iter(self.entries)

    def __len__(self) -> int:
        return len(self.entries)

    @property
    def params(self) -> tuple[Entry, ...]:
        return tuple(e for e in self.entries if not e.signal)

    @property
    def signals(self) -> tuple[Entry, ...]:
        """Signals in signal-index order (telemetry mask bit i = signals[i])."""
        return tuple(e for e in self.entries if e.signal)

    @property
    def persisted(self) -> tuple[Entry, ...]:
        return tuple(e for e in self.entries if e.persisted)

    def signal_index(self, name: str) -> int:
        e = self[name]
        if not e.signal:
            raise ProtocolError(f"{name!r} is a parameter, not a telemetry signal; signals: "
                                f"{', '.join(s.name for s in self.signals)}")
        return self.signals.index(e)

    def signal_mask(self, names: Iterable[str]) -> int:
        m = 0
        for n in names:
            m |= 1 << self.signal_index(n)
        return m

    def signals_in_mask(self, mask: int) -> tuple[Entry, ...]:
        sig = self.signals
        bad = [i for i in range(16) if mask >> i & 1 and i >= len(sig)]
        if bad or mask >> 16:
            raise ProtocolError(f"signal mask 0x{mask:04x} has bits beyond the {len(sig)} signals")
        return tuple(s for i, s in enumerate(sig) if mask >> i & 1)

    def canonical(self) -> bytes:
        """The canonical encoding the hash covers (every field of every entry)."""
        return b"picdrive.table/1\0" + b"".join(e.canonical() for e in self.entries)

    @cached_property
    def hash(self) -> int:
        """CRC-32 (zlib) of :meth:`canonical`: the table hash in hello."""
        return zlib.crc32(self.canonical()) & 0xFFFFFFFF

    @property
    def eeprom_data_bytes(self) -> int:
        return sum(e.ct.size for e in self.persisted)

    @property
    def eeprom_image_bytes(self) -> int:
        return EEPROM_HEADER_BYTES + self.eeprom_data_bytes + 2

    @property
    def param_store_bytes(self) -> int:
        return sum(e.ct.size for e in self.params)


def _check_entry(e: Entry) -> None:
    ct = CTYPES.get(e.ctype)
    where = f"protocol entry {e.name!r}"
    if ct is None:
        raise ProtocolError(f"{where}: ctype {e.ctype!r} is not one of {', '.join(CTYPES)}")
    if e.signal and e.ctype not in SIGNAL_CTYPES:
        raise ProtocolError(f"{where}: a telemetry signal travels as 16 bits; ctype must be int16 or uint16, "
                            f"not {e.ctype!r}")
    if not (isinstance(e.scale, float) and math.isfinite(e.scale) and e.scale > 0):
        raise ProtocolError(f"{where}: scale = {e.scale!r}: expected a finite positive number "
                            "(engineering value = raw x scale)")
    s32 = float32_from_bits(float32_bits(e.scale))
    if not (s32 > 0 and math.isfinite(s32)):
        raise ProtocolError(f"{where}: scale = {e.scale!r} does not fit a float32 (about 1.2e-38 .. 3.4e38)")
    for what, v in (("min_raw", e.min_raw), ("max_raw", e.max_raw), ("default_raw", e.default_raw)):
        if isinstance(v, bool) or not isinstance(v, int):
            raise ProtocolError(f"{where}: {what} = {v!r}: expected an integer (raw counts)")
        if not ct.lo <= v <= ct.hi:
            raise ProtocolError(f"{where}: {what} = {v} does not fit {e.ctype} [{ct.lo}, {ct.hi}]; "
                                "widen the ctype or narrow the limit")
    if not e.min_raw <= e.default_raw <= e.max_raw:
        raise ProtocolError(f"{where}: expected min_raw <= default_raw <= max_raw, got "
                            f"{e.min_raw} <= {e.default_raw} <= {e.max_raw}")
    if len(e.name) > NAME_MAX or not e.name.isascii():
        raise ProtocolError(f"{where}: names are ASCII, at most {NAME_MAX} characters")


def _pow2_scale(max_abs: float, counts: int = 32767, headroom: float = 1.25) -> float:
    """Smallest power of two s with counts * s >= headroom * max_abs."""
    return 2.0 ** math.ceil(math.log2(headroom * max_abs / counts))


def _profile_overrides(profile) -> dict[str, ParamOverride]:
    """Defaults taken from a drive profile (overrides given to build_table win)."""
    c, inv, u = profile.control, profile.inverter, profile.uart
    smax = int(math.ceil(c.speed_max_rpm))
    n1, n2 = profile.design.get("premise_rpm", [0.0, 3000.0])
    vmax = inv.bus_voltage_v * profile.max_duty()
    vs = _pow2_scale(inv.bus_voltage_v)
    as_ = _pow2_scale(max(inv.overcurrent_trip_a, inv.current_limit_a))
    ov = {
        "speed_setpoint": ParamOverride(min_raw=-smax, max_raw=smax, default_raw=0),
        "premise_low": ParamOverride(default_raw=int(round(n1))),
        "premise_high": ParamOverride(default_raw=int(round(n2))),
        "u_min": ParamOverride(scale=vs, min_raw=-int(vmax / vs), max_raw=0, default_raw=-int(vmax / vs)),
        "u_max": ParamOverride(scale=vs, min_raw=0, max_raw=int(vmax / vs), default_raw=int(vmax / vs)),
        "current_limit": ParamOverride(scale=as_, min_raw=0, max_raw=int(inv.overcurrent_trip_a / as_),
                                       default_raw=int(round(inv.current_limit_a / as_))),
        "link_timeout": ParamOverride(default_raw=int(round(u.link_timeout_ms))),
        "stall_timeout": ParamOverride(default_raw=int(round(c.stall_timeout_ms))),
        "voltage": ParamOverride(scale=vs), "integrator": ParamOverride(scale=vs),
        "current": ParamOverride(scale=as_),
    }
    if int(profile.design.get("rules", 2)) == 1:
        ov["controller"] = ParamOverride(default_raw=int(Controller.PID))
    return ov


def build_table(rules: int, overrides: Mapping[str, ParamOverride] | None = None, *, profile=None) -> Table:
    """Resolve the static definition for one build.

    ``rules``: number of fuzzy rules r (1..8); entries ``rule{j}_*`` exist for
    j = 1..r.  ``profile``: optional :class:`picdrive.profile.Profile` whose
    speed range, premise, bus voltage, current limit and timeouts give
    defaults.  ``overrides``: ``{name: ParamOverride}`` from the firmware's
    fixed-point plan (they win over the profile).  Raises
    :class:`ProtocolError` for an unknown name or a limit that does not fit.
    """
    defs = static_defs(rules)
    known = {d.name: d for d in defs}
    merged: dict[str, dict[str, Any]] = {}
    layers = []
    if profile is not None:
        layers.append(_profile_overrides(profile))
    if overrides:
        layers.append(dict(overrides))
    for layer in layers:
        for name, ov in layer.items():
            if name not in known:
                raise ProtocolError(f"override for unknown entry {name!r} (rules = {rules}); known entries: "
                                    f"{', '.join(known)}")
            if not isinstance(ov, ParamOverride):
                raise ProtocolError(f"override for {name!r} must be a protocol.ParamOverride, got {type(ov).__name__}")
            merged.setdefault(name, {}).update({k: v for k, v in dataclasses.asdict(ov).items() if v is not None})
    entries = []
    for d in defs:
        kw = dict(scale=d.scale, min_raw=d.min_raw, max_raw=d.max_raw, default_raw=d.default_raw, ctype=d.ctype)
        ov = merged.get(d.name, {})
        if d.signal and "ctype" in ov and ov["ctype"] in CTYPES:
            # a signal's limits are its type's range unless given
            kw["min_raw"], kw["max_raw"] = CTYPES[ov["ctype"]].lo, CTYPES[ov["ctype"]].hi
            kw["default_raw"] = max(kw["min_raw"], min(kw["max_raw"], kw["default_raw"]))
        kw.update(ov)
        scale = kw["scale"]
        if isinstance(scale, int) and not isinstance(scale, bool):
            scale = float(scale)
        e = Entry(id=d.id, name=d.name, unit=d.unit, ctype=kw["ctype"], scale=scale, min_raw=kw["min_raw"],
                  max_raw=kw["max_raw"], default_raw=kw["default_raw"], writable=d.writable, persisted=d.persisted,
                  signal=d.signal, doc=d.doc, values=d.values)
        _check_entry(e)
        entries.append(dataclasses.replace(e, scale=float32_from_bits(float32_bits(e.scale))))
    t = Table(tuple(entries), rules)
    if t.eeprom_image_bytes > EEPROM_BYTES:
        raise ProtocolError(f"the persisted parameters need {t.eeprom_image_bytes} B of EEPROM; the PIC18F4431 has "
                            f"{EEPROM_BYTES} B: use fewer rules or narrower ctypes")
    return t


# ---------------------------------------------------------------------------
# RAM budget (the C module's buffers; the state is measured from avr-nm)
# ---------------------------------------------------------------------------
def ram_budget(table: Table, capture_bytes: int = CAPTURE_BYTES_DEFAULT) -> dict[str, int]:
    """Bytes of the C module's buffers for a table: RX frame buffer and spill ring, TX frame buffer,
    telemetry frame buffer, replay store, parameter store, capture buffer.
    The scalar state (indices, counters, capture and telemetry settings) is
    :data:`STATE_BYTES` more; ``bench/link.py`` measures the total from the avr-gcc
    build (``avr-nm --size-sort -S``)."""
    return {
        "rx_frame": RX_BUFFER_BYTES,
        "rx_spill": RX_SPILL_BYTES,
        "tx_frame": MAX_BODY + 1,
        "telemetry_frame": MAX_PAYLOAD,
        "replay": REPLAY_BYTES,
        "param_store": table.param_store_bytes,
        "capture": capture_bytes,
    }


# -- invariants of the definition (checked at import: a broken table is a bug here) --
def _check_definition() -> None:
    codes = [c.code for c in COMMANDS] + [MSG_TELEMETRY, MSG_EVENT, MSG_NACK]
    assert len(codes) == len(set(codes)) and all(0 < c < ACK_BIT for c in codes)
    for c in COMMANDS:
        assert c.args_size <= MAX_PAYLOAD and c.reply_size <= MAX_PAYLOAD
        if c.side_effects:
            # replies of commands with side effects fit the replay store
            assert c.reply_tail is None and c.reply_size <= REPLAY_BYTES, c.name
    assert COMMAND_BY_NAME["param_info"].reply_size + NAME_MAX <= MAX_PAYLOAD
    assert 4 * PARAM_GET_MAX <= MAX_PAYLOAD
    assert TELEMETRY_HEADER_BYTES + 2 * len(DEFAULT_TELEMETRY_SIGNALS) * DEFAULT_SAMPLES_PER_FRAME <= MAX_PAYLOAD
    assert RX_BUFFER_BYTES == MAX_FRAME - 1 < 255   # a frame without its delimiter; byte indices
    assert RX_SPILL_BYTES & (RX_SPILL_BYTES - 1) == 0 and 8 <= RX_SPILL_BYTES <= 128   # an AND wraps it
    assert MAX_BODY < 254                 # one COBS block per frame
    assert [c.code for c in COMMANDS] == list(range(1, len(COMMANDS) + 1))   # the C dispatch table
    assert len(SIGNALS) <= 16
    for d in static_defs(8):
        assert len(d.name) <= NAME_MAX and d.unit in UNITS, d.name


_check_definition()
