"""The bench console's issue-12 features against the motor twin (duy2008 firmware, real time):

* Ctrl-C in a long command stops the motor and keeps the partial data, at the prompt (pexpect)
  and in a ``--run`` script (SIGINT), the same way;
* a board fault during ``--run`` fails the script unless an ``expect`` claims it; ``expect``
  passes and fails on the board's clock; ``--strict`` refuses another profile's board;
* ``scope`` on the firmware's triggered capture (setpoint trigger, pre-trigger, decimation);
* the board's state and latched fault shown on connect; a second console on a twin held by
  another client told what is going on;
* one rule for the console's files (no folder created, no foreign file replaced).

Waits on the board are on its clock: the console's own ``wait``/``expect`` read the board's
uptime, and the tests poll the twin's state with a generous failure bound only.
"""
import contextlib
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from picdrive.link import protocol as P
from picdrive.console.commands import ConsoleError
from picdrive.console.session import Console
from picdrive.console.files import written_by_picdrive
from picdrive.console.record import read_recording
from picdrive.link.client import Link
from picdrive.profile import load_profile
from picdrive_hil.twin import Twin

REPO = Path(__file__).resolve().parents[1]
FIRMWARE = REPO / "firmware_build" / "duy2008"
PROFILE = load_profile(REPO / "examples" / "duy2008.toml")
RPM = 60.0 / (2.0 * math.pi)

@pytest.fixture(scope="module")
def twin():
    yield from _serve_twin()


def _serve_twin():
    tw = Twin(PROFILE, FIRMWARE)
    srv = tw.serve(port=0, realtime=True)
    # these tests are not about the watchdog: a host starved for half a second (a loaded CI machine)
    # must not trip it under them (in RAM only; test_console_twin covers LINK_LOST)
    with Link.open(srv.url) as lk:
        lk.set("link_timeout", 5000)
    yield tw, srv
    srv.stop()
    tw.close()


def _env():
    env = dict(os.environ, MPLBACKEND="Agg", TERM="dumb")
    env.pop("DISPLAY", None)
    return env


def _spawn_console(url, tmp_path):
    """An interactive console on a terminal (pexpect, a dev dependency: missing is a failure)."""
    import pexpect
    return pexpect.spawn(sys.executable, ["-m", "picdrive", "console", url, "--history", str(tmp_path / "h")],
                         env=_env(), encoding="utf-8", timeout=20, dimensions=(40, 250))


def _quit(ch):
    """Leave the console with 'quit' and see it end."""
    import pexpect
    ch.send("quit\r")
    ch.expect(pexpect.EOF)


def _cli(url, *args, timeout=90, cwd=None):
    return subprocess.run([sys.executable, "-m", "picdrive", "console", url, *args], capture_output=True,
                          text=True, timeout=timeout, env=_env(), cwd=cwd)


def _until(pred, what, bound_s=30.0):
    """Poll the twin's state until ``pred()``; the bound only turns a hang into a failure."""
    end = time.monotonic() + bound_s
    while not pred():
        assert time.monotonic() < end, f"not seen within {bound_s} s: {what}"
        time.sleep(0.01)


def _board_state(url):
    with Link.open(url) as lk:
        st = lk.status()
        return P.State(st.state), st.fault


def _idle(url, tw=None):
    """Outputs off, no fault latched, and (given the twin) the rotor at rest."""
    with Link.open(url) as lk:
        lk.stop()
        if int(lk.status().fault):
            lk.fault_clear()
    if tw is not None:
        _until(lambda: abs(_rpm(tw)) < 5, "the rotor at rest")


def _rpm(tw):
    return tw.state()["speed_rad_s"] * RPM


@contextlib.contextmanager
def _console(url, tmp_path):
    """An in-process console (cheaper than a subprocess for checks of refusals)."""
    lines = []
    con = Console(url, write=lines.append, out_dir=tmp_path)
    con.connect()
    try:
        yield con, lines
    finally:
        con.close()


def _refused(con, line, msg):
    with pytest.raises(ConsoleError) as e:
        con.execute(line)
    assert msg in str(e.value), (line, str(e.value))


# --------------------------------------------------------------------------- Ctrl-C

def _check_partial_step(csv: Path):
    rec = read_recording(csv)
    assert rec.meta["interrupted"] == "Ctrl-C, partial data"
    t, y = rec.column("t_s"), rec.column("speed")
    assert rec.columns[:3] == ["t_s", "speed", "setpoint"] and len(t) > 50
    assert np.max(y) > 1000                          # the samples up to the Ctrl-C are there
    assert written_by_picdrive(csv.with_suffix(".png"))


def test_ctrl_c_at_the_prompt_stops_the_motor_and_keeps_the_step_data(twin, tmp_path):
    tw, srv = twin
    _idle(srv.url)
    png = tmp_path / "cut.png"
    ch = _spawn_console(srv.url, tmp_path)
    try:
        ch.expect("picdrive> ")
        ch.send(f"step 0 2400 --hold 30 --png {png}\r")
        ch.expect("hold 30 s")
        _until(lambda: _rpm(tw) > 1500, "the step running")
        ch.sendintr()
        ch.expect(r"error: step: interrupted \(Ctrl-C\); motor stopped \(outputs off\); partial data kept "
                  r"\(\d+ samples\): plot " + str(png))
        ch.expect("picdrive> ")
        ch.send("status\r")
        ch.expect("state idle, fault none")          # the console stopped it, not the watchdog
        ch.expect("picdrive> ")
        _quit(ch)
    finally:
        ch.close(force=True)
    _check_partial_step(png.with_suffix(".csv"))


def test_ctrl_c_in_a_script_does_the_same(twin, tmp_path):
    tw, srv = twin
    _idle(srv.url)
    png = tmp_path / "cut.png"
    s = tmp_path / "s.txt"
    s.write_text(f"step 0 2400 --hold 30 --png {png}\nspeed 100\n")
    p = subprocess.Popen([sys.executable, "-m", "picdrive", "console", srv.url, "--run", str(s)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
    try:
        _until(lambda: _rpm(tw) > 1500, "the step running")
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=30)
    finally:
        p.kill()
    assert p.returncode == 2, err
    assert "'step 0 2400 --hold 30" in err and "interrupted (Ctrl-C); motor stopped (outputs off); partial data kept" in err
    assert "picdrive> speed 100" not in out
    assert _board_state(srv.url) == (P.State.IDLE, P.Fault.NONE)
    _check_partial_step(png.with_suffix(".csv"))


def _running_with_a_recording(tw, send, csv):
    """Drive the motor at 1500 rpm with a recording running; returns once it turns."""
    send("speed 1500")
    send("start")
    send(f"record {csv}")
    _until(lambda: _rpm(tw) > 1000, "the motor running")


def _stopped_by_the_console(srv, t_signal):
    """The board idle with no fault latched: stopped by the console, not by its watchdog (which
    latches LINK_LOST after link_timeout, 5 s here) or by nothing at all."""
    state = _board_state(srv.url)
    assert state == (P.State.IDLE, P.Fault.NONE), state
    assert time.monotonic() - t_signal < 4.0, "the stop came no sooner than the board's watchdog would"


def _recording_kept(csv):
    rec = read_recording(csv)
    assert len(rec.column("t_s")) > 10 and np.max(rec.column("speed")) > 500


def test_sigterm_stops_the_motor_and_saves_the_recording(twin, tmp_path):
    tw, srv = twin
    _idle(srv.url, tw)
    csv = tmp_path / "rec.csv"
    p = subprocess.Popen([sys.executable, "-m", "picdrive", "console", srv.url, "--history", str(tmp_path / "h")],
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env=_env())

    def send(line):
        p.stdin.write(line + "\n")
        p.stdin.flush()
    try:
        _running_with_a_recording(tw, send, csv)
        time.sleep(0.2)                              # some samples in the recording
        p.send_signal(signal.SIGTERM)
        t_signal = time.monotonic()
        out, err = p.communicate(timeout=30)         # stdin stays open: not a Ctrl-D
    finally:
        p.kill()
    assert p.returncode == 128 + signal.SIGTERM, err
    assert "motor stopped (outputs off; SIGTERM received)" in out, out
    assert "recording saved to " + str(csv) in out and "console ended by SIGTERM" in out
    assert "Traceback" not in err, err
    _stopped_by_the_console(srv, t_signal)
    _recording_kept(csv)


def test_closing_the_terminal_stops_the_motor_and_saves_the_recording(twin, tmp_path):
    tw, srv = twin
    _idle(srv.url, tw)
    csv = tmp_path / "rec.csv"
    ch = _spawn_console(srv.url, tmp_path)
    try:
        ch.expect("picdrive> ")

        def send(line):
            ch.send(line + "\r")
            ch.expect("picdrive> ")
        _running_with_a_recording(tw, send, csv)
        time.sleep(0.2)
        ch.ptyproc.fileobj.close()                   # the terminal closes: the kernel sends SIGHUP
        t_signal = time.monotonic()
        _until(lambda: not ch.ptyproc.isalive(), "the console ending", bound_s=30)
        assert ch.ptyproc.exitstatus == 128 + signal.SIGHUP, (ch.ptyproc.exitstatus, ch.ptyproc.signalstatus)
    finally:
        ch.ptyproc.kill(signal.SIGKILL) if ch.ptyproc.isalive() else None
    _stopped_by_the_console(srv, t_signal)
    _recording_kept(csv)


def _console_running(srv, tw, tmp_path, rpm):
    """An interactive console at its prompt with the motor started at ``rpm`` from rest."""
    _idle(srv.url, tw)
    ch = _spawn_console(srv.url, tmp_path)
    ch.expect("picdrive> ")
    for line in (f"speed {rpm}", "start"):
        ch.send(line + "\r")
        ch.expect("picdrive> ")
    return ch


def test_ctrl_c_at_the_idle_prompt_stops_a_running_motor(twin, tmp_path):
    tw, srv = twin
    ch = _console_running(srv, tw, tmp_path, 1500)
    try:
        _until(lambda: _rpm(tw) > 1000, "the motor running")
        ch.sendintr()
        ch.expect(r"\^C: motor stopped \(outputs off\); 'quit' leaves")
        ch.expect("picdrive> ")
        ch.send("status\r")
        ch.expect("state idle, fault none")
        ch.expect("picdrive> ")
        ch.sendintr()                                # nothing driven: only the hint
        ch.expect(r"\^C \(type 'quit' to leave\)")
        ch.expect("picdrive> ")
        _quit(ch)
    finally:
        ch.close(force=True)


# --------------------------------------------------------------------------- scripts that assert

STALL = """\
set u_max 0
speed 1500
start
wait 0.8
{expect}
status
"""
"""An output limited to 0 V cannot turn the rotor: the board latches STALL after its stall_timeout (0.5 s)."""


def test_a_board_fault_fails_the_script_unless_expected(twin, tmp_path):
    tw, srv = twin
    _idle(srv.url, tw)                      # a stall needs a rotor at rest
    with Link.open(srv.url) as lk:
        u_max = lk.get("u_max")
    s = tmp_path / "s.txt"
    try:
        s.write_text(STALL.format(expect=""))
        r = _cli(srv.url, "--run", str(s))
        assert r.returncode == 2, r.stdout
        assert f"{s}:4: 'wait 0.8': board event fault stall during or after this line; the script fails" in r.stderr
        assert "picdrive> status" not in r.stdout
        # a console connecting now is shown the latched fault
        (tmp_path / "empty.txt").write_text("")
        r = _cli(srv.url, "--run", str(tmp_path / "empty.txt"))
        assert "board state fault: fault stall is latched (outputs off; 'clear' clears it)" in r.stdout
        # the same fault, expected: the script goes on
        s.write_text("clear\n" + STALL.format(expect="expect fault == stall within 0.5")
                     + "clear\nexpect state == idle\n")
        r = _cli(srv.url, "--run", str(s))
        assert r.returncode == 0, r.stdout + r.stderr
        assert "expect fault == stall: ok, fault = stall after " in r.stdout
        assert "expect state == idle: ok" in r.stdout
    finally:
        _idle(srv.url)
        s.write_text(f"set u_max {u_max!r}\n")
        assert _cli(srv.url, "--run", str(s)).returncode == 0


def test_expect_on_the_board_clock(twin, tmp_path):
    tw, srv = twin
    _idle(srv.url)
    s = tmp_path / "s.txt"
    s.write_text("speed 1500\nstart\nexpect speed == 1500 tol 45 within 1.5\nexpect state == run\n"
                 "expect speed > 2000 within 0.2\nstop\n")
    r = _cli(srv.url, "--run", str(s))
    assert r.returncode == 2
    assert "expect speed == 1500 rpm tol 45: ok, speed = " in r.stdout
    assert "expect state == run: ok, state = run" in r.stdout
    # the failure names the check, the board-clock window and the value seen
    line = r.stderr.strip().splitlines()[-1]
    assert line.startswith(f"picdrive: error: {s}:5: 'expect speed > 2000 within 0.2': expect speed > 2000 rpm: "
                           "failed within 0.2 s of the board's clock (")
    seen = float(line.split("speed is ")[1].split(" rpm")[0])
    assert abs(seen - 1500) < 100
    assert _board_state(srv.url)[0] == P.State.IDLE          # leaving the console stopped the motor
    with _console(srv.url, tmp_path) as (con, lines):
        for bad, msg in [("expect speed", "usage: expect"), ("expect speed ~ 3", "operator '~'"),
                         ("expect state == flying", "'flying' is not one of idle|run|brake|fault"),
                         ("expect speed == 1 within -1", "within -1 must not be negative"),
                         ("expect nosuch == 1", "nosuch")]:
            _refused(con, bad, msg)


def test_strict_refuses_a_board_of_another_profile(twin, tmp_path):
    tw, srv = twin
    s = tmp_path / "s.txt"
    s.write_text("info\n")
    r = _cli(srv.url, "--run", str(s), "--profile", "assawinchaichote2016")
    assert r.returncode == 0 and "WARNING: the board was built from another profile" in r.stdout
    r = _cli(srv.url, "--run", str(s), "--profile", "assawinchaichote2016", "--strict")
    assert r.returncode == 2 and "picdrive> info" not in r.stdout
    assert "--strict: the board was built from another profile (board hash 0x" in r.stderr
    r = _cli(srv.url, "--run", str(s), "--strict")
    assert r.returncode == 2 and "--strict compares the board with your profile: give --profile P too" in r.stderr


def test_a_second_console_is_told_the_twin_is_busy(twin, tmp_path):
    tw, srv = twin
    (tmp_path / "empty.txt").write_text("")
    with Link.open(srv.url):
        r = _cli(srv.url, "--run", str(tmp_path / "empty.txt"), timeout=60)
    assert r.returncode == 2
    assert "picdrive twin: busy: another client is connected to this twin" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


# --------------------------------------------------------------------------- scope

def test_scope_a_setpoint_step(twin, tmp_path):
    tw, srv = twin
    _idle(srv.url)
    png, png2 = tmp_path / "sc.png", tmp_path / "sc2.png"
    s = tmp_path / "s.txt"
    s.write_text(f"speed 1000\nstart\nexpect speed == 1000 tol 30 within 1\n"
                 f"scope arm speed,setpoint --trigger setpoint --pre 25% --decimation 2\nwait 0.05\n"
                 f"speed 2400\nscope read --png {png}\n"
                 f"speed 1000\nexpect speed < 1100 within 1\n"
                 f"scope single speed,current --trigger rising --level 2000 --samples 20 --pre 5 --png {png2} "
                 f"--timeout 2\n"
                 "stop\n")
    # the rising edge needs a step up while 'scope single' waits: a second client cannot act, so the
    # script above times out on it (board clock) and says so
    r = _cli(srv.url, "--run", str(s))
    assert "scope armed: speed, setpoint: 32 samples at 500 Hz (64.0 ms), trigger setpoint, 8 before it" in r.stdout
    assert f"plot {png}" in r.stdout
    assert r.returncode == 2 and ("scope: capture not done after 2 s of the board's clock (trigger not seen; "
                                  "trigger rising)") in r.stderr, r.stderr[-400:]
    rec = read_recording(png.with_suffix(".csv"))
    assert rec.columns == ["t_s", "speed", "setpoint"] and rec.units == ["s", "rpm", "rpm"]
    assert rec.rate_hz == 500 and "trigger setpoint" in rec.meta["scope"]
    t, sp, y = rec.column("t_s"), rec.column("setpoint"), rec.column("speed")
    assert len(t) == 32 and np.allclose(np.diff(t), 0.002)
    assert np.all(np.abs(sp[t < 0] - 1000) < 1) and np.all(np.abs(sp[t >= 0] - 2400) < 1)
    assert np.sum(t < 0) == 8
    assert abs(y[0] - 1000) < 60 and y[-1] > 2000            # the rotor follows within the 64 ms
    assert written_by_picdrive(png)
    head = png.with_suffix(".csv").read_text().splitlines()
    assert "t [s],speed [rpm],setpoint [rpm]" in head


# --------------------------------------------------------------------------- files

def test_one_rule_for_the_consoles_files(twin, tmp_path):
    tw, srv = twin
    _idle(srv.url)
    foreign = tmp_path / "mine.csv"
    foreign.write_text("my data\n")
    (tmp_path / "afile").write_text("x")
    with _console(srv.url, tmp_path) as (con, lines):
        # picdrive's one output rule (docs/outputs.md): a parent that is a file is refused by every write ...
        for cmd, what in [(f"step 0 1000 --png {tmp_path}/afile/x.png", "step --png"),
                          (f"plot --png {tmp_path}/afile/x.png", "plot --png"),
                          (f"record {tmp_path}/afile/x.csv", "recording"),
                          (f"scope single --png {tmp_path}/afile/x.png", "scope --png"),
                          (f"params save {tmp_path}/afile/x.json", "params save")]:
            _refused(con, cmd, f"{what} {tmp_path}/afile/x.{cmd.split('.')[-1]}: {tmp_path}/afile is a file, "
                               "not a folder")
        assert (tmp_path / "afile").read_text() == "x"
        _refused(con, f"record {foreign}", "is not a file picdrive wrote")
        # ... and a missing folder is created, as by every other command
        con.execute(f"params save {tmp_path}/new/x.json")
        assert (tmp_path / "new" / "x.json").is_file()
        assert con.plot is None and con.recorder is None
    assert foreign.read_text() == "my data\n"
    assert _board_state(srv.url)[0] == P.State.IDLE            # refused before the motor moved


# --------------------------------------------------------------------------- parameters

def test_parameters_explained_checked_and_kept(twin, tmp_path):
    import json
    tw, srv = twin
    _idle(srv.url)
    with Link.open(srv.url) as lk:
        kc, plow, phigh = lk.get("rule1_kc"), lk.get("premise_low"), lk.get("premise_high")
        acc, kcs = lk.param("accel_limit"), lk.param("rule1_kc").scale
    f = tmp_path / "board.params.json"
    s = tmp_path / "s.txt"
    s.write_text(f"help rule1_kc\nparams save {f}\nsave\nset rule1_kc 10\nhelp rule1_kc\n"
                 f"set accel_limit {acc.scale * 1.5:g}\nparams diff {f}\nparams load {f}\nparams diff {f}\n")
    r = _cli(srv.url, "--run", str(s))
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert "rule1_kc: parameter, rw, kept in EEPROM\n  Current-feedback gain of rule 1: subtracts kc x the measured" in out
    assert f"  unit V/A; limits " in out and f"; 1 count = {kcs:.6g} V/A" in out
    assert f"  now {kc:.6g} V/A; default of this build {kc:.6g} V/A; EEPROM " in out
    # after 'save' and a change: the EEPROM still holds the saved value, RAM the new one
    assert f"  now 10 V/A; default of this build {kc:.6g} V/A; EEPROM {kc:.6g} V/A" in out
    # a 33 % rounding is reported, as 'load' does
    assert f"(warning: rounded 33.33 % from {acc.scale * 1.5:g}: the board holds steps of {acc.scale:.6g} rpm/s)" in out
    assert f"  rule1_kc: board 10 V/A, file {kc:.6g} V/A" in out and "2 differences between the board and" in out
    assert f"loaded 18 parameters from {f} (2 changed)" in out and f"the board's 18 parameters equal {f}" in out
    assert json.loads(f.read_text())["identity"]["profile"] == "duy2008"
    # cross-checks: refused with the reason, nothing written
    with _console(srv.url, tmp_path) as (con, lines):
        for cmd, msg in [("set current_limit 0", "current_limit 0 A allows no torque: the next start latches STALL"),
                         (f"set premise_low {phigh + 100:g}", f"must be below premise_high {phigh:g} rpm"),
                         ("help nosuch", "no command or parameter 'nosuch'")]:
            _refused(con, cmd, msg)
        del lines[:]
        con.execute("help speed")                # a command and a signal: both explained
        assert lines[0].startswith("speed <rpm>") and lines[1] == "speed: signal (telemetry, read-only)"
    # a file of another build is refused unless forced
    d = json.loads(f.read_text())
    d["identity"]["table_hash"] = "0x12345678"
    d["params"]["rule1_kc"]["raw"] += 8
    d["params"]["rule1_kc"]["value"] += 8 * kcs             # value and raw agree: no hand edit
    other = tmp_path / "other.params.json"
    other.write_text(json.dumps(d))
    s.write_text(f"params load {other}\n")
    r = _cli(srv.url, "--run", str(s))
    assert r.returncode == 2 and "was saved from another firmware (table_hash file 0x12345678 board 0x" in r.stderr
    s.write_text(f"params load {other} --force\nget rule1_kc\nparams load {f}\n")
    r = _cli(srv.url, "--run", str(s))
    assert r.returncode == 0 and f"rule1_kc = {kc + 8 * kcs:.6g} V/A" in r.stdout, r.stdout + r.stderr
    with Link.open(srv.url) as lk:
        assert (lk.get("rule1_kc"), lk.get("premise_low"), lk.get("current_limit") > 0) == (kc, plow, True)


def test_view_keeps_a_typed_command_and_ctrl_c_stops_the_motor(twin, tmp_path):
    tw, srv = twin
    _idle(srv.url)
    ch = _spawn_console(srv.url, tmp_path)
    try:
        ch.expect("picdrive> ")
        ch.send("speed 1000\r")
        ch.expect("picdrive> ")
        ch.send("start\r")
        ch.expect("picdrive> ")
        ch.send("view\r")
        ch.expect(r"speed [-\d.]+ rpm \[")                 # the view is drawing
        ch.send("status\r")                              # typed while viewing: ends the view, then runs
        ch.expect(r"view: \d+ samples")
        ch.expect("picdrive> status")
        ch.expect("state run, fault none, setpoint 999.99 rpm")
        ch.expect("picdrive> ")
        ch.send("view\r")
        ch.expect(r"speed [-\d.]+ rpm \[")
        ch.sendintr()
        ch.expect(r"error: view: interrupted \(Ctrl-C\); motor stopped \(outputs off\)")
        ch.expect("picdrive> ")
        _quit(ch)
    finally:
        ch.close(force=True)
    assert _board_state(srv.url) == (P.State.IDLE, P.Fault.NONE)


# --------------------------------------------------------------------------- the documented session

def test_the_documented_bench_session_runs_and_fails_at_its_fault(twin, tmp_path):
    """examples/bench-session.txt, shown in docs/bench-session.md (scripts/bench_session.py)."""
    tw, srv = twin
    _idle(srv.url, tw)
    with Link.open(srv.url) as lk:
        before = lk.get_many("u_max", "rule1_kp")
    session = REPO / "examples" / "bench-session.txt"
    try:
        r = _cli(srv.url, "--strict", "--profile", "duy2008", "--run", str(session), cwd=tmp_path)
        out = r.stdout
        assert "expect speed == 1000 rpm tol 30: ok" in out
        assert "scope armed: speed, setpoint: 32 samples at 500 Hz (64.0 ms), trigger setpoint, 8 before it" in out
        assert "scope: captured 32 samples (" in out
        assert "expect speed == 2400 rpm tol 48: ok" in out
        assert f"1 difference between the board and {tmp_path / 'board.params.json'}" in out
        assert f"the board's 18 parameters equal {tmp_path / 'board.params.json'}" in out
        n = session.read_text().splitlines().index("wait 1") + 1
        assert r.returncode == 2
        assert r.stderr.strip() == (f"picdrive: error: {session}:{n}: 'wait 1': board event fault stall during or "
                                    "after this line; the script fails (if it is intended, follow the line with "
                                    "'expect fault == <name> within <s>')")
        assert written_by_picdrive(tmp_path / "scope_setpoint_step.png")
        rec = read_recording(tmp_path / "scope_setpoint_step.csv")
        sp = rec.column("setpoint")
        assert np.all(np.abs(sp[rec.column("t_s") < 0] - 1000) < 1) and np.all(np.abs(sp[8:] - 2400) < 1)
    finally:
        _idle(srv.url, tw)
        s = tmp_path / "restore.txt"
        s.write_text(f"set u_max {before['u_max']!r}\nset rule1_kp {before['rule1_kp']!r}\n")
        assert _cli(srv.url, "--run", str(s)).returncode == 0


def test_scope_refuses_what_the_firmware_cannot_capture(twin, tmp_path):
    tw, srv = twin
    with _console(srv.url, tmp_path) as (con, lines):
        for cmd, msg in [("scope single --trigger rising", "--trigger rising needs --level <rpm>"),
                         ("scope single --pre 10", "--pre needs a trigger"),
                         ("scope single --trigger current", "--trigger 'current': expected one of immediate, "
                                                            "setpoint, rising, falling (the firmware's triggers)"),
                         ("scope single speed,current,voltage --samples 40",
                          "need 120 words; the board's capture buffer holds 64 words (at most 21 samples of 3"),
                         ("scope single speed,nosuch", "nosuch not a signal of this board"),
                         ("scope read", "nothing armed by this console"),
                         ("scope arm --count 3", "--count applies to 'scope normal'")]:
            _refused(con, cmd, msg)
        # refused before arming, so the board's capture is left as it was
        cap = con.link.status().capture_state
        for cmd, msg in [("scope single --trigger setpoint", "--trigger setpoint with 'scope single' would never "
                          "fire: the prompt waits for the capture, so no setpoint can be typed; give --speed RPM"),
                         ("scope normal --trigger setpoint --count 2", "give --speed RPM"),
                         ("scope arm --speed 100", "--speed applies to 'scope single' and 'scope normal'"),
                         ("scope single speed --decimation 100 --timeout 2",
                          "--timeout 2 s is shorter than the capture itself (6.4 s: 64 samples at 10 Hz)"),
                         ("scope stop now", "scope stop takes no arguments")]:
            _refused(con, cmd, msg)
        assert con.link.status().capture_state == cap
        # 'scope normal': one file pair per capture, none overwritten
        con.execute(f"scope normal speed --count 3 --png {tmp_path / 'n.png'}")
        assert lines[-1] == (f"scope normal: 3 captures; plots {tmp_path / 'n_1.png'} .. {tmp_path / 'n_3.png'}, "
                             "data beside them (.csv)")
        for k in (1, 2, 3):
            assert written_by_picdrive(tmp_path / f"n_{k}.png")
            assert len(read_recording(tmp_path / f"n_{k}.csv").column("speed")) == 64
        assert not (tmp_path / "n.png").exists()
        # a capture longer than the old fixed 5 s wait is waited for (its length + 5 s of the board's clock)
        con.execute(f"scope single speed --samples 11 --decimation 500 --png {tmp_path / 'long.png'}")
        assert len(read_recording(tmp_path / "long.csv").column("speed")) == 11
        con.execute("scope arm speed --trigger setpoint")
        con.execute("scope stop")
        assert lines[-1].startswith("scope stop: no longer waiting for speed: 64 samples")
        _refused(con, "scope read", "nothing armed by this console")


def test_scope_single_fires_its_own_setpoint_step(twin, tmp_path):
    tw, srv = twin
    _idle(srv.url)
    png = tmp_path / "up.png"
    with _console(srv.url, tmp_path) as (con, lines):
        con.execute("speed 800")
        con.execute("start")
        con.execute("expect speed == 800 tol 30 within 1.5")
        con.execute(f"scope single speed,setpoint --trigger setpoint --speed 2000 --pre 25% --decimation 2 "
                    f"--png {png}")
        assert any(ln.startswith("speed setpoint 1999.98") and ln.endswith(" rpm (the scope's step)") for ln in lines)
        con.execute("stop")
    assert not any("fewer before the trigger than asked" in ln for ln in lines)   # it waited for the history
    rec = read_recording(png.with_suffix(".csv"))
    t, sp = rec.column("t_s"), rec.column("setpoint")
    assert np.sum(t < 0) == 8 and np.all(np.abs(sp[t < 0] - 800) < 1) and np.all(np.abs(sp[t >= 0] - 2000) < 1)


def test_ctrl_c_ends_the_scope_alone(twin, tmp_path):
    tw, srv = twin
    ch = _console_running(srv, tw, tmp_path, 1200)
    try:
        ch.send(f"scope normal speed --decimation 4 --png {tmp_path / 'n.png'}\r")
        ch.expect("scope capture 2: ")
        ch.sendintr()
        ch.expect(r"scope ended \(Ctrl-C\) after \d+ captures \(.*n_1.png \.\. .*\); motor state run "
                  r"\('stop' or Ctrl-C at the prompt stops it\)")
        ch.expect("picdrive> ")
        ch.send("status\r")
        ch.expect("state run, fault none")
        ch.expect("picdrive> ")
        ch.sendintr()                                # the second Ctrl-C, at the prompt: the motor stops
        ch.expect(r"\^C: motor stopped \(outputs off\)")
        ch.expect("picdrive> ")
        _quit(ch)
    finally:
        ch.close(force=True)
    assert written_by_picdrive(tmp_path / "n_2.png")


def test_a_fault_at_start_fails_that_line_and_clear_says_the_cause_remains(twin, tmp_path):
    tw, srv = twin
    _idle(srv.url, tw)
    s = tmp_path / "s.txt"
    s.write_text("speed 500\nstart\nstatus\n")
    tw.inject("hall", code=7)                        # the hall connector off: every sensor high
    try:
        r = _cli(srv.url, "--run", str(s))
        assert r.returncode == 2
        assert (f"{s}:2: 'start': start: fault hall_invalid latched at start, outputs off; the hall code is 7 now "
                "(111: every sensor reads high): the hall sensors' supply or ground is missing, or the connector "
                "is off; fix the cause, then 'clear' and 'start'") in r.stderr, r.stderr
        assert "running, setpoint" not in r.stdout and "picdrive> status" not in r.stdout
        with _console(srv.url, tmp_path) as (con, lines):
            con.execute("clear")
            assert lines[-1] == ("fault hall_invalid cleared, state idle; but the hall code is 7 now (111: every "
                                 "sensor reads high): the hall sensors' supply or ground is missing, or the connector "
                                 "is off: 'start' latches it again until that is fixed")
            tw.inject("hall", code=None)
            con.execute("speed 0")
            con.execute("start")
            assert lines[-1] == "running, setpoint 0 rpm"
            con.execute("stop")
    finally:
        tw.inject("hall", code=None)
        _idle(srv.url)
