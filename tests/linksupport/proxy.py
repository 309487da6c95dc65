"""A frame-aware TCP proxy between picdrive.link and a served FakeBoard, to lose or corrupt
chosen frames in either direction (tests of retries, duplicate SEQ and BAD_CRC)."""
from __future__ import annotations

import select
import socket
import threading
from typing import Callable

from picdrive.link import codec

# hook(frame) -> bytes to send instead (b"" drops it, None keeps it)
Hook = Callable[[codec.Frame], "bytes | None"]


class FrameProxy:
    def __init__(self, board_url: str, *, to_board: Hook | None = None, to_host: Hook | None = None):
        host, port = board_url.removeprefix("socket://").rsplit(":", 1)
        self._target = (host, int(port))
        self._hooks = {"to_board": to_board, "to_host": to_host}
        self._lsock = socket.create_server(("127.0.0.1", 0))
        self.url = f"socket://127.0.0.1:{self._lsock.getsockname()[1]}"
        self._stop = threading.Event()
        self._host: socket.socket | None = None
        self._t = threading.Thread(target=self._run, daemon=True, name="frameproxy")
        self._t.start()

    def _run(self) -> None:
        self._lsock.settimeout(0.1)
        while not self._stop.is_set():
            try:
                h, _ = self._lsock.accept()
            except socket.timeout:
                continue
            b = socket.create_connection(self._target)
            self._host = h
            for s in (h, b):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            decs = {h: codec.StreamDecoder(), b: codec.StreamDecoder()}
            route = {h: (b, self._hooks["to_board"]), b: (h, self._hooks["to_host"])}
            try:
                while not self._stop.is_set():
                    r, _, _ = select.select([h, b], [], [], 0.05)
                    for s in r:
                        data = s.recv(65536)
                        if not data:
                            raise ConnectionError
                        dst, hook = route[s]
                        if hook is None:
                            dst.sendall(data)
                            continue
                        out = b""
                        for f in decs[s].feed(data):
                            rep = hook(f)
                            out += f.encode() if rep is None else rep
                        if out:
                            dst.sendall(out)
            except (ConnectionError, OSError):
                pass
            finally:
                h.close()
                b.close()

    def send_to_host(self, data: bytes) -> None:
        """Bytes to the connected host, outside the stream (e.g. a reply held back earlier)."""
        assert self._host is not None, "no host connected"
        self._host.sendall(data)

    def close(self) -> None:
        self._stop.set()
        self._t.join(2)
        self._lsock.close()
