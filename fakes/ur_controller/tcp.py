"""A small threaded TCP service shared by the controller's three ports.

Besides serving, it lets fault injection do to the sockets what real failures do: drop every
client (FIN, or RST as after a crash), stop listening (connection refused), or freeze (sockets
stay open but nothing is read or answered, like a controller that hangs or a pulled cable).
"""

from __future__ import annotations

import contextlib
import logging
import socket
import struct
import threading
from collections.abc import Callable
from typing import Protocol

log = logging.getLogger(__name__)

_LINGER_RESET = struct.pack("ii", 1, 0)
# Linux only; elsewhere the stack's own acknowledgement timing stays.
_QUICKACK: int | None = getattr(socket, "TCP_QUICKACK", None)


def acknowledge_now(sock: socket.socket) -> None:
    """Acknowledge what was just read at once rather than after Linux's delayed-ACK timer
    (up to 40 ms on a connection the server answers nothing on). ur_rtde's RTDEIOInterface
    sends each write as its own data package and gets no reply; with delayed ACKs its second
    write of a pair reached the controller ~42 ms after the first (measured with its
    io_example's calls), where the RTDE guide applies client inputs every 2 ms cycle and
    the example reads the output back 10 ms later. The flag is cleared by the kernel, so it
    is set after every read."""
    if _QUICKACK is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.IPPROTO_TCP, _QUICKACK, 1)


class Handler(Protocol):
    """Per-client protocol logic."""

    def on_open(self) -> None: ...

    def feed(self, data: bytes) -> bool:
        """Handle received bytes; False closes the connection."""

    def on_close(self) -> None: ...


class TcpService:
    """Accepts clients on ``host:port`` and runs one thread per client."""

    def __init__(self, host: str, port: int, name: str,
                 make_handler: Callable[[socket.socket], Handler]) -> None:
        self.name = name
        self.frozen = False
        self._make_handler = make_handler
        self._clients: dict[socket.socket, Handler] = {}
        self._lock = threading.Lock()
        self._closed = False
        self._listener: socket.socket | None = socket.create_server((host, port))
        self._listener.settimeout(0.2)
        threading.Thread(target=self._accept, daemon=True, name=f"{name}-{host}").start()

    def handlers(self) -> list[Handler]:
        with self._lock:
            return list(self._clients.values())

    def _accept(self) -> None:
        while not self._closed and self._listener is not None:
            try:
                sock, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                break
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.settimeout(0.5)
            handler = self._make_handler(sock)
            with self._lock:
                self._clients[sock] = handler
            threading.Thread(target=self._serve, args=(sock, handler), daemon=True,
                             name=f"{self.name}-client").start()

    def _serve(self, sock: socket.socket, handler: Handler) -> None:
        try:
            handler.on_open()
            while not self._closed:
                try:
                    data = sock.recv(65536)
                except TimeoutError:
                    continue
                if not data:
                    break
                acknowledge_now(sock)
                if self.frozen:
                    continue  # a hung controller reads nothing and answers nothing
                if not handler.feed(data):
                    break
        except (OSError, ValueError, struct.error) as exc:
            log.debug("%s client: %s", self.name, exc)
        finally:
            if not self.frozen:
                self.drop(sock)

    def drop(self, sock: socket.socket, reset: bool = False) -> None:
        with self._lock:
            handler = self._clients.pop(sock, None)
        if handler is not None:
            handler.on_close()
        try:
            if reset:  # RST rather than FIN: the peer sees "connection reset", as on a crash
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, _LINGER_RESET)
            sock.close()
        except OSError:
            pass

    def drop_all(self, reset: bool = False) -> None:
        with self._lock:
            socks = list(self._clients)
        for sock in socks:
            self.drop(sock, reset)

    def stop_listening(self) -> None:
        """New connections are refused from now on."""
        self._closed = True
        if self._listener is not None:
            with contextlib.suppress(OSError):
                self._listener.close()
            self._listener = None

    def close(self, reset: bool = False) -> None:
        self.stop_listening()
        self.drop_all(reset)


def send_all(sock: socket.socket, data: bytes, lock: threading.Lock) -> bool:
    """Send under a per-socket lock (the cycle thread and the client thread both send)."""
    try:
        with lock:
            sock.sendall(data)
        return True
    except OSError:
        return False
