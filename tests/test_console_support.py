"""Test helpers for the console tests (imported by test_console*.py): an unpluggable "cable" between the console and a board.

:class:`Cable` listens on a fixed local port and forwards bytes both ways to a board's
``socket://`` URL (the fake board or the twin).  ``unplug()`` closes the port and every
connection, as pulling a USB-serial adapter does; ``plug()`` listens on the same port again,
so a console that reconnects to the same URL finds the board back.
"""
from __future__ import annotations

import select
import socket
import threading


class Cable:
    def __init__(self, board_url: str, port: int = 0):
        host, _, bport = board_url.removeprefix("socket://").rpartition(":")
        self.board = (host, int(bport))
        self._lsock = socket.create_server(("127.0.0.1", port))
        self.port = self._lsock.getsockname()[1]
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.connections = 0
        self._start()

    @property
    def url(self) -> str:
        return f"socket://127.0.0.1:{self.port}"

    def _start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._loop, args=(self._lsock,), daemon=True, name="cable")
        self._thread.start()

    def _loop(self, lsock: socket.socket) -> None:
        pairs: list[tuple[socket.socket, socket.socket]] = []
        try:
            while not self._stop.is_set():
                socks = [lsock] + [s for p in pairs for s in p]
                r, _, _ = select.select(socks, [], [], 0.02)
                if lsock in r:
                    c, _ = lsock.accept()
                    try:
                        b = socket.create_connection(self.board, timeout=2.0)
                    except OSError:
                        c.close()
                    else:
                        for s in (c, b):
                            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                        pairs.append((c, b))
                        self.connections += 1
                for pair in list(pairs):
                    for src, dst in (pair, pair[::-1]):
                        if src in r:
                            try:
                                data = src.recv(65536)
                            except OSError:
                                data = b""
                            if not data:
                                for s in pair:
                                    s.close()
                                pairs.remove(pair)
                                break
                            dst.sendall(data)
                        else:
                            continue
                        if pair not in pairs:
                            break
        finally:
            for p in pairs:
                for s in p:
                    s.close()

    def unplug(self) -> None:
        """Close the port and all connections (the console sees the link die)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        self._lsock.close()

    def plug(self) -> None:
        """Listen on the same port again."""
        self._lsock = socket.create_server(("127.0.0.1", self.port))
        self._start()

    def close(self) -> None:
        if not self._stop.is_set():
            self.unplug()


def test_cable_forwards_unplugs_and_replugs_on_the_same_port():
    echo = socket.create_server(("127.0.0.1", 0))
    stop = threading.Event()

    def serve():
        while not stop.is_set():
            r, _, _ = select.select([echo], [], [], 0.05)
            if r:
                c, _ = echo.accept()
                c.sendall(c.recv(100).upper())
                c.close()
    t = threading.Thread(target=serve, daemon=True)
    t.start()
    cable = Cable(f"socket://127.0.0.1:{echo.getsockname()[1]}")
    try:
        port = cable.port

        def ask():
            with socket.create_connection(("127.0.0.1", port), timeout=2) as s:
                s.sendall(b"hello")
                return s.recv(100)
        assert ask() == b"HELLO"
        cable.unplug()
        try:
            ask()
            raise AssertionError("an unplugged cable must refuse connections")
        except OSError:
            pass
        cable.plug()
        assert cable.port == port and ask() == b"HELLO"
        assert cable.connections == 2
    finally:
        cable.close()
        stop.set()
        t.join(1)
        echo.close()
