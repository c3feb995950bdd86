"""An asyncio server in a thread of its own, started and stopped from the cell's threads.

The PLC doors (OPC UA, Modbus TCP) each run their library's asyncio server on a private event
loop, so nothing they do waits on HTTP's loop or the other way round. What they share is the
hand-off at start: :meth:`LoopThread.start` returns once the server listens, or raises the
error that kept it from listening, so ``cell serve`` fails at once and says why.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from typing import ClassVar

log = logging.getLogger(__name__)


class LoopThread:
    """Base of a server whose :meth:`_main` serves on its own event loop until it is closed.

    ``_main`` sets ``self._ready`` once it listens; an exception before then is re-raised by
    :meth:`start`, one after it is logged (the cell's other doors keep serving).
    """

    thread_name: ClassVar[str]
    what: ClassVar[str]  # for messages: "the Modbus server"

    def __init__(self) -> None:
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None

    def start(self, timeout_s: float) -> None:
        self._thread = threading.Thread(target=self._run, name=self.thread_name, daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise TimeoutError(f"{self.what} did not start within {timeout_s:g} s")
        if self._error is not None:
            raise self._error

    def _join(self, timeout_s: float) -> None:
        if self._thread is not None:
            self._thread.join(timeout=timeout_s)

    async def _main(self) -> None:
        raise NotImplementedError

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as err:
            if not self._ready.is_set():
                self._error = err
            else:
                log.exception("%s stopped", self.what)
        finally:
            self._ready.set()
