"""``cell gripper [--config FILE] [--port DEVICE] {status,activate,open,close}``: commission a
serial gripper.

The first thing an integrator runs on a new cell: it proves the RS-485 link, the slave id and
the gripper's motion before the service depends on them. With ``--config`` the port, slave id,
baud rate and timeouts come from the file's ``[gripper]`` table (what the service will use);
options given on the command line override them.
"""

from __future__ import annotations

import argparse
import logging

from cell.commands.common import fail, print_json


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("gripper", help="drive a Robotiq-compatible gripper on a serial port")
    p.add_argument("--config", default=None, metavar="FILE",
                   help="take the link settings from FILE's [gripper] table")
    p.add_argument("--port", default=None, help="serial device, e.g. /dev/ttyUSB0")
    p.add_argument("--slave-id", type=int, default=None, help="Modbus slave id (default 9)")
    p.add_argument("--baudrate", type=int, default=None, help="default 115200")
    p.add_argument("--timeout", type=float, default=None,
                   help="per-request timeout in s (default 0.5)")
    p.add_argument("action", choices=["status", "activate", "open", "close"])
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from cell.config.schema import ConfigError, GripperConfig, load_config
    from drivers.errors import DriverError
    from drivers.robotiq import RobotiqGripper

    # The adapter turns pymodbus' "no response" log lines into typed errors; keep stderr clean.
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    try:
        gc = load_config(args.config).gripper if args.config else GripperConfig()
    except ConfigError as err:
        return fail(err.code, str(err), args.json)
    port = args.port or gc.port
    if not port:
        return fail("invalid_argument", "no serial port: pass --port or a --config whose "
                    "[gripper] port is set", args.json)
    try:
        gripper = RobotiqGripper(
            port, gc.slave_id if args.slave_id is None else args.slave_id,
            gc.baudrate if args.baudrate is None else args.baudrate,
            gc.timeout_s if args.timeout is None else args.timeout, gc.retries,
            motion_timeout_s=gc.motion_timeout_s, activation_timeout_s=gc.activation_timeout_s)
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
