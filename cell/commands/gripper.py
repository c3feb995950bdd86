"""``cell gripper --port DEVICE {status,activate,open,close}``: commission a serial gripper.

The first thing an integrator runs on a new cell: it proves the RS-485 link, the slave id and
the gripper's motion before the service depends on them.
"""

from __future__ import annotations

import argparse
import logging

from cell.commands.common import fail, print_json


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("gripper", help="drive a Robotiq-compatible gripper on a serial port")
    p.add_argument("--port", required=True, help="serial device, e.g. /dev/ttyUSB0")
    p.add_argument("--slave-id", type=int, default=9, help="Modbus slave id (default 9)")
    p.add_argument("--baudrate", type=int, default=115200)
    p.add_argument("--timeout", type=float, default=0.5, help="per-request timeout in s")
    p.add_argument("action", choices=["status", "activate", "open", "close"])
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from drivers.errors import DriverError
    from drivers.robotiq import RobotiqGripper

    # The adapter turns pymodbus' "no response" log lines into typed errors; keep stderr clean.
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    try:
        gripper = RobotiqGripper(args.port, args.slave_id, args.baudrate, args.timeout)
    except ValueError as err:
        return fail("invalid_argument", str(err), args.json)
    try:
        gripper.connect()
        if args.action == "activate":
            status = gripper.activate()
        elif args.action == "open":
            status = gripper.open()
        elif args.action == "close":
            status = gripper.close()
        else:
            status = gripper.status()
    except DriverError as err:
        return fail(err.code, str(err), args.json)
    finally:
        gripper.disconnect()
    if args.json:
        print_json(status.as_dict())
    else:
        state = "activated" if status.activated else "not activated"
        obj = ", object detected" if status.object_detected else ""
        fault = f", fault {status.fault}" if status.fault else ""
        print(f"gripper {state}: opening {status.position_mm:.1f} mm{obj}{fault}")
    return 0
