"""Byte-exact driver tests: a scripted serial port in place of pyserial's.

The idea of pymeasure's ``expected_protocol``: the test states every request the driver must
write and the exact reply the device gives, and the port asserts each write as it comes. A
driver that writes one byte too many, or none at all, fails at that byte, and a script left
unsent fails when the test ends.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import pytest
import serial

Script = list[tuple[bytes, bytes | OSError | None]]
"""Each request the driver must write, and the reply: bytes, None (silence), or an OSError the
write raises (the port failed under it: a USB adapter pulled, a driver error)."""


class ScriptedSerial:
    """Stands in for a pyserial port: checks each written frame, then makes its reply readable."""

    def __init__(self, script: Script) -> None:
        self.script = list(script)
        self.written: list[bytes] = []
        self.rx = b""
        self.is_open = True
        self.inter_byte_timeout = 0.0

    @property
    def in_waiting(self) -> int:
        return len(self.rx)

    def write(self, data: bytes) -> int:
        self.written.append(bytes(data))
        assert self.script, f"unexpected request {data.hex(' ')}"
        expected, reply = self.script.pop(0)
        assert data == expected, f"wrote {data.hex(' ')}, expected {expected.hex(' ')}"
        if isinstance(reply, OSError):
            raise reply
        self.rx += reply or b""
        return len(data)

    def read(self, size: int = 1) -> bytes:
        out, self.rx = self.rx[:size], self.rx[size:]
        return out

    def close(self) -> None:
        self.is_open = False


@contextmanager
def expected_serial(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[ScriptedSerial]]:
    """Patch pyserial's opener: each port a driver opens is the last one the test appended to
    the yielded list. On exit every script must have been sent in full."""
    made: list[ScriptedSerial] = []

    def opener(url: str, **kwargs: object) -> ScriptedSerial:
        assert made, f"the driver opened {url} before the test scripted a port"
        return made[-1]

    monkeypatch.setattr(serial, "serial_for_url", opener)
    yield made
    for port in made:
        assert not port.script, f"requests never sent: {[e.hex(' ') for e, _ in port.script]}"
