"""picdrive.link: the host side of the serial link, over any pyserial URL.

``Link.open(url)`` opens a port with :func:`serial.serial_for_url` (``/dev/ttyUSB0``,
``COM5``, ``socket://host:port``, ``loop://``), handshakes (hello: protocol version, build
id, profile hash, table hash), reads the board's parameter table entry by entry
(param_info), checks that it hashes to what hello announced and that it agrees with this
host's protocol definition, and then offers the drive in engineering units::

    from picdrive.link.client import Link
    with Link.open("socket://127.0.0.1:5000") as link:
        link.set("rule1_kp", 0.05)              # V/(rad/s), range-checked here and on the board
        link.configure_telemetry(["speed", "setpoint"], decimation=1)
        link.set_speed(1500.0)                   # rpm; the sign is the direction
        link.start()
        data = link.read_samples(seconds=1.0)   # numpy structured array: index, t, speed, setpoint
        print(link.telemetry_stats.dropped)

A background thread reads and decodes frames (:class:`picdrive.link.codec.StreamDecoder`),
hands replies to the waiting command, queues telemetry samples and events.  Commands are
serialised (thread-safe), time out after ``timeout`` seconds and are retried with the same
SEQ (the board answers a retry from its reply store, never executing twice) up to
``retries`` times before :class:`LinkTimeout`.

Keep-alive contract: a keep-alive thread sends heartbeat often enough to feed the board's
link watchdog, but only while the application shows it is alive: while one of its threads is
inside a call into the link (a command, ``read_samples``, ``capture_read``...) or returned
from one, or called :meth:`Link.app_alive`, within the last ``app_timeout`` seconds (default
``APP_TIMEOUT_S`` = 2 s).  An application that hangs therefore stops feeding the watchdog, and
the board stops the motor ``app_timeout`` + ``link_timeout`` after its last sign of life; an
application that waits longer than ``app_timeout`` without calling the link must call
``app_alive()`` from its main loop.  ``app_timeout=None`` restores a keep-alive that feeds the
watchdog for as long as the process runs (the application then vouches for itself).

Errors: :class:`LinkError` (base of all of them), :class:`LinkTimeout` (no reply: the board
may nevertheless have executed the command; a reply that arrives later is reported by
:meth:`Link.late_replies`), :class:`NackError` (the board refused: command, code, reason),
:class:`BadCrcError` (a NackError: the board received the command corrupted on every try),
:class:`HandshakeMismatch` (the board's build is not what this host can talk to or was told
to expect), :class:`ParamError` (refused on the host before sending: unknown name, read-only,
out of range), :class:`LinkProtocolError` (a command that cannot be encoded or a reply that
cannot be decoded; also a :class:`picdrive.link.protocol.ProtocolError`).
"""
from __future__ import annotations

import collections
import dataclasses
import logging
import os
import select
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator, Sequence

import numpy as np

from . import codec
from . import protocol as P
from ..errors import PicdriveError

__all__ = ["Link", "LinkError", "LinkTimeout", "NackError", "BadCrcError", "HandshakeMismatch", "ParamError",
           "LinkProtocolError", "LateReply", "BoardInfo", "Status", "TelemetryStats", "TelemetryConfig",
           "CaptureResult", "compare_tables", "APP_TIMEOUT_S"]

log = logging.getLogger("picdrive.link")

APP_TIMEOUT_S = 2.0
"""Default ``app_timeout``: the keep-alive feeds the board's watchdog only while the application
called into the link within this many seconds (module docstring)."""


class LinkError(PicdriveError):
    """The link failed (port, transport, protocol)."""


class LinkTimeout(LinkError):
    """No reply after the bounded retries.  The command may still have reached the board and been
    executed (only its replies were lost): ``command``, ``seq``; a reply that arrives later is
    reported by :meth:`Link.late_replies`."""

    def __init__(self, message: str, command: str = "", seq: int | None = None):
        self.command = command
        self.seq = seq
        super().__init__(message)


class LinkProtocolError(LinkError, P.ProtocolError):
    """A command that cannot be encoded (bad arguments) or a reply that cannot be decoded."""


class NackError(LinkError):
    """The board refused a command.  ``command`` (name), ``code`` (:class:`~picdrive.link.protocol.Nack`),
    ``reason`` (text), ``detail`` (what was asked)."""

    def __init__(self, command: str, code: int, detail: str = ""):
        self.command = command
        try:
            self.code = P.Nack(code)
            self.reason = P.NACK_REASONS[self.code]
            name = self.code.name
        except ValueError:
            self.code, self.reason, name = code, f"unknown NACK code {code}", str(code)
        self.detail = detail
        super().__init__(f"board rejected {command}{'(' + detail + ')' if detail else ''}: {name}: {self.reason}")


class BadCrcError(NackError):
    """The board answered every try of a command with a BAD_CRC NACK (or some tries with it and the
    others not at all): the command reached the board corrupted and was not executed."""

    def __init__(self, command: str, bad_crc: int, tries: int, detail: str = ""):
        self.command, self.detail = command, detail
        self.code = P.Nack.BAD_CRC
        self.reason = P.NACK_REASONS[self.code]
        self.bad_crc, self.tries = bad_crc, tries
        silent = tries - bad_crc
        LinkError.__init__(
            self, f"the board received {command}{'(' + detail + ')' if detail else ''} corrupted: BAD_CRC NACK on "
                  f"{bad_crc} of {tries} tries{f' (no reply to the other {silent})' if silent else ''}; it was not "
                  "executed.  Bytes are corrupted on the way to the board: check the cable, its ground and "
                  "shielding, and that both ends use the same baud rate")


@dataclass(frozen=True)
class LateReply:
    """A reply that arrived after its command had raised LinkTimeout: the board did receive it
    (``acked``: executed; else refused with ``nack_code``)."""
    command: str
    seq: int
    acked: bool
    nack_code: int | None
    timed_out_at: float       # host time (time.monotonic) of the LinkTimeout
    arrived_at: float


class HandshakeMismatch(LinkError):
    """The board's protocol version or table differs from what this host expects.
    ``differences`` lists each difference."""

    def __init__(self, message: str, differences: Sequence[str] = ()):
        self.differences = list(differences)
        super().__init__(message)


class ParamError(LinkError, ValueError):
    """A parameter request refused on the host (unknown name, read-only, out of range)."""


@dataclass(frozen=True)
class BoardInfo:
    """What hello reports."""
    proto_version: tuple[int, int]
    build_id: int
    profile_hash: int
    table_hash: int
    n_entries: int
    max_payload: int
    capture_words: int
    sample_hz: int           # 0 = not stated by the build
    features: int | None = None   # hello's features byte (protocol.FEATURE_*); None: a 2.0 build, not stated

    @property
    def has_ident(self) -> bool | None:
        """The build has the identification mode (None: a build before protocol 2.1 does not say)."""
        return None if self.features is None else bool(self.features & P.FEATURE_IDENT)


@dataclass(frozen=True)
class Status:
    state: P.State | int
    fault: P.Fault | int
    capture_state: P.CaptureState | int
    telem_generation: int
    crc_errors: int
    rx_overflows: int
    telem_dropped: int
    uptime_ms: int


@dataclass
class TelemetryStats:
    frames: int = 0
    samples: int = 0
    dropped: int = 0          # samples missing from the board's counter sequence
    overflowed: int = 0       # samples discarded on the host (buffer full)
    stale_frames: int = 0     # frames of an older configuration


@dataclass(frozen=True)
class TelemetryConfig:
    generation: int
    signals: tuple[P.Entry, ...]
    decimation: int
    samples_per_frame: int
    payload_len: int
    sample_hz: int
    t0: float                 # host time of the configuration

    @property
    def rate_hz(self) -> float:
        """Samples per second (0 if the build does not state its sample rate)."""
        return self.sample_hz / self.decimation if self.sample_hz and self.decimation else 0.0


@dataclass
class CaptureResult:
    data: np.ndarray           # structured: index, t (s, 0 at the trigger), signals
    trigger_index: int
    decimation: int


def _state(v: int, enum_cls):
    try:
        return enum_cls(v)
    except ValueError:
        return v


def compare_tables(board: P.Table, host: Sequence[P.ParamDef]) -> list[str]:
    """Differences between a board's table and this host's static definition (names, ids,
    units, access, kind).  Scales, limits, defaults and C types are per build and not compared."""
    diffs = []
    hb = {d.id: d for d in host}
    bb = {e.id: e for e in board}
    for i in sorted(set(hb) | set(bb)):
        d, e = hb.get(i), bb.get(i)
        if e is None:
            diffs.append(f"id 0x{i:02x}: host expects {d.name!r}, board has no such entry")
        elif d is None:
            diffs.append(f"id 0x{i:02x}: board has {e.name!r} ({e.unit}), unknown to this host")
        else:
            for what, hv, bv in (("name", d.name, e.name), ("unit", d.unit, e.unit),
                                 ("writable", d.writable, e.writable), ("persisted", d.persisted, e.persisted),
                                 ("signal", d.signal, e.signal)):
                if hv != bv:
                    diffs.append(f"id 0x{i:02x} {d.name!r}: {what} is {bv!r} on the board, {hv!r} on this host")
    return diffs


def _waiter(port) -> Callable[[float], None]:
    """A function that waits (up to t seconds) until the port may have bytes to read."""
    fd = None
    for get in (lambda: port.fileno(), lambda: port._socket.fileno()):  # posix serial, socket://
        try:
            fd = get()
            break
        except Exception:
            continue
    if fd is not None:
        def wait(t, fd=fd):
            try:
                select.select([fd], [], [], t)
            except (OSError, ValueError):
                time.sleep(t)
        return wait
    return lambda t: time.sleep(min(t, 0.001))


class Link:
    """A connection to one board.  Build with :meth:`open`."""

    # ---------------------------------------------------------------- opening
    @classmethod
    def open(cls, url: str, *, baudrate: int = 115200, timeout: float = 0.25, retries: int = 3,
             handshake: bool = True, keepalive: bool = True, expect_table_hash: int | None = None,
             expect_profile_hash: int | None = None, expect_build_id: int | None = None,
             app_timeout: float | None = APP_TIMEOUT_S, **serial_kwargs: Any) -> "Link":
        """Open ``url`` and handshake.

        Parameters
        ----------
        url : str
            Any pyserial URL: ``/dev/ttyUSB0``, ``COM5``, ``socket://host:port``, ``loop://``.
        baudrate : int
            Line rate, bit/s (the profile's ``uart.baud``).
        timeout : float
            Seconds per try of a command.
        retries : int
            Extra tries after the first.
        handshake : bool
            Say hello and read the parameter table (needed for everything in engineering units).
        keepalive : bool
            Start the heartbeat thread (:meth:`start_keepalive`).
        expect_table_hash, expect_profile_hash, expect_build_id : int, optional
            Refuse (:class:`HandshakeMismatch`) a board of another build or profile (e.g. the one
            a firmware folder was generated for).
        app_timeout : float or None
            The keep-alive contract, s (module docstring; None: feed while the process runs).

        Returns
        -------
        Link
            The open link; a context manager (closing it stops the keep-alive).

        Raises
        ------
        LinkError
            The port cannot be opened, or the handshake fails (:class:`LinkTimeout`,
            :class:`HandshakeMismatch`...).
        """
        import serial
        try:
            port = serial.serial_for_url(url, baudrate=baudrate, timeout=0, write_timeout=2.0, **serial_kwargs)
        except (serial.SerialException, OSError, ValueError) as e:
            raise LinkError(f"cannot open {url!r}: {e}; check the port name or URL (e.g. /dev/ttyUSB0, COM5, "
                            "socket://127.0.0.1:5000 for a running 'picdrive twin')") from None
        link = cls(port, url=url, timeout=timeout, retries=retries, app_timeout=app_timeout)
        try:
            if handshake:
                link.handshake(expect_table_hash=expect_table_hash, expect_profile_hash=expect_profile_hash,
                               expect_build_id=expect_build_id)
            if keepalive:
                link.start_keepalive()
        except BaseException:
            link.close()
            raise
        return link

    HOST_GAP_S = P.HOST_GAP_MS / 1000.0
    """Idle time after which the host abandons a partial frame (see protocol.HOST_GAP_MS)."""

    def __init__(self, port, *, url: str = "", timeout: float = 0.25, retries: int = 3,
                 telemetry_buffer: int = 1_000_000, app_timeout: float | None = APP_TIMEOUT_S):
        if timeout <= 0 or retries < 0:
            raise ValueError("timeout must be > 0 and retries >= 0")
        if app_timeout is not None and not app_timeout > 0:
            raise ValueError("app_timeout must be > 0 seconds (or None)")
        self.app_timeout = app_timeout
        self._app_calls = 0                     # application calls into the link in progress
        self._app_last = time.monotonic()       # when the application last showed it is alive
        self._timed_out: collections.OrderedDict[int, tuple[str, int, float]] = collections.OrderedDict()
        self._late: collections.deque = collections.deque(maxlen=1000)
        self.url = url
        self.timeout = float(timeout)
        self.retries = int(retries)
        self._port = port
        self._wait = _waiter(port)
        self._dec = codec.StreamDecoder()
        self._rx_tail = b""
        self._req_lock = threading.RLock()
        self._cv = threading.Condition()
        self._seq = os.urandom(1)[0]            # a new session does not reuse the last SEQ
        self._pending: tuple[int, int, Callable | None] | None = None
        self._reply: codec.Frame | None = None
        self._bad_crc = False
        self._dead: LinkError | None = None
        self._closing = False
        self._last_tx = 0.0
        self.info: BoardInfo | None = None
        self.table: P.Table | None = None
        self._table_stale = False
        # telemetry
        self._tm: TelemetryConfig | None = None
        self._tm_chunks: collections.deque = collections.deque()
        self._tm_buffered = 0
        self._tm_next = 0
        self._tm_max = int(telemetry_buffer)
        self.telemetry_stats = TelemetryStats()
        # events
        self._events: collections.deque = collections.deque(maxlen=1000)
        self.on_event: Callable[[float, P.Event | int, int], None] | None = None
        self.stats = {"tx_bytes": 0, "rx_bytes": 0, "requests": 0, "retries": 0, "stale_replies": 0,
                      "bad_crc_nacks": 0, "keepalive_errors": 0, "crc_errors": 0, "late_replies": 0,
                      "keepalive_withheld": 0}
        self.last_keepalive_error: LinkError | None = None
        self._keepalive: threading.Thread | None = None
        self._keepalive_period = 0.1
        self._keepalive_auto = True
        self._reader = threading.Thread(target=self._read_loop, name=f"picdrive-link-reader {url}", daemon=True)
        self._reader.start()

    # ---------------------------------------------------------------- closing
    def close(self) -> None:
        """Stop the threads and close the port (idempotent).  The board keeps its state; if it
        was running, its watchdog stops it after link_timeout."""
        if self._closing:
            return
        self._closing = True
        with self._cv:
            self._cv.notify_all()
        for t in (self._keepalive, self._reader):
            if t is not None and t is not threading.current_thread():
                t.join(2.0)
        try:
            self._port.close()
        except Exception:
            pass

    def __enter__(self) -> "Link":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        return self._closing

    # ---------------------------------------------------------------- reader
    def _read_loop(self) -> None:
        last_rx = time.monotonic()
        gap = self.HOST_GAP_S
        while not self._closing:
            try:
                data = self._port.read(4096)
            except Exception as e:                       # port gone
                self._die(LinkError(f"serial port {self.url!r} failed: {e}{self._peer_notice()}"))
                return
            now = time.monotonic()
            if data:
                self._rx_tail = (self._rx_tail + data)[-self.NOTICE_MAX:]
                self.stats["rx_bytes"] += len(data)
                frames = self._dec.feed(data)
                last_rx = now
            else:
                frames = self._dec.gap() if self._dec.partial and now - last_rx > gap else []
                if not frames:
                    self._wait(0.005)
            self.stats["crc_errors"] = self._dec.crc_errors
            for f in frames:
                try:
                    self._route(f, now)
                except Exception as e:                   # a frame we cannot use must not kill the reader
                    self.stats.setdefault("bad_frames", 0)
                    self.stats["bad_frames"] += 1
                    self.last_frame_error = e

    def _late_reply(self, f: codec.Frame, late: tuple[str, int, float], now: float) -> None:
        """A reply to a command that already raised LinkTimeout: the board did receive it."""
        cmd, _, t_out = late
        code = None
        if f.is_nack and len(f.payload) == 2:
            code = f.payload[1]
        r = LateReply(cmd, f.seq, bool(f.is_ack), code, t_out, now)
        self._late.append(r)
        self.stats["late_replies"] += 1
        what = "executed it" if r.acked else f"refused it (NACK {code})"
        log.warning("late reply: %s (SEQ %d) timed out %.3f s ago, but the board received it and %s",
                    cmd, f.seq, now - t_out, what)

    def late_replies(self) -> list[LateReply]:
        """Replies that arrived after their command raised LinkTimeout, since the last call: each
        says the board did receive that command (and whether it executed it)."""
        out = []
        while self._late:
            out.append(self._late.popleft())
        return out

    NOTICE_MAX = 512
    """The last bytes received are kept (this many) for :meth:`_peer_notice`."""

    def _peer_notice(self) -> str:
        """A text line the other end sent before closing (the twin says why it refused or dropped
        this client: ``picdrive twin: ...``), quoted for the error; "" if there is none."""
        k = self._rx_tail.rfind(b"picdrive twin: ")
        if k < 0:
            return ""
        line = self._rx_tail[k:].split(b"\n")[0].decode("ascii", "replace")
        return f"; the other end said: {line}"

    def _die(self, err: LinkError) -> None:
        with self._cv:
            self._dead = err
            self._cv.notify_all()

    def _route(self, f: codec.Frame, now: float) -> None:
        if f.is_reply:
            with self._cv:
                p = self._pending
                if f.is_nack and len(f.payload) == 2 and f.payload[1] == P.Nack.BAD_CRC:
                    self.stats["bad_crc_nacks"] += 1
                    if p is not None and self._reply is None:
                        self._bad_crc = True
                        self._cv.notify_all()
                    return
                if p is None or self._reply is not None or f.seq != p[0] or f.command_code != p[1]:
                    late = self._timed_out.get(f.seq)
                    if late is not None and late[1] == f.command_code:
                        del self._timed_out[f.seq]
                        self._late_reply(f, late, now)
                    else:
                        self.stats["stale_replies"] += 1
                    return
                if p[2] is not None and f.is_ack:
                    p[2](f)                               # runs before any frame that follows the reply
                self._reply = f
                self._cv.notify_all()
        elif f.type == P.MSG_TELEMETRY:
            self._on_telemetry(f, now)
        elif f.type == P.MSG_EVENT:
            ev, code = codec.decode_event(f.payload)
            ev = _state(ev, P.Event)
            if ev == P.Event.BOOT:
                self._table_stale = True
            self._events.append((now, ev, code))
            cb = self.on_event
            if cb is not None:
                try:
                    cb(now, ev, code)
                except Exception:
                    pass

    # ---------------------------------------------------------------- requests
    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFF
        return self._seq

    def _write(self, data: bytes) -> None:
        try:
            self._port.write(data)
        except Exception as e:
            self._die(LinkError(f"writing to {self.url!r} failed: {e}"))
            raise self._dead from None
        self.stats["tx_bytes"] += len(data)
        self._last_tx = time.monotonic()

    def request(self, cmd: str, args: dict | None = None, *, detail: str = "",
                on_ack: Callable[[codec.Frame], None] | None = None, timeout: float | None = None) -> dict:
        """Send a command and return its decoded ACK fields.  NACK -> NackError; no reply after
        ``1 + retries`` tries of ``timeout`` s (default: the link's) -> LinkTimeout.  Thread-safe."""
        if threading.current_thread() is self._keepalive:
            return self._request(cmd, args, detail=detail, on_ack=on_ack, timeout=timeout)
        with self._app_call():
            return self._request(cmd, args, detail=detail, on_ack=on_ack, timeout=timeout)

    def _app_call(self):
        """Context of an application call into the link (the keep-alive contract)."""
        link = self

        class _Ctx:
            def __enter__(self):
                with link._cv:
                    link._app_calls += 1

            def __exit__(self, *exc):
                with link._cv:
                    link._app_calls -= 1
                    link._app_last = time.monotonic()
        return _Ctx()

    def app_alive(self) -> None:
        """Tell the keep-alive that the application is alive (the keep-alive contract: call it
        from the application's main loop when it goes longer than ``app_timeout`` without
        calling the link)."""
        with self._cv:
            self._app_last = time.monotonic()
            self._cv.notify_all()

    def _app_is_alive(self, now: float) -> bool:
        return self.app_timeout is None or self._app_calls > 0 or now - self._app_last <= self.app_timeout

    def _request(self, cmd: str, args: dict | None, *, detail: str, on_ack, timeout: float | None) -> dict:
        try_s = self.timeout if timeout is None else float(timeout)
        c = P.COMMAND_BY_NAME.get(cmd)
        if c is None:
            raise LinkProtocolError(f"unknown command {cmd!r}; known: {', '.join(P.COMMAND_BY_NAME)}")
        try:
            payload = codec.command_payload(c, args)
        except P.ProtocolError as e:
            raise LinkProtocolError(str(e)) from None
        with self._req_lock:
            if self._closing:
                raise LinkError("the link is closed")
            if self._dead is not None:
                raise self._dead
            seq = self._next_seq()
            frame = codec.encode_frame(c.code, seq, payload, lead=True)
            self.stats["requests"] += 1
            tries = bad_crc = 0
            while True:
                with self._cv:
                    self._pending = (seq, c.code, on_ack)
                    self._reply = None
                    self._bad_crc = False
                self._write(frame)
                tries += 1
                deadline = time.monotonic() + try_s
                with self._cv:
                    while self._reply is None and not self._bad_crc and self._dead is None and not self._closing:
                        left = deadline - time.monotonic()
                        if left <= 0:
                            break
                        self._cv.wait(left)
                    reply, self._pending = self._reply, None
                    bad_crc += reply is None and self._bad_crc
                    dead = self._dead
                if reply is not None:
                    break
                if dead is not None:
                    raise dead
                if self._closing:
                    raise LinkError("the link was closed while waiting for a reply")
                if tries > self.retries:
                    if bad_crc:
                        raise BadCrcError(cmd, bad_crc, tries, detail)
                    with self._cv:
                        # remembered, so that a reply arriving later is reported, not dropped
                        self._timed_out[seq] = (cmd, c.code, time.monotonic())
                        while len(self._timed_out) > 128:
                            self._timed_out.popitem(last=False)
                    raise LinkTimeout(
                        f"no reply to {cmd}{'(' + detail + ')' if detail else ''} (SEQ {seq}) from "
                        f"{self.url or 'the board'} after {tries} tries of {try_s:g} s: the board may nevertheless "
                        "have received and executed it (a lost reply looks the same), so read its state (status) "
                        "before repeating it; a reply that still arrives is reported by late_replies().  Check the "
                        "cable or URL, the baud rate, and that the board (or twin) is running", cmd, seq)
                self.stats["retries"] += 1
        try:
            if reply.is_nack:
                _, code = codec.decode_nack(reply.payload)
                raise NackError(cmd, code, detail)
            return codec.decode_reply(c, reply.payload)
        except P.ProtocolError as e:
            raise LinkProtocolError(f"the board's reply to {cmd} cannot be decoded: {e}") from None

    # ---------------------------------------------------------------- handshake
    def hello(self) -> BoardInfo:
        d = self.request("hello")
        return BoardInfo((d["proto_major"], d["proto_minor"]), d["build_id"], d["profile_hash"], d["table_hash"],
                         d["n_entries"], d["max_payload"], d["capture_words"], d["sample_hz"],
                         d["features"][0] if d["features"] else None)

    def read_table(self, n_entries: int) -> P.Table:
        """The board's table, read with param_info (host docs and enum names attached)."""
        entries = []
        for i in range(n_entries):
            box: dict[str, bytes] = {}
            self.request("param_info", {"index": i}, detail=f"index {i}",
                         on_ack=lambda f, box=box: box.setdefault("payload", f.payload))
            try:
                entries.append(codec.decode_param_info(box["payload"]))
            except P.ProtocolError as e:
                raise HandshakeMismatch(f"cannot read the board's table entry {i}: {e}", [str(e)]) from None
        entries.sort(key=lambda e: e.id)
        rules = sum(1 for e in entries if e.name.endswith("_kp") and e.name.startswith("rule"))
        defs = {d.name: d for d in P.static_defs(max(1, min(8, rules)))}
        entries = [dataclasses.replace(e, doc=defs[e.name].doc, values=defs[e.name].values) if e.name in defs else e
                   for e in entries]
        return P.Table(tuple(entries), rules)

    def handshake(self, *, expect_table_hash: int | None = None, expect_profile_hash: int | None = None,
                  expect_build_id: int | None = None) -> BoardInfo:
        """hello + the table; raises HandshakeMismatch naming every difference."""
        info = self.hello()
        if info.proto_version[0] != P.PROTOCOL_VERSION[0]:
            raise HandshakeMismatch(
                f"the board speaks protocol {info.proto_version[0]}.{info.proto_version[1]}, this host "
                f"{P.PROTOCOL_VERSION[0]}.{P.PROTOCOL_VERSION[1]}: use the picdrive that generated its firmware, "
                "or regenerate and flash the firmware", [f"protocol major {info.proto_version[0]} != "
                                                         f"{P.PROTOCOL_VERSION[0]}"])
        if info.max_payload > P.MAX_PAYLOAD:
            raise HandshakeMismatch(f"the board sends payloads up to {info.max_payload} B, this host accepts "
                                    f"{P.MAX_PAYLOAD} B", ["max_payload"])
        table = self.read_table(info.n_entries)
        diffs = []
        if table.hash != info.table_hash:
            diffs.append(f"the entries read with param_info hash to 0x{table.hash:08x}, hello announced "
                         f"0x{info.table_hash:08x}")
        rules = table.rules
        if not 1 <= rules <= 8:
            diffs.append(f"the board's table has {rules} rules")
            host_defs = P.static_defs(1)
        else:
            host_defs = P.static_defs(rules)
        diffs += compare_tables(table, host_defs)
        if diffs:
            raise HandshakeMismatch(
                "the board's parameter table does not match this host's protocol definition, so values would be "
                "misread: " + "; ".join(diffs[:6]) + ("; ..." if len(diffs) > 6 else "")
                + ". Use the picdrive version that generated the firmware, or regenerate and flash it.", diffs)
        want = []
        for what, exp, got in (("table hash", expect_table_hash, info.table_hash),
                               ("profile hash", expect_profile_hash, info.profile_hash),
                               ("build id", expect_build_id, info.build_id)):
            if exp is not None and exp != got:
                want.append(f"{what} 0x{got:08x}, expected 0x{exp:08x}")
        if want:
            raise HandshakeMismatch("the board runs another build than expected: " + "; ".join(want)
                                    + ". Flash the firmware you generated, or open without expecting it.", want)
        self.info, self.table, self._table_stale = info, table, False
        return info

    def _check_table(self) -> P.Table:
        """The table, re-validated after the board rebooted (BOOT event)."""
        if self.table is None:
            raise LinkError("no parameter table: the link was opened without handshake; call handshake() first")
        if self._table_stale:
            info = self.hello()
            if info.table_hash != self.table.hash or info.build_id != self.info.build_id:
                raise HandshakeMismatch(
                    f"the board rebooted into another build (table hash 0x{self.table.hash:08x} -> "
                    f"0x{info.table_hash:08x}, build id 0x{self.info.build_id:08x} -> 0x{info.build_id:08x}); "
                    "reopen the link", ["table hash after reboot"])
            self._table_stale = False
            self._tm = None                  # the board restarted: telemetry is off
        return self.table

    # ---------------------------------------------------------------- parameters
    def param(self, name: str) -> P.Entry:
        """The table entry of a parameter or signal (unit, scale, limits, access)."""
        t = self._check_table()
        if name not in t:
            raise ParamError(f"no parameter or signal {name!r} on this board; known: {', '.join(e.name for e in t)}")
        return t[name]

    def params(self) -> tuple[P.Entry, ...]:
        return self._check_table().entries

    @staticmethod
    def _eng(e: P.Entry, raw: int):
        if e.values or e.unit in ("enum", "code"):
            return int(raw)
        return raw * e.scale

    def get_raw(self, *names: str) -> dict[str, int]:
        es = [self.param(n) for n in names]
        out = {}
        for i in range(0, len(es), P.PARAM_GET_MAX):
            part = es[i:i + P.PARAM_GET_MAX]
            vals = self.request("param_get", {"ids": [e.id for e in part]},
                                detail=", ".join(e.name for e in part))["values"]
            for e, v in zip(part, vals):
                out[e.name] = v
        return out

    def get(self, name: str):
        """Engineering value (raw x scale; int for enums and codes)."""
        return self.get_many(name)[name]

    def get_many(self, *names: str) -> dict[str, Any]:
        raw = self.get_raw(*names)
        return {n: self._eng(self.param(n), v) for n, v in raw.items()}

    def to_raw(self, name: str, value) -> int:
        """Raw value of an engineering value, checked against the board's limits (ParamError)."""
        e = self.param(name)
        if e.values and isinstance(value, str):
            if value not in e.values:
                raise ParamError(f"{name} = {value!r}: expected one of {', '.join(e.values)}")
            raw = e.values.index(value)
        else:
            try:
                raw = e.to_raw(value) if not (e.values or e.unit in ("enum", "code")) else int(value)
            except (P.ProtocolError, TypeError, ValueError) as err:
                raise ParamError(str(err)) from None
        if not e.min_raw <= raw <= e.max_raw:
            shown = f"{value:g}" if isinstance(value, (int, float)) and not isinstance(value, bool) else repr(value)
            raise ParamError(f"{name} = {shown} {e.unit} is outside the board's range "
                             f"[{e.min_value:.6g}, {e.max_value:.6g}] {e.unit} (raw {e.min_raw}..{e.max_raw}, "
                             f"1 count = {e.scale:.6g} {e.unit})")
        return raw

    def set(self, name: str, value) -> Any:
        """Write a parameter in engineering units.

        Parameters
        ----------
        name : str
            A writable parameter of the board's table (``rule1_kp``, ``u_max``...).
        value : float
            In the parameter's unit (:attr:`picdrive.link.protocol.Entry.unit`: V/(rad/s), V,
            rpm, A, ms...).

        Returns
        -------
        float
            The value the board stored, same unit (after rounding to its raw resolution).
        """
        e = self.param(name)
        if not e.writable:
            raise ParamError(f"{name} is read-only ({'a telemetry signal' if e.signal else 'fixed by the build'})")
        return self._eng(e, self.set_raw(name, self.to_raw(name, value)))

    def set_raw(self, name: str, raw: int, *, check: bool = True) -> int:
        """Write a raw value.  ``check=False`` skips the host-side checks (the board still enforces
        them: useful to test the board)."""
        e = self.param(name)
        if check:
            if not e.writable:
                raise ParamError(f"{name} is read-only")
            if not e.min_raw <= raw <= e.max_raw:
                raise ParamError(f"{name}: raw {raw} is outside [{e.min_raw}, {e.max_raw}]")
        stored = self.request("param_set", {"id": e.id, "value": int(raw)}, detail=f"{name}={raw}")["value"]
        if name == "link_timeout" and self._keepalive is not None and self._keepalive_auto:
            # the board's watchdog runs on the new timeout from now: re-time the heartbeat
            self._keepalive_period = self._auto_keepalive_period(stored * e.scale)
            with self._cv:
                self._cv.notify_all()
        return stored

    # ---------------------------------------------------------------- drive
    def set_speed(self, rpm: float) -> float:
        """Set the speed setpoint.

        Parameters
        ----------
        rpm : float
            Mechanical speed, rpm (signed: the sign is the direction).

        Returns
        -------
        float
            What the board stored, rpm.
        """
        raw = self.to_raw("speed_setpoint", rpm)
        return self._eng(self.param("speed_setpoint"),
                         self.request("set_speed", {"value": raw}, detail=f"{rpm:g} rpm")["value"])

    def start(self) -> None:
        self._check_table()
        self.request("start")

    def stop(self) -> None:
        self.request("stop")

    def brake(self) -> None:
        self.request("brake")

    def fault_clear(self) -> None:
        self.request("fault_clear")

    def select_controller(self, controller: str | int) -> str:
        """'pid' (rule 1 only) or 'fuzzy' (all rules blended); returns the name stored."""
        e = self.param("controller")
        raw = self.to_raw("controller", controller)
        got = self.request("select_controller", {"controller": raw}, detail=str(controller))["controller"]
        return e.values[got] if got < len(e.values) else str(got)

    def heartbeat(self) -> None:
        self.request("heartbeat")

    def status(self) -> Status:
        d = self.request("status")
        return Status(_state(d["state"], P.State), _state(d["fault"], P.Fault),
                      _state(d["capture_state"], P.CaptureState), d["telem_generation"], d["crc_errors"],
                      d["rx_overflows"], d["telem_dropped"], d["uptime_ms"])

    def save_eeprom(self) -> None:
        """Save the persisted parameters to the board's EEPROM (motor stopped)."""
        self._check_table()
        # a PIC18 writes an EEPROM byte in about 4 ms: ~0.2 s for the image, so wait longer; a retry
        # is answered from the reply store, never written twice
        self.request("eeprom_save", timeout=max(self.timeout, 1.0))

    def load_eeprom(self) -> None:
        """Reload the persisted parameters from EEPROM (motor stopped); a bad image is refused
        (NackError EEPROM_ERROR) and changes nothing."""
        self._check_table()
        self.request("eeprom_load", timeout=max(self.timeout, 1.0))

    def events(self) -> list[tuple[float, P.Event | int, int]]:
        """Events received since the last call: (host time, event, code)."""
        out = []
        while self._events:
            out.append(self._events.popleft())
        return out

    # ---------------------------------------------------------------- keep-alive
    def start_keepalive(self, period_s: float | None = None) -> None:
        """Send heartbeat whenever nothing was sent for ``period_s`` (default: a quarter of the
        board's link_timeout)."""
        if self._keepalive is not None:
            return
        self._keepalive_auto = period_s is None
        if period_s is None:
            try:
                period_s = self._auto_keepalive_period(self.get("link_timeout"))
            except LinkError:
                period_s = 0.1
        self._keepalive_period = min(1.0, max(0.005, period_s))
        self._keepalive = threading.Thread(target=self._keepalive_loop,
                                           name=f"picdrive-link-keepalive {self.url}", daemon=True)
        self._keepalive.start()

    @staticmethod
    def _auto_keepalive_period(link_timeout_ms: float) -> float:
        """A quarter of the board's link timeout, within [5 ms, 1 s]."""
        return min(1.0, max(0.005, link_timeout_ms / 1000.0 / 4.0))

    @property
    def alive(self) -> bool:
        """True while the link is open and its reader has not given up on the port."""
        return not self._closing and self._dead is None

    def _keepalive_loop(self) -> None:
        withheld = False
        while not self._closing and self._dead is None:
            period = self._keepalive_period
            now = time.monotonic()
            left = self._last_tx + period - now
            if left > 0:
                with self._cv:
                    self._cv.wait(left)
                continue
            if not self._app_is_alive(now):
                # the application has not shown life within app_timeout: no heartbeat, so the
                # board's watchdog stops the motor as it would if the host had gone
                if not withheld:
                    withheld = True
                    self.stats["keepalive_withheld"] += 1
                    log.warning("keep-alive withheld: the application has not called into the link for %.2f s "
                                "(app_timeout %.2f s); the board's watchdog will stop the motor",
                                now - self._app_last, self.app_timeout)
                with self._cv:
                    self._cv.wait(period)
                continue
            withheld = False
            try:
                self.request("heartbeat")
            except LinkError as e:
                self.stats["keepalive_errors"] += 1
                self.last_keepalive_error = e
                time.sleep(period)

    # ---------------------------------------------------------------- telemetry
    def configure_telemetry(self, signals: Iterable[str] = P.DEFAULT_TELEMETRY_SIGNALS, *, decimation: int = 1,
                            samples_per_frame: int | None = None) -> TelemetryConfig:
        """Stream telemetry signals; clears the sample buffer.

        Parameters
        ----------
        signals : iterable of str
            Telemetry signals of the board's table (``speed`` rpm, ``current`` A, ``voltage`` V...).
        decimation : int
            Send every ``decimation``-th speed-loop sample (1..65535).
        samples_per_frame : int, optional
            Samples per frame (default: as many as fit, at most 4).

        Returns
        -------
        TelemetryConfig
            The signals in frame order, the decimation, samples per frame, the board's
            speed-loop rate ``sample_hz`` and the telemetry rate ``rate_hz``, Hz.
        """
        t = self._check_table()
        names = list(signals)
        ents = [self.param(n) for n in names]
        for e in ents:
            if not e.signal:
                raise ParamError(f"{e.name} is a parameter, not a telemetry signal; signals: "
                                 f"{', '.join(s.name for s in t.signals)}")
        mask = t.signal_mask(names)
        ordered = t.signals_in_mask(mask)
        fit = (P.MAX_PAYLOAD - P.TELEMETRY_HEADER_BYTES) // (2 * len(ordered)) if ordered else 0
        spf = min(P.DEFAULT_SAMPLES_PER_FRAME, fit) if samples_per_frame is None else int(samples_per_frame)
        if not 1 <= decimation <= 65535:
            raise ParamError(f"decimation = {decimation}: expected 1..65535 (use stop_telemetry() to stop)")
        if not ordered or not 1 <= spf <= fit:
            raise ParamError(f"{len(ordered)} signals x {spf} samples per frame do not fit a frame; at most "
                             f"{fit} samples per frame for {len(ordered)} signals")
        sample_hz = self.info.sample_hz if self.info else 0

        def apply(f: codec.Frame, ordered=ordered):        # in the reader, before the first new frame
            r = codec.decode_reply("telem_config", f.payload)
            with self._cv:
                self._tm = TelemetryConfig(r["generation"], ordered, decimation, spf, r["payload_len"], sample_hz,
                                           time.monotonic())
                self._tm_chunks.clear()
                self._tm_buffered = 0
                self._tm_next = 0
                self.telemetry_stats = TelemetryStats()

        self.request("telem_config", {"mask": mask, "decimation": decimation, "samples_per_frame": spf},
                     detail=",".join(names), on_ack=apply)
        return self._tm

    def stop_telemetry(self) -> None:
        self.request("telem_config", {"mask": 0, "decimation": 0, "samples_per_frame": 0})
        with self._cv:
            self._tm = None

    @property
    def telemetry(self) -> TelemetryConfig | None:
        return self._tm

    def _on_telemetry(self, f: codec.Frame, now: float) -> None:
        with self._cv:
            tm = self._tm
            if tm is None or f.seq != tm.generation or len(f.payload) != tm.payload_len:
                self.telemetry_stats.stale_frames += 1
                return
            counter, vals = codec.decode_telemetry(f.payload, len(tm.signals))
            gap = (counter - self._tm_next) & 0xFFFF
            idx = self._tm_next + gap
            st = self.telemetry_stats
            st.frames += 1
            st.samples += len(vals)
            st.dropped += gap
            self._tm_next = idx + len(vals)
            self._tm_chunks.append((idx, vals, now))
            self._tm_buffered += len(vals)
            while self._tm_buffered > self._tm_max:
                _, old, _ = self._tm_chunks.popleft()
                self._tm_buffered -= len(old)
                st.overflowed += len(old)
            self._cv.notify_all()

    def flush_samples(self) -> None:
        """Discard the buffered telemetry samples."""
        with self._cv:
            self._tm_chunks.clear()
            self._tm_buffered = 0

    def _dtype(self, signals: Sequence[P.Entry]) -> np.dtype:
        fields = [("index", np.int64), ("t", np.float64)]
        for e in signals:
            fields.append((e.name, np.int32 if (e.values or e.unit in ("enum", "code")) else np.float64))
        return np.dtype(fields)

    def _to_records(self, signals, idx: np.ndarray, raw: np.ndarray, t: np.ndarray) -> np.ndarray:
        out = np.empty(len(idx), dtype=self._dtype(signals))
        out["index"], out["t"] = idx, t
        for j, e in enumerate(signals):
            col = raw[:, j].astype(np.int64)
            if e.ctype == "uint16":
                col &= 0xFFFF
            out[e.name] = col if out.dtype[e.name].kind == "i" else col * e.scale
        return out

    def read_samples(self, n: int | None = None, *, seconds: float | None = None,
                     timeout: float | None = None) -> np.ndarray:
        """Telemetry samples received since :meth:`configure_telemetry`.

        Parameters
        ----------
        n : int, optional
            The oldest n buffered samples (waits for them; :class:`LinkTimeout` after ``timeout``).
        seconds : float, optional
            Wait that long (s, host time), then everything buffered.  Give ``n`` or ``seconds``.
        timeout : float, optional
            With ``n``: the longest wait, s.

        Returns
        -------
        numpy.ndarray
            A structured array: ``index`` (sample number since configure_telemetry; gaps are
            dropped samples), ``t`` (s since the configuration: index x decimation / sample_hz,
            or host arrival time if the build does not state its rate) and one field per signal
            in engineering units (rpm, A, V...).
        """
        with self._app_call():                 # waiting here is the application being alive
            return self._read_samples(n, seconds, timeout)

    def _read_samples(self, n, seconds, timeout) -> np.ndarray:
        tm = self._tm
        if tm is None:
            raise LinkError("telemetry is not configured: call configure_telemetry() first")
        if (n is None) == (seconds is None):
            raise ValueError("give either n or seconds")
        with self._cv:
            if seconds is not None:
                end = time.monotonic() + seconds
                while not self._closing and time.monotonic() < end:
                    self._cv.wait(end - time.monotonic())
                take = self._tm_buffered
            else:
                if timeout is None:
                    timeout = 2.0 + (n / tm.rate_hz * 2.0 if tm.rate_hz else 5.0)
                end = time.monotonic() + timeout
                while self._tm_buffered < n:
                    left = end - time.monotonic()
                    if left <= 0 or self._closing or self._dead is not None:
                        raise LinkTimeout(f"{self._tm_buffered} of {n} telemetry samples arrived in {timeout:g} s "
                                          f"(configured rate {tm.rate_hz:g} Hz; dropped so far "
                                          f"{self.telemetry_stats.dropped})")
                    self._cv.wait(left)
                take = n
            idx, raw, host_t = [], [], []
            while take > 0 and self._tm_chunks:
                i0, vals, t_host = self._tm_chunks[0]
                k = min(take, len(vals))
                idx.append(np.arange(i0, i0 + k, dtype=np.int64))
                raw.append(vals[:k])
                host_t.append(np.full(k, t_host - tm.t0))
                if k == len(vals):
                    self._tm_chunks.popleft()
                else:
                    self._tm_chunks[0] = (i0 + k, vals[k:], t_host)
                self._tm_buffered -= k
                take -= k
        if not idx:
            return np.empty(0, dtype=self._dtype(tm.signals))
        idx_a = np.concatenate(idx)
        t = idx_a * (tm.decimation / tm.sample_hz) if tm.sample_hz else np.concatenate(host_t)
        return self._to_records(tm.signals, idx_a, np.concatenate(raw), t)

    def samples(self, *, timeout: float = 1.0) -> Iterator[np.void]:
        """Iterate over telemetry samples as they arrive (stops after ``timeout`` s without any)."""
        while True:
            try:
                rec = self.read_samples(1, timeout=timeout)
            except LinkTimeout:
                return
            yield rec[0]

    # ---------------------------------------------------------------- capture
    def capture_arm(self, signals: Iterable[str], n_samples: int, *, pre_trigger: int = 0,
                    trigger: str | P.Trigger = "immediate", threshold: float | None = None,
                    decimation: int = 1) -> None:
        """Arm a capture on the board: ``n_samples`` samples of ``signals``, ``pre_trigger`` of
        them before the trigger ('immediate', 'setpoint_change', 'speed_rising',
        'speed_falling'; speed triggers need ``threshold`` in rpm)."""
        t = self._check_table()
        names = list(signals)
        for n in names:
            if not self.param(n).signal:
                raise ParamError(f"{n} is not a signal")
        mask = t.signal_mask(names)
        nsig = len(t.signals_in_mask(mask))
        trig = P.Trigger[trigger.upper()] if isinstance(trigger, str) else P.Trigger(trigger)
        cap = self.info.capture_words if self.info else 0
        if n_samples < 1 or n_samples * nsig > cap:
            raise ParamError(f"{n_samples} samples x {nsig} signals need {n_samples * nsig} words; the board's "
                             f"capture buffer holds {cap} (at most {cap // max(1, nsig)} samples of {nsig} signals)")
        if not 0 <= pre_trigger < n_samples or (trig == P.Trigger.IMMEDIATE and pre_trigger):
            raise ParamError(f"pre_trigger = {pre_trigger}: expected 0..{n_samples - 1} (0 for an immediate trigger)")
        thr = 0
        if trig in (P.Trigger.SPEED_RISING, P.Trigger.SPEED_FALLING):
            if threshold is None:
                raise ParamError(f"trigger {trig.name.lower()} needs threshold (rpm)")
            thr = int(round(threshold / self.param("speed").scale))
            if not -32768 <= thr <= 32767:
                raise ParamError(f"threshold {threshold} rpm does not fit the speed signal's range")
        self.request("capture_arm", {"mask": mask, "n_samples": n_samples, "pre_trigger": pre_trigger,
                                     "decimation": decimation, "trigger": int(trig), "threshold": thr},
                     detail=f"{','.join(names)} x {n_samples}")
        self._cap = (t.signals_in_mask(mask), decimation)

    def capture_read(self, *, timeout: float = 5.0, poll_s: float = 0.02) -> CaptureResult:
        """Wait until the armed capture is done and read it (t = 0 at the trigger sample)."""
        if getattr(self, "_cap", None) is None:
            raise LinkError("no capture armed: call capture_arm() first")
        sig, dec = self._cap
        end = time.monotonic() + timeout
        while self.status().capture_state != P.CaptureState.DONE:
            if time.monotonic() > end:
                raise LinkTimeout(f"capture not done after {timeout:g} s (trigger not seen?)")
            time.sleep(poll_s)
        start, chunks = 0, []
        while True:
            r = self.request("capture_read", {"start": start, "count": 255}, detail=f"from {start}")
            vals = np.array(r["values"], dtype=np.int16).reshape(-1, len(sig))
            if len(vals):
                chunks.append(vals)
                start += len(vals)
            if start >= r["total"] or not len(vals):
                break
        raw = np.concatenate(chunks) if chunks else np.empty((0, len(sig)), np.int16)
        idx = np.arange(len(raw), dtype=np.int64)
        hz = self.info.sample_hz if self.info else 0
        tidx = r["trigger_index"]
        t = (idx - tidx) * (dec / hz) if hz else (idx - tidx).astype(float)
        return CaptureResult(self._to_records(sig, idx, raw, t), tidx, dec)
