"""The console against the fake board (the rendered C link module + a toy drive, served in
real time behind a local socket), through an unpluggable cable.

Every command is driven through Console.execute (in process) and checked against the board's
own state; the CLI is driven with --run (subprocess) and interactively (pexpect).  The same
console against the motor twin is in test_console_twin.py.
"""
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from picdrive.link import protocol as P
from picdrive.console.commands import ConsoleError
from picdrive.console.session import Console
from picdrive.console.record import read_recording
from picdrive.control_law import Rule, ScheduledLaw
from picdrive.analysis.metrics import step_metrics
from picdrive.analysis.steptest import sector_mean
from picdrive.profile import load_profile
from picdrive.result import DesignResult, save_design

from linksupport.fakeboard import FakeBoard
from test_console_support import Cable

REPO = Path(__file__).resolve().parents[1]
PROFILE = load_profile(REPO / "examples" / "duy2008.toml")
TABLE = P.build_table(2, {n: P.ParamOverride(scale=1 / 1024) for n in
                          ("rule1_kp", "rule1_ki", "rule1_kd", "rule1_kc", "rule2_kp", "rule2_ki", "rule2_kd", "rule2_kc")},
                      profile=PROFILE)


class Board:
    def __init__(self, profile_hash=None):
        self.fb = FakeBoard(TABLE, profile_hash=PROFILE.hash32 if profile_hash is None else profile_hash)
        self.cable = Cable(self.fb.serve())

    def close(self):
        self.cable.close()
        self.fb.close()


@pytest.fixture
def board():
    b = Board()
    yield b
    b.close()


def make_console(url, tmp_path, **kw):
    lines = []
    con = Console(url, out_dir=tmp_path, write=lines.append, reconnect_interval_s=0.05, **kw)
    con.lines = lines
    return con


@pytest.fixture
def con(board, tmp_path):
    c = make_console(board.cable.url, tmp_path)
    c.connect()
    yield c
    c.close()


def run(con, line):
    """Execute and return the lines it printed."""
    n = len(con.lines)
    con.execute(line)
    return [ln for ln in con.lines[n:] if not ln.startswith("board event: ")]   # events arrive asynchronously


def wait_for(pred, timeout=5.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.02)
    return False


# --------------------------------------------------------------------------- handshake

def test_handshake_names_build_protocol_and_profile(board, tmp_path):
    c = make_console(board.cable.url, tmp_path)
    c.connect()
    try:
        text = "\n".join(c.lines)
        major, minor = P.PROTOCOL_VERSION
        assert f"firmware build 0x{c.link.info.build_id:08x}, protocol {major}.{minor}" in text
        assert f"profile hash 0x{PROFILE.hash32:08x}" in text
        assert "profile: duy2008 (bundled profile with this hash)" in text
    finally:
        c.close()
    c = make_console(board.cable.url, tmp_path, profile=PROFILE)
    c.connect()
    try:
        assert any("profile duy2008: matches the board" in ln for ln in c.lines)
    finally:
        c.close()


def test_handshake_warns_on_another_profile(tmp_path):
    b = Board(profile_hash=0x01020304)
    try:
        c = make_console(b.cable.url, tmp_path, profile=PROFILE)
        c.connect()
        try:
            warn = [ln for ln in c.lines if ln.startswith("WARNING")]
            assert len(warn) == 1 and "board hash 0x01020304" in warn[0] and "duy2008" in warn[0]
        finally:
            c.close()
    finally:
        b.close()


# --------------------------------------------------------------------------- parameters

def test_params_get_set_and_a_rejected_value(board, con):
    out = run(con, "params rule1")
    assert len(out) == 4 and out[0].split()[0] == "rule1_kp" and "V/(rad/s)" in out[0] and "rw eeprom" in out[0]
    out = run(con, "set rule1_kp 0.5")
    assert out == ["rule1_kp = 0.5 V/(rad/s)"]
    assert board.fb.param("rule1_kp") == 512                       # 0.5 / (1/1024)
    assert run(con, "get rule1_kp")[0].startswith("rule1_kp = 0.5 V/(rad/s)   [-32 .. 31.999 V/(rad/s)]")
    # out of the firmware's limits: one line naming the range; nothing changes
    with pytest.raises(ConsoleError, match=r"set: rule1_kp = 40 V/\(rad/s\) is outside the board's range \[-32, 31.999"):
        run(con, "set rule1_kp 40")
    assert board.fb.param("rule1_kp") == 512
    with pytest.raises(ConsoleError, match="read-only"):
        run(con, "set speed 5")
    with pytest.raises(ConsoleError, match="no parameter or signal 'kp'"):
        run(con, "get kp")
    with pytest.raises(ConsoleError, match="'abc' is not a number"):
        run(con, "set rule1_kp abc")
    assert run(con, "set controller pid") == ["controller = pid"]
    assert board.fb.param("controller") == 0


def test_drive_commands_reach_the_board(board, con):
    st = lambda: P.State(board.fb.stat("state"))
    assert run(con, "speed 1200") == ["speed setpoint 1200 rpm"]
    assert board.fb.param("speed_setpoint") == 1200
    assert run(con, "start") == ["running, setpoint 1200 rpm"] and st() == P.State.RUN
    assert run(con, "reverse") == ["speed setpoint 1200 -> -1200 rpm"]
    assert board.fb.param("speed_setpoint") == -1200
    assert wait_for(lambda: con.link.get("speed") < -1100)
    out = run(con, "status")
    assert out[0].startswith("state run, fault none, setpoint -1200 rpm, speed -1")
    assert run(con, "brake") == ["braking"] and st() == P.State.BRAKE
    assert run(con, "stop") == ["stopped (outputs off)"] and st() == P.State.IDLE
    assert run(con, "controller pid") == ["controller pid"] and board.fb.param("controller") == 0
    assert run(con, "controller fuzzy") == ["controller fuzzy"] and board.fb.param("controller") == 1
    assert run(con, "controller") == ["controller fuzzy"]
    with pytest.raises(ConsoleError, match="expected pid or fuzzy"):
        run(con, "controller lqr")
    with pytest.raises(ConsoleError, match=r"speed_setpoint = 99999 rpm is outside the board's range \[-2600, 2600\]"):
        run(con, "speed 99999")
    run(con, "speed 0")
    with pytest.raises(ConsoleError, match="setpoint is 0 rpm"):
        run(con, "reverse")


def test_faults_and_clear(board, con):
    assert run(con, "faults") == ["no fault latched (state idle)"]
    board.fb.inject_fault(int(P.Fault.OVERCURRENT))
    assert wait_for(lambda: "board event: fault OVERCURRENT latched, outputs off ('faults', then 'clear')"
                    in con.lines)
    assert run(con, "faults") == ["fault overcurrent latched, state fault: outputs off; 'clear' clears it"]
    with pytest.raises(ConsoleError) as e:
        run(con, "start")
    # the board's refusal in the console's words: 'clear', not the protocol's fault_clear
    assert str(e.value) == "start: the board refused it: fault_active: a fault is latched; 'faults' shows it, 'clear' clears it"
    assert run(con, "clear") == ["fault overcurrent cleared, state idle"]
    assert run(con, "faults") == ["no fault latched (state idle)"]


def test_save_and_restore_eeprom(board, con):
    run(con, "set current_limit 1.25")
    assert run(con, "save")[0].startswith("saved ")
    run(con, "set current_limit 0.5")
    assert run(con, "restore")[0].startswith("restored ")
    assert con.link.get("current_limit") == pytest.approx(1.25, abs=TABLE["current_limit"].scale)
    run(con, "speed 100")
    run(con, "start")
    with pytest.raises(ConsoleError, match="wrong_state: not allowed in the board.s present state"):
        run(con, "save")


def _design(tmp_path, rules=2, hz=1000.0, sha=PROFILE.sha256, kp=0.25, **kw):
    law = ScheduledLaw(rules=tuple(Rule(kp * (j + 1), 1.5, 0.001, 0.0) for j in range(rules)),
                       premise_rad_s=(0.0, 272.27), sample_time_s=1.0 / hz, u_min_v=-40.0, u_max_v=40.0, **kw)
    r = DesignResult(method="mixed-pid", status="verified", profile_name="duy2008", profile_sha256=sha, law=law)
    return save_design(r, tmp_path / f"d{rules}_{hz:g}_{sha[:4]}_{kp}.design.json")


def test_load_pushes_a_designs_gains_or_nothing(board, con, tmp_path):
    out = run(con, f"load {_design(tmp_path)}")
    assert out[-1].startswith("loaded 13 parameters of mixed-pid design")
    assert board.fb.param("rule2_kp") == 512 and board.fb.param("rule1_ki") == round(1.5 * 1024)
    assert board.fb.param("premise_high") == round(272.27 * 60 / (2 * math.pi))
    assert board.fb.param("u_max") == round(40.0 / TABLE["u_max"].scale)
    before = {n: board.fb.param(n) for n in ("rule1_kp", "rule2_kp", "u_max")}
    for bad, msg in [(_design(tmp_path, rules=1), "the design has 1 rule"),
                     (_design(tmp_path, hz=500.0), "sampled at 500 Hz"),
                     (_design(tmp_path, sha="ab" * 32), "made from profile"),
                     (_design(tmp_path, kp=20.0), "nothing written.*rule2_kp = 40")]:
        with pytest.raises(ConsoleError, match=msg):
            run(con, f"load {bad}")
        assert {n: board.fb.param(n) for n in before} == before
    with pytest.raises(ConsoleError, match="cannot read design file"):
        run(con, f"load {tmp_path / 'none.json'}")
    # a law with the back-EMF voltage window also sets the board's current limit (its I_lim)
    d = _design(tmp_path, kp=0.3, current_limit_a=1.25, kb_v_s_per_rad=0.1433, r_ohm=21.2, integrator_limit_v=60.0)
    out = run(con, f"load {d}")
    assert out[-1].startswith("loaded 14 parameters of mixed-pid design")
    assert "integrator limit 60 V, back-EMF constant 0.1433 V s/rad and resistance 21.2 ohm are not parameters" \
        in out[-1]
    assert board.fb.param("current_limit") == round(1.25 / TABLE["current_limit"].scale)


# --------------------------------------------------------------------------- telemetry

def test_telemetry_record_and_view(board, con, tmp_path):
    out = run(con, "telemetry signals speed,setpoint,current")
    assert out[0].startswith("telemetry signals speed, setpoint, current (off")
    assert run(con, "telemetry rate 250") == ["telemetry rate 250 Hz (every 4th sample of 1000 Hz)"]
    with pytest.raises(ConsoleError, match="not a signal of this board"):
        run(con, "telemetry signals speed,rule1_kp")
    with pytest.raises(ConsoleError, match=r"0 < rate <= 1000 Hz"):
        run(con, "telemetry rate 5000")
    run(con, "speed 900")
    run(con, "start")
    csv = tmp_path / "rec.csv"
    out = run(con, f"record {csv}")
    assert out[0].startswith("telemetry on: speed, setpoint, current at 250 Hz")
    with pytest.raises(ConsoleError, match="recording .* is running"):
        run(con, "telemetry rate 100")
    time.sleep(1.0)
    out = run(con, "record stop")
    assert out[0].startswith(f"recording saved to {csv}")
    r = read_recording(csv)
    assert r.columns == ["t_s", "speed", "setpoint", "current"] and r.units == ["s", "rpm", "rpm", "A"]
    assert r.rate_hz == 250 and r.meta["profile"] == f"duy2008 hash 0x{PROFILE.hash32:08x}"
    assert r.meta["firmware"].startswith(f"build 0x{con.link.info.build_id:08x}")
    assert 200 <= r.samples <= 300 and r.dropped == 0
    assert np.allclose(np.diff(r.column("t_s")), 0.004)
    assert np.all(r.column("setpoint") == 900)
    out = run(con, "view 0.6")
    assert out[-1].startswith("view: ") and int(out[-1].split()[1]) > 100
    assert out[0].startswith("t ") and ("speed 899" in out[0] or "speed 900" in out[0]), out[0]
    assert run(con, "telemetry off") == ["telemetry off"] and con.link.telemetry is None


def test_plot_without_display_renders_a_live_png(board, con, tmp_path, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    out = run(con, "plot")
    assert any("no display" in ln for ln in out) and out[-1].startswith("plot open (agg)")
    png = tmp_path / "live.png"
    assert wait_for(png.exists, 10.0)
    with pytest.raises(ConsoleError, match="already open"):
        run(con, "plot")
    assert run(con, "plot off") == ["plot closed"]
    assert png.read_bytes()[:4] == b"\x89PNG"


# --------------------------------------------------------------------------- step

def test_step_metrics_match_the_toy_drive_and_the_saved_data(board, con, tmp_path):
    # the toy drive: speed += (setpoint - speed) / 20 every 1 ms sample, i.e. 1 - 0.95^k
    out = run(con, "step 0 1500 --hold 0.4 --png step.png".replace("step.png", str(tmp_path / "step.png")))
    rec = con.last_step
    m = rec.metrics
    rise = (math.log(0.1) - math.log(0.9)) / math.log(0.95) * 1e-3
    settle = math.log(0.02) / math.log(0.95) * 1e-3
    assert m.rise_time_s == pytest.approx(rise, abs=1e-3)
    assert m.settling_time_s == pytest.approx(settle, abs=2e-3)
    assert m.overshoot_pct == 0.0 and 0 <= m.steady_state_error <= 2.0
    assert rec.sample_period_s == 1e-3 and rec.dropped == 0 and len(rec.t_s) == 600
    assert out[1].startswith("step 0 -> 1500 rpm (telemetry, 600 samples at 1000 Hz): rise 4")
    r = read_recording(tmp_path / "step.csv")
    t, y = r.column("t_s"), r.column("speed")
    assert t[0] == pytest.approx(-0.2) and t[-1] == pytest.approx(0.399)
    # judged on the sector-mean speed of the board's profile, over the samples after the step only
    assert "judged on the sector-mean speed (" in out[1]
    ys = sector_mean(PROFILE, y[t >= 0], 1e-3, 1500.0)
    assert step_metrics(t[t >= 0], ys, 1500.0, y0=float(np.mean(y[t < 0])), t_step=0.0) == m
    assert (tmp_path / "step.png").read_bytes()[:4] == b"\x89PNG"
    assert board.fb.param("speed_setpoint") == 1500 and P.State(board.fb.stat("state")) == P.State.RUN
    for bad, msg in [("step 0", "usage"), ("step 0 9999", "outside the board's range"),
                     ("step 100 100", "no step")]:
        with pytest.raises(ConsoleError, match=msg):
            run(con, bad)


# --------------------------------------------------------------------------- errors, link loss

def test_unknown_command_and_usage_errors(con):
    with pytest.raises(ConsoleError, match="unknown command 'spd' \\(did you mean speed\\?\\); 'help' lists"):
        run(con, "spd 100")
    with pytest.raises(ConsoleError, match="usage: speed <rpm>"):
        run(con, "speed")
    with pytest.raises(ConsoleError, match="cannot parse"):
        run(con, 'set "x')
    assert con.run_line("frobnicate") is False and con.lines[-1].startswith("error: unknown command")
    assert run(con, "help step")[0].startswith("step <from> <to>")


def test_help_fits_80_columns_and_finds_a_parameter_by_a_part_of_its_name(con):
    from picdrive.console.commands import COMMANDS
    out = run(con, "help")
    assert max(map(len, out)) <= 80, max(out, key=len)
    flat = " ".join(" ".join(out).split())
    for c in COMMANDS.values():                      # every explanation whole: wrapped between words
        assert " ".join(c.help.split()) in flat, c.name
        assert any(ln.startswith("  " + c.usage.split()[0]) for ln in out), c.name
    out = run(con, "help kc")
    assert out[0] == "kc: see rule1_kc, rule2_kc"
    assert [ln.split(":")[0] for ln in out if ln.startswith("rule")] == ["rule1_kc", "rule2_kc"]
    assert "Current-feedback gain of rule 1" in out[2]


def test_link_lost_and_regained(board, con):
    run(con, "telemetry on")
    board.cable.unplug()
    assert wait_for(lambda: any(ln.startswith("link lost: ") for ln in con.lines), 5.0), \
        "the console notices the lost link while idle"
    with pytest.raises(ConsoleError, match="not connected: link lost"):
        run(con, "status")
    assert con.run_line("speed 100") is False               # one line, the console keeps running
    board.cable.plug()
    assert wait_for(lambda: any(ln.startswith("link regained after ") for ln in con.lines), 5.0), \
        "the console reconnects when the port is back"
    assert wait_for(lambda: any(ln.startswith("telemetry restored") for ln in con.lines), 2.0)
    assert run(con, "status")[0].startswith("state idle")
    assert con.link.telemetry is not None


def test_complete(con):
    assert con.complete("", "") == sorted(c + " " for c in __import__("picdrive.console.commands", fromlist=["x"]).COMMANDS)
    assert con.complete("st", "st") == ["start ", "status ", "step ", "stop "]
    assert con.complete("get rule1_k", "rule1_k") == ["rule1_kc", "rule1_kd", "rule1_ki", "rule1_kp"]
    assert "speed" not in con.complete("set sp", "sp") and con.complete("set sp", "sp") == ["speed_setpoint"]
    assert con.complete("set controller ", "") == ["fuzzy", "pid"]
    assert con.complete("controller ", "") == ["fuzzy", "pid"]
    assert con.complete("telemetry ", "") == ["off", "on", "rate", "signals"]
    assert con.complete("telemetry signals speed,cu", "cu") == ["current"]
    assert con.complete("help ste", "ste") == ["step"]


# --------------------------------------------------------------------------- CLI

def _cli(*args, timeout=60, cwd=None):
    env = dict(os.environ, MPLBACKEND="Agg")
    return subprocess.run([sys.executable, "-m", "picdrive", "console", *args], capture_output=True, text=True,
                          timeout=timeout, env=env, cwd=cwd)


def test_run_script_stops_at_the_first_error(board, tmp_path):
    s = tmp_path / "session.txt"
    s.write_text("# bench procedure\nspeed 500\nstart\nwait 0.3\nstatus\nset rule1_kp 99\nspeed 700\n")
    r = _cli(board.cable.url, "--run", str(s), "--out", str(tmp_path))
    assert r.returncode == 2
    assert f"picdrive: error: {s}:6: 'set rule1_kp 99': set: rule1_kp = 99" in r.stderr
    assert "picdrive> status\nstate run, fault none, setpoint 500 rpm" in r.stdout
    assert "picdrive> speed 700" not in r.stdout
    assert "motor stopped (leaving the console)" in r.stdout
    assert board.fb.param("speed_setpoint") == 500
    s.write_text("speed 300\nquit\nspeed 400\n")
    r = _cli(board.cable.url, "--run", str(s))
    assert r.returncode == 0 and board.fb.param("speed_setpoint") == 300, r.stderr
    r = _cli("socket://127.0.0.1:1", "--run", str(s))
    assert r.returncode == 2 and r.stderr.startswith("picdrive: error: cannot connect to socket://127.0.0.1:1")


def test_interactive_completion_history_and_errors(board, tmp_path):
    import pexpect                     # a dev dependency (pyproject): missing is a failure
    hist = tmp_path / "hist"
    env = dict(os.environ, MPLBACKEND="Agg", TERM="dumb")
    ch = pexpect.spawn(sys.executable, ["-m", "picdrive", "console", board.cable.url, "--history", str(hist)],
                       env=env, encoding="utf-8", timeout=15, dimensions=(40, 200))
    try:
        ch.expect("picdrive> ")
        ch.send("spe\t")                              # Tab completes the command
        ch.expect("speed ")
        ch.send("1000\r")
        ch.expect("speed setpoint 1000 rpm")
        ch.expect("picdrive> ")
        ch.send("set rule1_kp 77\r")                  # rejected value: one line, the prompt comes back
        ch.expect(r"error: set: rule1_kp = 77 V/\(rad/s\) is outside the board's range")
        ch.expect("picdrive> ")
        ch.send("blah\r")
        ch.expect("error: unknown command 'blah'")
        ch.expect("picdrive> ")
        board.cable.unplug()
        ch.expect("link lost: ", timeout=10)
        board.cable.plug()
        ch.expect("link regained after ", timeout=10)
        ch.send("get speed_setpoint\r")
        ch.expect("speed_setpoint = 1000 rpm")
        ch.expect("picdrive> ")
        ch.send("quit\r")
        ch.expect(pexpect.EOF)
    finally:
        ch.close(force=True)
    assert ch.exitstatus == 0
    assert hist.read_text().split("\n")[:5] == ["speed 1000", "set rule1_kp 77", "blah", "get speed_setpoint", "quit"]


def test_board_reboot_restores_telemetry(board, con):
    run(con, "telemetry on")
    board.fb.boot()                                   # power cycle: the board forgets the telemetry setup
    assert wait_for(lambda: any(ln.startswith("board event: boot") for ln in con.lines), 5.0)
    assert wait_for(lambda: any(ln.startswith("telemetry restored") for ln in con.lines), 5.0)
    n = con.link.telemetry_stats.samples
    assert wait_for(lambda: con.link.telemetry_stats.samples > n + 50, 3.0)
    assert not any(ln.startswith("link lost") for ln in con.lines)


def test_plot_with_a_display_but_no_window_backend_falls_back_to_png(board, con, tmp_path, monkeypatch):
    monkeypatch.setenv("DISPLAY", ":99")              # a display is announced ...
    monkeypatch.setenv("MPLBACKEND", "Agg")           # ... but matplotlib can only render files
    out = run(con, "plot")
    assert out[-2].startswith("no plot window (cannot open a plot: matplotlib backend 'agg' cannot open a window")
    assert out[-1].startswith("plot open (agg)") and out[-1].endswith(str(tmp_path / "live.png"))
    assert run(con, "plot off") == ["plot closed"]


def test_params_load_uses_a_hand_edited_value_and_says_so(con, tmp_path):
    import json
    f = tmp_path / "p.json"
    run(con, f"params save {f}")
    d = json.loads(f.read_text())
    was = d["params"]["rule1_kp"]["value"]
    d["params"]["rule1_kp"]["value"] = round(2 * was + 0.05, 3)           # edited by hand; raw left as it was
    f.write_text(json.dumps(d))
    out = run(con, f"params diff {f}")
    assert any(ln.startswith(f"  rule1_kp: the file's value {d['params']['rule1_kp']['value']:g} ") and
               "the value was edited, so it is used" in ln for ln in out), out
    assert out[-1].startswith("1 difference between the board and"), out
    out = run(con, f"params load {f}")
    assert "(1 changed)" in out[-1], out
    assert run(con, "get rule1_kp")[0].startswith(f"rule1_kp = {con.link.get('rule1_kp'):.6g}")
    assert abs(con.link.get("rule1_kp") - (2 * was + 0.05)) <= con.link.param("rule1_kp").scale
    d["params"]["rule1_kp"]["value"] = 1e9                                # beyond the board: nothing written
    f.write_text(json.dumps(d))
    before = con.link.get_raw("rule1_kp")
    with pytest.raises(ConsoleError, match="rule1_kp = 1e\\+09 .* outside the board's range"):
        run(con, f"params load {f}")
    assert con.link.get_raw("rule1_kp") == before


def test_console_without_a_url_lists_the_serial_ports(monkeypatch, capsys):
    from serial.tools import list_ports, list_ports_common
    from picdrive import cli
    usb = list_ports_common.ListPortInfo("/dev/ttyUSB0", skip_link_detection=True)
    usb.description, usb.manufacturer, usb.hwid = "FT232R USB UART", "FTDI", "USB VID:PID=0403:6001"
    acm = list_ports_common.ListPortInfo("/dev/ttyACM0", skip_link_detection=True)
    monkeypatch.setattr(list_ports, "comports", lambda: [usb, acm])
    assert cli.main(["console"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out == ["no URL given; serial ports found:",
                   "  /dev/ttyACM0",
                   "  /dev/ttyUSB0  (FT232R USB UART, FTDI, USB VID:PID=0403:6001)",
                   "connect with: picdrive console /dev/ttyACM0   (or socket://127.0.0.1:PORT of a running "
                   "'picdrive twin')"]
    monkeypatch.setattr(list_ports, "comports", lambda: [])
    assert cli.main(["console"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("no URL given, and no serial port found (is the USB-serial adapter plugged in") and \
        "connect with: picdrive console /dev/ttyUSB0" in out
