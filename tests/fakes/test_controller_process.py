"""The simulated controller in its own process, steered over its control channel."""

from __future__ import annotations

import threading

from fakes.ur_controller.process import ControllerProcess


def test_many_state_reads_use_one_reader_thread() -> None:
    # the simulated camera reads the true pose every frame: no thread per answer
    with ControllerProcess() as ctl:
        ctl.state()
        before = {t.ident for t in threading.enumerate()}
        states = [ctl.state() for _ in range(50)]
        after = {t.ident for t in threading.enumerate()}
    assert after == before
    assert all("q" in s and "host_monotonic_s" in s for s in states)
    stamps = [float(s["host_monotonic_s"]) for s in states]
    assert stamps == sorted(stamps)  # each answer is its own command's, in order
