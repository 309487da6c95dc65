"""The rendered C link module, driven through ctypes (tests/linksupport/fake_app.c as the app).

Python <-> C byte identity of frames both ways, every NACK path, duplicate-SEQ replay, EEPROM
image round trip and corrupt-image rejection, the watchdog (only while running, fed by host commands only), resynchronisation at the delimiter,
telemetry and capture.
"""
import random

import numpy as np
import pytest

from picdrive.link import codec, protocol as P
from picdrive.firmware.p18f4431 import bits
from picdrive.link.protocol_c import render_c
from picdrive.link.protocol import Nack

from linksupport.build import DEFAULT_BUILD_ID, DEFAULT_PROFILE_HASH
from linksupport.fakeboard import FakeBoard

TABLE = P.build_table(2, {"rule1_kp": P.ParamOverride(scale=1 / 1024, min_raw=-1000, max_raw=20000, default_raw=300),
                          "rule2_ki": P.ParamOverride(ctype="int32", min_raw=-100000, max_raw=100000, default_raw=-7),
                          "position": P.ParamOverride(ctype="uint16")})


class Peer:
    """Direct-mode driver: send a command, collect the frames the module emits."""

    def __init__(self, board: FakeBoard):
        self.b = board
        self.dec = codec.StreamDecoder()
        self.seq = 0
        self.other: list[codec.Frame] = []     # telemetry / events seen while waiting for replies

    def frames(self) -> list[codec.Frame]:
        self.b.lib.link_poll()                 # a pass of the firmware's main loop
        return self.dec.feed(self.b.take_tx())

    def raw(self, frame: bytes) -> list[codec.Frame]:
        self.b.feed(frame)
        return self.frames()

    def cmd(self, name, args=None, *, seq=None, payload=None):
        """Send a command; return the one reply frame (asserting there is exactly one)."""
        c = P.COMMAND_BY_NAME[name]
        if seq is None:
            self.seq = (self.seq + 1) & 0xFF
            seq = self.seq
        data = codec.encode_frame(c.code, seq, codec.command_payload(c, args) if payload is None else payload,
                                  lead=True)
        got = self.raw(data)
        replies = [f for f in got if f.is_reply]
        self.other += [f for f in got if not f.is_reply]
        assert len(replies) == 1, got
        assert replies[0].seq == seq
        return replies[0]

    def ok(self, name, args=None, **kw) -> dict:
        f = self.cmd(name, args, **kw)
        assert f.type == P.ack_type(P.COMMAND_BY_NAME[name].code), (name, f, NACK_NAME(f))
        return codec.decode_reply(name, f.payload)

    def nack(self, name, args=None, **kw) -> Nack:
        f = self.cmd(name, args, **kw)
        assert f.is_nack, (name, f)
        cmd, code = codec.decode_nack(f.payload)
        assert cmd == P.COMMAND_BY_NAME[name].code
        return Nack(code)


def NACK_NAME(f):
    return Nack(f.payload[1]).name if f.is_nack else ""


@pytest.fixture(scope="module")
def board():
    b = FakeBoard(TABLE, txq_bytes=4096)     # direct mode: the test empties the UART queue
    yield b
    b.close()


@pytest.fixture
def peer(board):
    board.erase_eeprom()
    board.boot()
    p = Peer(board)
    boot = p.frames()
    assert boot == [codec.Frame(P.MSG_EVENT, 0, bytes((P.Event.BOOT, 0)))]
    return p


# ---------------------------------------------------------------------------
def test_crc16_matches_binascii(board):
    assert board.lib.link_crc16(b"123456789", 9) == 0x29B1 == codec.crc16(b"123456789")
    rng = random.Random(1)
    for n in list(range(0, 50)) + [255]:
        data = bytes(rng.randrange(256) for _ in range(n))
        assert board.lib.link_crc16(data, n) == codec.crc16(data)


def test_hello_bytes_identical(peer):
    f = peer.cmd("hello", seq=0x42)
    want = codec.reply_payload("hello", dict(
        proto_major=P.PROTOCOL_VERSION[0], proto_minor=P.PROTOCOL_VERSION[1], build_id=DEFAULT_BUILD_ID,
        profile_hash=DEFAULT_PROFILE_HASH, table_hash=TABLE.hash, n_entries=len(TABLE), max_payload=P.MAX_PAYLOAD,
        capture_words=P.CAPTURE_BYTES_DEFAULT // 2, sample_hz=1000, features=[0]))
    assert peer.b.take_tx() == b""
    # the whole frame, byte for byte, as Python encodes it
    peer.b.feed(codec.encode_command("hello", 0x43))
    assert peer.b.take_tx() == codec.encode_frame(P.ack_type(0x01), 0x43, want)
    assert f.payload == want


def test_param_info_reproduces_the_table_and_its_hash(peer):
    entries = [codec.decode_param_info(peer.cmd("param_info", {"index": i}).payload) for i in range(len(TABLE))]
    for got, want in zip(entries, TABLE):
        assert got == P.Entry(**{**want.__dict__, "doc": "", "values": ()})
    assert P.Table(tuple(entries), TABLE.rules).hash == TABLE.hash
    assert peer.nack("param_info", {"index": len(TABLE)}) == Nack.UNKNOWN_PARAM


def test_commands_from_python_reach_c_unchanged(peer):
    """Every command frame Python encodes is accepted by C with the same TYPE, SEQ and payload."""
    peer.b.clear_log()
    sent = []
    rng = random.Random(3)
    for c in P.COMMANDS:
        for _ in range(3):
            payload = bytes(rng.randrange(256) for _ in range(rng.randrange(P.MAX_PAYLOAD + 1)))
            seq = rng.randrange(256)
            sent.append((c.code, seq, payload))
            peer.b.feed(codec.encode_frame(c.code, seq, payload))
            peer.frames()
            peer.b.tick(1)
            peer.b.feed(codec.encode_command("stop", (seq + 1) & 0xFF))   # leave RUN: no watchdog
    log = [(t, s, p) for t, s, p, _ in peer.b.log()]
    assert log[::2] == sent


def test_frames_from_c_decode_and_reencode_identically(peer):
    peer.ok("telem_config", {"mask": 0x7FF, "decimation": 1, "samples_per_frame": 1})
    peer.ok("set_speed", {"value": 1500})
    peer.ok("start")
    raw = b""
    for _ in range(50):
        peer.b.tick(1)
        peer.b.sample(1)
        raw += peer.b.take_tx()
    frames = codec.StreamDecoder().feed(raw)
    assert len(frames) == 50 and b"".join(f.encode() for f in frames) == raw


@pytest.mark.parametrize("name", [c.name for c in P.COMMANDS])
def test_malformed_length_every_command(peer, name):
    c = P.COMMAND_BY_NAME[name]
    if c.args_tail is not None:         # param_get: 0 ids or more than PARAM_GET_MAX
        assert peer.nack(name, payload=b"") == Nack.MALFORMED
        assert peer.nack(name, payload=bytes([0] * (P.PARAM_GET_MAX + 1))) == Nack.MALFORMED
    else:
        assert peer.nack(name, payload=bytes(c.args_size + 1)) == Nack.MALFORMED
        if c.args_size:
            assert peer.nack(name, payload=bytes(c.args_size - 1)) == Nack.MALFORMED


def test_unknown_command_and_board_only_types(peer):
    for t in (0x00, max(c.code for c in P.COMMANDS) + 1, 0x3F, 0x5F):
        peer.b.feed(codec.encode_frame(t, 9, b""))
        (f,) = peer.frames()
        assert f.is_nack and f.seq == 9 and codec.decode_nack(f.payload) == (t, Nack.UNKNOWN_COMMAND)
    # the board's own frame types (an echo on a loop-back fault) are not answered: no NACK storm
    for t in (P.MSG_TELEMETRY, P.MSG_EVENT, P.MSG_NACK, 0x81, 0xFF):
        peer.b.feed(codec.encode_frame(t, 9, b"\x01\x02"))
        assert peer.frames() == []
    peer.ok("heartbeat")


def test_param_get_set_ranges_and_read_only(peer):
    b = peer.b
    kp = TABLE["rule1_kp"]
    assert peer.ok("param_get", {"ids": [kp.id]})["values"] == [300]
    r = peer.ok("param_set", {"id": kp.id, "value": 20000})
    assert r == {"id": kp.id, "value": 20000} and b.param("rule1_kp") == 20000
    n_changed = b.stat("param_changed")
    for bad in (20001, -1001, 2**31 - 1, -2**31):
        assert peer.nack("param_set", {"id": kp.id, "value": bad}) == Nack.OUT_OF_RANGE
    assert b.param("rule1_kp") == 20000 and b.stat("param_changed") == n_changed   # rejected set changed nothing
    # int32 parameter and its sign
    ki2 = TABLE["rule2_ki"]
    assert peer.ok("param_set", {"id": ki2.id, "value": -99999})["value"] == -99999
    assert peer.nack("param_set", {"id": ki2.id, "value": 100001}) == Nack.OUT_OF_RANGE
    # uint16 parameter above int16
    lt = TABLE["link_timeout"]
    assert peer.ok("param_set", {"id": lt.id, "value": 60000})["value"] == 60000
    assert b.lib.link_param_i16(lt.id) == 32767                      # saturated accessor
    assert peer.nack("param_set", {"id": lt.id, "value": 19}) == Nack.OUT_OF_RANGE
    # read-only signal, unknown ids
    assert peer.nack("param_set", {"id": TABLE["speed"].id, "value": 1}) == Nack.READ_ONLY
    assert peer.nack("param_set", {"id": 0x1F, "value": 1}) == Nack.UNKNOWN_PARAM
    assert peer.nack("param_get", {"ids": [kp.id, 0x1F]}) == Nack.UNKNOWN_PARAM
    # several ids at once, parameters and signals mixed, in order
    ids = [TABLE[n].id for n in ("state", "rule1_kp", "rule2_ki", "link_timeout", "controller", "speed",
                                 "fault", "premise_high", "rule1_kp", "position")]
    vals = peer.ok("param_get", {"ids": ids})["values"]
    assert vals == [0, 20000, -99999, 60000, 1, 0, 0, 3000, 20000, 0]
    # set_speed / select_controller are the same store
    assert peer.ok("set_speed", {"value": -1234}) == {"value": -1234} and b.param("speed_setpoint") == -1234
    assert peer.nack("set_speed", {"value": 30001}) == Nack.OUT_OF_RANGE
    assert peer.ok("select_controller", {"controller": 0}) == {"controller": 0} and b.param("controller") == 0
    assert peer.nack("select_controller", {"controller": 2}) == Nack.OUT_OF_RANGE


def test_motion_commands_state_and_fault_active(peer):
    b = peer.b
    peer.ok("start")
    assert b.stat("state") == P.State.RUN
    peer.ok("brake")
    assert b.stat("state") == P.State.BRAKE
    peer.ok("stop")
    assert b.stat("state") == P.State.IDLE
    b.inject_fault(P.Fault.OVERCURRENT)
    assert peer.frames() == [codec.Frame(P.MSG_EVENT, 1, bytes((P.Event.FAULT, P.Fault.OVERCURRENT)))]
    assert peer.nack("start") == Nack.FAULT_ACTIVE
    st = peer.ok("status")
    assert st["state"] == P.State.FAULT and st["fault"] == P.Fault.OVERCURRENT
    peer.ok("fault_clear")
    peer.ok("start")
    assert peer.ok("status")["state"] == P.State.RUN


def test_bad_crc_nack_once_until_a_valid_frame(peer):
    good = codec.encode_command("heartbeat", 0x31)
    bad = bytearray(good)
    bad[-2] ^= 0x01                                 # the CRC low byte (the last is the delimiter)
    peer.b.feed(bytes(bad))
    (f,) = peer.frames()
    assert f.is_nack and f.seq == 0x31 and codec.decode_nack(f.payload) == (P.COMMAND_BY_NAME["heartbeat"].code,
                                                                            Nack.BAD_CRC)
    peer.b.feed(bytes(bad))
    assert peer.frames() == []                     # not again before a valid frame
    peer.b.feed(good)
    (f,) = peer.frames()
    assert f.type == P.ack_type(0x11) and f.seq == 0x31
    peer.b.feed(bytes(bad))                        # (an identical retry is now answered from the store)
    (f,) = peer.frames()
    assert f.is_nack and f.payload[1] == Nack.BAD_CRC
    assert peer.ok("status")["crc_errors"] == 3


def test_duplicate_seq_is_replayed_not_executed(peer):
    b = peer.b
    kp = TABLE["rule1_kp"].id
    frame = codec.encode_command("param_set", 0x77, {"id": kp, "value": 555})
    b.feed(frame)
    first = b.take_tx()
    n = b.stat("param_changed")
    b.feed(frame)
    assert b.take_tx() == first and b.stat("param_changed") == n       # same bytes, not executed again
    # a different SEQ with the same content is a new command
    b.feed(codec.encode_command("param_set", 0x78, {"id": kp, "value": 555}))
    b.take_tx()
    assert b.stat("param_changed") == n + 1
    # start: app_command called once for the duplicate
    frame = codec.encode_command("start", 0x79)
    b.feed(frame)
    r1 = b.take_tx()
    c = b.stat("commands")
    b.feed(frame)
    assert b.take_tx() == r1 and b.stat("commands") == c
    # a NACK is replayed too, and a read command with a long reply is answered afresh (identically)
    frame = codec.encode_command("param_set", 0x7A, {"id": kp, "value": 10**6})
    b.feed(frame)
    r1 = b.take_tx()
    b.feed(frame)
    assert b.take_tx() == r1
    frame = codec.encode_command("param_info", 0x7B, {"index": 3})
    b.feed(frame)
    r1 = b.take_tx()
    b.feed(frame)
    assert b.take_tx() == r1


def test_eeprom_round_trip_matches_python_image(peer):
    b = peer.b
    values = {"rule1_kp": 1234, "rule2_ki": -65000, "link_timeout": 250, "controller": 0, "premise_high": 2500}
    for name, v in values.items():
        peer.ok("param_set", {"id": TABLE[name].id, "value": v})
    peer.ok("set_speed", {"value": 900})                       # not persisted
    peer.ok("eeprom_save")
    img = codec.eeprom_image(TABLE, values)
    assert bytes(b.eeprom[:len(img)]) == img
    assert all(x == 0xFF for x in b.eeprom[len(img):])
    assert codec.parse_eeprom_image(TABLE, bytes(b.eeprom)) == (P.EepromResult.OK, {
        **{e.name: e.default_raw for e in TABLE.persisted}, **values})
    # change, load back
    peer.ok("param_set", {"id": TABLE["rule1_kp"].id, "value": 1})
    peer.ok("eeprom_load")
    assert b.param("rule1_kp") == 1234 and b.param("speed_setpoint") == 900
    # and at boot
    assert b.boot() == P.EepromResult.OK
    assert b.param("rule2_ki") == -65000 and b.param("link_timeout") == 250 and b.param("speed_setpoint") == 0


def test_eeprom_python_image_loads_in_c(peer):
    values = {"rule1_kp": -1000, "accel_limit": 65535, "u_min": -5, "rule2_ki": 100000}
    img = codec.eeprom_image(TABLE, values)
    peer.b.eeprom[:len(img)] = img
    assert peer.b.boot() == P.EepromResult.OK
    for k, v in values.items():
        assert peer.b.param(k) == v


def _assert_defaults(b):
    for e in TABLE.params:
        assert b.param(e.name) == e.default_raw, e.name


def test_eeprom_corrupt_or_foreign_image_is_rejected_and_changes_nothing(peer):
    b = peer.b
    assert peer.nack("eeprom_load") == Nack.EEPROM_ERROR          # blank
    assert b.boot() == P.EepromResult.BLANK
    _assert_defaults(b)
    good = codec.eeprom_image(TABLE, {"rule1_kp": 4321})
    for i in range(len(good)):                                     # every single-byte corruption
        img = bytearray(good)
        img[i] ^= 0x10
        b.eeprom[:len(img)] = bytes(img)
        r = b.boot()
        assert r != P.EepromResult.OK, i
        _assert_defaults(b)
        if r == P.EepromResult.CORRUPT:
            assert b.stat("fault") == P.Fault.EEPROM_CRC          # the fake firmware latches it
        assert codec.parse_eeprom_image(TABLE, bytes(img))[0] == r  # Python says the same
    # valid CRC but a value out of range: rejected whole
    bad = codec.eeprom_image(TABLE, {"rule1_kp": 20001})
    b.eeprom[:len(bad)] = bad
    assert b.boot() == P.EepromResult.CORRUPT
    _assert_defaults(b)
    # image of another table
    other = codec.eeprom_image(P.build_table(2))
    b.eeprom[:len(other)] = other
    assert b.boot() == P.EepromResult.OTHER_BUILD
    # a load command with a bad image changes nothing and NACKs
    b.eeprom[:len(good)] = good
    b.eeprom[len(good) - 1] ^= 0xFF
    p = Peer(b)
    p.frames()
    p.ok("param_set", {"id": TABLE["rule1_kp"].id, "value": 77})
    assert p.nack("eeprom_load") == Nack.EEPROM_ERROR
    assert b.param("rule1_kp") == 77


def test_eeprom_refused_while_running(peer):
    peer.ok("start")
    assert peer.nack("eeprom_save") == Nack.WRONG_STATE
    assert peer.nack("eeprom_load") == Nack.WRONG_STATE
    peer.ok("brake")
    assert peer.nack("eeprom_save") == Nack.WRONG_STATE
    peer.ok("stop")
    peer.ok("eeprom_save")


def test_watchdog_only_while_running(peer):
    b = peer.b
    timeout = b.param("link_timeout")
    b.tick(10 * timeout)                                       # idle: never times out
    assert b.stat("link_lost") == 0 and peer.frames() == []
    peer.ok("brake")
    b.tick(10 * timeout)                                       # braking: not armed either
    assert b.stat("link_lost") == 0
    peer.ok("start")
    for _ in range(5):                                         # heartbeats keep it alive
        b.tick(timeout - 1)
        peer.ok("heartbeat")
    b.tick(timeout - 1)
    assert b.stat("link_lost") == 0 and b.stat("state") == P.State.RUN
    b.tick(2)
    assert b.stat("link_lost") == 1 and b.stat("state") == P.State.FAULT
    assert peer.frames() == [codec.Frame(P.MSG_EVENT, 1, bytes((P.Event.WATCHDOG, P.Fault.LINK_LOST)))]
    b.tick(10 * timeout)
    assert b.stat("link_lost") == 1                           # once
    st = peer.ok("status")
    assert st["fault"] == P.Fault.LINK_LOST
    # shorter timeout takes effect
    peer.ok("fault_clear")
    peer.ok("param_set", {"id": TABLE["link_timeout"].id, "value": 20})
    peer.ok("start")
    b.tick(21)
    assert b.stat("link_lost") == 2


def test_host_commands_feed_the_watchdog_but_garbage_does_not(peer):
    b = peer.b
    peer.ok("param_set", {"id": TABLE["link_timeout"].id, "value": 50})
    peer.ok("start")
    for _ in range(4):
        b.tick(40)
        peer.nack("param_get", {"ids": [0x1F]})               # a NACKed command is still a host command
    for _ in range(4):
        b.tick(10)
        b.feed(bytes([0xA5, 3, 1, 2, 3, 4, 5, 6, 7, 0]) + bytes(range(30)))   # garbage
    b.tick(20)
    assert b.stat("link_lost") == 1


def test_board_frames_echoed_back_do_not_feed_the_watchdog(peer):
    """A loop-back fault (TX wired to RX, an echoing adapter): every frame the board sends comes
    back with a valid CRC.  Only host commands feed the watchdog, so it still trips."""
    b = peer.b
    timeout = b.param("link_timeout")
    peer.ok("telem_config", {"mask": 0xF, "decimation": 1, "samples_per_frame": 1})
    peer.ok("start")
    echoed = 0
    for _ in range(2 * timeout):
        b.tick(1)
        b.sample(1)
        b.lib.link_poll()
        out = b.take_tx()
        echoed += len(codec.StreamDecoder().feed(out))
        b.feed(out)                                           # the loop-back
    assert echoed > timeout                                   # telemetry kept coming back
    assert b.stat("link_lost") == 1 and b.stat("state") == P.State.FAULT


def test_resync_at_the_next_delimiter(peer):
    b = peer.b
    hb = codec.encode_command("heartbeat", 0x55)
    # garbage, then a frame: answered at once
    b.feed(bytes([0xA5, 0x05, 0x11, 0xA5, 0xA5, 0x01, 0x02]) + hb)
    assert [f.seq for f in peer.frames() if f.is_ack] == [0x55]
    # a truncated frame is dropped by the host's delimiter before the next command
    b.feed(codec.encode_command("heartbeat", 0x56)[:-3])
    b.feed(codec.encode_command("heartbeat", 0x57))
    assert [f.seq for f in peer.frames() if f.is_ack] == [0x57]
    # without the leading delimiter the two merge: both are dropped, nothing is executed
    b.feed(codec.encode_frame(0x11, 0x58)[:-2])
    b.feed(codec.encode_frame(0x11, 0x59))
    assert [f for f in peer.frames() if not f.is_nack] == []
    # a pause inside a frame changes nothing: the board has no frame timer
    frame = codec.encode_command("heartbeat", 0x5A)
    b.feed(frame[:4])
    b.tick(1000)
    b.feed(frame[4:])
    assert [f.seq for f in peer.frames() if f.is_ack] == [0x5A]


@pytest.mark.parametrize("seed", range(6))
def test_c_and_python_decoders_accept_the_same_frames(board, seed):
    """Random streams of frames, corrupted frames, garbage and gaps: the C module and
    codec.StreamDecoder accept exactly the same frames in the same order."""
    rng = random.Random(seed)
    board.boot()
    board.take_tx()
    board.clear_log()
    dec = codec.StreamDecoder()
    py = []
    for _ in range(300):
        k = rng.random()
        if k < 0.4:
            n = rng.randrange(P.MAX_PAYLOAD + 1)
            data = codec.encode_frame(P.COMMAND_BY_NAME["heartbeat"].code if rng.random() < 0.5 else rng.randrange(256),
                                      rng.randrange(256), bytes(rng.randrange(256) for _ in range(n)))
        elif k < 0.6:
            data = bytearray(codec.encode_frame(0x11, rng.randrange(256), bytes(rng.randrange(40))))
            data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
            data = bytes(data[:rng.randrange(1, len(data) + 1)])
        elif k < 0.9:
            data = bytes(rng.choice([0x00, 0xA5, rng.randrange(50), rng.randrange(256)])
                         for _ in range(rng.randrange(1, 30)))
        else:
            board.feed(codec.encode_command("stop", 0))          # keep the watchdog out of the picture
            py += dec.feed(codec.encode_command("stop", 0))
            continue
        board.feed(data)
        py += dec.feed(data)
        board.take_tx()
    board.feed(b"\0")
    py += dec.feed(b"\0")
    # the C module logs host commands only (board frame types are ignored)
    py = [f for f in py if not (f.type & P.ACK_BIT or f.type in (P.MSG_NACK, P.MSG_EVENT, P.MSG_TELEMETRY))]
    c = [codec.Frame(t, s, p) for t, s, p, _ in board.log()]
    assert c == py and len(c) > 60


def test_telemetry_counter_generation_drops_and_decimation(peer):
    b = peer.b
    t = TABLE
    mask = t.signal_mask(["speed", "state", "position"])
    r = peer.ok("telem_config", {"mask": mask, "decimation": 2, "samples_per_frame": 3})
    assert r["payload_len"] == 2 + 2 * 3 * 3
    gen = r["generation"]
    b.sample(2 * 3 * 4)
    frames = [f for f in peer.frames() if f.type == P.MSG_TELEMETRY]
    assert [f.seq for f in frames] == [gen] * 4
    counters = [codec.decode_telemetry(f.payload, 3)[0] for f in frames]
    assert counters == [0, 3, 6, 9]
    vals = codec.decode_telemetry(frames[0].payload, 3)[1]
    assert vals.shape == (3, 3) and (vals[:, 1] == P.State.IDLE).all()
    # a blocked UART: one frame waits, later samples are dropped and counted; the counter shows the gap
    b.set_tx_blocked(True)
    b.sample(2 * 3 * 5)
    b.set_tx_blocked(False)
    b.sample(2 * 3)
    frames = [f for f in peer.frames() if f.type == P.MSG_TELEMETRY]
    counters = [codec.decode_telemetry(f.payload, 3)[0] for f in frames]
    # two frames were held (one in the TX frame buffer, one filled); samples 18..26 were dropped
    assert counters == [12, 15, 27]
    assert peer.ok("status")["telem_dropped"] == 27 - 18
    # reconfigure: new generation, counter restarts; decimation 0 = off
    r2 = peer.ok("telem_config", {"mask": 1, "decimation": 1, "samples_per_frame": 1})
    assert r2["generation"] == (gen + 1) & 0xFF
    b.sample(1)
    (f,) = [f for f in peer.frames() if f.type == P.MSG_TELEMETRY]
    assert f.seq == r2["generation"] and codec.decode_telemetry(f.payload, 1)[0] == 0
    peer.ok("telem_config", {"mask": 0, "decimation": 0, "samples_per_frame": 0})
    b.sample(10)
    assert [f for f in peer.frames() if f.type == P.MSG_TELEMETRY] == []


@pytest.mark.parametrize("args", [
    {"mask": 0, "decimation": 1, "samples_per_frame": 1},
    {"mask": 1 << len(P.SIGNALS), "decimation": 1, "samples_per_frame": 1},   # beyond the table
    {"mask": 1, "decimation": 1, "samples_per_frame": 0},
    {"mask": 0x7FF, "decimation": 1, "samples_per_frame": 2},           # 2 + 44 > 40
    {"mask": 0xF, "decimation": 1, "samples_per_frame": 5},             # 2 + 40 > 40
])
def test_telem_config_out_of_range(peer, args):
    assert peer.nack("telem_config", args) == Nack.OUT_OF_RANGE


def _read_capture(peer, nsig):
    start, vals = 0, []
    while True:
        r = peer.ok("capture_read", {"start": start, "count": 255})
        assert r["state"] == P.CaptureState.DONE and r["start"] == start
        got = np.array(r["values"], dtype=np.int16).reshape(-1, nsig)
        if len(got) == 0:
            break
        vals.append(got)
        start += len(got)
    return r["total"], r["trigger_index"], np.concatenate(vals)


def test_capture_immediate_and_chunked_read(peer):
    mask = TABLE.signal_mask(["position", "state"])
    assert peer.nack("capture_read", {"start": 0, "count": 1}) == Nack.WRONG_STATE
    peer.ok("capture_arm", {"mask": mask, "n_samples": 30, "pre_trigger": 0, "decimation": 1,
                            "trigger": P.Trigger.IMMEDIATE, "threshold": 0})
    assert peer.ok("status")["capture_state"] == P.CaptureState.ARMED
    peer.ok("set_speed", {"value": 3000})
    peer.ok("start")
    for _ in range(29):
        peer.b.tick(1)
        peer.b.sample(1)
    assert peer.nack("capture_read", {"start": 0, "count": 1}) == Nack.BUSY
    peer.b.sample(1)
    total, tidx, vals = _read_capture(peer, 2)
    assert total == 30 and tidx == 0 and vals.shape == (30, 2)
    pos = vals[:, 1].astype(np.int64)                              # signals in mask order: state, position
    assert (vals[:, 0] == P.State.RUN).all() and (np.diff(pos) >= 0).all() and pos[-1] > pos[0]
    assert peer.nack("capture_read", {"start": 31, "count": 1}) == Nack.OUT_OF_RANGE


@pytest.mark.parametrize("cap_names", [["speed", "setpoint", "position", "state"], ["position", "state"]])
def test_capture_with_telemetry_records_the_same_values(peer, cap_names):
    """Telemetry and a capture in the same samples: with the same mask the capture copies the
    values the telemetry sample just read (one read per signal), with another mask it reads its
    own; either way each captured sample equals the telemetry sample of the same instant."""
    tel_names = ["speed", "setpoint", "position", "state"]
    tmask, cmask = TABLE.signal_mask(tel_names), TABLE.signal_mask(cap_names)
    peer.ok("set_speed", {"value": 3000})
    peer.ok("start")
    peer.ok("telem_config", {"mask": tmask, "decimation": 1, "samples_per_frame": 1})
    peer.ok("capture_arm", {"mask": cmask, "n_samples": 12, "pre_trigger": 0, "decimation": 1,
                            "trigger": P.Trigger.IMMEDIATE, "threshold": 0})
    tel = []
    for _ in range(12):
        peer.b.tick(1)
        peer.b.sample(1)
        tel += [f for f in peer.frames() if f.type == P.MSG_TELEMETRY]
    rows = np.concatenate([codec.decode_telemetry(f.payload, 4)[1] for f in tel])
    total, tidx, vals = _read_capture(peer, len(cap_names))
    order = [s.name for s in TABLE.signals_in_mask(tmask)]
    cols = [order.index(s.name) for s in TABLE.signals_in_mask(cmask)]
    assert total == 12 and len(rows) == 12 and np.diff(rows[:, order.index("position")]).any()
    assert (vals == rows[:, cols]).all()


def test_capture_setpoint_trigger_with_pre_trigger(peer):
    mask = TABLE.signal_mask(["setpoint"])
    peer.ok("capture_arm", {"mask": mask, "n_samples": 50, "pre_trigger": 10, "decimation": 2,
                            "trigger": P.Trigger.SETPOINT_CHANGE, "threshold": 0})
    peer.ok("start")
    for _ in range(200):                                           # long pre-history, no trigger
        peer.b.tick(1)
        peer.b.sample(1)
    assert peer.ok("status")["capture_state"] == P.CaptureState.ARMED
    peer.ok("set_speed", {"value": 777})
    for _ in range(200):
        peer.b.tick(1)
        peer.b.sample(1)
    total, tidx, vals = _read_capture(peer, 1)
    assert total == 50 and tidx == 10
    assert (vals[:10, 0] == 0).all() and (vals[11:, 0] == 777).all()


def test_capture_speed_threshold_trigger(peer):
    speed = TABLE.signal_mask(["speed"])
    peer.ok("capture_arm", {"mask": speed, "n_samples": 40, "pre_trigger": 20, "decimation": 1,
                            "trigger": P.Trigger.SPEED_RISING, "threshold": 1000})
    peer.ok("set_speed", {"value": 500})
    peer.ok("start")
    for _ in range(100):                       # at 500 rpm: a full pre-trigger history
        peer.b.tick(1)
        peer.b.sample(1)
    peer.ok("set_speed", {"value": 2000})
    for _ in range(300):
        peer.b.tick(1)
        peer.b.sample(1)
    total, tidx, vals = _read_capture(peer, 1)
    assert total == 40 and tidx == 20
    assert vals[tidx - 1, 0] < 1000 <= vals[tidx, 0]
    assert (np.diff(vals[:, 0].astype(int)) >= 0).all()


@pytest.mark.parametrize("args", [
    dict(mask=0, n_samples=10, pre_trigger=0, decimation=1, trigger=0, threshold=0),
    dict(mask=1, n_samples=0, pre_trigger=0, decimation=1, trigger=0, threshold=0),
    dict(mask=1, n_samples=10, pre_trigger=0, decimation=0, trigger=0, threshold=0),
    dict(mask=1, n_samples=10, pre_trigger=10, decimation=1, trigger=1, threshold=0),
    dict(mask=1, n_samples=10, pre_trigger=3, decimation=1, trigger=0, threshold=0),   # immediate + pre
    dict(mask=1, n_samples=10, pre_trigger=0, decimation=1, trigger=4, threshold=0),
    dict(mask=3, n_samples=P.CAPTURE_BYTES_DEFAULT // 4 + 1, pre_trigger=0, decimation=1, trigger=0, threshold=0),
])
def test_capture_arm_out_of_range(peer, args):
    assert peer.nack("capture_arm", args) == Nack.OUT_OF_RANGE


def test_rx_spill_holds_what_arrives_behind_a_waiting_frame(peer):
    """While a complete frame waits for the main loop, the bytes behind it wait in the spill ring
    (LINK_RX_SPILL - 1 bytes) and are framed when the main loop is done with it: every command
    in it is answered.  Bytes that find the ring full are lost and counted; the frame they
    belonged to is dropped whole, the one before it is not, and the next one after a delimiter
    is accepted."""
    def answered(n_polls=12):
        seqs = []
        for _ in range(n_polls):
            seqs += [f.seq for f in peer.frames() if f.is_ack]
        return seqs

    size = len(codec.encode_command("heartbeat", 0))
    k = (P.RX_SPILL_BYTES - 1) // size             # whole frames the ring holds
    assert k >= 1 and (k + 1) * size - (P.RX_SPILL_BYTES - 1) == 1
    frames = [codec.encode_command("heartbeat", 0x31 + j) for j in range(k + 1)]
    for x in b"".join(frames):                   # no poll in between: the first waits, k behind it
        peer.b.lib.link_rx_byte(x)
    assert answered() == [0x31 + j for j in range(k + 1)]
    assert peer.ok("status")["rx_overflows"] == 0
    # one frame more than the ring holds behind a waiting frame: its last byte (the delimiter) is lost
    frames = [codec.encode_command("heartbeat", 0x41 + j) for j in range(k + 2)]
    lost = 1
    for x in b"".join(frames):
        peer.b.lib.link_rx_byte(x)
    assert answered() == [0x41 + j for j in range(k + 1)]    # the last lost its end: dropped
    peer.b.feed(codec.encode_command("heartbeat", 0x51))
    assert answered() == [0x51]
    assert peer.ok("status")["rx_overflows"] == lost
    # garbage longer than any frame is dropped at the next delimiter, without a NACK
    for _ in range(3 * P.MAX_FRAME):
        peer.b.lib.link_rx_byte(0x01)
    assert peer.frames() == []
    assert peer.ok("status")["rx_overflows"] == lost


def test_modelled_uart_small_tx_queue_carries_whole_frames():
    """With an 8-byte UART queue the module still emits whole, valid frames at line rate."""
    b = FakeBoard(TABLE, txq_bytes=8, baud=115200)
    try:
        b.rx(codec.encode_command("telem_config", 1, {"mask": 0xF, "decimation": 1, "samples_per_frame": 4}))
        out = b.advance(1.0)
        frames = codec.StreamDecoder().feed(out)
        tel = [f for f in frames if f.type == P.MSG_TELEMETRY]
        counters = [codec.decode_telemetry(f.payload, 4)[0] for f in tel]
        assert len(tel) > 200 and counters == list(range(counters[0], counters[0] + 4 * len(tel), 4))
        assert len(out) <= 11520 + 1
    finally:
        b.close()


def test_build_without_capture_and_eeprom():
    """The generation options: a module rendered without capture NACKs its commands
    UNKNOWN_COMMAND and reports 0 capture words; without EEPROM it refuses eeprom_save and
    loads nothing.  Everything else works as in the full build."""
    files = render_c(TABLE, build_id=1, profile_hash=2, sample_hz=1000, capture=False, eeprom=False,
                     sfr_bits=bits())
    assert "#define LINK_WITH_CAPTURE       0" in files["link_fw.h"]
    b = FakeBoard(TABLE, files=files, txq_bytes=4096)
    try:
        assert b.boot() == P.EepromResult.BLANK
        p = Peer(b)
        p.frames()
        assert p.ok("hello")["capture_words"] == 0
        assert p.nack("capture_arm", {"mask": 1, "n_samples": 4, "pre_trigger": 0, "decimation": 1, "trigger": 0,
                                      "threshold": 0}) == Nack.UNKNOWN_COMMAND
        assert p.nack("capture_read", {"start": 0, "count": 1}) == Nack.UNKNOWN_COMMAND
        assert p.nack("eeprom_save") == Nack.EEPROM_ERROR
        assert p.nack("eeprom_load") == Nack.EEPROM_ERROR
        p.ok("param_set", {"id": TABLE["rule1_kp"].id, "value": 123})
        assert b.param("rule1_kp") == 123
        assert p.ok("telem_config", {"mask": 3, "decimation": 1, "samples_per_frame": 1})["payload_len"] == 6
    finally:
        b.close()


def test_firmware_generation_options_reach_the_link_module():
    """`picdrive firmware --no-capture --no-eeprom --capture-bytes N`: codegen passes the link's
    generation options to the renderer, the build id tells the builds apart, and a bad buffer
    size is refused with a one-line error."""
    from picdrive.firmware import codegen
    from picdrive.errors import PicdriveError
    from picdrive.paths import repo_root
    from picdrive.profile import load_profile
    prof, design = load_profile("duy2008"), repo_root() / "examples" / "duy2008.fuzzy-hinf.design.json"
    full = codegen.generate(prof, design)
    lean = codegen.generate(prof, design, link_capture=False, link_eeprom=False)
    small = codegen.generate(prof, design, capture_bytes=64)
    assert "#define LINK_WITH_CAPTURE       1" in full.files["link_fw.h"]
    assert "#define LINK_WITH_EEPROM        1" in full.files["link_fw.h"]
    assert "#define LINK_WITH_CAPTURE       0" in lean.files["link_fw.h"]
    assert "#define LINK_WITH_EEPROM        0" in lean.files["link_fw.h"]
    assert "#define LINK_CAPTURE_WORDS      32u" in small.files["link_fw.h"]
    assert len({full.build_id, lean.build_id, small.build_id}) == 3
    assert any("no capture" in line for line in lean.summary)
    with pytest.raises(PicdriveError, match="capture buffer of 300 B"):
        codegen.generate(prof, design, capture_bytes=300)


def test_identification_build_is_a_generation_option():
    """`picdrive firmware --identify`: the identification mode only in that build, which leaves
    the EEPROM persistence out and says so; hello's features tell the builds apart."""
    from picdrive.firmware import codegen
    from picdrive.paths import repo_root
    from picdrive.profile import load_profile
    prof, design = load_profile("duy2008"), repo_root() / "examples" / "duy2008.fuzzy-hinf.design.json"
    drive = codegen.generate(prof, design)
    ident = codegen.generate(prof, design, identify=True)
    assert drive.build_id != ident.build_id
    assert "#define LINK_FEATURES           0u" in drive.files["link_fw.h"]
    assert f"#define LINK_FEATURES           {P.FEATURE_IDENT}u" in ident.files["link_fw.h"]
    assert "#define LINK_WITH_EEPROM        1" in drive.files["link_fw.h"]
    assert "#define LINK_WITH_EEPROM        0" in ident.files["link_fw.h"]
    for sym in ("ident_ovd", "ident_pos", "ident_m", "FW_IDENT_OVD", "LINK_CMD_IDENT:", "LINK_STATE_IDENT"):
        assert not any(sym in drive.files[f] for f in ("drive.c", "drive_params.h", "link_fw.c")), sym
        assert sym in ident.files["drive.c"] + ident.files["drive_params.h"], sym
    assert any("no identification mode" in line for line in drive.summary)
    assert any("identification build" in line and "no EEPROM" in line for line in ident.summary)
