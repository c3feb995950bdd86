"""``cell config check FILE``: validate a cell config without touching any hardware.

What an integrator runs after every edit of a real cell's file: the strict schema, the
commissioning checks and every rule a start refuses on (:mod:`cell.config.checks`: sample or
weak API tokens on real hardware, device combinations the factory cannot build), every problem
listed with its key. Exit 0 when ``cell serve`` would start with the file, 2 otherwise.
"""

from __future__ import annotations

import argparse

from cell.commands.common import print_json


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("config", help="check a cell config file")
    what = p.add_subparsers(dest="config_command", required=True, metavar="ACTION")
    chk = what.add_parser("check", help="validate FILE (schema and commissioning checks); no "
                          "hardware is touched")
    chk.add_argument("file", metavar="FILE", help="cell config (TOML)")
    chk.set_defaults(func=run_check)


def run_check(args: argparse.Namespace) -> int:
    import os
    import sys

    # An OAK's settings are validated by its adapter, whose depthai import warns on stdout when
    # no USB is reachable; no device is touched here, and the warning would corrupt --json.
    os.environ.setdefault("DEPTHAI_LEVEL", "error")

    from cell.config.schema import ConfigError, load_config
    from cell.runtime import startup_problems

    try:
        config = load_config(args.file)
        problems = startup_problems(config)
        if problems:
            raise ConfigError(f"{args.file}: cell serve refuses this config", problems)
    except ConfigError as err:
        if args.json:
            print_json({"file": args.file, "ok": False, "error": {
                "code": err.code, "message": str(err),
                "problems": [p.as_dict() for p in err.problems]}})
        else:
            print(f"{args.file}: {len(err.problems)} problem(s)", file=sys.stderr)
            for p in err.problems:
                print(f"  {p}", file=sys.stderr)
        return 2
    devices = {"robot": config.robot.kind + (" (simulated controller)"
                                             if config.robot.kind == "ur"
                                             and config.sim.ur_controller else ""),
               "camera": config.camera.kind, "gripper": config.gripper.kind}
    warnings: list[str] = []
    out = {"file": args.file, "ok": True, "real_hardware": config.has_real_device(),
           "devices": devices, "accepted": list(config.commissioning.accept),
           "warnings": warnings,
           "state": {"job_db": config.api.job_db, "calibration_dir": config.api.calibration_dir,
                     "image_log_dir": config.api.image_log_dir}}
    if args.json:
        print_json(out)
    else:
        kinds = ", ".join(f"{k} {v}" for k, v in devices.items())
        print(f"{args.file}: valid ({kinds}; "
              f"{'real hardware' if out['real_hardware'] else 'all simulated'})")
        if config.commissioning.accept:
            print(f"  accepted on purpose: {', '.join(config.commissioning.accept)}")
        for warning in warnings:
            print(f"  warning: {warning}")
    return 0
