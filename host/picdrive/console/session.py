"""``picdrive console <serial URL>``: the bench console.

What the engineer lives in at the bench, against a real board
(``/dev/ttyUSB0``, ``COM5``) or the twin (``socket://127.0.0.1:<port>``).  It
is built only on :mod:`picdrive.link` (seam 6): it opens the URL with
``Link.open``, shows the handshake, and turns typed commands into link calls.

Commands (``help`` lists them, ``help <command>`` explains one):

=======================  ==================================================
``speed <rpm>``          speed setpoint (mechanical rpm; negative reverses)
``start`` ``stop``       run / coast down
``brake``                active brake
``reverse``              negate the speed setpoint
``params [text]``        the board's parameter table: value, unit, limits
``get <name>``           one parameter, with unit and limits
``set <name> <value>``   write a parameter (engineering units); the board
                         enforces its limits and says so when it refuses
``controller pid|fuzzy`` switch the control law (plain PID / fuzzy blend)
``load <design.json>``   push a design result's gains (checked first)
``save`` ``restore``     parameters to / from the board's EEPROM
``faults`` ``clear``     show / clear latched faults
``status``               run state, setpoint, speed, controller, faults
``info``                 the handshake again
``telemetry ...``        ``signals a,b,c`` / ``rate <Hz>`` / ``on`` / ``off``
``plot [off]``           live plot window (PNG file when there is no display)
``view [seconds]``       compact text view of the telemetry
``record <f.csv>``       record telemetry to CSV; ``record stop`` ends it
``step <from> <to>``     step test, ``--hold <s>``: metrics + PNG plot
``wait <seconds>``       pause (for scripts)
``quit``                 leave (stops the motor first if it runs)
=======================  ==================================================

Scripting: ``--run session.txt`` runs the file's commands (one per line,
``#`` comments) and exits non-zero on the first error, so a bench procedure
is reproducible.  Interactive sessions have tab completion and a persistent
history (``--history``, default ``$XDG_STATE_HOME/picdrive/console_history``).

A bad command, a value the board refuses or a lost link gets a one-line
explanation and the console keeps running; a lost link is reopened in the
background and announced when it is back.
"""
from __future__ import annotations

import difflib
import math
import os
import shlex
import signal
import sys
import threading
from pathlib import Path
from typing import Callable

from ..errors import PicdriveError
from .commands import (ALIASES, COMMANDS, NACK_WORDS, ConsoleError, Quit, Terminated, bundled_profile_by_hash, expects_fault,
                       state_name)

__all__ = ["Console", "Terminated", "default_history_path", "register", "main"]

PROMPT = "picdrive> "

STOP_SIGNALS = tuple(getattr(signal, n) for n in ("SIGHUP", "SIGTERM") if hasattr(signal, n))
"""Signals that end the console (terminal closed, killed): the motor is stopped first."""


def default_history_path() -> Path:
    env = os.environ.get("PICDRIVE_HISTORY")
    if env:
        return Path(env)
    state = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return Path(state) / "picdrive" / "console_history"


NOT_DRIVEN = "the motor was not driven"

#: a bench procedure is a few hundred lines; far more is the wrong file
SCRIPT_MAX_BYTES = 1 << 20


def read_script(path: str | Path) -> list[str]:
    """The lines of a ``--run`` session file: a regular UTF-8 text file of bounded size."""
    from ..fileio import read_input_text
    return read_input_text(path, "session file", limit_bytes=SCRIPT_MAX_BYTES, error=ConsoleError).splitlines()


def _interruption(e: BaseException) -> str:
    """What interrupted a command: Ctrl-C, or the signal that ends the console."""
    return e.signame if isinstance(e, Terminated) else "Ctrl-C"


# ---------------------------------------------------------------------------
# the console
# ---------------------------------------------------------------------------

class Console:
    """One console session on one serial URL.

    ``opener(url)`` returns an open :class:`picdrive.link.client.Link` (default
    ``Link.open``); ``profile``: a local :class:`picdrive.profile.Profile` to
    compare with the board's handshake; ``out_dir``: where step plots go;
    ``write``: output function (default: print to stdout).
    """

    def __init__(self, url: str, *, profile=None, out_dir: str | Path = ".", opener=None,
                 write: Callable[[str], None] | None = None, interactive: bool = False,
                 reconnect_interval_s: float = 0.5, strict: bool = False):
        self.url = url
        self.profile = profile
        self.strict = strict
        self.out_dir = Path(out_dir)
        self.interactive = interactive
        self.reconnect_interval_s = reconnect_interval_s
        self._opener = opener
        self._write = write or self._print
        self._out_lock = threading.RLock()
        self._at_prompt = False
        self.link = None
        self._lost: str | None = None           # reason while the link is lost
        self._closing = threading.Event()
        self._reconnector: threading.Thread | None = None
        # telemetry selection and sinks
        self.tele_signals: list[str] = []
        self.tele_rate_hz: float = 0.0
        self.tele_on = False
        self._sinks_lock = threading.Lock()
        self._pump: threading.Thread | None = None
        self._pump_stop = threading.Event()
        self.recorder = None
        self.plot = None
        self._view = None
        self._collect: list | None = None
        self.last_step = None
        self.interrupt_note = ""
        self.scope_armed = None                 # what 'scope arm' set up, until 'scope read'
        self.pending_line: str | None = None    # a command typed during 'view', run next
        self._heartbeat_s = 0.5
        self._rec_dropped_seen = 0
        self._watcher: threading.Thread | None = None
        # board events (faults, watchdog, reboot) not yet accounted for by an 'expect'
        self._events_lock = threading.Lock()
        self.unexpected: list[str] = []
        self.terminating: str | None = None     # the signal (SIGHUP, SIGTERM) that ends the session

    def on_stop_signal(self, signum, frame) -> None:
        """SIGHUP / SIGTERM handler: later ones are ignored (the stop and the saving must run to
        the end); raises :class:`Terminated` in the main thread, which unwinds to ``close``."""
        for s in STOP_SIGNALS:
            signal.signal(s, signal.SIG_IGN)
        self.terminating = signal.Signals(signum).name
        raise Terminated(self.terminating)

    # -- output ---------------------------------------------------------------

    @staticmethod
    def _print(text: str) -> None:
        try:
            sys.stdout.write(text + "\n")
            sys.stdout.flush()
        except (OSError, ValueError):       # the terminal is gone (SIGHUP): stopping must go on
            pass

    def say(self, text: str) -> None:
        with self._out_lock:
            self._write(text)

    def notify(self, text: str) -> None:
        """A message from a background thread: printed above the prompt."""
        with self._out_lock:
            if self._at_prompt and self.interactive and self._write == self._print:
                try:
                    import readline
                    buf = readline.get_line_buffer()
                except ImportError:
                    buf = ""
                sys.stdout.write("\r\x1b[K" + text + "\n" + PROMPT + buf)
                sys.stdout.flush()
            else:
                self._write(text)

    # -- connection -------------------------------------------------------------

    def _open(self):
        if self._opener is not None:
            return self._opener(self.url)
        from ..link.client import Link
        return Link.open(self.url)

    def connect(self) -> None:
        """Open the link and show the handshake (raises LinkError if the board is not there)."""
        link = self._open()
        if self.strict:
            try:
                self._check_identity(link)
            except ConsoleError:
                link.close()
                raise
        self._attach(link)
        self.say(f"connected to {self.url}")
        for line in self.handshake_lines():
            self.say(line)
        self.say(self.state_line())

    def _check_identity(self, link) -> None:
        """``--strict``: refuse a board built from another profile than ``--profile``."""
        if self.profile is None:
            return
        mine = self.profile.hash32
        if mine != link.info.profile_hash:
            raise ConsoleError(f"--strict: the board was built from another profile (board hash "
                               f"0x{link.info.profile_hash:08x}, local profile {self.profile.name} hash 0x{mine:08x}); "
                               "flash the firmware of this profile, pass the right --profile, or drop --strict")

    def state_line(self) -> str:
        """The board's run state and latched fault, as shown on connect and on reconnection."""
        from ..link import protocol as P
        st = self.link.status()
        if int(st.fault):
            return (f"board state {state_name(st.state)}: fault {state_name(st.fault)} is latched "
                    "(outputs off; 'clear' clears it)")
        extra = ""
        if st.state in (P.State.RUN, P.State.BRAKE):
            extra = f", setpoint {self.link.get('speed_setpoint'):g} rpm: the motor is driven ('stop' stops it)"
        return f"board state {state_name(st.state)}, no fault latched{extra}"

    def _note_event(self, what: str) -> None:
        if self.interactive:                    # only a script fails on a board event
            return
        with self._events_lock:
            self.unexpected.append(what)

    def take_unexpected(self) -> list[str]:
        """Board events (faults, watchdog, reboot) since the last call."""
        with self._events_lock:
            out, self.unexpected = self.unexpected, []
        return out

    def _attach(self, link) -> None:
        self.link = link
        self._lost = None
        link.on_event = self._on_event
        self.retime_heartbeat()
        if self._watcher is None or not self._watcher.is_alive():
            self._watcher = threading.Thread(target=self._watch_link, name="picdrive-console-watch", daemon=True)
            self._watcher.start()

    def handshake_lines(self) -> list[str]:
        """The handshake as shown at connect and by ``info``; warns on a profile mismatch."""
        info, table = self.link.info, self.link.table
        rules = table.rules
        rate = f"{info.sample_hz} Hz" if info.sample_hz else "not stated"
        lines = [f"firmware build 0x{info.build_id:08x}, protocol {info.proto_version[0]}.{info.proto_version[1]}, "
                 f"profile hash 0x{info.profile_hash:08x}, table hash 0x{info.table_hash:08x} "
                 f"({len(table)} entries, {rules} rule{'s' if rules != 1 else ''}), speed loop {rate}"]
        if self.profile is not None:
            mine = self.profile.hash32
            if mine == info.profile_hash:
                lines.append(f"profile {self.profile.name}: matches the board (hash 0x{mine:08x})")
            else:
                lines.append(f"WARNING: the board was built from another profile: board hash 0x{info.profile_hash:08x}, "
                             f"local profile {self.profile.name} hash 0x{mine:08x}; limits and gains may not fit "
                             "this motor. Regenerate and flash the firmware, or pass the right --profile")
        else:
            name = bundled_profile_by_hash(info.profile_hash)
            lines.append(f"profile: {name} (bundled profile with this hash)" if name else
                         "profile: not a bundled profile (pass --profile P to compare with yours)")
        return lines

    def _on_event(self, t, event, code) -> None:
        from ..link import protocol as P
        name = event.name.lower() if hasattr(event, "name") else str(event)
        if event == P.Event.WATCHDOG:
            self._note_event("fault link_lost (watchdog)")
            self.notify("board event: watchdog: no valid frame from the host within link_timeout while running; "
                        "motor stopped")
        elif event == P.Event.FAULT:
            try:
                what = P.Fault(code).name
            except ValueError:
                what = str(code)
            self._note_event(f"fault {what.lower()}")
            self.notify(f"board event: fault {what} latched, outputs off ('faults', then 'clear')")
        elif event == P.Event.BOOT:
            self._note_event("boot (the board restarted)")
            self.notify(f"board event: boot (reset cause {code}): the board restarted")
            threading.Thread(target=self._after_reboot, name="picdrive-console-reboot", daemon=True).start()
        else:
            self.notify(f"board event: {name} code {code}")

    @property
    def connected(self) -> bool:
        return self.link is not None

    def require_link(self):
        """The open link; a :class:`ConsoleError` saying it is lost (and being reconnected) otherwise."""
        if self.link is None:
            raise ConsoleError(f"not connected: link lost ({self._lost}); reconnecting to {self.url} in the background")
        return self.link

    @property
    def lost_reason(self) -> str | None:
        """Why the link was lost (None while it is up or was never lost)."""
        return self._lost

    def link_lost(self, reason: str) -> None:
        """Drop the link and start reconnecting in the background."""
        with self._out_lock:
            if self.link is None and self._lost is not None:
                return
            link, self.link = self.link, None
            self._lost = reason
        self.notify(f"link lost: {reason}; reconnecting to {self.url} (commands will fail until it is back)")
        self.stop_pump()
        if self.recorder is not None:
            with self._sinks_lock:
                rec, self.recorder = self.recorder, None
            try:
                p = rec.close()
                self.notify(f"recording saved to {p} ({rec.samples} samples) because the link was lost")
            except PicdriveError as e:
                self.notify(f"recording lost: {e}")
        if link is not None:
            try:
                link.close()
            except Exception:
                pass
        if not self._closing.is_set() and (self._reconnector is None or not self._reconnector.is_alive()):
            self._reconnector = threading.Thread(target=self._reconnect_loop, name="picdrive-console-reconnect",
                                                 daemon=True)
            self._reconnector.start()

    def _after_reboot(self) -> None:
        """The board restarted: its telemetry is off; re-validate the table and restore it."""
        from ..link.client import LinkError
        link = self.link
        if link is None or not self.tele_on:
            return
        try:
            self.apply_telemetry()
            self.notify(f"telemetry restored: {', '.join(self.tele_signals)} at {self.tele_rate_hz:g} Hz")
        except LinkError as e:              # e.g. the board rebooted into another build
            if self.link is link:
                self.link_lost(str(e))

    def _reconnect_loop(self) -> None:
        from ..link.client import HandshakeMismatch, LinkError
        tries = 0
        said = ""
        while not self._closing.is_set():
            self._closing.wait(self.reconnect_interval_s)
            if self._closing.is_set():
                return
            tries += 1
            try:
                link = self._open()
            except HandshakeMismatch as e:  # the port is back, with a board this host cannot use
                if str(e) != said:
                    said = str(e)
                    self.notify(f"cannot use the board on {self.url}: {e}; still trying")
                continue
            except LinkError:
                continue
            if self._closing.is_set():
                link.close()
                return
            if self.strict:
                try:
                    self._check_identity(link)
                except ConsoleError as e:
                    link.close()
                    if str(e) != said:
                        said = str(e)
                        self.notify(f"cannot use the board on {self.url}: {e}; still trying")
                    continue
            self._attach(link)
            try:
                state = self.state_line()
            except LinkError as e:
                state = f"state unknown ({e})"
            self.notify(f"link regained after {tries} tries: " + " / ".join(self.handshake_lines() + [state]))
            if self.tele_on:
                try:
                    self.apply_telemetry()
                    self.notify(f"telemetry restored: {', '.join(self.tele_signals)} at {self.tele_rate_hz:g} Hz")
                except PicdriveError as e:
                    self.notify(f"telemetry not restored: {e}")
            return

    def retime_heartbeat(self) -> None:
        """Heartbeat at a quarter of the board's link_timeout (at most 0.5 s), so a console
        waiting at its prompt keeps a running motor's watchdog fed with margin."""
        from ..link.client import Link, LinkError
        period = 0.5
        link = self.link
        if link is not None and "link_timeout" in link.table:
            try:
                period = min(0.5, Link._auto_keepalive_period(link.get("link_timeout")))
            except LinkError:
                pass
        self._heartbeat_s = period

    def _watch_link(self) -> None:
        """Notice a lost link while the console is idle; feed the board's watchdog."""
        from ..link.client import LinkError, NackError
        while not self._closing.wait(self._heartbeat_s):
            link = self.link
            if link is None:
                continue
            try:
                link.heartbeat()
            except NackError:
                pass
            except LinkError as e:
                if self.link is link:
                    self.link_lost(str(e))

    # -- telemetry ---------------------------------------------------------------

    def apply_telemetry(self):
        """Configure the board's telemetry to the selection (``tele_signals`` at ``tele_rate_hz``)
        and (re)start the pump that feeds the sinks; returns the link's telemetry configuration."""
        link = self.require_link()
        hz = link.info.sample_hz
        if hz:
            dec = max(1, int(round(hz / self.tele_rate_hz)))
        else:
            dec = max(1, int(round(self.tele_rate_hz)))
        self.stop_pump()
        cfg = link.configure_telemetry(self.tele_signals, decimation=dec)
        self.start_pump()
        return cfg

    def start_pump(self) -> None:
        """Start the thread that reads telemetry samples and hands them to the sinks."""
        self._pump_stop.clear()
        self._pump = threading.Thread(target=self._pump_loop, name="picdrive-console-telemetry", daemon=True)
        self._pump.start()

    def stop_pump(self) -> None:
        """Stop the telemetry pump (before the telemetry is reconfigured or switched off)."""
        self._pump_stop.set()
        p = self._pump
        if p is not None and p is not threading.current_thread():
            p.join(2.0)
        self._pump = None

    def _pump_loop(self) -> None:
        from ..link.client import LinkError
        link = self.link
        while not self._pump_stop.is_set() and link is not None and self.link is link:
            try:
                recs = link.read_samples(seconds=0.05)
            except LinkError as e:
                if self.link is not link or self._pump_stop.is_set():
                    return
                try:
                    link.heartbeat()             # the link is alive: only the telemetry stopped
                    self.notify(f"telemetry stopped: {e}")
                except LinkError:
                    threading.Thread(target=self.link_lost, args=(str(e),), daemon=True).start()
                return
            if len(recs):
                self._dispatch(recs, link.telemetry_stats.dropped)

    def _dispatch(self, recs, dropped_total: int) -> None:
        """Hand a batch of samples to the step collector, recorder, plot and view.  Runs in
        the pump thread under the sinks lock, so a sink is never closed while it is fed."""
        names = [n for n in recs.dtype.names if n not in ("index", "t")]
        t = recs["t"]
        closed_plot = False
        with self._sinks_lock:
            if self._collect is not None:
                self._collect.append(recs)
            for s in (self.recorder, self.plot, self._view):
                if s is None:
                    continue
                cols = [recs[n] if n in names else None for n, _ in s.signals]
                rows = [[float(c[k]) if c is not None else math.nan for c in cols] for k in range(len(recs))]
                if s is self.recorder:
                    drop = dropped_total - self._rec_dropped_seen
                    self._rec_dropped_seen = dropped_total
                    for k, vals in enumerate(rows):
                        s.write(float(t[k]), vals, dropped=drop if k == 0 else 0)
                else:
                    for k, vals in enumerate(rows):
                        s.feed(float(t[k]), vals)
            if self.plot is not None and not self.plot.alive:
                self.plot, closed_plot = None, True
        if closed_plot:
            self.notify("plot window closed")

    SINKS = ("recorder", "plot", "view", "collect")

    def set_sink(self, kind: str, sink):
        """Attach (or with None detach) a telemetry sink under the sinks lock; returns the previous one.

        ``kind``: ``"recorder"`` (a :class:`~picdrive.console.record.Recorder`; its dropped-sample
        count starts from the link's count now), ``"plot"``, ``"view"`` (objects with ``signals``
        and ``feed(t, values)``) or ``"collect"`` (a list that receives each batch of samples).
        """
        if kind not in self.SINKS:
            raise ValueError(f"sink {kind!r}: expected one of {', '.join(self.SINKS)}")
        attr = {"view": "_view", "collect": "_collect"}.get(kind, kind)
        with self._sinks_lock:
            old = getattr(self, attr)
            if kind == "recorder" and sink is not None and self.link is not None:
                self._rec_dropped_seen = self.link.telemetry_stats.dropped
            setattr(self, attr, sink)
        return old

    def plot_control(self, *args) -> None:
        """Send a control message to the live plot under the sinks lock (never while it is fed)."""
        with self._sinks_lock:
            if self.plot is not None:
                self.plot.control(*args)

    def close_plot(self) -> bool:
        """Close the live plot, if one is open."""
        with self._sinks_lock:
            plot, self.plot = self.plot, None
        if plot is not None:
            plot.close()
        return plot is not None

    def signal_units(self, names) -> list[tuple[str, str]]:
        link = self.require_link()
        return [(n, link.param(n).unit) for n in names]

    # -- executing commands ---------------------------------------------------------

    def execute(self, line: str) -> None:
        """Run one command line; raises ConsoleError (or a PicdriveError) on failure."""
        from ..link.client import HandshakeMismatch, LinkError, NackError, ParamError
        try:
            words = shlex.split(line, comments=True)
        except ValueError as e:
            raise ConsoleError(f"cannot parse {line.strip()!r}: {e}") from None
        if not words:
            return
        name, args = words[0].lower(), words[1:]
        name = ALIASES.get(name, name)
        cmd = COMMANDS.get(name)
        if cmd is None:
            near = difflib.get_close_matches(name, list(COMMANDS) + list(ALIASES), n=3, cutoff=0.6)
            hint = f" (did you mean {', '.join(near)}?)" if near else ""
            raise ConsoleError(f"unknown command {words[0]!r}{hint}; 'help' lists the commands")
        link = self.require_link() if cmd.needs_link else self.link
        try:
            cmd.func(self, args)
        except KeyboardInterrupt as e:
            raise ConsoleError(f"{name}: interrupted ({_interruption(e)}); {self.stop_after_interrupt()}") from None
        except NackError as e:
            raise ConsoleError(f"{name}: {self._nack_text(e)}") from None
        except ParamError as e:
            raise ConsoleError(f"{name}: {e}") from None
        except HandshakeMismatch as e:
            raise ConsoleError(f"{name}: {e}") from None
        except LinkError as e:
            if link is not None and self.link is link:
                self.link_lost(str(e))
            raise ConsoleError(f"{name}: link lost: {e}") from None
        except ConsoleError:
            raise
        except PicdriveError as e:          # design file, recording, step or plot errors
            raise ConsoleError(f"{name}: {e}") from None

    def stop_after_interrupt(self) -> str:
        """Ctrl-C in a command: outputs off if the motor is driven (the same in a script and at
        the prompt); returns what was done, for the message."""
        from ..link import protocol as P
        from ..link.client import LinkError
        link = self.link
        if link is None:
            return f"the link is lost ({self._lost}): the board's watchdog stops a running motor"
        for _ in range(3):                       # a second Ctrl-C must not leave the motor running
            try:
                if link.status().state in (P.State.RUN, P.State.BRAKE):
                    link.stop()
                    return "motor stopped (outputs off)"
                return NOT_DRIVEN
            except KeyboardInterrupt:
                continue
            except LinkError as e:
                return f"could not reach the board to stop the motor ({e}); its watchdog stops it"
        return "motor stop not confirmed"

    @staticmethod
    def _nack_text(e) -> str:
        """A board refusal in the console's words (its command names, not the protocol's)."""
        from ..link import protocol as P
        code = e.code.name.lower() if hasattr(e.code, "name") else str(e.code)
        reason = e.reason
        for board, mine in NACK_WORDS.items():
            reason = reason.replace(board, mine)
        if e.code == P.Nack.FAULT_ACTIVE:
            reason = "a fault is latched; 'faults' shows it, 'clear' clears it"
        detail = f" ({e.detail})" if e.detail else ""
        return f"the board refused it{detail}: {code}: {reason}"

    def run_line(self, line: str) -> bool:
        """Run a line, print a one-line explanation on failure; True if it succeeded."""
        try:
            self.execute(line)
            return True
        except Quit:
            raise
        except PicdriveError as e:
            self.say(f"error: {e}")
            return False

    def run_script(self, path: str | Path, lines: list[str] | None = None) -> int:
        """Run the commands of a file (``lines``: its lines, already read with :func:`read_script`);
        stop at the first error (ConsoleError names file and line)."""
        p = Path(path)
        if lines is None:
            lines = read_script(p)
        prev = None
        try:
            for no, line in enumerate(lines, 1):
                text = line.strip()
                if not text or text.startswith("#"):
                    continue
                if not expects_fault(text):
                    self._fail_on_events(p, prev)
                self.say(PROMPT + text)
                try:
                    self.execute(text)
                except Quit:
                    self._fail_on_events(p, prev)
                    return 0
                except PicdriveError as e:
                    raise ConsoleError(f"{p}:{no}: {text!r}: {e}") from None
                if self.terminating:
                    break
                prev = (no, text)
            self._fail_on_events(p, prev)
        except KeyboardInterrupt as e:
            raise ConsoleError(f"{p}: interrupted ({_interruption(e)}); {self.stop_after_interrupt()}") from None
        if self.terminating:                 # a command caught it (Ctrl-C handling) and returned
            raise ConsoleError(f"{p}: interrupted ({self.terminating}); {self.stop_after_interrupt()}")
        return 0

    def _fail_on_events(self, path, prev) -> None:
        """A board fault, watchdog trip or restart not claimed by an 'expect' fails the script."""
        ev = self.take_unexpected()
        if ev:
            where = f"{path}:{prev[0]}: {prev[1]!r}" if prev else f"{path}"
            raise ConsoleError(f"{where}: board event {', '.join(ev)} during or after this line; the script "
                               "fails (if it is intended, follow the line with 'expect fault == <name> within <s>')")

    def close(self) -> None:
        """Stop the motor, stop background work, save an open recording, close the plot and the link."""
        why = f"outputs off; {self.terminating} received" if self.terminating else "leaving the console"
        if self.link is not None:            # the motor first: the rest may be slow or fail
            from ..link import protocol as P
            from ..link.client import LinkError
            for _ in range(3):               # a Ctrl-C while leaving must not leave the motor running
                try:
                    if self.link.status().state in (P.State.RUN, P.State.BRAKE):
                        self.link.stop()
                        self.say(f"motor stopped ({why})")
                    break
                except KeyboardInterrupt:
                    continue
                except LinkError:
                    break
        self._closing.set()
        self.stop_pump()
        if self.recorder is not None:
            rec, self.recorder = self.recorder, None
            try:
                p = rec.close()
                self.say(f"recording saved to {p} ({rec.samples} samples, {rec.dropped} dropped)")
            except PicdriveError as e:
                self.say(f"recording lost: {e}")
        self.close_plot()
        if self.link is not None:
            self.link.close()
            self.link = None
        for t in (self._watcher, self._reconnector):
            if t is not None and t is not threading.current_thread():
                t.join(2.0)

    # -- interactive ------------------------------------------------------------

    def complete(self, line: str, text: str) -> list[str]:
        """Completions of the word ``text`` at the end of ``line`` (what is typed so far)."""
        try:
            words = shlex.split(line)
        except ValueError:
            words = line.split()
        if line and not line[-1].isspace() and words:
            words = words[:-1]                         # the word being completed
        if not words:
            return sorted(c + " " for c in list(COMMANDS) if c.startswith(text))
        cmd = COMMANDS.get(ALIASES.get(words[0].lower(), words[0].lower()))
        if cmd is None or cmd.complete is None:
            return []
        try:
            opts = cmd.complete(self, words[1:], text)
        except Exception:
            return []
        return sorted(o for o in opts if o.startswith(text))

    def _prompt_interrupt(self) -> str:
        """Ctrl-C at the prompt: a driven motor is stopped (as inside a command), else a hint."""
        what = self.stop_after_interrupt()
        if what == NOT_DRIVEN:
            return "^C (type 'quit' to leave)"
        return f"^C: {what}; 'quit' leaves"

    def repl(self, history: Path | None = None) -> int:
        """The interactive loop (readline: completion and history)."""
        try:
            import readline
        except ImportError:                            # Windows without pyreadline
            readline = None
        if readline is not None:
            matches: list[str] = []

            def completer(text, state):
                nonlocal matches
                if state == 0:
                    buf = readline.get_line_buffer()[:readline.get_endidx()]
                    matches = self.complete(buf, text)
                return matches[state] if state < len(matches) else None

            readline.set_completer(completer)
            readline.set_completer_delims(" \t\n,")
            readline.parse_and_bind("tab: complete")
            if history is not None:
                try:
                    history.parent.mkdir(parents=True, exist_ok=True)
                    if history.exists():
                        readline.read_history_file(str(history))
                except OSError as e:
                    self.say(f"warning: history file {history} not usable: {e.strerror}")
                    history = None
                readline.set_history_length(2000)
        self.say("type 'help' for the commands, Tab completes, 'quit' leaves")
        try:
            while True:
                try:
                    with self._out_lock:
                        self._at_prompt = True
                    if self.pending_line is not None:      # typed during 'view': run it now
                        line, self.pending_line = self.pending_line, None
                        self.say(PROMPT + line)
                        if readline is not None:
                            readline.add_history(line)
                    else:
                        line = input(PROMPT)
                except EOFError:
                    self.say("")
                    break
                except KeyboardInterrupt:
                    if self.terminating:
                        break
                    self.say(self._prompt_interrupt())
                    continue
                finally:
                    with self._out_lock:
                        self._at_prompt = False
                try:
                    self.run_line(line)
                except Quit:
                    break
                except KeyboardInterrupt as e:
                    self.say(f"interrupted ({_interruption(e)}); {self.stop_after_interrupt()}")
                if self.terminating:
                    break
        finally:
            if readline is not None and history is not None:
                try:
                    readline.write_history_file(str(history))
                except OSError:
                    pass
        return 0




# ---------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------

def register(subparsers) -> None:
    p = subparsers.add_parser(
        "console", help="the bench console: speeds, gains, live plots, step tests, recording",
        description="Serial tuning console on any pyserial URL: /dev/ttyUSB0, COM5, or "
                    "socket://127.0.0.1:PORT of a running 'picdrive twin'.")
    p.add_argument("url", nargs="?", help="serial URL of the board or the twin (none: list the serial ports)")
    p.add_argument("--profile", help="local drive profile (name or path) to compare with the board's")
    p.add_argument("--run", metavar="SESSION.TXT",
                   help="run the commands of a file, then exit (non-zero on the first error)")
    p.add_argument("--out", default=".", help="folder for step plots and live PNGs (default: current folder)")
    p.add_argument("--strict", action="store_true",
                   help="refuse a board built from another profile than --profile (default: a warning)")
    p.add_argument("--history", help="history file (default: $PICDRIVE_HISTORY or "
                                     "$XDG_STATE_HOME/picdrive/console_history)")
    p.set_defaults(func=main)


def _connect_hint(url: str, e) -> str:
    """Why a connection failed, said accurately for a socket that answers but a board that does not."""
    from ..link.client import LinkTimeout
    if isinstance(e, LinkTimeout) and url.startswith("socket://"):
        return (f"the socket accepted the connection but no board answered the handshake: a picdrive twin "
                f"serves one client at a time, so another console or program is probably connected to it; "
                f"close that one (or start a second twin on another port) ({e})")
    return str(e)


def serial_ports_text() -> str:
    """What ``picdrive console`` without a URL prints: the serial ports pyserial finds, and how to
    connect."""
    from serial.tools import list_ports
    ports = sorted(list_ports.comports(), key=lambda p: p.device)
    lines = ["no URL given; serial ports found:" if ports else "no URL given, and no serial port found "
             "(is the USB-serial adapter plugged in, and are you allowed to open it? on Linux: the "
             "'dialout' group)"]
    for p in ports:
        what = ", ".join(x for x in (p.description if p.description != "n/a" else "", p.manufacturer or "",
                                     p.hwid if p.hwid != "n/a" else "") if x)
        lines.append(f"  {p.device}" + (f"  ({what})" if what else ""))
    lines.append("connect with: picdrive console " + (ports[0].device if ports else "/dev/ttyUSB0") +
                 "   (or socket://127.0.0.1:PORT of a running 'picdrive twin')")
    return "\n".join(lines)


def main(args) -> int:
    from ..link.client import LinkError
    if args.url is None:
        print(serial_ports_text())
        return 0
    profile = None
    if args.profile:
        from ..profile import load_profile
        profile = load_profile(args.profile)
    out = Path(args.out)
    if not out.is_dir():
        raise ConsoleError(f"--out {out}: no such folder; create it or choose another")
    script = read_script(args.run) if args.run else None     # before the board is touched
    if args.strict and profile is None:
        raise ConsoleError("--strict compares the board with your profile: give --profile P too")
    interactive = args.run is None
    con = Console(args.url, profile=profile, out_dir=out, interactive=interactive, strict=args.strict)
    try:
        con.connect()
    except LinkError as e:
        raise ConsoleError(f"cannot connect to {args.url}: {_connect_hint(args.url, e)}") from None
    # the terminal closed (SIGHUP) or the console killed (SIGTERM): stop the motor and keep the
    # recording, as 'quit' does, instead of dying with the motor driven until the watchdog trips
    before = {}
    try:
        before = {s: signal.signal(s, con.on_stop_signal) for s in STOP_SIGNALS}
    except ValueError:                      # not the main thread (embedded): the caller handles signals
        pass
    try:
        if args.run:
            return con.run_script(args.run, script)
        history = Path(args.history) if args.history else default_history_path()
        con.repl(history)
    except Terminated:
        pass
    finally:
        try:
            con.close()
        finally:
            for s, h in before.items():
                signal.signal(s, h)
    if con.terminating:
        con.say(f"console ended by {con.terminating}")
        return 128 + getattr(signal, con.terminating)
    return 0


# -- scope ----------------------------------------------------------------------
