"""Run a simulated controller in a child process and steer it (see :mod:`.control`)."""

from __future__ import annotations

import contextlib
import json
import os
import queue
import random
import socket
import subprocess
import sys
import threading
from typing import Any

READY_TIMEOUT_S = 20.0
_PORTS = (29999, 30001, 30002, 30003, 30004)


def free_loopback_host() -> str:
    """A loopback address on which the controller's fixed ports are all free.

    Tests of several engineers run at once on one machine, so addresses are drawn at random
    from 127.16.0.0/12 rather than counted from 127.0.0.2.
    """
    rng = random.Random(os.getpid() ^ int.from_bytes(os.urandom(4), "little"))
    for _ in range(50):
        host = f"127.{rng.randint(16, 31)}.{rng.randint(0, 255)}.{rng.randint(2, 254)}"
        try:
            for port in _PORTS:
                with socket.create_server((host, port)):
                    pass
        except OSError:
            continue
        return host
    raise RuntimeError("no free loopback address for a simulated controller")


class ControllerProcess:
    """``python -m fakes.ur_controller --control --host HOST`` with a typed control API."""

    def __init__(self, host: str | None = None, *, powered: bool = False,
                 remote_control: bool = True, wait: bool = True) -> None:
        """Start the controller; ``wait``: return once it listens (else :meth:`wait_ready`,
        or the first command, waits for that: a controller boots while its client starts)."""
        host = host or free_loopback_host()
        self.host = host
        argv = [sys.executable, "-m", "fakes.ur_controller", "--host", host, "--control"]
        if powered:
            argv.append("--powered")
        if not remote_control:
            argv.append("--local-control")
        self._proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                      text=True, bufsize=1)
        # One reader for the controller's whole life: the simulated camera asks for the true
        # pose every frame, and a thread per answer made ~30 threads a second (each one's
        # stack mapped and unmapped) in the process that runs the cell.
        self._lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read_lines, name="controller-replies", daemon=True).start()
        self._lock = threading.Lock()
        self._ready = False
        if wait:
            self.wait_ready()

    def wait_ready(self, timeout_s: float = READY_TIMEOUT_S) -> None:
        """Block until the controller listens on its ports (at once when it already does)."""
        with self._lock:
            self._await_ready(timeout_s)

    def _await_ready(self, timeout_s: float) -> None:
        if self._ready:
            return
        ready = self._readline(timeout_s)
        if "ready" not in ready:
            self.close()
            raise RuntimeError(f"controller on {self.host} did not start: {ready!r}")
        self._ready = True

    def _read_lines(self) -> None:
        with contextlib.suppress(OSError, ValueError):  # closed under it
            for line in self._stdout:
                self._lines.put(line)
        self._lines.put("")  # end of file: the controller is gone

    def _readline(self, timeout_s: float) -> str:
        try:
            return self._lines.get(timeout=timeout_s)
        except queue.Empty:
            raise TimeoutError(f"controller on {self.host} did not answer") from None

    @property
    def _stdout(self) -> Any:
        return self._proc.stdout

    def command(self, line: str, timeout_s: float = 5.0) -> dict[str, Any]:
        with self._lock:
            self._await_ready(READY_TIMEOUT_S)
            assert self._proc.stdin is not None
            while True:  # an answer that came after its command timed out is not this one's
                try:
                    if self._lines.get_nowait() == "":
                        self._lines.put("")  # the end stays for every later read
                        break
                except queue.Empty:
                    break
            self._proc.stdin.write(line + "\n")
            self._proc.stdin.flush()
            reply: dict[str, Any] = json.loads(self._readline(timeout_s))
        if not reply.get("ok"):
            raise RuntimeError(reply.get("error", "control command failed"))
        return reply

    # -- the steering API ----------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        return self.command("state")

    def power(self) -> None:
        self.command("power")

    def protective_stop(self, after_s: float = 0.0) -> None:
        self.command(f"pstop {after_s}")

    def emergency_stop(self, after_s: float = 0.0) -> None:
        self.command(f"estop {after_s}")

    def release_emergency_stop(self) -> None:
        self.command("estop-release")

    def drop_connections(self, reset: bool = False) -> None:
        self.command("drop reset" if reset else "drop")

    def stall_stream(self, duration_s: float) -> None:
        self.command(f"stall {duration_s}")

    def freeze(self) -> None:
        self.command("freeze")

    def set_contact_plane_z(self, z_m: float | None) -> None:
        """A horizontal surface at height ``z_m`` (base frame) the tool can touch; None: none."""
        self.command("contact" if z_m is None else f"contact {z_m}")

    def set_remote_control(self, on: bool) -> None:
        self.command("remote on" if on else "remote off")

    def kill(self) -> None:
        """SIGKILL: the controller dies; the kernel closes its sockets."""
        self._proc.kill()
        self._proc.wait(timeout=5.0)

    @property
    def pid(self) -> int:
        return self._proc.pid

    @property
    def alive(self) -> bool:
        return self._proc.poll() is None

    def close(self) -> None:
        if self._proc.poll() is None:
            self._proc.terminate()
            try:
                self._proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait(timeout=5.0)
        for stream in (self._proc.stdin, self._proc.stdout):
            if stream is not None:
                stream.close()

    def __enter__(self) -> ControllerProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
