"""``cell camera snapshot [--config FILE] --out FRAME.png``: save one frame.

The first look through a new cell's camera (focus, exposure, is the target in view), and a
way for external tests to get an image. Without ``--config`` it is the simulated camera with
the built-in settings, looking at the target from a fixed pose.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from cell.commands.common import fail, print_json

if TYPE_CHECKING:
    from cell.config import CellConfig
    from drivers.camera import Camera

# Where the built-in simulated camera looks from: the target ~400 mm ahead, slightly tilted.
SNAPSHOT_DISTANCE_MM = 400.0
SNAPSHOT_TILT_RAD = (0.12, -0.08, 0.05)


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("camera", help="camera commissioning")
    csub = p.add_subparsers(dest="camera_command", required=True, metavar="ACTION")
    snap = csub.add_parser("snapshot", help="save one frame as an image file")
    snap.add_argument("--config", default=None, help="cell config (default: built-in sim)")
    snap.add_argument("--out", required=True, help="image file to write (.png)")
    snap.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for a frame")
    snap.add_argument("--json", action="store_true", help="print JSON")
    snap.set_defaults(func=run_snapshot)


def _sim_camera(config: CellConfig) -> Camera:
    import numpy as np

    from estimator.transforms import T_from_pose
    from fakes.sim_camera import SimCamera

    target = config.target.model()
    centre = target.points_mm.mean(axis=0)
    T_camera_target = T_from_pose([0.0, 0.0, SNAPSHOT_DISTANCE_MM], SNAPSHOT_TILT_RAD) @ \
        T_from_pose(-centre, [0.0, 0.0, 0.0])
    T_base_flange = np.eye(4)  # the camera frame is the base frame here: the pose is fixed

    def pose_source() -> tuple[np.ndarray, float]:
        import time

        return T_base_flange, time.monotonic()

    fps = float(getattr(config.camera, "fps", 15.0))
    return SimCamera(config.camera.model(), target, T_camera_target, np.eye(4), pose_source,
                     fps=fps)


def _oak_camera(config: CellConfig) -> Camera:
    from drivers.oak import OakCamera, OakSettings

    cc = config.camera
    return OakCamera(OakSettings(width=cc.width, height=cc.height,
                                 fps=float(getattr(cc, "fps", 30.0))))


def run_snapshot(args: argparse.Namespace) -> int:
    import cv2

    from cell.config import ConfigError, load_config
    from drivers.errors import DriverError

    try:
        config = load_config(args.config)
    except ConfigError as err:
        return fail(err.code, str(err), args.json)
    kind = str(getattr(config.camera, "kind", "sim"))
    try:
        camera = _oak_camera(config) if kind == "oak" else _sim_camera(config)
    except ValueError as err:
        return fail("config_invalid", str(err), args.json)
    try:
        camera.connect()
        frame = camera.latest_frame(timeout_s=args.timeout)
    except DriverError as err:
        return fail(err.code, str(err), args.json)
    finally:
        camera.disconnect()
    try:
        ok = cv2.imwrite(args.out, frame.image)
    except cv2.error as err:
        return fail("write_failed", f"cannot write {args.out}: {err}", args.json)
    if not ok:
        return fail("write_failed", f"cannot write {args.out} (check the folder and the "
                    "extension, e.g. .png)", args.json)
    info = {
        "out": args.out, "camera": kind, "width": int(frame.image.shape[1]),
        "height": int(frame.image.shape[0]), "sequence": frame.sequence,
        "timestamp_s": frame.timestamp_s,
    }
    if args.json:
        print_json(info)
    else:
        print(f"saved {info['width']}x{info['height']} frame {frame.sequence} from the {kind} "
              f"camera to {args.out}")
    return 0
