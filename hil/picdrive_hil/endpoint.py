"""The twin's serial endpoint: a TCP socket (``socket://127.0.0.1:<port>``)
and optionally a pseudo-terminal, so ``picdrive.link``, ``picdrive console``
and any pyserial program open the virtual board exactly as a COM port.

One client at a time on the socket (a second connection waits until the
first closes, as a COM port can only be opened once); the pty is always
there.  Bytes from the client enter the board's EUSART at the host's baud
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
"""
from __future__ import annotations

import errno
import math
import os
import select
import socket
import sys
import threading
import time

from .build import TwinError

CHUNK_S = 1e-3          # simulated time advanced per loop iteration in real time
MAX_LAG_S = 0.25        # if the twin falls this far behind the wall clock, it drops the debt
READ_BYTES = 4096       # bytes read from the socket / pty at a time


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
        for s in (self._client, self._lsock):
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
        try:
            c, addr = self._lsock.accept()
        except (BlockingIOError, InterruptedError):
            return
        c.setblocking(False)
        c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._client = c
        self.log(f"client connected from {addr[0]}:{addr[1]}")

    def _drop_client(self) -> None:
        if self._client is not None:
            try:
                self._client.close()
            except OSError:
                pass
            self._client = None
            # what the departed client sent and the board has not received is dropped: the next
            # client must not have it run for them (queued pty bytes, if any, go with it)
            n = self.twin.uart_flush_input() + len(self._pend_sock)
            self._pend_sock = b""
            self.dropped_on_disconnect += n
            self.log("client disconnected" + (f"; {n} bytes it sent that the board had not yet received "
                                              "were dropped" if n else ""))

    def status(self) -> dict:
        """Counters of the endpoint: bytes in/out, lag events and the simulated time they gave up,
        bytes dropped on a client's disconnect, bytes waiting for room in the twin's input queue, and
        whether a socket client is connected (once it is not, nothing it sent reaches the board)."""
        d = {"bytes_in": self.bytes_in, "bytes_out": self.bytes_out, "lag_events": self.lag_events,
             "client_connected": self._client is not None,
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
            return
        self.bytes_out += len(data)
        if self._client is not None:
            try:
                self._client.sendall(data)
            except OSError:
                self._drop_client()
        if self._pty_master is not None:
            try:
                os.write(self._pty_master, data)
            except OSError:
                pass        # nobody has the pty open; like a UART, bytes are lost

    def _step(self) -> None:
        """One pass of the serving loop: accept, move bytes, advance the twin (paced)."""
        if self._client is None:
            self._accept()
        self._pump_in()
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
        fds = []
        if self._client is None:
            fds.append(self._lsock)
        elif not self._pend_sock:                  # bytes waiting for room: do not wake on more
            fds.append(self._client)
        if self._pty_master is not None and not self._pend_pty:
            fds.append(self._pty_master)
        try:
            select.select(fds, [], [], timeout)
        except (OSError, ValueError):
            time.sleep(timeout)
