"""``python -m fakes.ur_controller --host 127.0.0.2``: serve one simulated UR5e controller.

It starts as a real controller boots: powered off, brakes on. ur_rtde's RTDEControlInterface
(and every ur_rtde example that moves) then fails with "Failed to start control script", and
the controller says why in an RTDE text message. Start it with --powered, or power it on
as on a real cell: dashboard (port 29999) "power on", then "brake release" (~2 s). Reading
clients (RTDEReceiveInterface, the dashboard, the secondary and real-time ports) work either
way. See docs/simulator.md."""

from __future__ import annotations

import argparse
import contextlib
import gc
import logging
import os
import signal
import sys
import threading

from fakes.ur_controller.control import serve
from fakes.ur_controller.server import URController


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fakes.ur_controller", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--host", default="127.0.0.2",
                        help="loopback address to serve (the ports are fixed by ur_rtde)")
    parser.add_argument("--local-control", action="store_true",
                        help="report the pendant in local control (ur_rtde then refuses)")
    parser.add_argument("--powered", action="store_true",
                        help="start powered on with brakes released (RUNNING)")
    parser.add_argument("--protective-stop-after", type=float, metavar="S",
                        help="fault injection: raise a protective stop S seconds after start")
    parser.add_argument("--control", action="store_true",
                        help="accept control commands on stdin (see fakes.ur_controller.control)")
    parser.add_argument("-v", "--verbose", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        stream=sys.stderr)

    _raise_priority()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    # Under --control a program owns this controller (the cell's factory, a test): a terminal's
    # Ctrl-C is for that program, which stops the arm and then ends the controller itself. A
    # controller that died first would leave the cell a lost arm and a false alarm.
    signal.signal(signal.SIGINT,
                  signal.SIG_IGN if args.control else (lambda *_: stop.set()))
    with URController(args.host, remote_control=not args.local_control) as ctl:
        if args.powered:
            ctl.engine.brake_release()
        if args.protective_stop_after is not None:
            ctl.faults.protective_stop(args.protective_stop_after)
        # A full garbage collection walked every start-up object with the 500 Hz clock
        # stopped (59 ms measured): freeze them out of its reach, as a real controller's
        # cycle never pauses for its own housekeeping.
        gc.collect()
        gc.freeze()
        print(f"UR controller simulator ready on {args.host} "
              "(dashboard 29999, script 30003, RTDE 30004)", flush=True)
        if not args.powered and not args.control:  # --control: stdout is the JSON channel
            print("powered off, brakes on: ur_rtde control fails until the dashboard gets "
                  "'power on' and 'brake release' (or start with --powered)", flush=True)
        if args.control:
            threading.Thread(target=_control, args=(ctl, stop), daemon=True).start()
        stop.wait()
    return 0


def _raise_priority() -> None:
    """A real controller runs its 500 Hz loop as a real-time task; the simulator asks for a
    higher scheduling priority (nice -10) where it may, so CPU-bound neighbours delay its
    cycle less. Without the permission it runs at normal priority and catches up instead."""
    with contextlib.suppress(OSError, AttributeError):
        os.setpriority(os.PRIO_PROCESS, 0, -10)


def _control(ctl: URController, stop: threading.Event) -> None:
    serve(ctl, sys.stdin, sys.stdout)
    stop.set()  # stdin closed: the parent is gone


if __name__ == "__main__":
    raise SystemExit(main())
