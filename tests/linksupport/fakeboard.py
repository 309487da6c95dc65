"""FakeBoard: the rendered C link module + fake_app.c, loaded with ctypes.

Two ways to drive it:

* direct (C-level tests, fuzz): ``feed(bytes)`` puts bytes straight into link_rx_byte with a
  link_poll after each, ``take_tx()`` returns what the module queued for the UART,
  ``tick(ms)`` / ``sample(n)`` advance its time bases;
* modelled time (link tests, bench): ``rx(bytes)`` queues host bytes that arrive at the baud
  rate, ``advance(seconds)`` runs the 1 kHz tick, the sample clock and both UART directions
  (10 bits per byte) and returns the bytes that left the board's UART.

``serve()`` runs the modelled board in a thread, in step with the wall clock, behind
``socket://127.0.0.1:<port>``, so that ``picdrive.link`` talks to it like to a real port.
"""
from __future__ import annotations

import ctypes as C
import select
import shutil
import socket
import tempfile
import threading
import time
from pathlib import Path

from picdrive.link import protocol as P

from . import build

_STATS = {"param_changed": 0, "link_lost": 1, "commands": 2, "eeprom_writes": 3, "last_param_changed": 4,
          "state": 5, "fault": 6, "frames_logged": 7, "rx_delivered": 8}


class FakeBoard:
    def __init__(self, table: P.Table | None = None, *, files: dict[str, str] | None = None,
                 baud: int = 115200, sample_hz: int = 1000, txq_bytes: int = 64,
                 build_id: int = build.DEFAULT_BUILD_ID, profile_hash: int = build.DEFAULT_PROFILE_HASH,
                 capture_bytes: int = P.CAPTURE_BYTES_DEFAULT, sanitize: bool = False):
        self.table = table if table is not None else P.build_table(2)
        self.files = files if files is not None else build.render(
            self.table, build_id=build_id, profile_hash=profile_hash, sample_hz=sample_hz,
            capture_bytes=capture_bytes)
        so = build.shared_library(self.files, sanitize=sanitize)
        # a private copy: every FakeBoard has its own C globals
        self._dir = Path(tempfile.mkdtemp(prefix="fakeboard-"))
        private = self._dir / "libfakeboard.so"
        shutil.copy(so, private)
        self.lib = C.CDLL(str(private))
        self._declare()
        self.baud, self.sample_hz, self.txq_bytes = baud, sample_hz, txq_bytes
        self._lock = threading.RLock()
        self._srv: threading.Thread | None = None
        self._stop = threading.Event()
        self._lsock: socket.socket | None = None
        self.peer_rx_bytes = 0
        self.erase_eeprom()
        self.boot()

    def _declare(self) -> None:
        L = self.lib
        u8p = C.POINTER(C.c_uint8)
        for name, res, args in (
            ("peer_reset", None, [C.c_uint32, C.c_uint32, C.c_uint16]),
            ("peer_boot", C.c_uint8, [C.c_uint32, C.c_uint32, C.c_uint16]),
            ("peer_erase_eeprom", None, []),
            ("peer_eeprom", u8p, []),
            ("peer_rx", None, [C.c_char_p, C.c_uint32]),
            ("peer_take_tx", C.c_uint32, [u8p, C.c_uint32]),
            ("peer_advance_ns", C.c_uint32, [C.c_uint64, u8p, C.c_uint32]),
            ("peer_feed", None, [C.c_char_p, C.c_uint32]),
            ("peer_tick", None, [C.c_uint32]),
            ("peer_sample", None, [C.c_uint32]),
            ("peer_inject_fault", None, [C.c_uint8]),
            ("peer_set_tx_blocked", None, [C.c_uint8]),
            ("peer_now_ns", C.c_uint64, []),
            ("peer_txq_used", C.c_uint32, []),
            ("peer_stat", C.c_uint32, [C.c_int]),
            ("peer_log_get", C.c_int, [C.c_uint32, u8p, u8p, u8p, C.POINTER(C.c_uint32)]),
            ("peer_log_clear", None, []),
            ("link_crc16", C.c_uint16, [C.c_char_p, C.c_uint8]),
            ("link_param_get", C.c_int32, [C.c_uint8]),
            ("link_param_i16", C.c_int16, [C.c_uint8]),
            ("link_param_set", C.c_uint8, [C.c_uint8, C.c_int32]),
            ("link_eeprom_load", C.c_uint8, []),
            ("link_eeprom_save", C.c_uint8, []),
            ("link_event", None, [C.c_uint8, C.c_uint8]),
            ("link_sample", None, []),
            ("link_poll", None, []),
            ("link_tick_ms", None, []),
            ("link_rx_byte", None, [C.c_uint8]),
            ("link_init", None, []),
        ):
            f = getattr(L, name)
            f.restype = res
            f.argtypes = args

    # -- lifecycle ------------------------------------------------------------
    def boot(self) -> P.EepromResult:
        """Reset the board (RAM, link module, toy drive, clocks) and load the EEPROM as the
        firmware does at power-up.  The EEPROM keeps its content."""
        with self._lock:
            return P.EepromResult(self.lib.peer_boot(self.baud, self.sample_hz, self.txq_bytes))

    def close(self) -> None:
        self.stop()
        shutil.rmtree(self._dir, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- direct mode ----------------------------------------------------------
    def feed(self, data: bytes) -> None:
        with self._lock:
            self.lib.peer_feed(bytes(data), len(data))

    def take_tx(self) -> bytes:
        buf = (C.c_uint8 * 8192)()
        out = b""
        with self._lock:
            while True:
                n = self.lib.peer_take_tx(buf, len(buf))
                out += bytes(buf[:n])
                if n < len(buf):
                    return out

    def tick(self, ms: int = 1) -> None:
        with self._lock:
            self.lib.peer_tick(ms)

    def sample(self, n: int = 1) -> None:
        with self._lock:
            self.lib.peer_sample(n)

    # -- modelled time --------------------------------------------------------
    def rx(self, data: bytes) -> None:
        with self._lock:
            self.lib.peer_rx(bytes(data), len(data))

    def advance(self, seconds: float) -> bytes:
        ns = int(round(seconds * 1e9))
        cap = int(seconds * 200000) + 4096
        buf = (C.c_uint8 * cap)()
        with self._lock:
            n = self.lib.peer_advance_ns(ns, buf, cap)
        return bytes(buf[:n])

    @property
    def now_s(self) -> float:
        return self.lib.peer_now_ns() / 1e9

    # -- inspection and injection ---------------------------------------------
    def stat(self, name: str) -> int:
        with self._lock:
            return int(self.lib.peer_stat(_STATS[name]))

    @property
    def eeprom(self):
        """The 256-byte EEPROM as a writable ctypes array."""
        return (C.c_uint8 * 256).from_address(C.addressof(self.lib.peer_eeprom().contents))

    def erase_eeprom(self) -> None:
        with self._lock:
            self.lib.peer_erase_eeprom()

    def inject_fault(self, code: int) -> None:
        with self._lock:
            self.lib.peer_inject_fault(int(code))

    def set_tx_blocked(self, blocked: bool) -> None:
        with self._lock:
            self.lib.peer_set_tx_blocked(1 if blocked else 0)

    def param(self, name: str) -> int:
        with self._lock:
            return int(self.lib.link_param_get(self.table[name].id))

    def log(self) -> list[tuple[int, int, bytes, int]]:
        """Frames the module accepted (passed CRC): (type, seq, payload, rx byte count)."""
        out = []
        t, s = C.c_uint8(), C.c_uint8()
        pl = (C.c_uint8 * P.MAX_PAYLOAD)()
        at = C.c_uint32()
        with self._lock:
            i = 0
            while True:
                n = self.lib.peer_log_get(i, C.byref(t), C.byref(s), pl, C.byref(at))
                if n < 0:
                    break
                out.append((t.value, s.value, bytes(pl[:n]), at.value))
                i += 1
        return out

    def clear_log(self) -> None:
        with self._lock:
            self.lib.peer_log_clear()

    # -- socket server --------------------------------------------------------
    def serve(self, speed: float = 1.0) -> str:
        """Serve the modelled board on a local TCP port, its time in step with the wall clock
        (``speed`` x real time).  Returns the pyserial URL."""
        if self._srv is not None:
            raise RuntimeError("already serving")
        self._lsock = socket.create_server(("127.0.0.1", 0))
        self._lsock.setblocking(False)
        port = self._lsock.getsockname()[1]
        self._stop.clear()
        self._srv = threading.Thread(target=self._serve_loop, args=(speed,), name="fakeboard", daemon=True)
        self._srv.start()
        return f"socket://127.0.0.1:{port}"

    def stop(self) -> None:
        if self._srv is not None:
            self._stop.set()
            self._srv.join(5)
            self._srv = None
        if self._lsock is not None:
            self._lsock.close()
            self._lsock = None

    def _serve_loop(self, speed: float) -> None:
        conn: socket.socket | None = None
        t0 = time.perf_counter()
        sim0_ns = self.lib.peer_now_ns()
        max_step_ns = 20_000_000
        try:
            while not self._stop.is_set():
                socks = [self._lsock] + ([conn] if conn is not None else [])
                r, _, _ = select.select(socks, [], [], 0.0005)
                if self._lsock in r:
                    try:
                        c, _ = self._lsock.accept()
                        if conn is not None:
                            conn.close()
                        conn = c
                        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                        conn.setblocking(False)
                    except BlockingIOError:
                        pass
                if conn is not None and conn in r:
                    try:
                        data = conn.recv(65536)
                    except (BlockingIOError, InterruptedError):
                        data = None
                    except OSError:
                        data = b""
                    if data == b"":
                        conn.close()
                        conn = None
                    elif data:
                        self.peer_rx_bytes += len(data)
                        self.rx(data)
                target_ns = sim0_ns + int((time.perf_counter() - t0) * speed * 1e9)
                while True:
                    dt_ns = target_ns - self.lib.peer_now_ns()
                    if dt_ns <= 0:
                        break
                    out = self.advance(min(dt_ns, max_step_ns) / 1e9)
                    if out and conn is not None:
                        try:
                            conn.setblocking(True)
                            conn.sendall(out)
                            conn.setblocking(False)
                        except OSError:
                            conn.close()
                            conn = None
        finally:
            if conn is not None:
                conn.close()
