"""The twin's serial endpoint: a TCP socket (``socket://127.0.0.1:<port>``)
and optionally a pseudo-terminal, so ``picdrive.link``, ``picdrive console``
and any pyserial program open the virtual board exactly as a COM port.

One client at a time on the socket, as a COM port can only be opened once: a
second connection is refused with a text line saying so (``picdrive twin:
busy: ...``, then closed), unless the first leaves within half a second; the
pty is always there.  Bytes from the client enter the board's EUSART at the host's baud
rate, one frame time each; bytes the board sends reach the client once they
have left the wire.

Real-time mode paces the simulation to the wall clock (``speed`` simulated
seconds per wall second, 1 by default), which is what a host with wall-clock
timeouts needs.  If the twin falls ``MAX_LAG_S`` or more behind (a loaded
machine, a stopped process), it does not race to catch up: the debt is given
up, pacing resumes from the present, and the server says so (a log line,
``lag_events`` and ``lag_s``).  Free-running mode (``realtime=False``) runs as
fast as the twin can, for in-process use only.  With ``stop_after_s`` the
server stops on its own once that much simulated time has run (``picdrive twin
--duration``), so a scripted run ends at a simulated instant, not a wall-clock one.

Input: bytes the board has not yet received belong to the client that sent
them; when that client disconnects they are dropped (``dropped_on_disconnect``)
so that a departed client's command never runs for the next one.  When the
twin's input queue is full the server stops reading the socket / pty until
there is room again (TCP backpressure), so no byte is lost silently.

Output: the board does not wait for its host.  The server hands the client
whole frames only, keeping the socket's own queue short (``KERNEL_QUEUE_BYTES``),
and holds the rest; a client that stops reading is disconnected once
``CLIENT_BACKLOG_BYTES`` wait for it, after its last whole frame and a text
line saying why (``picdrive twin: disconnected: ...``), also logged.  The
text lines follow a frame delimiter and end with a newline: a frame decoder
rejects them, :class:`picdrive.link.client.Link` quotes them.
"""
from __future__ import annotations

import errno
import fcntl
import math
import os
import select
import socket
import struct
import sys
import termios
import threading
import time

from picdrive.link.protocol import DELIMITER

from .build import TwinError

P_DELIM = bytes([DELIMITER])
CHUNK_S = 1e-3          # simulated time advanced per loop iteration in real time
MAX_LAG_S = 0.25        # if the twin falls this far behind the wall clock, it drops the debt
READ_BYTES = 4096       # bytes read from the socket / pty at a time
KERNEL_QUEUE_BYTES = 4096     # at most this much unsent in the client socket's own queue: room
#                               is left there for the last frame and the disconnect notice
CLIENT_BACKLOG_BYTES = 32768  # board output held for a client that does not read, then it is dropped
#                               (about 3 s of a 115 200-baud line, far beyond any host's hiccup)
SECOND_CLIENT_WAIT_S = 0.5    # a second connection waits this long for the first to leave
NEW_CLIENT_S = 0.2            # a refused connection's notice waits this long for its first bytes
HANG_UP_S = 2.0               # how long a hung-up client's input is drained before the socket closes
NOTICE = b"\x00picdrive twin: "   # a text line to the client: after a delimiter, ended by a newline


def _unsent(sock: socket.socket) -> int:
    """Bytes in a TCP socket's send queue not yet taken by the peer (Linux SIOCOUTQ; 0 elsewhere)."""
    try:
        return struct.unpack("i", fcntl.ioctl(sock.fileno(), termios.TIOCOUTQ, b"\0\0\0\0"))[0]
    except OSError:
        return 0


class TwinServer:
    """Serve a Twin's UART on a socket (and a pty); see the module docstring."""

    def __init__(self, twin: "picdrive_hil.twin.Twin", *, port: int = 0, host: str = "127.0.0.1", realtime: bool = True,
                 pty: bool = False, speed: float = 1.0, log=None, clock=time.perf_counter,
                 stop_after_s: float | None = None):
        if not (speed > 0):
            raise ValueError("speed must be > 0 (simulated seconds per wall second)")
        if stop_after_s is not None and not (stop_after_s > 0):
            raise ValueError("stop_after_s must be > 0 (simulated seconds) or None")
        self.twin = twin
        # serving ends once the twin's clock reaches this simulated time, s (inf: never)
        self.stop_at_s = math.inf if stop_after_s is None else twin.t + float(stop_after_s)
        self.realtime = realtime
        self.speed = float(speed)
        self.log = log or (lambda msg: None)
        self._lsock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._lsock.bind((host, port))
        except OSError as e:
            self._lsock.close()
            raise TwinError(f"cannot listen on {host}:{port}: {e.strerror}; choose another --port") from None
        self._lsock.listen(1)
        self._lsock.setblocking(False)
        self.host, self.port = self._lsock.getsockname()[:2]
        self._client: socket.socket | None = None
        self._pty_master = self._pty_slave = None
        self.pty_path: str | None = None
        if pty:
            self._open_pty()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None
        self.lag_events = 0             # times the twin fell MAX_LAG_S behind the wall clock
        self.lag_s = 0.0                # simulated time given up by those resynchronisations
        self.bytes_in = self.bytes_out = 0
        self.dropped_on_disconnect = 0  # bytes of departed clients the board had not yet received
        self._clock = clock             # wall clock (seconds); a test may substitute its own
        self._pend_sock = b""           # read from the client, not yet accepted by the twin (queue full)
        self._out = bytearray()         # board output not yet handed to the client's socket
        self._hanging: list = []        # (socket, deadline) told why and closing: see _hang_up
        self._waiting = None            # (socket, address, deadline) of a second connection: see _accept
        self.clients_refused = 0        # connections refused because another client was connected
        self.clients_dropped_slow = 0   # clients disconnected because they stopped reading
        self._pend_pty = b""
        self._t_wall0: float | None = None
        self._t_sim0 = 0.0

    @property
    def url(self) -> str:
        return f"socket://{self.host}:{self.port}"

    # -- pty -------------------------------------------------------------------
    def _open_pty(self) -> None:
        import tty
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._pty_master, self._pty_slave = master, slave
        self.pty_path = os.ttyname(slave)

    # -- life cycle --------------------------------------------------------------
    def start(self) -> "TwinServer":
        self._thread = threading.Thread(target=self._run, name=f"twin-{self.port}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        for s in [self._client, self._lsock] + [h[0] for h in self._hanging] + ([self._waiting[0]] if self._waiting else []):
            if s is not None:
                try:
                    s.close()
                except OSError:
                    pass
        self._client = None
        for fd in (self._pty_master, self._pty_slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._pty_master = self._pty_slave = None

    close = stop

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()

    def wait(self) -> None:
        """Block until the server stops (Ctrl-C stops it)."""
        try:
            while self._thread is not None and self._thread.is_alive():
                self._thread.join(0.2)
        finally:
            self.stop()
        if self.error is not None:
            raise self.error

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # -- the loop ------------------------------------------------------------------
    def _accept(self) -> None:
        """Take a new connection: the client if there is none; else it waits ``SECOND_CLIENT_WAIT_S``
        for the present one to leave (a client closing as the next opens: its last bytes may still
        be queued ahead of its end), then is refused with a notice."""
        w = self._waiting
        if w is not None and (self._client is None or time.monotonic() > w[2]):
            self._waiting = None
            if self._client is None:
                self._take(w[0], w[1])
            else:
                self._refuse(w[0], w[1])
        try:
            c, addr = self._lsock.accept()
        except (BlockingIOError, InterruptedError):
            return
        c.setblocking(False)
        if self._client is None:
            self._take(c, addr)
        elif self._waiting is None:
            self._waiting = (c, addr, time.monotonic() + SECOND_CLIENT_WAIT_S)
        else:
            self._refuse(c, addr)

    def _take(self, c: socket.socket, addr) -> None:
        c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._client = c
        self._out.clear()
        self.log(f"client connected from {addr[0]}:{addr[1]}")

    def _refuse(self, c: socket.socket, addr) -> None:
        self.clients_refused += 1
        self.log(f"refused a second client from {addr[0]}:{addr[1]}: another client is connected")
        self._hang_up(c, b"busy: another client is connected to this twin, which serves one at a time "
                         b"like a serial port; close that one, or start a second twin on another port", new=True)

    def _hang_up(self, c: socket.socket, notice: bytes, *, new: bool = False) -> None:
        """Send a client a notice line and close it.  What it sends meanwhile is read and discarded
        until it closes too (at most ``HANG_UP_S``): closing with its bytes unread would reset the
        connection, and a reset throws away the notice before the client reads it.  A ``new``
        connection gets the notice once it has sent something (or after ``NEW_CLIENT_S``):
        pyserial discards what arrives while it opens the port."""
        now = time.monotonic()
        self._hanging.append([c, NOTICE + notice + b"\n", now + (NEW_CLIENT_S if new else 0.0), now + HANG_UP_S])
        self._service_hang_ups()

    def _service_hang_ups(self) -> None:
        keep = []
        now = time.monotonic()
        for h in self._hanging:
            c, notice, send_at, deadline = h
            heard = gone = False
            try:
                while True:
                    b = c.recv(READ_BYTES)
                    if not b:
                        gone = True                           # EOF: the client closed
                        break
                    heard = True
            except (BlockingIOError, InterruptedError):
                pass
            except OSError:
                gone = True
            if notice is not None and not gone and (heard or now >= send_at):
                try:
                    c.send(notice)
                    c.shutdown(socket.SHUT_WR)
                except OSError:
                    gone = True
                h[1] = None
            if gone or now > deadline:
                c.close()
            else:
                keep.append(h)
        self._hanging = keep

    def _drop_client(self, why: str = "") -> None:
        if self._client is not None:
            if why:
                self._hang_up(self._client, f"disconnected: {why}".encode())
            else:
                try:
                    self._client.close()
                except OSError:
                    pass
            self._client = None
            self._out.clear()
            # what the departed client sent and the board has not received is dropped: the next
            # client must not have it run for them (queued pty bytes, if any, go with it)
            n = self.twin.uart_flush_input() + len(self._pend_sock)
            self._pend_sock = b""
            self.dropped_on_disconnect += n
            self.log(("client dropped: " + why if why else "client disconnected")
                     + (f"; {n} bytes it sent that the board had not yet received were dropped" if n else ""))

    def _send_out(self) -> None:
        """Hand the client whole frames while its socket's queue is short; drop it if it stops reading."""
        if self._client is None or not self._out:
            return
        room = KERNEL_QUEUE_BYTES - _unsent(self._client)
        end = self._out.rfind(P_DELIM, 0, max(room, 0)) + 1       # whole frames that fit
        if end > 0:
            try:
                n = self._client.send(self._out[:end])
            except (BlockingIOError, InterruptedError):
                n = 0
            except OSError:
                self._drop_client()
                return
            del self._out[:n]
        if len(self._out) > CLIENT_BACKLOG_BYTES:
            self.clients_dropped_slow += 1
            self._drop_client(f"this client read nothing while {len(self._out)} bytes of the board's output "
                              "waited for it (the board does not wait for its host); the frames before this "
                              "line are whole; reconnect, and keep reading the port")

    def status(self) -> dict:
        """Counters of the endpoint: bytes in/out, lag events and the simulated time they gave up,
        bytes dropped on a client's disconnect, bytes waiting for room in the twin's input queue, and
        whether a socket client is connected (once it is not, nothing it sent reaches the board)."""
        d = {"bytes_in": self.bytes_in, "bytes_out": self.bytes_out, "lag_events": self.lag_events,
             "client_connected": self._client is not None, "clients_refused": self.clients_refused,
             "clients_dropped_slow": self.clients_dropped_slow, "output_waiting": len(self._out),
             "lag_s": self.lag_s, "dropped_on_disconnect": self.dropped_on_disconnect,
             "input_waiting": len(self._pend_sock) + len(self._pend_pty)}
        if getattr(self.twin, "processor", False):
            # the processor twin: interrupt durations, missed periods, stack and memory (pil.Report)
            d["processor"] = self.twin.processor_report().as_dict()
        return d

    def _feed(self, data: bytes) -> bytes:
        """Give bytes to the twin's UART input; returns what did not fit (kept for later)."""
        if not data:
            return b""
        k = self.twin.uart_write(data)
        return data[k:]

    def _pump_in(self) -> None:
        # bytes that did not fit last time go first; while some wait, nothing more is read, so
        # the sender is held back by TCP flow control (or the pty's buffer) instead of losing bytes
        self._pend_sock = self._feed(self._pend_sock)
        self._pend_pty = self._feed(self._pend_pty)
        if self._client is not None and not self._pend_sock:
            try:
                data = self._client.recv(READ_BYTES)
                if not data:
                    self._drop_client()
                else:
                    self.bytes_in += len(data)
                    self._pend_sock = self._feed(data)
            except (BlockingIOError, InterruptedError):
                pass
            except OSError:
                self._drop_client()
        if self._pty_master is not None and not self._pend_pty:
            try:
                data = os.read(self._pty_master, READ_BYTES)
                if data:
                    self.bytes_in += len(data)
                    self._pend_pty = self._feed(data)
            except BlockingIOError:
                pass
            except OSError as e:
                if e.errno not in (errno.EIO, errno.EAGAIN):
                    raise

    def _pump_out(self) -> None:
        data = self.twin.uart_read()
        if not data:
            self._send_out()
            return
        self.bytes_out += len(data)
        if self._client is not None:
            self._out += data
            self._send_out()
        if self._pty_master is not None:
            try:
                os.write(self._pty_master, data)
            except OSError:
                pass        # nobody has the pty open; like a UART, bytes are lost

    def _step(self) -> None:
        """One pass of the serving loop: accept, move bytes, advance the twin (paced)."""
        self._pump_in()
        self._accept()
        if self._hanging:
            self._service_hang_ups()
        end = self.stop_at_s
        if self.twin.t >= end:
            self._pump_out()
            self._stop.set()
            return
        if not self.realtime:
            self.twin.run_until(min(self.twin.t + CHUNK_S, end))
            self._pump_out()
            return
        if self._t_wall0 is None:
            self._t_wall0, self._t_sim0 = self._clock(), self.twin.t
        target = self._t_sim0 + (self._clock() - self._t_wall0) * self.speed
        now = self.twin.t
        debt = target - now
        if debt >= MAX_LAG_S * self.speed:
            # fell behind (loaded machine, stopped process): give the debt up and pace from the
            # present again; racing to catch up would run the board faster than its host's clock
            self.lag_events += 1
            self.lag_s += debt - CHUNK_S
            self._t_sim0 -= debt - CHUNK_S
            target = now + CHUNK_S
            self.log(f"fell {debt / self.speed:.3f} s behind the wall clock (machine too slow or the process "
                     f"was stopped); resynchronised: the board saw {debt - CHUNK_S:.3f} s less time than its host "
                     f"({self.lag_events} time{'s' if self.lag_events != 1 else ''} so far, "
                     f"{self.lag_s:.3f} s in all)")
        if target > now:
            self.twin.run_until(min(target, now + 4 * CHUNK_S, end))
        self._pump_out()
        # sleep until the next chunk is due or bytes arrive
        nxt = (self.twin.t + CHUNK_S - self._t_sim0) / self.speed + self._t_wall0
        self._wait_io(max(0.0, min(nxt - self._clock(), CHUNK_S)))

    def _run(self) -> None:
        try:
            self._t_wall0 = None
            while not self._stop.is_set():
                self._step()
        except BaseException as e:                      # report, then stop serving
            self.error = e
            print(f"picdrive twin: stopped: {e}", file=sys.stderr)
            self._drop_client()

    def _wait_io(self, timeout: float) -> None:
        fds = [self._lsock]
        if self._client is not None and not self._pend_sock:    # bytes waiting for room: do not wake on more
            fds.append(self._client)
        if self._pty_master is not None and not self._pend_pty:
            fds.append(self._pty_master)
        try:
            select.select(fds, [], [], timeout)
        except (OSError, ValueError):
            time.sleep(timeout)
