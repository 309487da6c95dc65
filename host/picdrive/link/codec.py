"""Frame codec: the host side of :mod:`picdrive.link.protocol`, with the same tables.

* :func:`encode_frame` / :class:`Frame` -- body LEN, TYPE, SEQ, payload,
  CRC-16/CCITT-FALSE (``binascii.crc_hqx(data, 0xFFFF)``) over LEN..payload,
  high byte first; on the wire COBS(body) then the delimiter 0x00.
* :func:`cobs_encode`, :func:`cobs_decode` -- consistent overhead byte stuffing.
* :class:`StreamDecoder` -- the streaming receiver with exactly the C
  module's rule: bytes up to each 0x00 are one candidate, dropped whole unless
  it COBS-decodes to a body of LEN + 5 bytes whose CRC holds;
  :meth:`StreamDecoder.gap` (no byte for ``HOST_GAP_MS``) drops a partial one.
* :func:`encode_command`, :func:`decode_reply` -- payloads of the commands in
  :data:`picdrive.link.protocol.COMMANDS` (little-endian ``struct`` layouts).
* :func:`decode_telemetry`, :func:`decode_event`, :func:`decode_nack`.
* :func:`eeprom_image`, :func:`parse_eeprom_image` -- the EEPROM image of the
  persisted parameters, byte for byte as the C module writes it.
"""
from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass
from typing import Any, Iterable, Mapping

import numpy as np

from . import protocol as P
from .protocol import ProtocolError

__all__ = [
    "crc16", "cobs_encode", "cobs_decode", "Frame", "encode_frame", "frame_body", "parse_body", "StreamDecoder",
    "encode_command", "decode_reply", "reply_payload", "command_payload", "decode_nack", "decode_event",
    "decode_telemetry", "telemetry_payload_len", "eeprom_image", "parse_eeprom_image", "decode_param_info",
]

_DELIM = bytes((P.DELIMITER,))


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor)."""
    return binascii.crc_hqx(data, 0xFFFF)


def cobs_encode(data: bytes) -> bytes:
    """COBS: each run of non-zero bytes (at most 254) is preceded by its length + 1; the zeros
    are implied.  The result holds no 0x00."""
    out = bytearray()
    for block in bytes(data).split(b"\0"):
        while len(block) >= 254:
            out.append(255)
            out += block[:254]
            block = block[254:]
        out.append(len(block) + 1)
        out += block
    return bytes(out)


def cobs_decode(data: bytes) -> bytes | None:
    """Inverse of :func:`cobs_encode` for bodies shorter than 254 bytes, as the C module decodes:
    every code byte after the first implies the zero before its block.  None if a block is cut
    short or a 0x00 occurs."""
    out, i, n = bytearray(), 0, len(data)
    while i < n:
        code = data[i]
        if code == 0 or i + code > n:
            return None
        if i:
            out.append(0)
        out += data[i + 1:i + code]
        i += code
    return bytes(out)


def frame_body(type_: int, seq: int, payload: bytes = b"") -> bytes:
    """LEN, TYPE, SEQ, payload, CRC (high byte first): the part of a frame the CRC protects."""
    payload = bytes(payload)
    if len(payload) > P.MAX_PAYLOAD:
        raise ProtocolError(f"payload of {len(payload)} B exceeds the frame limit of {P.MAX_PAYLOAD} B")
    if not (0 <= type_ <= 255 and 0 <= seq <= 255):
        raise ProtocolError(f"TYPE {type_!r} and SEQ {seq!r} must be bytes (0..255)")
    body = bytes((len(payload), type_, seq)) + payload
    c = crc16(body)
    return body + bytes((c >> 8, c & 0xFF))


def parse_body(body: bytes) -> Frame | None:
    """The frame of a decoded body, or None unless its length is LEN + 5 and its CRC holds."""
    n = len(body)
    if n < P.BODY_OVERHEAD or body[0] + P.BODY_OVERHEAD != n or crc16(body) != 0:
        return None
    return Frame(body[1], body[2], bytes(body[3:n - 2]))


@dataclass(frozen=True)
class Frame:
    """A decoded frame (TYPE, SEQ, payload); :meth:`encode` gives its bytes."""
    type: int
    seq: int
    payload: bytes = b""

    def encode(self) -> bytes:
        return encode_frame(self.type, self.seq, self.payload)

    @property
    def is_ack(self) -> bool:
        return bool(self.type & P.ACK_BIT)

    @property
    def is_nack(self) -> bool:
        return self.type == P.MSG_NACK

    @property
    def is_reply(self) -> bool:
        return self.is_ack or self.is_nack

    @property
    def command_code(self) -> int | None:
        """The command a reply answers (ACK: from TYPE; NACK: from the payload)."""
        if self.is_ack:
            return self.type & ~P.ACK_BIT
        if self.is_nack and len(self.payload) >= 1:
            return self.payload[0]
        return None


def encode_frame(type_: int, seq: int, payload: bytes = b"", *, lead: bool = False) -> bytes:
    """Bytes of one frame on the wire: COBS(body), 0x00 (``lead``: a 0x00 before it too, as the
    host sends commands, so that a partial frame before it is dropped at once).  Raises
    ProtocolError if the payload is too long."""
    return (_DELIM if lead else b"") + cobs_encode(frame_body(type_, seq, payload)) + _DELIM


class StreamDecoder:
    """Streaming frame receiver, same rule as the C module's ``rx_frame``.

    ``feed(data)`` returns the frames completed by ``data``; ``gap()`` is
    called when no byte arrived for ``HOST_GAP_MS`` and drops a partial
    frame.  Counters: ``crc_errors`` (non-empty candidates rejected: bad
    COBS, length or CRC), ``bytes_in``.

    Bounded like the firmware's receive buffer: a candidate longer than
    :data:`~picdrive.link.protocol.RX_BUFFER_BYTES` (the longest encoded
    frame without its delimiter) cannot be a frame, so its bytes are
    dropped as they arrive and only the fact that one is under way is kept
    until its delimiter (then counted as a CRC error): a noisy line without
    a 0x00 holds at most that many bytes, however long it runs.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._oversize = False           # the candidate under way is too long to be a frame
        self.crc_errors = 0
        self.bytes_in = 0

    @property
    def pending(self) -> int:
        """Bytes held of a partial frame (at most ``RX_BUFFER_BYTES``)."""
        return len(self._buf)

    @property
    def partial(self) -> bool:
        """A candidate frame is under way (bytes since the last delimiter), held or oversize."""
        return bool(self._buf) or self._oversize

    def feed(self, data: bytes) -> list[Frame]:
        data = bytes(data)
        self.bytes_in += len(data)
        parts = data.split(_DELIM)
        out = []
        for k, part in enumerate(parts[:-1]):
            if k == 0:
                oversize = self._oversize or len(self._buf) + len(part) > P.RX_BUFFER_BYTES
                cand = b"" if oversize else bytes(self._buf) + part
            else:
                oversize, cand = len(part) > P.RX_BUFFER_BYTES, part
            self._buf.clear()
            self._oversize = False
            if not cand and not oversize:
                continue
            body = cobs_decode(cand) if not oversize else None
            f = parse_body(body) if body is not None else None
            if f is None:
                self.crc_errors += 1
            else:
                out.append(f)
        tail = parts[-1]
        if self._oversize or len(self._buf) + len(tail) > P.RX_BUFFER_BYTES:
            self._buf.clear()
            self._oversize = bool(tail) or self._oversize
        else:
            self._buf += tail
        return out

    def gap(self) -> list[Frame]:
        """Drop a partial frame (what follows it up to the next 0x00 then fails its checks)."""
        self.reset()
        return []

    def reset(self) -> None:
        self._buf.clear()
        self._oversize = False


# ---------------------------------------------------------------------------
# Command payloads
# ---------------------------------------------------------------------------
def _command(cmd: str | P.Command) -> P.Command:
    if isinstance(cmd, P.Command):
        return cmd
    try:
        return P.COMMAND_BY_NAME[cmd]
    except KeyError:
        raise ProtocolError(f"unknown command {cmd!r}; known: {', '.join(P.COMMAND_BY_NAME)}") from None


def _fmt(fields: Iterable[P.Field]) -> str:
    return "<" + "".join(f.fmt for f in fields)


def command_payload(cmd: str | P.Command, args: Mapping[str, Any] | None = None) -> bytes:
    """Payload of a command from its named arguments (``args_tail`` as a list)."""
    c = _command(cmd)
    args = dict(args or {})
    try:
        out = struct.pack(_fmt(c.args), *(args.pop(f.name) for f in c.args))
        if c.args_tail is not None:
            items = list(args.pop(c.args_tail.name))
            out += struct.pack("<" + c.args_tail.fmt * len(items), *items)
    except KeyError as e:
        raise ProtocolError(f"{c.name}: argument {e.args[0]!r} missing; expected "
                            f"{', '.join(f.name for f in c.args) or 'none'}") from None
    except struct.error as e:
        raise ProtocolError(f"{c.name}: an argument does not fit its field ({e})") from None
    if args:
        raise ProtocolError(f"{c.name}: unexpected argument(s) {', '.join(args)}")
    if len(out) > P.MAX_PAYLOAD:
        raise ProtocolError(f"{c.name}: {len(out)} B of arguments exceed {P.MAX_PAYLOAD} B")
    return out


def encode_command(cmd: str | P.Command, seq: int, args: Mapping[str, Any] | None = None) -> bytes:
    """Frame bytes of a command, as the host sends it (a 0x00 before the frame too)."""
    c = _command(cmd)
    return encode_frame(c.code, seq, command_payload(c, args), lead=True)


def reply_payload(cmd: str | P.Command, fields: Mapping[str, Any] | None = None) -> bytes:
    """ACK payload of a command from its named reply fields (the inverse of :func:`decode_reply`)."""
    c = _command(cmd)
    fields = dict(fields or {})
    try:
        out = struct.pack(_fmt(c.reply), *(fields.pop(f.name) for f in c.reply))
        if c.reply_tail is not None:
            t = c.reply_tail
            items = fields.pop(t.name)
            out += items.encode("ascii") if t.fmt == "s" else struct.pack("<" + t.fmt * len(items), *items)
    except KeyError as e:
        raise ProtocolError(f"{c.name} reply: field {e.args[0]!r} missing") from None
    if fields:
        raise ProtocolError(f"{c.name} reply: unexpected field(s) {', '.join(fields)}")
    return out


def decode_reply(cmd: str | P.Command, payload: bytes) -> dict[str, Any]:
    """Fields of an ACK payload (the tail as a list, or a str for text)."""
    c = _command(cmd)
    fmt = _fmt(c.reply)
    size = struct.calcsize(fmt)
    if len(payload) < size or (c.reply_tail is None and len(payload) != size):
        raise ProtocolError(f"{c.name} reply of {len(payload)} B; expected {size} B"
                            + (" or more" if c.reply_tail is not None else ""))
    d = dict(zip((f.name for f in c.reply), struct.unpack_from(fmt, payload)))
    if c.reply_tail is not None:
        rest = payload[size:]
        t = c.reply_tail
        if t.fmt == "s":
            d[t.name] = rest.decode("ascii", errors="replace")
        else:
            isz = struct.calcsize("<" + t.fmt)
            if len(rest) % isz:
                raise ProtocolError(f"{c.name} reply: {len(rest)} B of {t.name} is not a whole number of items")
            d[t.name] = list(struct.unpack("<" + t.fmt * (len(rest) // isz), rest))
    return d


def decode_param_info(payload: bytes) -> P.Entry:
    """An :class:`~picdrive.link.protocol.Entry` from a param_info reply (names,
    units and enum values come from the board; docs are empty)."""
    d = decode_reply("param_info", payload)
    ct = P.CTYPE_BY_CODE.get(d["ctype"])
    if ct is None:
        raise ProtocolError(f"param_info of id 0x{d['id']:02x}: unknown C type code {d['ctype']}")
    if d["unit"] >= len(P.UNITS):
        raise ProtocolError(f"param_info of {d['name']!r}: unit index {d['unit']} unknown to this host "
                            f"(knows {len(P.UNITS)} units): update picdrive")
    return P.Entry(id=d["id"], name=d["name"], unit=P.UNITS[d["unit"]], ctype=ct.name,
                   scale=P.float32_from_bits(d["scale_bits"]), min_raw=d["min"], max_raw=d["max"],
                   default_raw=d["default"], writable=bool(d["flags"] & P.FLAG_WRITABLE),
                   persisted=bool(d["flags"] & P.FLAG_PERSISTED), signal=bool(d["flags"] & P.FLAG_SIGNAL))


def decode_nack(payload: bytes) -> tuple[int, int]:
    """(command TYPE, NACK code) of a NACK payload."""
    if len(payload) != 2:
        raise ProtocolError(f"NACK payload of {len(payload)} B; expected 2")
    return payload[0], payload[1]


def decode_event(payload: bytes) -> tuple[int, int]:
    """(event, code) of an event payload."""
    if len(payload) != 2:
        raise ProtocolError(f"event payload of {len(payload)} B; expected 2")
    return payload[0], payload[1]


def telemetry_payload_len(n_signals: int, samples_per_frame: int) -> int:
    return P.TELEMETRY_HEADER_BYTES + 2 * n_signals * samples_per_frame


def decode_telemetry(payload: bytes, n_signals: int) -> tuple[int, np.ndarray]:
    """(counter of the first sample, int16 array of shape (samples, n_signals))."""
    body = len(payload) - P.TELEMETRY_HEADER_BYTES
    if n_signals <= 0 or body < 0 or body % (2 * n_signals):
        raise ProtocolError(f"telemetry payload of {len(payload)} B does not hold whole samples of "
                            f"{n_signals} signals")
    counter = payload[0] | payload[1] << 8
    vals = np.frombuffer(payload, dtype="<i2", offset=P.TELEMETRY_HEADER_BYTES).reshape(-1, n_signals)
    return counter, vals


# ---------------------------------------------------------------------------
# EEPROM image
# ---------------------------------------------------------------------------
_PACK = {"uint8": "<B", "int8": "<b", "uint16": "<H", "int16": "<h", "int32": "<i"}


def eeprom_image(table: P.Table, values: Mapping[str, int] | None = None) -> bytes:
    """The EEPROM image the C module writes for ``table`` with raw ``values``
    (missing names: the default)."""
    values = dict(values or {})
    data = b""
    for e in table.persisted:
        v = values.pop(e.name, e.default_raw)
        data += struct.pack(_PACK[e.ctype], v)
    if values:
        raise ProtocolError(f"not persisted parameters in the EEPROM values: {', '.join(values)}")
    img = P.EEPROM_MAGIC + bytes((P.EEPROM_LAYOUT_VERSION,)) + struct.pack("<I", table.hash) \
        + bytes((len(data),)) + data
    c = crc16(img)
    return img + bytes((c >> 8, c & 0xFF))


def parse_eeprom_image(table: P.Table, image: bytes) -> tuple[P.EepromResult, dict[str, int]]:
    """(result, raw values) by the C module's rule: BLANK without the magic,
    OTHER_BUILD for another table, CORRUPT for a bad CRC or an out-of-range
    value (values then empty)."""
    image = bytes(image)
    if image[:2] != P.EEPROM_MAGIC:
        return P.EepromResult.BLANK, {}
    n = table.eeprom_data_bytes
    if len(image) < P.EEPROM_HEADER_BYTES or image[2] != P.EEPROM_LAYOUT_VERSION or image[7] != n \
            or struct.unpack_from("<I", image, 3)[0] != table.hash:
        return P.EepromResult.OTHER_BUILD, {}
    end = P.EEPROM_HEADER_BYTES + n
    if len(image) < end + 2 or crc16(image[:end]) != (image[end] << 8 | image[end + 1]):
        return P.EepromResult.CORRUPT, {}
    out, off = {}, P.EEPROM_HEADER_BYTES
    for e in table.persisted:
        (v,) = struct.unpack_from(_PACK[e.ctype], image, off)
        if not e.min_raw <= v <= e.max_raw:
            return P.EepromResult.CORRUPT, {}
        out[e.name] = v
        off += e.ct.size
    return P.EepromResult.OK, out
