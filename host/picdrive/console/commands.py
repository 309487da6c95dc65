"""The console's commands: the command table (:func:`command`, :data:`COMMANDS`), every
command as ``fn(con, args)`` on a :class:`picdrive.console.session.Console`, and the helpers the
commands share (parameter names and values, the board's clock, the step and scope procedures).
``help`` in the console lists them; the module docstring of :mod:`picdrive.console.session`
tabulates them."""
from __future__ import annotations

import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from .step import parse_number
from ..errors import PicdriveError

__all__ = ["ConsoleError", "Quit", "Command", "COMMANDS", "ALIASES", "command", "NACK_WORDS",
           "expects_fault", "state_name", "bundled_profile_by_hash", "board_time_s", "run_step"]


class Terminated(KeyboardInterrupt):
    """SIGHUP or SIGTERM arrived: handled like Ctrl-C inside a command (the motor is stopped,
    partial data kept), then the console ends instead of returning to the prompt."""

    def __init__(self, signame: str):
        super().__init__(signame)
        self.signame = signame


class ConsoleError(PicdriveError):
    """A console command failed; the message is the one line the user sees."""


class Quit(Exception):
    """Raised by ``quit``: the session ends."""



# ---------------------------------------------------------------------------
# command table
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Command:
    name: str
    usage: str
    help: str
    func: Callable
    complete: Callable | None = None
    needs_link: bool = True


COMMANDS: dict[str, Command] = {}
ALIASES = {"exit": "quit", "q": "quit", "?": "help", "eeprom-save": "save", "eeprom-load": "restore"}


def command(name: str, usage: str, help: str, complete=None, needs_link: bool = True):
    def deco(fn):
        COMMANDS[name] = Command(name, usage, help, fn, complete, needs_link)
        return fn
    return deco


def _number(s: str, what: str) -> float:
    return parse_number(s, what, ConsoleError)


def _nargs(cmd: str, args: list[str], lo: int, hi: int | None = None) -> None:
    hi = lo if hi is None else hi
    if not lo <= len(args) <= hi:
        raise ConsoleError(f"usage: {COMMANDS[cmd].usage}")


# ---------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------

NACK_WORDS = {"fault_clear": "'clear'", "eeprom_save": "'save'", "eeprom_load": "'restore'",
              "set_speed": "'speed'", "select_controller": "'controller'"}
"""Board command names as the console says them."""


def expects_fault(line: str) -> bool:
    """An 'expect' on the fault or state: it claims the board events before it."""
    w = line.split()
    return len(w) >= 2 and w[0].lower() == "expect" and w[1].lower() in ("fault", "state")


def bundled_profile_by_hash(h: int) -> str | None:
    """Name of the bundled profile whose hash the board reports, if any."""
    import warnings
    from ..profile import bundled_profiles, load_profile
    for name, path in bundled_profiles().items():
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                if load_profile(path).hash32 == h:
                    return name
        except PicdriveError:
            continue
    return None


def _fmt_value(e, v) -> str:
    if e.values and isinstance(v, int) and 0 <= v < len(e.values):
        return e.values[v]
    if isinstance(v, int):
        return str(v)
    return f"{v:.6g}"


def _unit(e) -> str:
    return "" if e.unit in ("1", "enum", "code") else f" {e.unit}"


def _limits(e) -> str:
    if e.values:
        return "|".join(e.values)
    return f"{e.min_value:.6g} .. {e.max_value:.6g}{_unit(e)}"


def _param_names(con, writable_only=False, signals=None) -> list[str]:
    if con.link is None or con.link.table is None:
        return []
    out = []
    for e in con.link.table:
        if signals is True and not e.signal:
            continue
        if signals is False and e.signal:
            continue
        if writable_only and not e.writable:
            continue
        out.append(e.name)
    return out


def _files(ext: str):
    def comp(con, args, text):
        d, _, stem = text.rpartition("/")
        folder = Path(d or ".")
        try:
            items = list(folder.iterdir())
        except OSError:
            return []
        out = []
        for q in items:
            if q.name.startswith(".") and not stem.startswith("."):
                continue
            name = (d + "/" if d else "") + q.name
            if q.is_dir():
                out.append(name + "/")
            elif q.name.endswith(ext):
                out.append(name)
        return out
    return comp


def _every(n: int) -> str:
    if n == 1:
        return "every sample"
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"every {n}{suffix} sample"


def state_name(v) -> str:
    return v.name.lower() if hasattr(v, "name") else str(v)


BOARD_POLL_S = 0.01
"""Host pause between two reads of the board's clock (a pace, not a timing: deadlines are the board's)."""


def board_time_s(con) -> float:
    """The board's clock (its uptime), s: the twin's simulated time, a real board's own time."""
    return con.require_link().status().uptime_ms / 1000.0


def _wait(con, seconds: float) -> None:
    """Let ``seconds`` pass on the board's clock (the host's when no board is connected)."""
    if con.link is None:
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            time.sleep(min(left, 0.05))
        return
    end = board_time_s(con) + seconds
    while board_time_s(con) < end:
        time.sleep(BOARD_POLL_S)


# ---------------------------------------------------------------------------
# commands
# ---------------------------------------------------------------------------

@command("help", "help [command | parameter]", "list the commands, or explain a command or a parameter "
         "(description, unit, limits, default, EEPROM value)", needs_link=False,
         complete=lambda con, args, text: list(COMMANDS) + _param_names(con) if not args else [])
def _help(con: Console, args):
    _nargs("help", args, 0, 1)
    if args:
        name = ALIASES.get(args[0].lower(), args[0].lower())
        c = COMMANDS.get(name)
        if con.link is not None and args[0] in con.link.table:
            if c is not None:                    # 'speed': a command and a signal
                con.say(f"{c.usage}\n  {c.help}")
            _help_param(con, args[0])
            return
        word = args[0].lower()
        related = [e.name for e in con.link.table if word in e.name.lower().split("_")] \
            if c is None and con.link is not None else []
        if related:                              # 'help kc': the parameters of which it is a part
            con.say(f"{args[0]}: see {', '.join(related)}")
            for n in related:
                _help_param(con, n)
            return
        if c is None:
            extra = "" if con.link is not None else " (parameters are explained when connected)"
            raise ConsoleError(f"no command or parameter {args[0]!r}{extra}; 'help' lists the commands, "
                               "'params' the parameters")
        con.say(f"{c.usage}\n  {c.help}")
        return
    for line in help_table(COMMANDS.values()):
        con.say(line)


HELP_USAGE_COLUMN = 26
"""Width of the usage column of ``help``; a longer usage gets a line of its own."""


def help_table(commands, width: int | None = None) -> list[str]:
    """``help``'s list: usage, then the explanation wrapped at whole words to the terminal's width
    (at most 80 columns)."""
    import shutil
    import textwrap
    if width is None:
        width = min(80, shutil.get_terminal_size((80, 24)).columns)
    col = HELP_USAGE_COLUMN
    indent = " " * (col + 4)
    out = []
    for c in commands:
        text = textwrap.wrap(c.help, width=width, initial_indent=indent, subsequent_indent=indent,
                             break_long_words=False, break_on_hyphens=False)
        if len(c.usage) <= col:
            text[0] = f"  {c.usage:<{col}}  " + text[0][len(indent):]
        else:
            text = textwrap.wrap(c.usage, width=width, initial_indent="  ", subsequent_indent="    ",
                                 break_long_words=False, break_on_hyphens=False) + text
        out += text
    return out


def _help_param(con, name: str) -> None:
    """``help <param>``: description, unit, limits, default, value now and in EEPROM."""
    from .params import param_help
    link = con.link
    e = link.param(name)
    kind = "signal (telemetry, read-only)" if e.signal else ("parameter, " + ("rw" if e.writable else "read-only")
                                                             + (", kept in EEPROM" if e.persisted else ""))
    con.say(f"{e.name}: {kind}")
    con.say(f"  {param_help(e.name, e.doc)}")
    unit = "" if e.unit in ("1",) else e.unit
    con.say(f"  unit {unit or '(none)'}; limits {_limits(e)}" + ("" if e.values else f"; 1 count = {e.scale:.6g}"
                                                                 f"{_unit(e)}"))
    now = link.get(name)
    line = f"  now {_fmt_value(e, now)}{_unit(e)}"
    if not e.signal:
        line += f"; default of this build {_fmt_value(e, link._eng(e, e.default_raw))}{_unit(e)}"
    if e.persisted:
        line += f"; EEPROM {_eeprom_value(con, e)}"
    con.say(line)


def _eeprom_value(con, e) -> str:
    """The EEPROM's value of ``e``.  The protocol has no EEPROM read: with the motor stopped the
    image is loaded and the RAM values written back at once (raw, exact); otherwise not shown."""
    from ..link import protocol as P
    from ..link.client import NackError
    link = con.link
    if link.status().state != P.State.IDLE:
        return "not read while the motor is driven (stop it first)"
    names = [x.name for x in link.table.persisted if x.writable]
    ram = link.get_raw(*names)
    try:
        link.load_eeprom()
    except NackError as err:
        if err.code == P.Nack.EEPROM_ERROR:
            return "none (no valid image of this build: 'save' writes one)"
        raise
    try:
        got = link.get(e.name)
    finally:
        for n in names:                    # the RAM values back, exactly
            link.set_raw(n, ram[n])
    return f"{_fmt_value(e, got)}{_unit(e)}"


@command("speed", "speed <rpm>", "set the speed setpoint in rpm (mechanical; negative = reverse)")
def _speed(con, args):
    _nargs("speed", args, 1)
    rpm = _number(args[0], "speed")
    got = con.link.set_speed(rpm)
    con.say(f"speed setpoint {got:g} rpm")


START_CHECK_LOOPS = 5
"""Speed-loop periods the console watches after ``start`` for a fault the first samples latch
(an invalid hall code latches after two), before it reports the motor running."""


def fault_cause(con, fault) -> tuple[str, bool | None]:
    """What the board shows now of a latched fault's cause: (words, whether the cause is still
    present); ``("", None)`` when the board shows nothing of it.  HALL_INVALID: the hall code."""
    from ..link import protocol as P
    link = con.link
    if int(fault) == int(P.Fault.HALL_INVALID) and "hall" in link.table:
        code = int(link.get("hall"))
        if code == 7:
            return ("the hall code is 7 now (111: every sensor reads high): the hall sensors' supply or "
                    "ground is missing, or the connector is off", True)
        if code == 0:
            return ("the hall code is 0 now (000: every sensor reads low): the hall sensors' supply is "
                    "missing or shorted, or the connector is off", True)
        return f"the hall code is {code} now, a valid code", False
    return "", None


@command("start", "start", "close the speed loop (the motor runs at the setpoint)")
def _start(con, args):
    from ..link import protocol as P
    _nargs("start", args, 0)
    link = con.link
    link.start()
    # a fault the first samples latch (hall code invalid, a bus out of range) must fail this line,
    # not the next one: watch a few loop periods on the board's clock before saying "running"
    hz = link.info.sample_hz or 1000.0
    t_end = board_time_s(con) + max(0.005, START_CHECK_LOOPS / hz)
    while True:
        st = link.status()
        if int(st.fault):
            cause, _ = fault_cause(con, st.fault)
            raise ConsoleError(f"start: fault {state_name(st.fault)} latched at start, outputs off"
                               + (f"; {cause}" if cause else "") + "; fix the cause, then 'clear' and 'start'")
        if st.state != P.State.RUN or st.uptime_ms / 1000.0 >= t_end:
            break
        time.sleep(BOARD_POLL_S / 5)
    if st.state != P.State.RUN:
        raise ConsoleError(f"start: the board is {state_name(st.state)} after 'start', not running "
                           "('status' shows why)")
    con.say(f"running, setpoint {link.get('speed_setpoint'):g} rpm")


@command("stop", "stop", "outputs off (the motor coasts down)")
def _stop(con, args):
    _nargs("stop", args, 0)
    con.link.stop()
    con.say("stopped (outputs off)")


@command("brake", "brake", "brake (low-side switches on)")
def _brake(con, args):
    _nargs("brake", args, 0)
    con.link.brake()
    con.say("braking")


@command("reverse", "reverse", "negate the speed setpoint (reverses the direction)")
def _reverse(con, args):
    _nargs("reverse", args, 0)
    sp = con.link.get("speed_setpoint")
    if sp == 0:
        raise ConsoleError("reverse: the setpoint is 0 rpm, nothing to reverse; set one with 'speed <rpm>'")
    got = con.link.set_speed(-sp)
    con.say(f"speed setpoint {sp:g} -> {got:g} rpm")


@command("params", "params [text] | params save|load|diff FILE [--force]",
         "the parameter table: value, unit, limits, access (filtered by text); save/load/diff the persisted "
         "parameters to/from a JSON file with the firmware identity (load refuses another build unless --force)",
         complete=lambda con, args, text: (["save", "load", "diff"] + _param_names(con)) if not args else
         _files(".json")(con, args, text))
def _params(con, args):
    if args and args[0].lower() in ("save", "load", "diff"):
        _params_file(con, args[0].lower(), args[1:])
        return
    _nargs("params", args, 0, 1)
    link = con.link
    ents = [e for e in link.table.params if not args or args[0].lower() in e.name.lower()]
    sigs = [e for e in link.table.signals if not args or args[0].lower() in e.name.lower()]
    if not ents and not sigs:
        raise ConsoleError(f"no parameter or signal matches {args[0]!r}; 'params' lists them all")
    vals = link.get_many(*[e.name for e in ents]) if ents else {}
    rows = [(e.name, _fmt_value(e, vals[e.name]) + _unit(e), _limits(e),
             ("rw" if e.writable else "ro") + (" eeprom" if e.persisted else "")) for e in ents]
    if rows:
        w = [max(len(r[i]) for r in rows) for i in range(3)]
        for r in rows:
            con.say(f"  {r[0]:<{w[0]}}  {r[1]:>{w[1]}}  [{r[2]}]  {r[3]}")
    if sigs:
        con.say("  signals (telemetry, read-only): " + ", ".join(f"{e.name}{' [' + e.unit + ']' if e.unit not in ('1',) else ''}"
                                                             for e in sigs))


def _params_file(con, sub: str, args) -> None:
    import json
    from .files import output_path
    from .params import cross_check, identity_differences, params_document, read_params_file
    from ..fileio import atomic_write_text
    force = "--force" in args
    rest = [a for a in args if a != "--force"]
    if len(rest) != 1 or (force and sub != "load"):
        raise ConsoleError(f"usage: params {sub} FILE.json" + (" [--force]" if sub == "load" else ""))
    link = con.link
    ents = [e for e in link.table.persisted if e.writable]
    if sub == "save":
        path = output_path(rest[0], ".json", "params save")
        raws = link.get_raw(*[e.name for e in ents])
        vals = {e.name: link._eng(e, raws[e.name]) for e in ents}
        info = link.info
        prof = con.profile.name if con.profile is not None else bundled_profile_by_hash(info.profile_hash) or "?"
        doc = params_document(info, prof, ents, vals, raws)
        atomic_write_text(path, json.dumps(doc, indent=1) + "\n")
        con.say(f"saved {len(ents)} parameters of firmware build 0x{info.build_id:08x} to {path}")
        return
    path = Path(rest[0]).expanduser().absolute()
    d = read_params_file(path)
    idiff = identity_differences(d["identity"], link.info)
    board = link.get_raw(*[e.name for e in ents])
    byname = {e.name: e for e in ents}
    fileraw, edited = _file_raws(link, d["params"], byname, path)
    for note in edited:
        con.say(note)
    fileps = d["params"]
    if sub == "diff":
        if idiff:
            con.say("identity differs: " + "; ".join(idiff))
        n = 0
        for e in ents:
            if e.name not in fileps:
                con.say(f"  {e.name}: board {_fmt_value(e, link._eng(e, board[e.name]))}{_unit(e)}, not in the file")
                n += 1
            elif fileraw[e.name] != board[e.name]:
                con.say(f"  {e.name}: board {_fmt_value(e, link._eng(e, board[e.name]))}{_unit(e)}, file "
                        f"{_fmt_value(e, link._eng(e, fileraw[e.name]))}{_unit(e)}")
                n += 1
        extra = [k for k in fileps if k not in {e.name for e in ents}]
        for k in extra:
            con.say(f"  {k}: in the file, not a persisted parameter of this board")
        con.say(f"{n + len(extra)} difference{'s' if n + len(extra) != 1 else ''} between the board and {path}"
                if n + len(extra) else f"the board's {len(ents)} parameters equal {path}")
        return
    # load
    if idiff and not force:
        raise ConsoleError(f"params load: nothing written: {path} was saved from another firmware ("
                           + "; ".join(idiff) + "); gains and scales may not fit this board: 'params diff' "
                           "shows the values, --force loads the parameters this board has")
    todo = fileraw
    skipped = [k for k in fileps if k not in byname]
    bad = [f"{k} raw {r} outside {byname[k].min_raw}..{byname[k].max_raw}" for k, r in todo.items()
           if not byname[k].min_raw <= r <= byname[k].max_raw]
    if bad:
        raise ConsoleError("params load: nothing written: " + "; ".join(bad))
    problems = cross_check(_with_related(con, {k: link._eng(byname[k], r) for k, r in todo.items()
                                               if not byname[k].values}))
    if problems:
        raise ConsoleError("params load: nothing written: " + "; ".join(problems))
    changed = 0
    for k, r in todo.items():
        if board[k] != r:
            link.set_raw(k, r)
            changed += 1
    con.say(f"loaded {len(todo)} parameters from {path} ({changed} changed"
            + (f"; not on this board: {', '.join(skipped)}" if skipped else "") + "); 'save' keeps them in EEPROM")


def _file_raws(link, fileps: dict, byname: dict, path) -> tuple[dict, list[str]]:
    """The raw count of each parameter of a parameter file that this board has, and a note for
    each whose ``value`` no longer matches its ``raw`` count: the value was edited by hand, so
    the value is what is meant (converted at this board's scale, range-checked)."""
    raws, notes = {}, []
    for k, v in fileps.items():
        e = byname.get(k)
        if e is None:
            continue
        raw, val = v["raw"], v.get("value")
        raws[k] = raw
        if val is None:
            continue
        if isinstance(val, bool) or not isinstance(val, (int, float)) or not math.isfinite(val):
            raise ConsoleError(f"{path}: parameter {k!r}: value {val!r} is not a number; write it in "
                               f"{e.unit} or restore the file from 'params save'")
        if e.values or e.unit in ("enum", "code"):
            same = val == raw
        else:
            same = abs(val - raw * e.scale) <= 0.5 * e.scale * (1 + 1e-9)
        if not same:
            raws[k] = link.to_raw(k, val)
            notes.append(f"  {k}: the file's value {val:g}{_unit(e)} is not its raw count {raw} "
                         f"({_fmt_value(e, link._eng(e, raw))}{_unit(e)}): the value was edited, so it is used "
                         f"(raw {raws[k]})")
    return raws, notes


@command("get", "get <name>", "read a parameter or signal, with its unit and limits",
         complete=lambda con, args, text: _param_names(con) if not args else [])
def _get(con, args):
    _nargs("get", args, 1)
    e = con.link.param(args[0])
    v = con.link.get(args[0])
    con.say(f"{e.name} = {_fmt_value(e, v)}{_unit(e)}   [{_limits(e)}]{'' if e.writable else ' read-only'}")


@command("set", "set <name> <value>", "write a parameter in engineering units (the board's limits apply)",
         complete=lambda con, args, text: _param_names(con, writable_only=True, signals=False) if not args else
         (list(con.link.param(args[0]).values) if con.link and len(args) == 1 and args[0] in con.link.table else []))
def _set(con, args):
    from .params import ROUNDING_WARN, cross_check
    _nargs("set", args, 2)
    link = con.link
    e = link.param(args[0])
    value = args[1] if e.values and not args[1].lstrip("-").isdigit() else _number(args[1], args[0])
    link.to_raw(e.name, value)                  # the board's range first (ParamError names it)
    if not e.values:
        problems = cross_check(_with_related(con, {e.name: float(value)}), involving=e.name)
        if problems:
            raise ConsoleError(f"set: nothing written: {'; '.join(problems)}")
    got = link.set(args[0], value)
    note = ""
    if not e.values and value and abs(got - value) / abs(value) > ROUNDING_WARN:
        note = (f"  (warning: rounded {abs(got - value) / abs(value) * 100:.2f} % from {value:g}: the board "
                f"holds steps of {e.scale:.6g}{_unit(e)})")
    if e.name == "link_timeout":
        con.retime_heartbeat()
    con.say(f"{e.name} = {_fmt_value(e, got)}{_unit(e)}{note}")


CROSS_CHECKED = ("current_limit", "premise_low", "premise_high", "u_min", "u_max")


def _with_related(con, values: dict) -> dict:
    """``values`` completed with the board's values of the parameters they are checked against."""
    link = con.link
    if not any(n in CROSS_CHECKED for n in values):
        return dict(values)
    others = [n for n in CROSS_CHECKED if n in link.table and n not in values]
    out = link.get_many(*others) if others else {}
    out.update(values)
    return out


@command("controller", "controller pid|fuzzy", "switch the control law: pid (rule 1) or fuzzy (rules blended)",
         complete=lambda con, args, text: ["pid", "fuzzy"] if not args else [])
def _controller(con, args):
    _nargs("controller", args, 0, 1)
    if not args:
        e = con.link.param("controller")
        con.say(f"controller {_fmt_value(e, con.link.get('controller'))}")
        return
    choice = args[0].lower()
    if choice not in ("pid", "fuzzy"):
        raise ConsoleError(f"controller {args[0]!r}: expected pid or fuzzy")
    got = con.link.select_controller(choice)
    con.say(f"controller {got}")


@command("save", "save", "save the persisted parameters to the board's EEPROM (motor stopped)")
def _save(con, args):
    _nargs("save", args, 0)
    con.link.save_eeprom()
    n = len(con.link.table.persisted)
    con.say(f"saved {n} parameters to EEPROM")


@command("restore", "restore", "load the persisted parameters from the board's EEPROM (motor stopped)")
def _restore(con, args):
    _nargs("restore", args, 0)
    con.link.load_eeprom()
    con.say(f"restored {len(con.link.table.persisted)} parameters from EEPROM")


@command("faults", "faults", "show the latched fault")
def _faults(con, args):
    _nargs("faults", args, 0)
    st = con.link.status()
    if int(st.fault) == 0:
        con.say(f"no fault latched (state {state_name(st.state)})")
    else:
        con.say(f"fault {state_name(st.fault)} latched, state {state_name(st.state)}: outputs off; 'clear' clears it")


@command("clear", "clear", "clear the latched fault (a cause still present latches again)")
def _clear(con, args):
    _nargs("clear", args, 0)
    before = con.link.status()
    con.link.fault_clear()
    after = con.link.status()
    if int(after.fault):
        cause, _ = fault_cause(con, after.fault)
        con.say(f"fault {state_name(after.fault)} latched again: its cause is still present"
                + (f" ({cause})" if cause else ""))
    elif int(before.fault):
        cause, present = fault_cause(con, before.fault)
        if present:
            # the firmware checks the halls only while it drives: cleared now, latched again at 'start'
            con.say(f"fault {state_name(before.fault)} cleared, state {state_name(after.state)}; but {cause}: "
                    "'start' latches it again until that is fixed")
        else:
            con.say(f"fault {state_name(before.fault)} cleared, state {state_name(after.state)}")
    else:
        con.say("no fault was latched")


@command("status", "status", "run state, setpoint, speed, controller, fault, link counters")
def _status(con, args):
    _nargs("status", args, 0)
    link = con.link
    st = link.status()
    names = [n for n in ("speed_setpoint", "controller", "speed", "current", "voltage") if n in link.table]
    v = link.get_many(*names)
    ctl = link.param("controller")
    parts = [f"state {state_name(st.state)}", f"fault {state_name(st.fault)}",
             f"setpoint {v.get('speed_setpoint', float('nan')):g} rpm"]
    if "speed" in v:
        parts.append(f"speed {v['speed']:.1f} rpm")
    if "current" in v:
        parts.append(f"current {v['current']:.3f} A")
    if "voltage" in v:
        parts.append(f"voltage {v['voltage']:.2f} V")
    parts.append(f"controller {_fmt_value(ctl, v['controller'])}")
    con.say(", ".join(parts))
    tm = link.telemetry
    tele = (f"telemetry {','.join(e.name for e in tm.signals)} at {tm.rate_hz:g} Hz, "
            f"{link.telemetry_stats.samples} samples, {link.telemetry_stats.dropped} dropped") if tm else "telemetry off"
    con.say(f"link: uptime {st.uptime_ms / 1000:.1f} s, crc errors {st.crc_errors}, rx overflows {st.rx_overflows}, "
            f"{tele}" + (f", recording to {con.recorder.path} ({con.recorder.samples} samples)" if con.recorder else ""))


@command("info", "info", "the handshake: firmware build, protocol, profile, table")
def _info(con, args):
    _nargs("info", args, 0)
    for line in con.handshake_lines():
        con.say(line)


@command("wait", "wait <seconds>", "pause for seconds of the board's clock (in scripts: let the motor settle)",
         needs_link=False)
def _wait_cmd(con, args):
    _nargs("wait", args, 1)
    s = _number(args[0], "wait")
    if not 0 <= s <= 3600:
        raise ConsoleError(f"wait {s:g} s: expected 0..3600 s")
    _wait(con, s)


EXPECT_OPS = {"==": lambda v, x, tol: abs(v - x) <= tol, "!=": lambda v, x, tol: abs(v - x) > tol,
              "<": lambda v, x, tol: v < x + tol, "<=": lambda v, x, tol: v <= x + tol,
              ">": lambda v, x, tol: v > x - tol, ">=": lambda v, x, tol: v >= x - tol}
EXPECT_USAGE = "expect <signal|parameter|state|fault> <op> <value> [tol <t>] [within <s>]"


def parse_expect(con, args):
    """``expect`` arguments -> (entry, op, value (raw index for an enum), tol, within_s)."""
    if len(args) < 3:
        raise ConsoleError(f"usage: {EXPECT_USAGE}, e.g. 'expect speed == 2400 tol 24 within 0.5' or "
                           "'expect fault == stall within 2'")
    name, op, val = args[0], args[1], args[2]
    e = con.link.param(name)
    if op not in EXPECT_OPS:
        raise ConsoleError(f"expect: operator {op!r}: expected one of {' '.join(EXPECT_OPS)}")
    tol, within = 0.0, 0.0
    rest = args[3:]
    while rest:
        if len(rest) < 2 or rest[0] not in ("tol", "within"):
            raise ConsoleError(f"expect: {' '.join(rest)!r}: expected 'tol <t>' or 'within <s>'; usage: {EXPECT_USAGE}")
        v = _number(rest[1], rest[0])
        if v < 0:
            raise ConsoleError(f"expect: {rest[0]} {v:g} must not be negative")
        if rest[0] == "tol":
            tol = v
        else:
            within = v
        rest = rest[2:]
    if e.values:
        if op not in ("==", "!="):
            raise ConsoleError(f"expect {name}: a named value ({'|'.join(e.values)}) takes == or != only")
        if val.lower() not in e.values:
            raise ConsoleError(f"expect {name}: {val!r} is not one of {'|'.join(e.values)}")
        return e, op, e.values.index(val.lower()), 0.0, within
    return e, op, _number(val, f"expect {name}"), tol, within


@command("expect", EXPECT_USAGE,
         "check a signal, parameter, the state or the latched fault, now or within <s> of the board's clock; "
         "a failed check fails a script; 'expect fault == X' also accepts the board's fault event X in a script",
         complete=lambda con, args, text: (_param_names(con) if not args else
                                           list(EXPECT_OPS) if len(args) == 1 else
                                           list(con.link.param(args[0]).values) if len(args) == 2 and con.link
                                           and args[0] in con.link.table else ["tol", "within"]))
def _expect(con, args):
    e, op, x, tol, within = parse_expect(con, args)
    link = con.link
    check = EXPECT_OPS[op]
    unit = _unit(e)
    want = (f"{e.name} {op} {e.values[x]}" if e.values else
            f"{e.name} {op} {x:g}{unit}" + (f" tol {tol:g}" if tol else ""))
    t0 = board_time_s(con)
    n = 0
    while True:
        v = link.get(e.name)
        n += 1
        now = board_time_s(con)
        if check(float(v), float(x), tol):
            break
        if now - t0 >= within:
            got = _fmt_value(e, v) + unit
            span = f" within {within:g} s of the board's clock ({n} readings)" if within else ""
            raise ConsoleError(f"expect {want}: failed{span}: {e.name} is {got}")
        time.sleep(BOARD_POLL_S)
    if e.name in ("state", "fault") and e.values and e.values[int(v)] not in ("none", "idle", "run", "brake"):
        con.take_unexpected()                 # the fault this line expects is no script failure
    con.say(f"expect {want}: ok, {e.name} = {_fmt_value(e, v)}{unit} after {now - t0:.3f} s (board clock)")


@command("quit", "quit", "leave the console (stops the motor if it runs)", needs_link=False)
def _quit(con, args):
    raise Quit()


@command("load", "load <design.json>", "push a design result's gains (checked against the board first)",
         complete=_files(".json"))
def _load(con, args):
    _nargs("load", args, 1)
    from ..profile import hash32
    from ..result import load_design
    link = con.link
    r = load_design(args[0], require_usable=True, profile=con.profile)
    law = r.law
    rules = link.table.rules
    if law.n_rules != rules:
        raise ConsoleError(f"load: the design has {law.n_rules} rule(s), the firmware {rules}: regenerate the "
                           "firmware from this design (picdrive firmware) or design with the board's rule count")
    hz = link.info.sample_hz
    if hz and abs(1.0 / law.sample_time_s - hz) > 1e-6 * hz:
        raise ConsoleError(f"load: the design is sampled at {1.0 / law.sample_time_s:g} Hz, the board's speed loop "
                           f"runs at {hz} Hz; discrete gains do not carry over: design for {hz} Hz")
    if r.profile_sha256 and hash32(r.profile_sha256) != link.info.profile_hash:
        raise ConsoleError(f"load: the design was made from profile {r.profile_name!r} (hash 0x{hash32(r.profile_sha256):08x}), "
                           f"the board was built from profile hash 0x{link.info.profile_hash:08x}; "
                           "use a design of the board's profile")
    from ..firmware.fixedpoint import law_parameters     # the firmware owns the law -> parameter mapping
    values = {k: v for k, v in law_parameters(law).items() if k in link.table}
    # check everything before writing anything: no half-pushed design
    from ..link.client import ParamError
    asked = dict(values)                  # the design's values (rounding is reported against them)
    problems = []
    for name, v in list(values.items()):
        e = link.param(name)
        try:
            link.to_raw(name, v)
        except ParamError as err:
            # a limit the design puts exactly on the board's limit may round one count beyond it
            edge = e.max_value if v > e.max_value else e.min_value
            if abs(v - edge) <= e.scale:
                values[name] = edge
            else:
                problems.append(str(err))
    if problems:
        raise ConsoleError("load: nothing written, the board cannot hold these values: " + "; ".join(problems))
    from .params import ROUNDING_WARN, cross_check
    problems = cross_check(_with_related(con, values))
    if problems:
        raise ConsoleError("load: nothing written: " + "; ".join(problems))
    width = max(len(n) for n in values)
    worst = 0.0
    for name, v in values.items():
        e = link.param(name)
        got = link.set(name, v)
        rel = abs(got - asked[name]) / abs(asked[name]) if asked[name] else abs(got - v)
        worst = max(worst, rel)
        note = "" if rel <= ROUNDING_WARN else f"  (rounded {rel * 100:.2f} %)"
        con.say(f"  {name:<{width}} {got:>12.6g}{_unit(e)}{note}")
    fixed = []
    if law.derivative_filter_hz:
        fixed.append(f"derivative filter {law.derivative_filter_hz:g} Hz")
    if getattr(law, "integrator_limit_v", None) is not None:
        fixed.append(f"integrator limit {law.integrator_limit_v:g} V")
    if getattr(law, "current_limit_a", None) is not None:
        fixed.append(f"back-EMF constant {law.kb_v_s_per_rad:g} V s/rad and resistance {law.r_ohm:g} ohm")
    extra = (f"; the design's {', '.join(fixed)} are not parameters: the firmware build's own values apply"
             if fixed else "")
    con.say(f"loaded {len(values)} parameters of {r.method} design from {args[0]} "
            f"(largest rounding {worst * 100:.3f} %){extra}; 'save' keeps them in EEPROM")


# -- telemetry, views, recording ----------------------------------------------

DEFAULT_RATE_HZ = 200.0


def _ensure_signals(con):
    if not con.tele_signals:
        from ..link import protocol as P
        con.tele_signals = [n for n in P.DEFAULT_TELEMETRY_SIGNALS if n in con.link.table]
    if not con.tele_rate_hz:
        hz = con.link.info.sample_hz
        con.tele_rate_hz = min(DEFAULT_RATE_HZ, float(hz)) if hz else DEFAULT_RATE_HZ


def _telemetry_on(con, quiet=False):
    _ensure_signals(con)
    cfg = con.apply_telemetry()
    con.tele_on = True
    if not quiet:
        con.say(f"telemetry on: {', '.join(e.name for e in cfg.signals)} at {cfg.rate_hz:g} Hz "
                f"({_every(cfg.decimation)}, {cfg.samples_per_frame} per frame)")
    return cfg


def _bandwidth_note(con, n_signals: int, rate_hz: float) -> str:
    from ..link import protocol as P
    fit = (P.MAX_PAYLOAD - P.TELEMETRY_HEADER_BYTES) // (2 * n_signals)
    spf = min(P.DEFAULT_SAMPLES_PER_FRAME, fit)
    bytes_s = rate_hz / spf * (P.FRAME_OVERHEAD + P.TELEMETRY_HEADER_BYTES + 2 * n_signals * spf)
    baud = con.profile.uart.baud if con.profile is not None else 115200
    cap = baud / 10.0
    if bytes_s > 0.9 * cap:
        return (f"; warning: needs {bytes_s:.0f} B/s of the {cap:.0f} B/s a {baud}-baud link carries: "
                "samples will be dropped (lower the rate or the number of signals)")
    return ""


def _complete_telemetry(con, args, text):
    if not args:
        return ["signals", "rate", "on", "off"]
    if args[0] == "signals":
        done = ",".join(args[1:]).split(",") if len(args) > 1 else []
        return [n for n in _param_names(con, signals=True) if n not in done]
    return []


@command("telemetry", "telemetry [signals a,b,c | rate <Hz> | on | off]",
         "choose the telemetry signals and rate, switch it on/off; alone: show the selection",
         complete=_complete_telemetry)
def _telemetry(con, args):
    link = con.link
    _ensure_signals(con)
    if not args:
        tm = link.telemetry
        state = (f"on: {', '.join(e.name for e in tm.signals)} at {tm.rate_hz:g} Hz, "
                 f"{link.telemetry_stats.samples} samples, {link.telemetry_stats.dropped} dropped") if tm else "off"
        con.say(f"telemetry {state}; selected {', '.join(con.tele_signals)} at {con.tele_rate_hz:g} Hz; "
                f"board samples at {link.info.sample_hz or '?'} Hz")
        con.say("signals: " + ", ".join(f"{e.name} [{e.unit}]" for e in link.table.signals))
        return
    sub, rest = args[0].lower(), args[1:]
    if sub in ("signals", "rate", "on", "off") and con.recorder is not None and sub != "on":
        raise ConsoleError(f"telemetry {sub}: a recording to {con.recorder.path} is running; 'record stop' first")
    if sub == "signals":
        names = [n for a in rest for n in a.split(",") if n]
        if not names:
            raise ConsoleError("usage: telemetry signals NAME[,NAME...], e.g. 'telemetry signals speed,current'")
        sig = {e.name for e in link.table.signals}
        bad = [n for n in names if n not in sig]
        if bad:
            raise ConsoleError(f"telemetry signals: {', '.join(bad)} not a signal of this board; signals: "
                               f"{', '.join(e.name for e in link.table.signals)}")
        if len(set(names)) != len(names):
            raise ConsoleError("telemetry signals: a signal is listed twice")
        from ..link import protocol as P
        if 2 * len(names) + P.TELEMETRY_HEADER_BYTES > P.MAX_PAYLOAD:
            raise ConsoleError(f"telemetry signals: at most {(P.MAX_PAYLOAD - P.TELEMETRY_HEADER_BYTES) // 2} signals fit a frame")
        con.tele_signals = names
        if con.tele_on:
            _telemetry_on(con)
            if con.plot is not None and con.plot.alive:
                con.plot_control("signals", con.signal_units(names))
        else:
            con.say(f"telemetry signals {', '.join(names)} (off; 'telemetry on', 'plot', 'view' or 'record' start it)"
                    + _bandwidth_note(con, len(names), con.tele_rate_hz))
    elif sub == "rate":
        if len(rest) != 1:
            raise ConsoleError("usage: telemetry rate <Hz>, e.g. 'telemetry rate 200'")
        hz = _number(rest[0], "rate")
        top = link.info.sample_hz
        if hz <= 0 or (top and hz > top):
            raise ConsoleError(f"telemetry rate {hz:g} Hz: expected 0 < rate <= {top or '?'} Hz (the speed-loop rate)")
        dec = max(1, int(round(top / hz))) if top else max(1, int(round(hz)))
        con.tele_rate_hz = top / dec if top else hz
        note = f" ({_every(dec)} of {top} Hz)" if top else ""
        if con.tele_on:
            _telemetry_on(con, quiet=True)
        con.say(f"telemetry rate {con.tele_rate_hz:g} Hz{note}"
                + _bandwidth_note(con, len(con.tele_signals), con.tele_rate_hz))
    elif sub == "on":
        if rest:
            raise ConsoleError("usage: telemetry on")
        _telemetry_on(con)
    elif sub == "off":
        if rest:
            raise ConsoleError("usage: telemetry off")
        con.stop_pump()
        link.stop_telemetry()
        con.tele_on = False
        con.close_plot()
        con.say("telemetry off")
    else:
        raise ConsoleError(f"telemetry {args[0]!r}: expected signals, rate, on or off")


PLOT_USAGE = "plot [--png FILE] [--window S] | plot off | pause | resume | window S | ylim UNIT LO HI|auto"


@command("plot", PLOT_USAGE,
         "live plot of the telemetry (a PNG file updated each second without a display): signals of one unit "
         "share an axis; the last --window seconds (default 5); a min/max envelope when samples outnumber "
         "pixels; a new segment (no line back in time) when the telemetry is reconfigured; pause/resume "
         "freeze the drawing; ylim fixes an axis",
         complete=lambda con, args, text: ["off", "pause", "resume", "window", "ylim", "--png", "--window"]
         if not args else [])
def _plot(con, args):
    from .plot import LivePlot, PlotError, display_available
    sub = args[0].lower() if args else ""
    if sub in ("off", "pause", "resume", "window", "ylim"):
        if sub == "off":
            _nargs("plot", args, 1)
            con.say("plot closed" if con.close_plot() else "no plot open")
            return
        if con.plot is None or not con.plot.alive:
            raise ConsoleError(f"plot {sub}: no plot open ('plot' opens one)")
        if sub in ("pause", "resume"):
            _nargs("plot", args, 1)
            con.plot.control("pause", sub == "pause")
            con.say("plot paused (telemetry still recorded; 'plot resume')" if sub == "pause" else "plot resumed")
        elif sub == "window":
            _nargs("plot", args, 2)
            w = _number(args[1], "plot window")
            if not 0.01 <= w <= 600:
                raise ConsoleError(f"plot window {w:g} s: expected 0.01..600 s")
            con.plot.control("window", w)
            con.say(f"plot window {w:g} s")
        else:
            units = sorted({u for _, u in con.plot.signals})
            if len(args) not in (3, 4) or args[1] not in units:
                raise ConsoleError(f"usage: plot ylim UNIT LO HI | plot ylim UNIT auto; units: {', '.join(units)}")
            if len(args) == 3:
                if args[2].lower() != "auto":
                    raise ConsoleError("usage: plot ylim UNIT LO HI | plot ylim UNIT auto")
                con.plot.control("ylim", args[1], None, None)
                con.say(f"plot [{args[1]}] axis automatic")
            else:
                lo, hi = _number(args[2], "ylim"), _number(args[3], "ylim")
                if not lo < hi:
                    raise ConsoleError(f"plot ylim: {lo:g} must be below {hi:g}")
                con.plot.control("ylim", args[1], lo, hi)
                con.say(f"plot [{args[1]}] axis {lo:g} .. {hi:g}")
        return
    png, window = None, 5.0
    it = iter(args)
    for a in it:
        v = next(it, None)
        if a not in ("--png", "--window") or v is None:
            raise ConsoleError(f"usage: {PLOT_USAGE}")
        if a == "--png":
            from .files import output_path
            png = str(output_path(v, ".png", "plot --png"))
        else:
            window = _number(v, "--window")
            if not 0.01 <= window <= 600:
                raise ConsoleError(f"--window {window:g} s: expected 0.01..600 s")
    if con.plot is not None and con.plot.alive:
        raise ConsoleError("a plot is already open ('plot off' closes it)")
    if not con.tele_on:
        _telemetry_on(con)
    sigs = con.signal_units(con.tele_signals)
    plot = None
    if png is None and display_available():
        try:
            plot = LivePlot(sigs, window_s=window)
        except PlotError as e:            # e.g. only non-interactive matplotlib backends installed
            png = str((con.out_dir / "live.png").absolute())
            con.say(f"no plot window ({e}): the live plot goes to {png}, redrawn every second; "
                    "'view' shows a text view")
    elif png is None:
        png = str((con.out_dir / "live.png").absolute())
        con.say(f"no display for a plot window (DISPLAY is not set): the live plot goes to {png}, "
                "redrawn every second; 'view' shows a text view")
    if plot is None:
        plot = LivePlot(sigs, png_path=png, backend="Agg", window_s=window)
    con.set_sink("plot", plot)
    con.say(f"plot open ({plot.backend}): {', '.join(n for n, _ in sigs)}" + (f" -> {png}" if png else ""))


@command("view", "view [seconds]", "compact text view of the telemetry for seconds of the board's clock "
         "(at the prompt: until Enter; a command typed meanwhile ends the view and runs; 2 s in scripts)")
def _view(con, args):
    from .plot import TextView
    _nargs("view", args, 0, 1)
    seconds = _number(args[0], "view") if args else (math.inf if con.interactive else 2.0)
    if not seconds > 0:
        raise ConsoleError("view: seconds must be positive")
    if not con.tele_on:
        _telemetry_on(con)
    tv = TextView(con.signal_units(con.tele_signals))
    con.set_sink("view", tv)
    tty = con.interactive and sys.stdout.isatty()
    typed = con.interactive and sys.stdin.isatty() and os.name == "posix"
    end = board_time_s(con) + seconds
    period = 0.25 if tty else 0.5
    try:
        while board_time_s(con) < end:
            if typed:
                import select
                ready, _, _ = select.select([sys.stdin], [], [], period)
                if ready:                            # a line typed while viewing: it ends the view and runs
                    line = sys.stdin.readline()
                    if line.strip():
                        con.pending_line = line.rstrip("\n")
                    break
            else:
                time.sleep(period)
            line = tv.render()
            if tty:                                  # redraw in place: one terminal row
                import shutil
                width = shutil.get_terminal_size().columns - 1
                sys.stdout.write("\r\x1b[K" + line[:width])
                sys.stdout.flush()
            else:
                con.say(line)
            if con.link is None:
                raise ConsoleError(f"view: link lost ({con.lost_reason})")
    finally:
        con.set_sink("view", None)
        if tty:
            sys.stdout.write("\n")
    con.say(f"view: {tv.count} samples")


@command("record", "record <file.csv> | record stop", "record the telemetry to CSV (header: signals, units, rate, firmware, profile)",
         complete=lambda con, args, text: (["stop"] + _files(".csv")(con, args, text)) if not args else [])
def _record(con, args):
    from .record import Recorder
    _nargs("record", args, 0, 1)
    if not args:
        if con.recorder is None:
            con.say("not recording")
        else:
            con.say(f"recording to {con.recorder.path}: {con.recorder.samples} samples, {con.recorder.dropped} dropped")
        return
    if args[0].lower() == "stop":
        if con.recorder is None:
            raise ConsoleError("record stop: no recording is running")
        rec = con.set_sink("recorder", None)
        p = rec.close()
        con.say(f"recording saved to {p}: {rec.samples} samples, {rec.dropped} dropped")
        return
    if con.recorder is not None:
        raise ConsoleError(f"already recording to {con.recorder.path}; 'record stop' first")
    cfg = con.link.telemetry if con.tele_on else None
    if cfg is None:
        cfg = _telemetry_on(con)
    info = con.link.info
    prof = con.profile.name if con.profile is not None else (bundled_profile_by_hash(info.profile_hash) or "?")
    rec = Recorder(args[0], [(e.name, e.unit) for e in cfg.signals], cfg.rate_hz or con.tele_rate_hz,
                   firmware=f"build 0x{info.build_id:08x} table 0x{info.table_hash:08x}",
                   profile=f"{prof} hash 0x{info.profile_hash:08x}",
                   protocol=f"{info.proto_version[0]}.{info.proto_version[1]}")
    con.set_sink("recorder", rec)          # its dropped count starts from the link's now
    con.say(f"recording {', '.join(n for n, _ in rec.signals)} at {rec.rate_hz:g} Hz to {rec.path} "
            "('record stop' ends it)")


# -- step test ----------------------------------------------------------------

STEP_SIGNALS = ("speed", "setpoint", "voltage", "current")
STEP_PRE_S = 0.2           # samples kept before the step (y0 and the plot)
STEP_SETTLE_TIMEOUT_S = 5.0
STEP_AFTER_STOP_S = 0.1   # an interrupted step keeps this much of the coast-down after the stop
STEP_REST_TOL = 0.005      # "at rest" before a step from 0: |speed| within 0.5 % of the step


def _collected(collect: list):
    import numpy as np
    return np.concatenate(collect) if collect else None


def _step_wait(con, collect: list, until, timeout_s: float, what: str):
    """Wait until ``until(data)`` is true for the samples collected so far."""
    end = time.monotonic() + timeout_s
    while True:
        data = _collected(collect)
        if data is not None and len(data) and until(data):
            return data
        if con.link is None:
            raise ConsoleError(f"step: link lost ({con.lost_reason}) while {what}")
        if time.monotonic() > end:
            raise ConsoleError(f"step: timed out after {timeout_s:g} s while {what}")
        time.sleep(0.02)


def run_step(con, from_rpm: float, to_rpm: float, hold_s: float):
    """Run a step on the board through the link; returns a :class:`StepRecord` (analysed)."""
    import numpy as np
    from ..link import protocol as P
    from .step import StepRecord, analyse_step
    link = con.link
    hz = link.info.sample_hz
    if not hz:
        raise ConsoleError("step: the board does not state its speed-loop rate, so samples cannot be timed")
    for v in (from_rpm, to_rpm):
        link.to_raw("speed_setpoint", v)             # ParamError names the range
    st = link.status()
    if int(st.fault):
        raise ConsoleError(f"step: fault {state_name(st.fault)} is latched; 'clear' it first")
    sigs = [n for n in STEP_SIGNALS if n in link.table]
    if "speed" not in sigs:
        raise ConsoleError("step: the board has no 'speed' signal")
    band = 0.02 * abs(to_rpm - from_rpm)
    was = (con.tele_on, list(con.tele_signals), con.tele_rate_hz)
    collect: list = []
    con.stop_pump()
    link.configure_telemetry(sigs, decimation=1)
    con.set_sink("collect", collect)
    con.start_pump()
    interrupted = ""
    k0 = None
    step_index = None                      # defined once the step is commanded
    n_pre = int(round(STEP_PRE_S * hz))
    n_hold = int(round(hold_s * hz))
    try:
        spd_tol = max(band, 2.0 * link.param("speed").scale)

        def settled_at_from(d):
            tail = d["speed"][-n_pre:]
            return len(d) >= n_pre and bool(np.all(np.abs(tail - from_rpm) <= spd_tol))
        if from_rpm == 0:
            # from rest: outputs off until the motor stands, then start and step at once (a drive
            # held running at setpoint 0 counts toward its stall timeout)
            spd_tol = max(STEP_REST_TOL * abs(to_rpm), 2.0 * link.param("speed").scale)
            link.set_speed(0.0)
            if st.state != P.State.IDLE:
                link.stop()
            _step_wait(con, collect, settled_at_from, STEP_SETTLE_TIMEOUT_S + STEP_PRE_S,
                       f"waiting for the motor to stand still (±{spd_tol:g} rpm)")
            link.start()
        else:
            link.set_speed(from_rpm)
            if st.state != P.State.RUN:
                link.start()
            _step_wait(con, collect, settled_at_from, STEP_SETTLE_TIMEOUT_S + STEP_PRE_S,
                       f"waiting for the speed to settle at {from_rpm:g} rpm (±{spd_tol:g} rpm)")
        link.set_speed(to_rpm)
        sp_tol = 0.5 * link.param("setpoint").scale if "setpoint" in sigs else None
        t_cmd_index = int(_collected(collect)["index"][-1]) + 1

        def step_index(d):
            if sp_tol is None:
                return t_cmd_index
            moved = np.nonzero((d["index"] >= t_cmd_index - 1) & (np.abs(d["setpoint"] - from_rpm) > sp_tol))[0]
            return int(d["index"][moved[0]]) if moved.size else None

        def done(d):
            k0 = step_index(d)
            return k0 is not None and int(d["index"][-1]) >= k0 + n_hold - 1
        data = _step_wait(con, collect, done, hold_s + 3.0, f"recording the step to {to_rpm:g} rpm")
    except KeyboardInterrupt:
        # Ctrl-C: outputs off at once, then keep what was recorded
        interrupted = con.stop_after_interrupt()
        # the telemetry in flight up to the stop, and 0.1 s of the coast-down after it (board samples)
        n_then = sum(len(c) for c in collect)
        try:
            _step_wait(con, collect, lambda d: len(d) >= n_then + int(STEP_AFTER_STOP_S * hz), 2.0,
                       "collecting the samples up to the stop")
        except (ConsoleError, KeyboardInterrupt):
            pass                                  # keep what arrived
        data = _collected(collect)
        if data is None or not len(data):
            raise ConsoleError(f"step: interrupted (Ctrl-C) before any sample; {interrupted}") from None
        if k0 is None:
            k0 = step_index(data) if step_index is not None else None
    finally:
        con.set_sink("collect", None)
        con.stop_pump()
        if was[0]:
            con.tele_signals, con.tele_rate_hz = was[1], was[2]
            try:
                _telemetry_on(con, quiet=True)
            except PicdriveError as e:
                con.say(f"telemetry not restored: {e}")
        elif con.link is not None:
            con.link.stop_telemetry()
    if not interrupted:
        k0 = step_index(data)
    idx = data["index"]
    if k0 is None:                  # interrupted before the step: t = 0 at the last sample
        k0 = int(idx[-1])
    sel = (idx >= k0 - n_pre) & (idx < k0 + n_hold)
    d = data[sel]
    t = (d["index"] - k0) / float(hz)
    info = link.info
    prof = con.profile.name if con.profile is not None else bundled_profile_by_hash(info.profile_hash) or "?"
    gains = {e.name: float(link.get(e.name)) for e in link.table.params
             if e.name.startswith("rule") or e.name in STEP_GAIN_PARAMS} if con.link is not None else {}
    rec = StepRecord(from_rpm, to_rpm, hold_s, t, d["speed"].astype(float), 1.0 / hz, source="telemetry",
                     signals={n: d[n].astype(float) for n in sigs if n != "speed"},
                     units={n: link.param(n).unit for n in sigs},
                     firmware=(f"firmware build 0x{info.build_id:08x} table 0x{info.table_hash:08x} "
                               f"protocol {info.proto_version[0]}.{info.proto_version[1]}"),
                     profile=f"{prof} hash 0x{info.profile_hash:08x}",
                     controller=_fmt_value(link.param("controller"), link.get("controller")),
                     dropped=int(np.sum(np.diff(d["index"]) - 1)) if len(d) else 0, gains=gains)
    st = link.status()
    rec.fault = state_name(st.fault) if int(st.fault) else ""
    if interrupted:
        rec.interrupted = True
        con.interrupt_note = interrupted
        return rec
    if not rec.fault:
        pre = d["speed"][t < 0]
        analyse_step(rec, pre_speed_rpm=pre if len(pre) else None, profile=_board_profile(con))
    return rec


STEP_GAIN_PARAMS = ("setpoint_weight", "premise_low", "premise_high", "u_min", "u_max", "current_limit",
                    "accel_limit")


def _board_profile(con):
    """The profile the board was built from, if known here (--profile, or a bundled one with its hash)."""
    if con.profile is not None:
        return con.profile if con.profile.hash32 == con.link.info.profile_hash else None
    name = bundled_profile_by_hash(con.link.info.profile_hash)
    if name is None:
        return None
    import warnings
    from ..profile import load_profile
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_profile(name)


@command("step", "step <from> <to> [--hold <s>] [--png FILE]",
         "step test: settle at <from> rpm, step to <to>, record <hold> s at the full sample rate, "
         "print rise/settling/overshoot/steady-state error, save the plot (PNG) and the data (CSV)",
         complete=lambda con, args, text: ["--hold", "--png"] if len(args) >= 2 else [])
def _step(con, args):
    from .record import Recorder
    from .step import parse_step_args, save_step_plot
    from .files import output_path
    f, t, hold, png = parse_step_args(args)
    if con.recorder is not None:
        raise ConsoleError(f"step: a recording to {con.recorder.path} is running; 'record stop' first "
                           "(the step saves its own CSV)")
    if png is None:
        stamp = time.strftime("%Y%m%d-%H%M%S")
        png = con.out_dir / f"step_{f:g}_{t:g}_{stamp}.png"
    png = output_path(png, ".png", "step --png")        # checked before the motor moves
    csv = output_path(png.with_suffix(".csv"), ".csv", "step data")
    con.say(f"step {f:g} -> {t:g} rpm, hold {hold:g} s ...")
    con.interrupt_note = ""
    rec = run_step(con, f, t, hold)
    con.last_step = rec
    png = save_step_plot(rec, png)
    names = ["speed"] + list(rec.signals)
    with Recorder(csv, [(n, rec.units.get(n, "")) for n in names], 1.0 / rec.sample_period_s,
                  firmware=rec.firmware, profile=rec.profile,
                  protocol="{}.{}".format(*con.link.info.proto_version), relative_time=False,
                  notes=[f"step: {rec.from_rpm:g} -> {rec.to_rpm:g} rpm, hold {rec.hold_s:g} s, t = 0 at the step"]
                  + [x for x in rec.identity_lines()[2:]]
                  + ([f"fault: {rec.fault}"] if rec.fault else [])
                  + (["interrupted: Ctrl-C, partial data"] if rec.interrupted else []),
                  what="step data") as w:
        cols = [rec.speed_rpm] + [rec.signals[n] for n in rec.signals]
        for k in range(len(rec.t_s)):
            w.write(float(rec.t_s[k]), [c[k] for c in cols])
    if rec.interrupted:
        raise ConsoleError(f"step: interrupted (Ctrl-C); {con.interrupt_note}; partial data kept "
                           f"({len(rec.t_s)} samples): plot {png}, data {csv}")
    if rec.fault:
        raise ConsoleError(f"step: fault {rec.fault} latched during the step, outputs off; no metrics "
                           f"(plot {png}, data {csv}); 'faults', then 'clear'")
    con.say(rec.summary())
    if rec.dropped:
        con.say(f"warning: {rec.dropped} telemetry samples were dropped during the step")
    con.say(f"plot {png}\ndata {csv}\nmotor left running at {t:g} rpm ('stop' stops it)")




def _scope_arm(con, st) -> dict:
    """Arm the board's capture per ``st``; returns what was armed (for the read and the files)."""
    link = con.link
    if not st.signals:
        st.signals = [n for n in ("speed", "setpoint") if n in link.table] or ["speed"]
    sig = {e.name for e in link.table.signals}
    bad = [n for n in st.signals if n not in sig]
    if bad:
        raise ConsoleError(f"scope: {', '.join(bad)} not a signal of this board; signals: "
                           f"{', '.join(e.name for e in link.table.signals)}")
    if len(set(st.signals)) != len(st.signals):
        raise ConsoleError("scope: a signal is listed twice")
    ordered = [e.name for e in link.table.signals_in_mask(link.table.signal_mask(st.signals))]
    words = link.info.capture_words
    most = words // len(ordered)
    n = st.samples if st.samples is not None else most
    if n > most:
        raise ConsoleError(f"scope: --samples {n} x {len(ordered)} signals need {n * len(ordered)} words; the "
                           f"board's capture buffer holds {words} words (at most {most} samples of "
                           f"{len(ordered)} signals): fewer samples or signals")
    pre = st.pre_samples(n)
    if pre >= n:
        raise ConsoleError(f"scope: --pre {pre} must be below the {n} samples")
    hz = link.info.sample_hz
    rate = (hz / st.decimation) if hz else 0.0
    if st.timeout_s is not None and rate and st.timeout_s <= n / rate:
        # refused before arming: a wait shorter than the capture could never see it done
        raise ConsoleError(f"scope: --timeout {st.timeout_s:g} s is shorter than the capture itself ({n / rate:.3g} s: "
                           f"{n} samples at {rate:g} Hz); a longer --timeout, fewer --samples or a smaller "
                           "--decimation")
    from .scope import TRIGGERS
    link.capture_arm(ordered, n, pre_trigger=pre, trigger=TRIGGERS[st.trigger], threshold=st.level_rpm,
                     decimation=st.decimation)
    armed = dict(setup=st, signals=ordered, n=n, pre=pre, t_armed=board_time_s(con), rate=rate)
    con.scope_armed = armed
    return armed




def _scope_describe(armed) -> str:
    st = armed["setup"]
    trig = st.trigger + (f" at {st.level_rpm:g} rpm" if st.level_rpm is not None else "")
    rate = f"{armed['rate']:g} Hz" if armed["rate"] else f"decimation {st.decimation}"
    return (f"{', '.join(armed['signals'])}: {armed['n']} samples at {rate} "
            f"({armed['n'] / armed['rate'] * 1e3:.1f} ms), trigger {trig}, {armed['pre']} before it")


def _scope_timeout_s(armed, timeout_s=None) -> float:
    """The board-clock wait for ``armed``: the one given, else the capture's length + the default."""
    from .scope import DEFAULT_TIMEOUT_S
    st = armed["setup"]
    if timeout_s is None:
        timeout_s = st.timeout_s
    if timeout_s is None:
        timeout_s = (armed["n"] / armed["rate"] if armed["rate"] else 0.0) + DEFAULT_TIMEOUT_S
    return timeout_s


def _scope_paths(con, st, png=None, csv=None, index: int | None = None):
    """The capture's PNG and CSV: as given (``index`` k appends ``_k`` to the stem: one pair per
    capture of 'scope normal'), else ``scope_<time>[_k].png`` in the output folder."""
    from .files import output_path
    png = Path(png or st.png or con.out_dir / f"scope_{time.strftime('%Y%m%d-%H%M%S')}.png")
    csv = Path(csv or st.csv or png.with_suffix(".csv"))
    if index is not None:
        png = png.with_name(f"{png.stem}_{index}{png.suffix}")
        csv = csv.with_name(f"{csv.stem}_{index}{csv.suffix}")
    return output_path(png, ".png", "scope --png"), output_path(csv, ".csv", "scope --csv")


def _scope_read(con, armed, png=None, csv=None, timeout_s=None, quiet=False):
    """Wait (board clock) for the armed capture, read it, save PNG and CSV; returns (png, csv, data).
    ``png``/``csv``: the paths (:func:`_scope_paths`)."""
    from ..link import protocol as P
    from .record import Recorder
    from .scope import save_scope_plot
    link = con.link
    st = armed["setup"]
    timeout_s = _scope_timeout_s(armed, timeout_s)
    if png is None or csv is None:
        png, csv = _scope_paths(con, st, png, csv)
    t0 = board_time_s(con)
    while True:
        s = link.status()
        if s.capture_state == P.CaptureState.DONE:
            break
        if s.capture_state == P.CaptureState.IDLE:
            raise ConsoleError("scope: no capture is armed on the board (it restarted or another program "
                               "read it); arm again")
        if s.uptime_ms / 1000.0 - t0 > timeout_s:
            what = "trigger not seen" if s.capture_state == P.CaptureState.ARMED else "still recording"
            raise ConsoleError(f"scope: capture not done after {timeout_s:g} s of the board's clock ({what}; "
                               f"trigger {st.trigger}); the capture stays armed ('scope read' waits again)")
        time.sleep(BOARD_POLL_S)
    cap = link.capture_read(timeout=5.0)
    d = cap.data
    info = link.info
    units = {n: link.param(n).unit for n in armed["signals"]}
    prof = con.profile.name if con.profile is not None else bundled_profile_by_hash(info.profile_hash) or "?"
    ident = (f"firmware build 0x{info.build_id:08x} table 0x{info.table_hash:08x}, profile {prof} hash "
             f"0x{info.profile_hash:08x}, controller {_fmt_value(link.param('controller'), link.get('controller'))}")
    desc = _scope_describe(armed)
    level = ("speed", st.level_rpm) if st.level_rpm is not None else None
    save_scope_plot(png, d["t"], {n: d[n].astype(float) for n in armed["signals"]}, units,
                    title=f"picdrive scope: {ident}", trigger_note=desc, level=level)
    with Recorder(csv, [(n, units[n]) for n in armed["signals"]], armed["rate"] or 1.0,
                  firmware=f"build 0x{info.build_id:08x} table 0x{info.table_hash:08x}",
                  profile=f"{prof} hash 0x{info.profile_hash:08x}",
                  protocol=f"{info.proto_version[0]}.{info.proto_version[1]}", relative_time=False,
                  notes=[f"scope: {desc}; t = 0 at the trigger sample (index {cap.trigger_index})"],
                  what="scope --csv") as w:
        for k in range(len(d)):
            w.write(float(d["t"][k]), [float(d[n][k]) for n in armed["signals"]])
    con.scope_armed = None
    if not quiet:
        stats = "; ".join(f"{n} {float(d[n].min()):.4g}..{float(d[n].max()):.4g}{_unit(link.param(n))}"
                          for n in armed["signals"])
        short = (f"; {armed['pre'] - cap.trigger_index} fewer before the trigger than asked: it came "
                 f"{cap.trigger_index / armed['rate'] * 1e3:.1f} ms after arming, before the pre-trigger history "
                 "filled" if armed["rate"] and cap.trigger_index < armed["pre"] else "")
        con.say(f"scope: captured {len(d)} samples ({stats}){short}")
        con.say(f"plot {png}\ndata {csv}")
    return png, csv, d


@command("scope", "scope [single|normal|arm|read|stop] [SIGNALS] [--trigger T] [--level RPM] [--speed RPM] "
         "[--pre N|P%] [--samples N] [--decimation D] [--count N] [--timeout S] [--png F] [--csv F]",
         "the board's triggered capture (exact timing, in its own buffer): 'single' arms and waits, 'arm' "
         "returns at once (then trigger it, e.g. 'speed 2400', and 'scope read'), 'normal' re-arms after each "
         "capture (--count N, or until Ctrl-C, which ends the scope alone: the motor keeps running), one "
         "PNG/CSV pair per capture (_1, _2, ...); triggers immediate|setpoint|rising|falling (speed crossing "
         "--level rpm); --speed RPM[,RPM...] writes the setpoint right after arming (the step that fires the "
         "trigger while the prompt waits); 'stop' forgets an armed capture; plot with units and the trigger "
         "marked, CSV with units; alone: the capture's state",
         complete=lambda con, args, text: (["single", "normal", "arm", "read", "stop", "--trigger", "--level",
                                            "--speed", "--pre", "--samples", "--decimation", "--count",
                                            "--timeout", "--png", "--csv"]
                                           + (["immediate", "setpoint", "rising", "falling"] if args and args[-1] == "--trigger" else [])
                                           + _param_names(con, signals=True)))
def _scope(con, args):
    from .scope import parse_scope_args
    link = con.link
    if not args:
        s = link.status()
        armed = con.scope_armed
        con.say(f"capture {state_name(s.capture_state)}; buffer {link.info.capture_words} words"
                + (f"; armed: {_scope_describe(armed)}" if armed else ""))
        return
    st = parse_scope_args(args)
    if st.mode == "stop":
        armed, con.scope_armed = con.scope_armed, None
        con.say("scope stop: " + (f"no longer waiting for {_scope_describe(armed)}; the board's capture stays "
                                  "armed until the next 'scope' arms another (it only fills its own buffer)"
                                  if armed else "nothing armed by this console"))
        return
    if st.mode == "read":
        armed = con.scope_armed
        if armed is None:
            raise ConsoleError("scope read: nothing armed by this console; 'scope arm ...' first")
        _scope_read(con, armed, png=st.png, csv=st.csv, timeout_s=st.timeout_s)
        return
    if st.mode == "arm":
        armed = _scope_arm(con, st)
        con.say(f"scope armed: {_scope_describe(armed)}; 'scope read' waits for it")
        return
    done: list = []
    try:
        if st.mode == "single":
            png, csv = _scope_paths(con, st)        # refused before arming when not writable
            armed = _scope_arm(con, st)
            con.say(f"scope armed: {_scope_describe(armed)}")
            _scope_step(con, st, armed, 0)
            _scope_read(con, armed, png, csv)
            return
        # normal: capture, save, re-arm; one file pair per capture
        count = st.count if st.count is not None else (None if con.interactive else 1)
        base = (st.png or con.out_dir / f"scope_{time.strftime('%Y%m%d-%H%M%S')}.png", st.csv)
        k = 0
        while count is None or k < count:
            png, csv = _scope_paths(con, st, *base, index=k + 1)
            armed = _scope_arm(con, st)
            _scope_step(con, st, armed, k)
            _, _, d = _scope_read(con, armed, png, csv, quiet=True)
            k += 1
            done.append(png)
            con.say(f"scope capture {k}: {len(d)} samples -> {png}")
        con.say(f"scope normal: {k} captures; plots {done[0]}" + (f" .. {done[-1]}" if k > 1 else "")
                + ", data beside them (.csv)")
    except KeyboardInterrupt as e:
        if isinstance(e, Terminated) or not con.interactive:
            raise                               # the console ends (or the script fails): motor stopped
        # Ctrl-C at the prompt ends the scope alone: the motor keeps doing what it did
        con.scope_armed = None
        state = state_name(con.link.status().state)
        con.say(f"scope ended (Ctrl-C) after {len(done)} captures"
                + (f" ({done[0]} .. {done[-1]})" if done else "")
                + f"; motor state {state}" + (" ('stop' or Ctrl-C at the prompt stops it)"
                                              if state in ("run", "brake") else ""))


def _scope_step(con, st, armed, k: int) -> None:
    """Write the k-th ``--speed`` setpoint (cycling), the step that fires the armed trigger, once
    the pre-trigger history has filled (board clock): the capture then holds all of it."""
    if st.speed_rpm:
        if armed["pre"] and armed["rate"]:
            _wait(con, max(0.0, armed["t_armed"] + (armed["pre"] + 1) / armed["rate"] - board_time_s(con)))
        got = con.link.set_speed(st.speed_rpm[k % len(st.speed_rpm)])
        con.say(f"speed setpoint {got:g} rpm (the scope's step)")
