"""picdrive.link against the fake board (the rendered C module + fake_app.c) served on a
local socket in real time, with UART timing."""
import dataclasses
import socket
import threading
import time

import numpy as np
import pytest

from picdrive.link import codec
from picdrive.link import protocol as P
from picdrive.firmware.p18f4431 import bits
from picdrive.link.protocol_c import render_c
from picdrive.link.client import BadCrcError, HandshakeMismatch, Link, LinkError, LinkTimeout, NackError, ParamError
from picdrive.link.protocol import Nack

from linksupport import build
from linksupport.fakeboard import FakeBoard
from linksupport.proxy import FrameProxy

TABLE = P.build_table(2, {"rule1_kp": P.ParamOverride(scale=1 / 1024, min_raw=0, max_raw=20000, default_raw=300),
                          "position": P.ParamOverride(ctype="uint16")})
FAST = 1_000_000     # baud for tests that are not about timing


@pytest.fixture
def board():
    b = FakeBoard(TABLE, baud=FAST)
    yield b
    b.close()


@pytest.fixture
def link(board):
    url = board.serve()
    with Link.open(url, baudrate=FAST) as lk:
        yield lk


def test_open_handshake_reads_the_table(board, link):
    assert link.info.table_hash == TABLE.hash and link.info.build_id == build.DEFAULT_BUILD_ID
    assert link.info.profile_hash == build.DEFAULT_PROFILE_HASH and link.info.sample_hz == 1000
    assert link.table.hash == TABLE.hash
    e = link.param("rule1_kp")
    assert (e.unit, e.scale, e.min_raw, e.max_raw) == ("V/(rad/s)", 1 / 1024, 0, 20000)
    assert link.param("controller").values == ("pid", "fuzzy")        # host docs attached
    assert [x.name for x in link.params()] == [x.name for x in TABLE]


def test_get_set_in_engineering_units_with_local_and_board_checks(board, link):
    assert link.get("rule1_kp") == pytest.approx(300 / 1024)
    assert link.set("rule1_kp", 1.5) == 1.5 and board.param("rule1_kp") == 1536
    assert link.set("rule1_kp", 0.1) == pytest.approx(round(0.1 * 1024) / 1024)      # board resolution
    n = board.stat("param_changed")
    with pytest.raises(ParamError, match=r"rule1_kp = 20 V/\(rad/s\) is outside the board's range \[0, 19.53"):
        link.set("rule1_kp", 20.0)
    assert board.stat("param_changed") == n                                          # nothing sent
    with pytest.raises(NackError) as ei:                                             # the board checks too
        link.set_raw("rule1_kp", 20001, check=False)
    assert ei.value.code == Nack.OUT_OF_RANGE and ei.value.command == "param_set"
    assert "OUT_OF_RANGE" in str(ei.value) and "rule1_kp=20001" in str(ei.value)
    assert board.param("rule1_kp") == round(0.1 * 1024)
    with pytest.raises(ParamError, match="read-only"):
        link.set("speed", 1.0)
    with pytest.raises(NackError, match="READ_ONLY"):
        link.set_raw("speed", 1, check=False)
    with pytest.raises(ParamError, match="no parameter or signal 'kp'"):
        link.get("kp")
    with pytest.raises(ParamError, match="finite number"):
        link.set("rule1_kp", float("nan"))
    many = link.get_many(*[e.name for e in TABLE])                   # > PARAM_GET_MAX ids: split
    assert len(many) == len(TABLE) and many["link_timeout"] == 500.0 and many["state"] == 0


def test_controller_speed_and_drive_commands(board, link):
    assert link.select_controller("pid") == "pid" and link.get("controller") == 0
    assert link.select_controller(1) == "fuzzy"
    with pytest.raises(ParamError, match="expected one of pid, fuzzy"):
        link.select_controller("lqr")
    assert link.set_speed(-1200.4) == -1200.0
    with pytest.raises(ParamError, match="speed_setpoint"):
        link.set_speed(40000)
    link.start()
    assert link.status().state == P.State.RUN
    link.brake()
    assert link.status().state == P.State.BRAKE
    link.stop()
    st = link.status()
    assert st.state == P.State.IDLE and st.fault == P.Fault.NONE and st.uptime_ms > 0


def test_faults_events_and_fault_active(board, link):
    link.events()
    board.inject_fault(P.Fault.STALL)
    deadline = time.monotonic() + 2
    ev = []
    while not ev and time.monotonic() < deadline:
        ev = link.events()
        time.sleep(0.01)
    assert [(e, c) for _, e, c in ev] == [(P.Event.FAULT, P.Fault.STALL)]
    with pytest.raises(NackError) as ei:
        link.start()
    assert ei.value.code == Nack.FAULT_ACTIVE and "fault_clear" in str(ei.value)
    assert link.status().fault == P.Fault.STALL
    link.fault_clear()
    link.start()
    assert link.status().state == P.State.RUN


def test_telemetry_numpy_time_column_and_no_drops(board, link):
    cfg = link.configure_telemetry(["speed", "setpoint", "state", "position"])
    assert cfg.samples_per_frame == 4 and cfg.rate_hz == 1000
    link.set_speed(1000)
    link.start()
    d = link.read_samples(400)
    assert d.dtype.names == ("index", "t", "speed", "setpoint", "state", "position")
    assert d["state"].dtype.kind == "i" and d["speed"].dtype == np.float64
    assert (np.diff(d["index"]) == 1).all() and np.allclose(np.diff(d["t"]), 1e-3)
    assert link.telemetry_stats.dropped == 0
    d2 = link.read_samples(seconds=0.3)
    assert d2["index"][0] == d["index"][-1] + 1                   # continuous across calls
    assert abs(d2["speed"][-1] - 1000) < 20 and (d2["setpoint"] == 1000).all()
    pos = d2["position"]
    assert (pos >= 0).all() and (pos <= 65535).all()               # uint16 signal
    it = link.samples(timeout=1.0)
    recs = [next(it) for _ in range(5)]
    assert recs[1]["index"] == recs[0]["index"] + 1
    link.stop_telemetry()
    with pytest.raises(LinkError, match="not configured"):
        link.read_samples(1)


def test_telemetry_drops_are_counted_from_the_counter(board, link):
    link.configure_telemetry(["speed"], samples_per_frame=1)
    link.read_samples(50)
    board.set_tx_blocked(True)                                     # the board's UART stalls
    time.sleep(0.2)
    board.set_tx_blocked(False)
    d = link.read_samples(seconds=0.2)
    st = link.telemetry_stats
    assert st.dropped > 100
    assert np.diff(d["index"]).max() > 100                         # the gap is in the index column
    assert link.status().telem_dropped == st.dropped


def test_capture_with_pre_trigger_on_setpoint_change(board, link):
    link.set_speed(200)
    link.start()
    time.sleep(0.1)
    link.capture_arm(["setpoint", "speed"], 30, pre_trigger=5, trigger="setpoint_change", decimation=2)
    time.sleep(0.05)
    link.set_speed(800)
    r = link.capture_read(timeout=2)
    d = r.data
    assert len(d) == 30 and r.trigger_index == 5
    assert np.allclose(d["t"][5], 0.0) and np.allclose(np.diff(d["t"]), 2e-3)
    assert (d["setpoint"][:5] == 200).all() and (d["setpoint"][6:] == 800).all()
    with pytest.raises(ParamError, match="capture buffer holds 64"):
        link.capture_arm(["speed", "setpoint"], 40)
    with pytest.raises(ParamError, match="needs threshold"):
        link.capture_arm(["speed"], 10, trigger="speed_rising")


def test_eeprom_save_load_and_corrupt_image(board, link):
    link.set("rule1_kp", 2.0)
    link.set("link_timeout", 300)
    link.save_eeprom()
    link.set("rule1_kp", 1.0)
    link.load_eeprom()
    assert link.get("rule1_kp") == 2.0 and link.get("link_timeout") == 300
    board.eeprom[10] ^= 0xFF
    link.set("rule1_kp", 1.0)
    with pytest.raises(NackError) as ei:
        link.load_eeprom()
    assert ei.value.code == Nack.EEPROM_ERROR
    assert link.get("rule1_kp") == 1.0
    link.start()
    with pytest.raises(NackError, match="WRONG_STATE"):
        link.save_eeprom()


def test_keepalive_feeds_the_watchdog_and_its_absence_trips_it():
    b = FakeBoard(TABLE, baud=115200)
    try:
        url = b.serve()
        with Link.open(url) as lk:                     # keep-alive on, timed from the board's 500 ms
            assert lk.alive
            lk.start()
            lk.set("link_timeout", 60)                 # shortened while running: the heartbeat re-times
            time.sleep(0.5)                            # > 8 x link_timeout, nothing sent by the test
            assert lk.status().state == P.State.RUN and b.stat("link_lost") == 0
        time.sleep(0.2)                                # the host went away while running: tripped
        assert b.stat("link_lost") == 1 and b.stat("state") == P.State.FAULT
        with Link.open(url, keepalive=False) as lk:
            lk.events()
            lk.fault_clear()
            lk.start()
            t0 = time.monotonic()
            while b.stat("link_lost") == 1 and time.monotonic() - t0 < 2:
                time.sleep(0.005)
            assert b.stat("link_lost") == 2
            assert 0.055 < time.monotonic() - t0 < 0.5
            time.sleep(0.05)
            assert (P.Event.WATCHDOG, P.Fault.LINK_LOST) in [(e, c) for _, e, c in lk.events()]
            st = lk.status()
            assert st.state == P.State.FAULT and st.fault == P.Fault.LINK_LOST
    finally:
        b.close()


def test_lost_reply_is_retried_with_the_same_seq_and_not_executed_twice(board):
    url = board.serve()
    dropped = []

    def drop_first_param_set_ack(f):
        if f.type == P.ack_type(P.COMMAND_BY_NAME["param_set"].code) and not dropped:
            dropped.append(f)
            return b""
        return None

    px = FrameProxy(url, to_host=drop_first_param_set_ack)
    try:
        with Link.open(px.url, baudrate=FAST, timeout=0.1, keepalive=False) as lk:
            n = board.stat("param_changed")
            assert lk.set("rule1_kp", 3.0) == 3.0
            assert dropped and lk.stats["retries"] >= 1
            assert board.stat("param_changed") == n + 1          # executed once
    finally:
        px.close()


def test_corrupted_command_gets_bad_crc_nack_and_is_resent(board):
    url = board.serve()
    hit = []

    def corrupt_first_set(f):
        if f.type == P.COMMAND_BY_NAME["param_set"].code and not hit:
            hit.append(f)
            b = bytearray(f.encode())
            b[-3] ^= 0x40
            return bytes(b)
        return None

    px = FrameProxy(url, to_board=corrupt_first_set)
    try:
        with Link.open(px.url, baudrate=FAST, timeout=1.0, keepalive=False) as lk:
            t0 = time.monotonic()
            assert lk.set("rule1_kp", 4.0) == 4.0
            assert time.monotonic() - t0 < 0.9                  # resent on the NACK, not after the 1 s timeout
            assert hit and lk.stats["bad_crc_nacks"] == 1 and lk.stats["retries"] >= 1
            assert lk.status().crc_errors == 1
    finally:
        px.close()


def test_timeout_after_bounded_retries_and_unopenable_url():
    srv = socket.create_server(("127.0.0.1", 0))        # accepts, never answers
    port = srv.getsockname()[1]
    try:
        t0 = time.monotonic()
        with pytest.raises(LinkTimeout, match="no reply to hello .* after 3 tries of 0.1 s"):
            Link.open(f"socket://127.0.0.1:{port}", timeout=0.1, retries=2)
        assert 0.25 < time.monotonic() - t0 < 2.0
    finally:
        srv.close()
    with pytest.raises(LinkError, match="cannot open 'socket://127.0.0.1:1'"):
        Link.open("socket://127.0.0.1:1")
    with pytest.raises(LinkTimeout):                      # loop:// hears only its own commands
        Link.open("loop://", timeout=0.05, retries=0)
    lk = Link.open("loop://", handshake=False, keepalive=False)
    lk.close()
    lk.close()


def _served(files):
    b = FakeBoard(TABLE, files=files, baud=FAST)
    return b, b.serve()


def test_handshake_expectations():
    b = FakeBoard(TABLE, baud=FAST)
    try:
        url = b.serve()
        with pytest.raises(HandshakeMismatch, match="table hash .* expected 0x00000001") as ei:
            Link.open(url, baudrate=FAST, expect_table_hash=1)
        assert ei.value.differences
        with pytest.raises(HandshakeMismatch, match="profile hash"):
            Link.open(url, baudrate=FAST, expect_profile_hash=build.DEFAULT_PROFILE_HASH + 1)
        with Link.open(url, baudrate=FAST, expect_table_hash=TABLE.hash, expect_build_id=build.DEFAULT_BUILD_ID,
                       expect_profile_hash=build.DEFAULT_PROFILE_HASH) as lk:
            assert lk.info.table_hash == TABLE.hash
    finally:
        b.close()


def test_handshake_mismatch_board_of_another_definition():
    """A board whose table says rule1_kp is in V/A (another definition): the host refuses to
    misread it and names the difference."""
    e = TABLE["rule1_kp"]
    other = P.Table(tuple(dataclasses.replace(x, unit="V/A") if x is e else x for x in TABLE), 2)
    b, url = _served(render_c(other, build_id=1, profile_hash=2, sample_hz=1000, sfr_bits=bits()))
    try:
        with pytest.raises(HandshakeMismatch) as ei:
            Link.open(url, baudrate=FAST)
        assert any("'rule1_kp': unit is 'V/A' on the board, 'V/(rad/s)' on this host" in d
                   for d in ei.value.differences)
    finally:
        b.close()


def test_handshake_mismatch_wrong_announced_hash_and_protocol_version():
    files = build.render(TABLE)
    h = files["link_fw.h"].replace(f"0x{TABLE.hash:08X}UL", f"0x{TABLE.hash ^ 1:08X}UL")
    b, url = _served({**files, "link_fw.h": h})
    try:
        with pytest.raises(HandshakeMismatch, match="param_info hash to"):
            Link.open(url, baudrate=FAST)
    finally:
        b.close()
    major, minor = P.PROTOCOL_VERSION[:2]
    h = files["link_fw.h"].replace(f"#define LINK_PROTO_MAJOR        {major}u", f"#define LINK_PROTO_MAJOR        {major + 1}u")
    b, url = _served({**files, "link_fw.h": h})
    try:
        with pytest.raises(HandshakeMismatch, match=f"the board speaks protocol {major + 1}.{minor}, this host {major}.{minor}"):
            Link.open(url, baudrate=FAST)
    finally:
        b.close()


def test_reboot_revalidates_the_table(board, link):
    link.configure_telemetry(["speed"])
    board.boot()                                          # same build reboots: BOOT event
    time.sleep(0.05)
    link.set("rule1_kp", 1.0)                             # re-validated with hello, then written
    assert link.telemetry is None and link.table.hash == TABLE.hash


def test_thread_safe_concurrent_requests(board, link):
    errors = []

    def worker(k):
        try:
            for i in range(30):
                v = (k * 100 + i) / 1024
                link.set("rule1_kp", v)
                link.get("premise_high")
                link.status()
        except Exception as e:            # pragma: no cover - reported below
            errors.append(e)

    ts = [threading.Thread(target=worker, args=(k,)) for k in range(4)]
    for t in ts:
        t.start()
    for t in ts:
        t.join(30)
    assert not errors and all(not t.is_alive() for t in ts)
    assert link.get("premise_high") == 3000
    assert link.get("rule1_kp") * 1024 == board.param("rule1_kp")


def test_close_is_clean(board):
    url = board.serve()
    lk = Link.open(url, baudrate=FAST)
    threads = [lk._reader, lk._keepalive]
    lk.close()
    assert all(not t.is_alive() for t in threads)
    with pytest.raises(LinkError, match="closed"):
        lk.status()
    with Link.open(url, baudrate=FAST) as lk2:            # the board accepts a new connection
        assert lk2.status().state == P.State.IDLE


def test_protocol_errors_are_link_errors(board):
    url = board.serve()

    def truncate_status_reply(f):
        if f.type == P.ack_type(P.COMMAND_BY_NAME["status"].code):
            return codec.encode_frame(f.type, f.seq, f.payload[:-1])
        return None

    px = FrameProxy(url, to_host=truncate_status_reply)
    try:
        with Link.open(px.url, baudrate=FAST, keepalive=False) as lk:
            with pytest.raises(LinkError, match="set_speed"):           # an argument that does not fit
                lk.request("set_speed", {"value": 10 ** 9})
            with pytest.raises(LinkError, match="reply to status cannot be decoded"):
                lk.status()
            with pytest.raises(P.ProtocolError):                        # still a ProtocolError too
                lk.status()
            assert lk.get("rule1_kp") == pytest.approx(300 / 1024)      # the link carries on
    finally:
        px.close()


def test_bad_crc_nacks_on_every_try_are_reported_as_bad_crc_not_as_no_reply(board):
    url = board.serve()

    def corrupt_every_set(f):
        if f.type == P.COMMAND_BY_NAME["param_set"].code:
            b = bytearray(f.encode())
            b[-3] ^= 0x40
            return bytes(b)
        return None

    px = FrameProxy(url, to_board=corrupt_every_set)
    try:
        with Link.open(px.url, baudrate=FAST, timeout=0.2, retries=2, keepalive=False) as lk:
            n = board.stat("param_changed")
            with pytest.raises(BadCrcError) as ei:
                lk.set("rule1_kp", 4.0)
            msg = str(ei.value)
            # the board NACKs one corrupted frame per valid frame it gets: the first try, then silence
            assert msg.startswith("the board received param_set(rule1_kp=4096) corrupted: BAD_CRC NACK on 1 of 3")
            assert "was not executed" in msg and "cable" in msg
            assert isinstance(ei.value, NackError) and ei.value.code == Nack.BAD_CRC
            assert board.stat("param_changed") == n
    finally:
        px.close()


def test_a_reply_after_link_timeout_is_reported_and_the_timeout_says_it_may_have_run(board):
    url = board.serve()
    held = []

    def hold_param_set_acks(f):
        if f.type == P.ack_type(P.COMMAND_BY_NAME["param_set"].code):
            held.append(f)
            return b""
        return None

    px = FrameProxy(url, to_host=hold_param_set_acks)
    try:
        with Link.open(px.url, baudrate=FAST, timeout=0.1, retries=1, keepalive=False) as lk:
            n = board.stat("param_changed")
            with pytest.raises(LinkTimeout, match="may nevertheless have received and executed it") as ei:
                lk.set("rule1_kp", 3.0)
            assert ei.value.command == "param_set" and board.stat("param_changed") == n + 1   # it ran
            assert held and lk.late_replies() == []
            px.send_to_host(held[0].encode())                   # the reply turns up after all
            t0 = time.monotonic()
            late = []
            while not late and time.monotonic() - t0 < 2.0:
                late = lk.late_replies()
                time.sleep(0.005)
            assert len(late) == 1
            r = late[0]
            assert r.command == "param_set" and r.acked and r.seq == ei.value.seq == held[0].seq
            assert lk.stats["late_replies"] == 1 and lk.stats["stale_replies"] == 0
            assert lk.get("rule1_kp") == 3.0                   # and the link carries on
    finally:
        px.close()


def test_keepalive_feeds_the_watchdog_only_while_the_application_is_alive():
    b = FakeBoard(TABLE, baud=115200)
    try:
        url = b.serve()
        with Link.open(url, app_timeout=0.3) as lk:
            lk.start()
            lk.set("link_timeout", 250)                      # heartbeat every 62 ms: margin on a loaded machine
            for _ in range(10):                               # alive: calls app_alive from its loop
                time.sleep(0.1)
                lk.app_alive()
            lk.configure_telemetry(["speed"])
            lk.read_samples(seconds=0.8)                      # alive: waiting inside a link call
            assert b.stat("link_lost") == 0 and lk.status().state == P.State.RUN
            time.sleep(1.2)                                   # "hung": no call for > app_timeout + link_timeout
            assert b.stat("link_lost") == 1 and b.stat("state") == P.State.FAULT
            assert lk.stats["keepalive_withheld"] == 1
            lk.fault_clear()                                  # back: the keep-alive resumes
            lk.start()
            time.sleep(0.25)
            assert lk.status().state == P.State.RUN and b.stat("link_lost") == 1
        time.sleep(0.5)                                       # closed while running: tripped (the host left)
        with Link.open(url, app_timeout=None) as lk:          # explicit: the process vouches for itself
            lk.fault_clear()
            lk.start()
            n = b.stat("link_lost")
            time.sleep(0.8)
            assert b.stat("link_lost") == n and lk.status().state == P.State.RUN
            lk.stop()
    finally:
        b.close()
