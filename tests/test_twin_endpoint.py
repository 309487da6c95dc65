"""`picdrive twin` and the twin's serial endpoint: a socket and a pty that
pyserial programs open like a COM port, real-time pacing, EEPROM image
kept across runs, clear errors for bad arguments."""
import json
import signal
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import pytest
import serial

from picdrive.link import codec
from picdrive.link import protocol as P
from picdrive.link.client import Link
from picdrive.profile import ProfileWarning

warnings.simplefilter("ignore", ProfileWarning)

ROOT = Path(__file__).resolve().parents[1]
FW = ROOT / "firmware_build" / "duy2008"

def picdrive(*args, **kw):
    return subprocess.Popen([sys.executable, "-m", "picdrive", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=ROOT, **kw)


def read_frame(port, timeout=2.0):
    dec = codec.StreamDecoder()
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        data = port.read(256)
        if data:
            for f in dec.feed(data):
                return f
        else:
            time.sleep(0.005)
    raise AssertionError("no frame from the twin")


def test_cli_serves_socket_and_pty_and_keeps_the_eeprom(tmp_path):
    ee = tmp_path / "board.eeprom"
    p = picdrive("twin", "--profile", "duy2008", "--firmware", str(FW), "--pty", "--eeprom", str(ee))
    try:
        url = p.stdout.readline().strip()
        pty = p.stdout.readline().strip()
        assert url.startswith("socket://127.0.0.1:") and pty.startswith("/dev/")
        build_id = json.loads((FW / "board.json").read_text())["build_id"]
        lk = Link.open(url)
        assert lk.info.build_id == build_id
        old = lk.get_raw("stall_timeout")["stall_timeout"]
        lk.set_raw("stall_timeout", old + 7)
        lk.save_eeprom()
        lk.close()
        # any pyserial program: a raw hello frame over the pty
        with serial.serial_for_url(pty, baudrate=115200, timeout=0) as port:
            port.write(codec.encode_command("hello", 0x33))
            f = read_frame(port)
        assert f.seq == 0x33 and codec.decode_reply("hello", f.payload)["build_id"] == build_id
    finally:
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=20)
    assert p.returncode == 0, err
    assert "client connected" in err
    image = ee.read_bytes()
    assert len(image) == 256 and image != b"\xff" * 256
    # a second run starts from the saved image: the parameter came back; SIGTERM also saves
    p = picdrive("twin", "--profile", "duy2008", "--firmware", str(FW), "--eeprom", str(ee))
    try:
        url = p.stdout.readline().strip()
        lk = Link.open(url)
        assert lk.get_raw("stall_timeout")["stall_timeout"] == old + 7
        lk.set_raw("stall_timeout", old + 9)
        lk.save_eeprom()
        lk.close()
    finally:
        p.send_signal(signal.SIGTERM)
        p.communicate(timeout=20)
    assert p.returncode == 0
    assert ee.read_bytes() != image


@pytest.mark.parametrize("args, message", [
    (["--perturb", "resistnce=1.1"], "unknown perturbation 'resistnce'"),
    (["--perturb", "resistance=0"], r"\[0.1, 10\]"),
    (["--speed", "0"], "--speed"),
])
def test_cli_rejects_bad_arguments_with_a_clear_message(args, message):
    import re
    p = picdrive("twin", "--profile", "duy2008", "--firmware", str(FW), *args)
    out, err = p.communicate(timeout=60)
    assert p.returncode == 2
    assert re.search(message, err) and err.startswith("picdrive: error:")
    assert out == ""


def test_cli_names_a_missing_firmware_folder(tmp_path):
    p = picdrive("twin", "--profile", "duy2008", "--firmware", str(tmp_path / "nope"))
    out, err = p.communicate(timeout=60)
    assert p.returncode == 2 and "does not exist" in err and "picdrive firmware" in err


def test_real_time_pacing_and_speed_factor():
    from picdrive_hil.twin import Twin
    tw = Twin("duy2008", FW)
    for speed in (1.0, 3.0):
        srv = tw.serve(port=0, realtime=True)
        srv.speed = speed
        t_sim0, t0 = tw.t, time.perf_counter()
        time.sleep(0.6)
        ds, dw = tw.t - t_sim0, time.perf_counter() - t0
        srv.stop()
        assert ds == pytest.approx(speed * dw, rel=0.15), (speed, ds, dw)
    tw.close()


def test_a_client_that_disconnects_leaves_the_board_running_and_a_new_one_connects():
    from picdrive_hil.twin import Twin
    tw = Twin("duy2008", FW)
    with tw.serve(port=0) as srv:
        lk = Link.open(srv.url)
        lk.close()
        lk = Link.open(srv.url)                         # reconnect to the same endpoint
        assert lk.status().uptime_ms > 0
        lk.close()
        assert srv.error is None and srv.running
    tw.close()


class FakeClock:
    """The endpoint's wall clock, moved by the test (no real sleeps for the stall)."""

    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def test_pacing_resynchronises_after_a_stall_and_says_it_fell_behind():
    from picdrive_hil.endpoint import TwinServer
    from picdrive_hil.twin import Twin
    tw = Twin("duy2008", FW)
    clock, logs = FakeClock(), []
    srv = TwinServer(tw, realtime=True, clock=clock, log=logs.append)     # stepped by hand, no thread
    try:
        dt = 0.002
        for _ in range(50):
            clock.t += dt
            srv._step()
        assert srv.lag_events == 0
        clock.t += 0.5                                   # the process was stopped for 0.5 s
        srv._step()
        assert srv.lag_events == 1 and any("behind the wall clock" in m for m in logs)
        for _ in range(20):                              # settle back into pace
            clock.t += dt
            srv._step()
        s0, c0 = tw.t, clock.t
        for _ in range(150):
            clock.t += dt
            srv._step()
        # in step with the (fake) wall clock again: neither racing ahead nor falling behind
        assert tw.t - s0 == pytest.approx(clock.t - c0, rel=0.03)
        assert srv.lag_events == 1 and srv.status()["lag_events"] == 1
        assert srv.status()["lag_s"] == pytest.approx(0.5, abs=0.01)
    finally:
        srv.stop()
        tw.close()


def _wait_sim(tw, seconds, wall_limit=30.0):
    """Wait until the served twin's simulated clock advanced by ``seconds``."""
    t_end, limit = tw.t + seconds, time.monotonic() + wall_limit
    while tw.t < t_end:
        assert time.monotonic() < limit, "the twin did not advance"
        time.sleep(0.01)


def test_a_departed_clients_queued_command_does_not_run_for_the_next_client():
    import socket
    from picdrive_hil.twin import Twin
    tw = Twin("duy2008", FW)
    try:
        with tw.serve(port=0) as srv:
            s = socket.create_connection((srv.host, srv.port))
            # 0.5 s of line time of filler ahead of set_speed + start: still queued when it leaves
            s.sendall(bytes(6000) + codec.encode_command("set_speed", 1, {"value": 2000})
                      + codec.encode_command("start", 2))
            s.close()
            _wait_sim(tw, 1.0)
            assert abs(tw.state()["speed_rpm"]) < 1.0              # the motor never started
            assert srv.dropped_on_disconnect > 0 and tw.uart_pending() == 0
            lk = Link.open(srv.url)                                 # the next client finds it idle
            assert lk.status().state == P.State.IDLE
            lk.close()
    finally:
        tw.close()


def test_input_beyond_the_twins_queue_is_held_back_not_dropped():
    import socket
    from picdrive_hil.endpoint import TwinServer
    from picdrive_hil.twin import Twin
    tw = Twin("duy2008", FW)
    clock = FakeClock()                                     # frozen: the board receives nothing meanwhile
    srv = TwinServer(tw, realtime=True, clock=clock)
    s = socket.create_connection((srv.host, srv.port))
    try:
        sent = 100_000                                      # > the 64 KiB input queue
        s.setblocking(False)
        data, off = bytes(sent), 0
        for _ in range(2000):
            if off < len(data):
                try:
                    off += s.send(data[off:])
                except BlockingIOError:
                    pass
            srv._step()
        assert off == sent
        st = srv.status()
        assert st["input_waiting"] > 0                       # held back by the endpoint ...
        assert srv.bytes_in == tw.uart_pending() + st["input_waiting"]    # ... and none lost
    finally:
        s.close()
        srv.stop()
        tw.close()


class ChattyBoard:
    """A board that only talks (a telemetry stream of whole frames), for the endpoint's output path."""

    FRAME = codec.encode_frame(0x40, 1, bytes(range(1, 35)))

    def __init__(self):
        self.t = 0.0

    def run_until(self, t):
        self.t = t

    def uart_write(self, data):
        return len(data)

    def uart_read(self):
        return self.FRAME * 20

    def uart_flush_input(self):
        return 0


def _read_all(s, bound_s=10.0):
    """Everything the peer sends until it closes (the bound turns a hang into a failure)."""
    s.settimeout(bound_s)
    out = b""
    while True:
        b = s.recv(65536)
        if not b:
            return out
        out += b


def test_a_client_that_stops_reading_is_told_why_it_was_dropped_after_whole_frames():
    import socket
    from picdrive_hil.endpoint import CLIENT_BACKLOG_BYTES, NOTICE, TwinServer
    srv = TwinServer(ChattyBoard(), realtime=False)
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)     # a small window: the backlog builds fast
    s.connect((srv.host, srv.port))
    try:
        for _ in range(20000):                                     # the client reads nothing meanwhile
            srv._step()
            if srv.clients_dropped_slow:
                break
        assert srv.clients_dropped_slow == 1 and not srv.status()["client_connected"]
        for _ in range(50):
            srv._step()                                            # the hang-up drains and closes
        data = _read_all(s)
    finally:
        s.close()
        srv.stop()
    k = data.find(NOTICE)
    assert k > 0, data[-200:]
    n = len(ChattyBoard.FRAME)
    assert k % n == 0 and data[:k] == ChattyBoard.FRAME * (k // n)  # every frame before it is whole
    line = data[k + 1:].decode()
    assert line.startswith("picdrive twin: disconnected: this client read nothing while ") and line.endswith("\n")
    assert int(line.split("while ")[1].split()[0]) > CLIENT_BACKLOG_BYTES and "reconnect" in line


def test_a_second_client_is_refused_with_a_message_and_the_first_keeps_the_board():
    import socket
    from picdrive_hil.twin import Twin
    tw = Twin("duy2008", FW)
    try:
        with tw.serve(port=0) as srv:
            with Link.open(srv.url) as first:
                with socket.create_connection((srv.host, srv.port)) as second:
                    second.sendall(codec.encode_command("start", 1))
                    said = _read_all(second)
                assert b"picdrive twin: busy: another client is connected" in said
                with pytest.raises(Exception, match="the other end said: picdrive twin: busy"):
                    Link.open(srv.url)
                assert first.status().state == P.State.IDLE           # the refused 'start' never ran
            assert srv.status()["clients_refused"] == 2
            with Link.open(srv.url) as third:                          # the board is free again
                assert third.status().uptime_ms > 0
            # a client closing as the next opens: the next one waits for it instead of being refused
            first = Link.open(srv.url)
            threading.Timer(0.1, first.close).start()
            with Link.open(srv.url) as fourth:
                assert fourth.status().uptime_ms > 0
            assert srv.status()["clients_refused"] == 2
    finally:
        tw.close()
