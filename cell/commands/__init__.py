"""Subcommands of ``cell``. Each module exposes ``register(subparsers)``; heavy imports stay
inside the command functions so ``cell --help`` is fast."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from cell.commands import bench, calibrate, camera, config, gripper, serve, teach, vision

Register = Callable[["argparse._SubParsersAction[argparse.ArgumentParser]"], None]

COMMANDS: list[Register] = [
    vision.register,  # detect, estimate
    bench.register,
    gripper.register,
    camera.register,
    serve.register,
    calibrate.register,
    teach.register,
    config.register,
]
