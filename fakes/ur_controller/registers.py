"""The controller's RTDE register file and I/O image, shared by every connection and the script.

A real controller has ONE set of input/output registers: whatever a client last wrote stays
there (the control script reads stale arguments from it as readily as fresh ones), and an input
register written by one RTDE connection cannot be claimed by another. Both facts matter to the
ur_rtde client, so they are modelled here rather than per connection.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

from fakes.ur_sim.engine import EngineSnapshot

NUM_REGISTERS = 48


@dataclass
class RegisterFile:
    """Input/output registers and the digital/analog output image. Guard with ``lock``."""

    lock: threading.RLock = field(default_factory=threading.RLock)
    in_int: list[int] = field(default_factory=lambda: [0] * NUM_REGISTERS)
    in_double: list[float] = field(default_factory=lambda: [0.0] * NUM_REGISTERS)
    in_bits: int = 0  # input_bit_registers 0..127 as one integer
    out_int: list[int] = field(default_factory=lambda: [0] * NUM_REGISTERS)
    out_double: list[float] = field(default_factory=lambda: [0.0] * NUM_REGISTERS)
    out_bits: int = 0
    standard_do: int = 0
    configurable_do: int = 0
    tool_do: int = 0
    analog_out: list[float] = field(default_factory=lambda: [0.0, 0.0])
    external_ft: tuple[float, ...] = (0.0,) * 6
    pending_io: dict[str, object] = field(default_factory=dict)  # masked writes, see rtde
    payload_kg: float = 0.0
    payload_cog_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # monotonic time of the last client write of each input int register (RTDE watchdog)
    in_int_written_s: list[float] = field(default_factory=lambda: [0.0] * NUM_REGISTERS)
    _owners: dict[str, int] = field(default_factory=dict)

    def claim(self, names: list[str], owner: int) -> list[str]:
        """Claim input variables for one connection; returns the names another one owns.

        Nothing is claimed when any name is taken, as the controller refuses the whole recipe.
        """
        with self.lock:
            taken = [n for n in names if self._owners.get(n, owner) != owner]
            if not taken:
                for n in names:
                    self._owners[n] = owner
            return taken

    def release(self, owner: int) -> None:
        with self.lock:
            for name in [n for n, o in self._owners.items() if o == owner]:
                del self._owners[name]

    def digital_output_bits(self) -> int:
        return self.standard_do | (self.configurable_do << 8) | (self.tool_do << 16)


@dataclass(frozen=True)
class ControllerView:
    """What one controller cycle publishes: the arm, the registers, the program state."""

    snap: EngineSnapshot
    regs: RegisterFile
    runtime_state: int
