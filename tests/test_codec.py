"""The Python codec: properties (Hypothesis) and the error paths."""
import binascii
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from picdrive.link import codec, protocol as P
from picdrive.link.protocol import ProtocolError

TABLE = P.build_table(2)
SETTINGS = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])

payloads = st.binary(max_size=P.MAX_PAYLOAD)
bytes8 = st.integers(0, 255)
frames = st.builds(codec.Frame, bytes8, bytes8, payloads)


def cobs_reference(data: bytes) -> bytes | None:
    """COBS decoding written from the definition: split at the code bytes, each block is
    code - 1 data bytes followed by a zero, the zero after the last block is not part of the data."""
    out, i = [], 0
    while i < len(data):
        code = data[i]
        block = data[i + 1:i + code]
        if code == 0 or len(block) != code - 1:
            return None
        out.append(block)
        i += code
    return b"\0".join(out)


def reference(stream: bytes, gaps: set[int]) -> list[codec.Frame]:
    """Whole-array statement of the rule: the bytes between two delimiters (or the start of the
    stream / a gap and a delimiter) are one candidate; it is a frame if it COBS-decodes to LEN,
    TYPE, SEQ, payload and a CRC that matches, LEN + 5 bytes in all."""
    out, start = [], 0
    for i, b in enumerate(stream):
        if i in gaps:
            start = i
        if b != P.DELIMITER:
            continue
        cand, start = stream[start:i], i + 1
        body = cobs_reference(cand)
        if not body or len(body) < 5 or body[0] + 5 != len(body):
            continue
        if binascii.crc_hqx(body[:-2], 0xFFFF) != struct.unpack(">H", body[-2:])[0]:
            continue
        out.append(codec.Frame(body[1], body[2], bytes(body[3:-2])))
    return out


def stream_decode(stream: bytes, cuts: list[int], gaps: set[int]) -> list[codec.Frame]:
    d = codec.StreamDecoder()
    out = []
    bounds = sorted(set(c for c in cuts if 0 < c < len(stream)) | set(g for g in gaps if 0 < g < len(stream)))
    prev = 0
    for b in bounds + [len(stream)]:
        if prev in gaps and prev > 0:
            out += d.gap()
        out += d.feed(stream[prev:b])
        prev = b
    out += d.gap()                       # the end of the stream is a gap
    return out


@SETTINGS
@given(frames)
def test_frame_round_trip(f):
    data = f.encode()
    assert len(data) == len(f.payload) + P.FRAME_OVERHEAD and data[-1] == P.DELIMITER
    assert P.DELIMITER not in data[:-1]
    assert codec.StreamDecoder().feed(data) == [f]
    assert codec.StreamDecoder().feed(codec.encode_frame(f.type, f.seq, f.payload, lead=True)) == [f]


@SETTINGS
@given(st.binary(max_size=600))
def test_cobs_round_trip_and_no_zero(data):
    enc = codec.cobs_encode(data)
    assert 0 not in enc and len(enc) <= len(data) + 1 + len(data) // 254
    if len(data) < 254:
        assert codec.cobs_decode(enc) == data == cobs_reference(enc)


# streams built from frames, corrupted frames and garbage that is rich in delimiters and LEN bytes
garbage = st.lists(st.one_of(st.just(P.DELIMITER), st.integers(0, P.MAX_PAYLOAD + 5), bytes8), max_size=60).map(bytes)


@st.composite
def streams(draw):
    parts = draw(st.lists(st.one_of(
        frames.map(lambda f: f.encode()),
        st.tuples(frames, st.integers(1, 10_000)).map(lambda t: t[0].encode()[:max(1, t[1] % len(t[0].encode()))]),
        st.tuples(frames, st.integers(0, 10_000)).map(
            lambda t: (lambda b, k: b[:k] + bytes([b[k] ^ 0x10]) + b[k + 1:])(t[0].encode(), t[1] % len(t[0].encode()))),
        garbage), max_size=12))
    s = b"".join(parts)
    n = max(1, len(s))
    cuts = draw(st.lists(st.integers(0, n), max_size=8))
    gaps = set(draw(st.lists(st.integers(1, n), max_size=3)))
    return s, cuts, gaps


@SETTINGS
@given(streams())
def test_stream_decoder_applies_the_rule_for_any_chunking_and_gaps(case):
    s, cuts, gaps = case
    assert stream_decode(s, cuts, gaps) == reference(s, gaps)


@SETTINGS
@given(st.lists(frames, min_size=1, max_size=6), st.binary(max_size=80))
def test_garbage_before_a_delimiter_never_hides_a_frame(fs, junk):
    data = junk + b"\0" + b"".join(f.encode() for f in fs)
    assert codec.StreamDecoder().feed(data) == fs


@SETTINGS
@given(garbage, frames, frames)
def test_resync_at_the_next_delimiter(junk, f, g):
    """After any garbage, a frame sent as the host sends it (a delimiter before it) is always
    recovered, at its own delimiter: no byte after it is needed."""
    d = codec.StreamDecoder()
    d.feed(junk)
    assert d.feed(codec.encode_frame(f.type, f.seq, f.payload, lead=True)) == [f]
    assert d.feed(g.encode()) == [g]


@SETTINGS
@given(frames, st.lists(st.integers(0, 8 * P.MAX_FRAME - 1), min_size=1, max_size=3, unique=True))
def test_one_to_three_bit_flips_are_rejected(f, bits):
    """Bit flips anywhere but in the delimiter: the frame is rejected (CRC-16 detects every
    1-3 bit error within its length; a flip that makes a zero splits the frame into two
    candidates that fail their length check)."""
    data = bytearray(f.encode())
    bits = [b for b in bits if b < 8 * (len(data) - 1)]
    for b in bits:
        data[b // 8] ^= 1 << (b % 8)
    if not bits:
        return
    d = codec.StreamDecoder()
    assert d.feed(bytes(data)) == [] and d.crc_errors >= 1


# ---- the three defects of the 1.x framing (each test fails on it) ----
def _frame_with_crc_low(byte: int, payload: bytes) -> codec.Frame:
    for seq in range(256):
        f = codec.Frame(0x04, seq, payload)
        if codec.crc16(codec.frame_body(f.type, f.seq, f.payload)[:-2]) & 0xFF == byte:
            return f
    raise AssertionError("no SEQ gives that CRC byte")


def test_a_frame_inside_a_payload_is_never_executed():
    """1.x: a frame carried inside another frame's payload executed when the outer start byte
    was lost.  Now the inner frame's bytes are stuffed: no loss of outer bytes exposes it."""
    inner = codec.encode_frame(0x07, 0x42)             # "stop", as a host would send it
    outer = codec.encode_frame(0x04, 0x01, inner[:-1] + b"\x00" * 0 + inner[:P.MAX_PAYLOAD - len(inner)])
    assert len(outer) > len(inner)
    for k in range(1, len(outer) - 1):                 # lose the first k bytes, then the rest
        for data in (outer[k:], b"\0" + outer[k:]):
            got = codec.StreamDecoder().feed(data)
            assert codec.Frame(0x07, 0x42) not in got


def test_a_frame_cut_one_byte_short_is_not_completed_by_the_next_frame():
    """1.x: a frame missing its last byte was completed by the next frame's start byte when its
    CRC low byte equalled it (1 in 256).  Now the cut frame merges with the next one (without
    the host's leading delimiter) or is ended by that delimiter: rejected either way."""
    for low in range(256):
        f = _frame_with_crc_low(low, bytes((1, 2, 3, 4, 5)))
        nxt = codec.Frame(0x11, 0x77)
        cut = f.encode()[:-2]                           # the last body-carrying byte lost
        for data in (cut + nxt.encode(), cut + codec.encode_frame(nxt.type, nxt.seq, b"", lead=True)):
            got = codec.StreamDecoder().feed(data)
            assert f not in got and all(g == nxt for g in got)


def test_a_len_one_short_with_a_recomputed_crc_is_rejected():
    """1.x: LEN one short and a CRC recomputed over the shorter frame was accepted (1 in 256,
    when the byte after it completed the CRC).  Now LEN must equal the decoded length - 5."""
    for seq in range(256):
        body = bytearray(codec.frame_body(0x04, seq, bytes((9, 1, 2, 3, 4)))[:-2])
        for delta in (-1, 1):
            bad = bytearray(body)
            bad[0] = (bad[0] + delta) & 0xFF
            c = codec.crc16(bytes(bad))
            wire = codec.cobs_encode(bytes(bad) + bytes((c >> 8, c & 0xFF))) + b"\0"
            d = codec.StreamDecoder()
            assert d.feed(wire) == [] and d.crc_errors == 1


def _value_for(fmt, draw):
    lo, hi = {"B": (0, 255), "b": (-128, 127), "H": (0, 65535), "h": (-32768, 32767),
              "I": (0, 2**32 - 1), "i": (-2**31, 2**31 - 1)}[fmt]
    return draw(st.integers(lo, hi))


@st.composite
def command_cases(draw):
    c = draw(st.sampled_from(P.COMMANDS))
    args = {f.name: _value_for(f.fmt, draw) for f in c.args}
    if c.args_tail is not None:
        args[c.args_tail.name] = draw(st.lists(st.integers(0, 255), min_size=1, max_size=P.PARAM_GET_MAX))
    reply = {f.name: _value_for(f.fmt, draw) for f in c.reply}
    if c.reply_tail is not None:
        if c.reply_tail.fmt == "s":
            reply[c.reply_tail.name] = draw(st.text("abcdefghijklmnopqrstuvwxyz_0123456789", max_size=P.NAME_MAX))
        else:
            n = (P.MAX_PAYLOAD - c.reply_size) // struct.calcsize("<" + c.reply_tail.fmt)
            reply[c.reply_tail.name] = draw(st.lists(_int_strategy(c.reply_tail.fmt), max_size=n))
    return c, args, reply, draw(bytes8)


def _int_strategy(fmt):
    lo, hi = {"h": (-32768, 32767), "i": (-2**31, 2**31 - 1), "B": (0, 255)}[fmt]
    return st.integers(lo, hi)


@SETTINGS
@given(command_cases())
def test_command_and_reply_payloads_round_trip(case):
    c, args, reply, seq = case
    data = codec.encode_command(c.name, seq, args)
    (f,) = codec.StreamDecoder().feed(data)
    assert f.type == c.code and f.seq == seq
    assert len(f.payload) == c.args_size + (len(args.get(c.args_tail.name, [])) if c.args_tail else 0)
    rp = codec.reply_payload(c, reply)
    assert len(rp) <= P.MAX_PAYLOAD
    assert codec.decode_reply(c, rp) == reply
    ack = codec.Frame(P.ack_type(c.code), seq, rp)
    assert ack.is_ack and ack.command_code == c.code


@SETTINGS
@given(st.dictionaries(st.sampled_from([e.name for e in TABLE.persisted]), st.integers(-40000, 70000)))
def test_eeprom_image_round_trip_and_corruption(values):
    values = {k: v for k, v in values.items() if TABLE[k].min_raw <= v <= TABLE[k].max_raw}
    img = codec.eeprom_image(TABLE, values)
    assert len(img) == TABLE.eeprom_image_bytes
    res, got = codec.parse_eeprom_image(TABLE, img + b"\xff" * 10)
    assert res == P.EepromResult.OK
    assert got == {**{e.name: e.default_raw for e in TABLE.persisted}, **values}
    for i in range(len(img)):
        bad = bytearray(img)
        bad[i] ^= 0x5A
        assert codec.parse_eeprom_image(TABLE, bytes(bad))[0] != P.EepromResult.OK


def test_eeprom_layout_by_hand():
    t = P.build_table(1)
    img = codec.eeprom_image(t, {"controller": 0})
    n = t.eeprom_data_bytes
    assert img[:2] == b"PD" and img[2] == 1 and struct.unpack("<I", img[3:7])[0] == t.hash and img[7] == n
    assert img[8] == 0                                      # controller (uint8) is the first persisted entry
    assert struct.unpack(">H", img[-2:])[0] == binascii.crc_hqx(img[:-2], 0xFFFF)
    assert codec.parse_eeprom_image(t, b"\xff" * 64)[0] == P.EepromResult.BLANK
    assert codec.parse_eeprom_image(P.build_table(2), img)[0] == P.EepromResult.OTHER_BUILD


def test_telemetry_decode():
    vals = np.array([[1, -2, 3], [4, 5, -32768]], dtype="<i2")
    payload = struct.pack("<H", 65535) + vals.tobytes()
    counter, got = codec.decode_telemetry(payload, 3)
    assert counter == 65535 and (got == vals).all()
    with pytest.raises(ProtocolError, match="whole samples"):
        codec.decode_telemetry(payload + b"\0", 3)
    assert codec.telemetry_payload_len(4, 4) == 34


def test_param_info_decode():
    e = TABLE["rule1_kp"]
    rp = codec.reply_payload("param_info", dict(id=e.id, ctype=e.ct.code, flags=e.flags, unit=e.unit_index,
                                                 scale_bits=e.scale_bits, min=e.min_raw, max=e.max_raw,
                                                 default=e.default_raw, name=e.name))
    got = codec.decode_param_info(rp)
    assert got.name == e.name and got.scale == e.scale and got.unit == e.unit and got.writable and got.persisted
    bad = bytearray(rp)
    bad[3] = 200
    with pytest.raises(ProtocolError, match="unit index 200"):
        codec.decode_param_info(bytes(bad))


@pytest.mark.parametrize("call, words", [
    (lambda: codec.encode_frame(1, 0, bytes(P.MAX_PAYLOAD + 1)), "exceeds the frame limit"),
    (lambda: codec.encode_frame(256, 0), "must be bytes"),
    (lambda: codec.encode_command("nope", 0), "unknown command 'nope'"),
    (lambda: codec.encode_command("param_set", 0, {"id": 1}), "argument 'value' missing"),
    (lambda: codec.encode_command("param_set", 0, {"id": 1, "value": 2, "x": 3}), "unexpected argument"),
    (lambda: codec.encode_command("param_set", 0, {"id": 300, "value": 2}), "does not fit"),
    (lambda: codec.decode_reply("hello", b"\0" * 3), "expected 20 B"),
    (lambda: codec.decode_nack(b"\0"), "expected 2"),
])
def test_codec_errors_name_the_problem(call, words):
    with pytest.raises(ProtocolError, match=words):
        call()


@pytest.mark.parametrize("chunk", [4096, 5_000_000])
def test_five_megabytes_without_a_delimiter_are_not_held(chunk):
    """Bounded like the firmware's receive buffer: bytes past the longest encoded frame are
    dropped as they arrive, the candidate counts as one error at its delimiter, and the next
    frame decodes."""
    d = codec.StreamDecoder()
    noise = bytes(range(1, 256)) * (5_000_000 // 255)
    held = 0
    for k in range(0, len(noise), chunk):
        assert d.feed(noise[k:k + chunk]) == []
        held = max(held, d.pending)
    assert held <= P.RX_BUFFER_BYTES and d.partial
    f = codec.Frame(0x81, 7, b"\x01\x02")
    assert d.feed(codec.encode_frame(f.type, f.seq, f.payload, lead=True)) == [f]
    assert d.crc_errors == 1 and not d.partial and d.pending == 0
    # an oversize candidate cut by a gap: the frame after it (no leading delimiter) decodes
    d.feed(noise[:1000])
    d.gap()
    assert d.feed(f.encode()) == [f]
