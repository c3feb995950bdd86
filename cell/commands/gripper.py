"""``cell gripper [--config FILE] [--port DEVICE] {status,activate,open,close}``: commission the
cell's gripper.

The first thing an integrator runs on a new cell: it proves the link, the address and the
gripper's motion before the service depends on them. The gripper is the one ``--config``'s
``[gripper]`` table names, built from its config class by the hardware factory
(:func:`cell.devices.factory.build_gripper`), so it is driven with the settings the service will
use; without ``--config`` it is a Robotiq-compatible gripper (``kind = "robotiq"``) with the
table's defaults. The options override the keys of the same meaning (``--port``: ``port``,
``--slave-id``: ``slave_id``, ``--baudrate``, ``--timeout``: ``timeout_s``) of a kind that has
them.
"""

from __future__ import annotations

import argparse
import logging

from cell.commands.common import fail, print_json


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("gripper", help="drive the configured gripper (without --config: a "
                       "Robotiq-compatible one on --port)")
    p.add_argument("--config", default=None, metavar="FILE",
                   help="the gripper and its link settings from FILE's [gripper] table")
    p.add_argument("--port", default=None, help="serial device, e.g. /dev/ttyUSB0")
    p.add_argument("--slave-id", type=int, default=None, help="Modbus slave id (default 9)")
    p.add_argument("--baudrate", type=int, default=None, help="default 115200")
    p.add_argument("--timeout", type=float, default=None,
                   help="per-request timeout in s (default 0.5)")
    p.add_argument("action", choices=["status", "activate", "open", "close"])
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from cell.config.devices import GripperConfig, RobotiqGripperConfig
    from cell.config.schema import ConfigError, load_config
    from cell.devices.factory import build_gripper
    from drivers.errors import DriverError

    # The adapter turns pymodbus' "no response" log lines into typed errors; keep stderr clean.
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    gc: GripperConfig = RobotiqGripperConfig()
    try:
        if args.config:
            config = load_config(args.config)
            gc = config.gripper
    except ConfigError as err:
        return fail(err.code, str(err), args.json)
    given = {key: value for key, value in (("port", args.port), ("slave_id", args.slave_id),
                                           ("baudrate", args.baudrate),
                                           ("timeout_s", args.timeout)) if value is not None}
    foreign = [key for key in given if key not in type(gc).model_fields]
    if foreign:
        return fail("invalid_argument", f"[gripper] kind = {gc.kind!r} has no "
                    f"{', '.join(foreign)}", args.json)
    try:
        gc = type(gc).model_validate({**gc.model_dump(), **given})
    except ValidationError as err:
        return fail("invalid_argument", "; ".join(
            f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in err.errors()), args.json)
    if getattr(gc, "port", None) == "":
        return fail("invalid_argument", "no serial port: pass --port or a --config whose "
                    "[gripper] port is set", args.json)
    try:
        gripper, release = build_gripper(gc)
    except (ConfigError, ValueError) as err:
        return fail("invalid_argument", str(err), args.json)
    if gripper is None:
        release()
        return fail("invalid_argument", f"[gripper] kind = {gc.kind!r}: the cell has no gripper",
                    args.json)
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
        release()
    if args.json:
        print_json(status.as_dict())
    else:
        state = "activated" if status.activated else "not activated"
        obj = ", object detected" if status.object_detected else ""
        fault = f", fault {status.fault}" if status.fault else ""
        print(f"gripper {state}: opening {status.position_mm:.1f} mm{obj}{fault}")
    return 0
