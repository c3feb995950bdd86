"""What the Machine Vision state machine keeps over a restart: the selected mode and the
prepared recipe (OPC 40100-1 expects a vision system to come back in the mode it was set to,
with its recipe prepared, rather than needing a PLC to set it up again after a power cycle).

Running and halted states are not kept: a job does not survive a restart, a Halt and a Reset
both clear the automatic mode (an operator set the system aside), and an Error is found anew
from the arm's state. One small JSON file beside the job database, replaced atomically; an
unreadable file is logged and read as "nothing selected" (the safe start: Preoperational).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

from cell.files import replace_text

log = logging.getLogger(__name__)

FILE_NAME = "machine_vision.json"


@dataclass(frozen=True)
class Remembered:
    automatic: bool = False  # SelectModeAutomatic was the last mode choice
    prepared: str = ""  # the prepared recipe's name


class MachineVisionMemory:
    """The remembered mode and recipe (``path=None``: in memory only, nothing kept)."""

    def __init__(self, path: str | Path | None) -> None:
        self.path = None if path is None else Path(path)

    @staticmethod
    def beside_job_db(job_db: str) -> MachineVisionMemory:
        if job_db == ":memory:":
            return MachineVisionMemory(None)
        return MachineVisionMemory(Path(job_db).parent / FILE_NAME)

    def load(self) -> Remembered:
        if self.path is None or not self.path.exists():
            return Remembered()
        try:
            data = json.loads(self.path.read_text())
            automatic, prepared = data["automatic"], data["prepared"]
            if not isinstance(automatic, bool) or not isinstance(prepared, str):
                raise TypeError("automatic must be a bool and prepared a string")
            return Remembered(automatic, prepared)
        except (OSError, ValueError, KeyError, TypeError) as err:
            log.warning("cannot read %s (%r): the vision system starts Preoperational with "
                        "no recipe prepared", self.path, err)
            return Remembered()

    def save(self, remembered: Remembered) -> None:
        """Best effort: a failed write is logged (the state in memory is what PLCs see)."""
        if self.path is None:
            return
        text = json.dumps({"automatic": remembered.automatic, "prepared": remembered.prepared})
        try:
            replace_text(self.path, text + "\n")
        except OSError as err:
            log.warning("cannot write %s: %s; the mode and recipe are not kept over a restart",
                        self.path, err)
