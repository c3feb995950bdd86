"""``cell camera snapshot [--config FILE] --out FRAME.png``: save one frame.

The first look through a new cell's camera (focus, exposure, is the target in view), and a
way for external tests to get an image. Without ``--config`` it is the simulated camera with
the built-in settings, looking at the target from the simulated arm's home pose. The camera
is built by :func:`cell.devices.factory.build_camera`, the one place that chooses real or fake.
"""

from __future__ import annotations

import argparse
from typing import Any

from cell.commands.common import fail, print_json, progress_bars


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("camera", help="camera commissioning")
    csub = p.add_subparsers(dest="camera_command", required=True, metavar="ACTION")
    snap = csub.add_parser("snapshot", help="save one frame as an image file")
    snap.add_argument("--config", default=None, help="cell config (default: built-in sim)")
    snap.add_argument("--out", required=True, help="image file to write (.png)")
    snap.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for a frame")
    snap.set_defaults(func=run_snapshot)


def run_snapshot(args: argparse.Namespace) -> int:
    import cv2

    from cell.config.devices import OakCameraConfig
    from cell.config.schema import ConfigError, load_config
    from cell.devices.factory import build_camera
    from drivers.errors import DriverError

    try:
        config = load_config(args.config)
    except ConfigError as err:
        return fail(err.code, str(err), args.json)
    kind = config.camera.kind
    oak = config.camera if isinstance(config.camera, OakCameraConfig) else None
    try:
        camera, release = build_camera(config)
    except (ConfigError, ValueError) as err:
        return fail("config_invalid", str(err), args.json)
    try:
        with progress_bars(not args.json) as progress:
            if progress is not None:
                progress("snapshot", 0, 2)
            camera.connect()
            if progress is not None:
                progress("snapshot", 1, 2)
            frame = camera.latest_frame(timeout_s=args.timeout)
            in_force = camera.get_settings()
            if progress is not None:
                progress("snapshot", 2, 2)
    except DriverError as err:
        return fail(err.code, str(err), args.json)
    finally:
        release()
    try:
        ok = cv2.imwrite(args.out, frame.image)
    except cv2.error as err:
        return fail("write_failed", f"cannot write {args.out}: {err}", args.json)
    if not ok:
        return fail("write_failed", f"cannot write {args.out} (check the folder and the "
                    "extension, e.g. .png)", args.json)
    cam = frame.camera
    info = {
        "out": args.out, "camera": kind, "width": int(frame.image.shape[1]),
        "height": int(frame.image.shape[0]), "sequence": frame.sequence,
        "timestamp_s": frame.timestamp_s,
        # What the camera runs with: check these against the [camera] table.
        "settings": {
            "device_id": oak.device_id if oak is not None else None,
            "socket": oak.socket if oak is not None else None,
            "fps": config.camera.fps, "exposure_us": in_force.exposure_us,
            "iso": in_force.iso, "focus": in_force.focus,
        },
        # The intrinsics valid for this image: what a real cell's [camera] table should hold.
        "intrinsics": {
            "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
            "width": cam.width, "height": cam.height, "dist": list(cam.dist),
        },
    }
    if args.json:
        print_json(info)
    else:
        print(f"saved {info['width']}x{info['height']} frame {frame.sequence} from the {kind} "
              f"camera to {args.out}")
        print("settings in force: " + _settings_line(info["settings"]))
        c = info["intrinsics"]
        print(f"intrinsics: fx {c['fx']:.2f} fy {c['fy']:.2f} cx {c['cx']:.2f} cy {c['cy']:.2f}"
              f" dist {[round(d, 5) for d in c['dist']]}")
    return 0


def _settings_line(s: dict[str, Any]) -> str:
    focus = s["focus"]
    parts = [f"{s['fps']:g} fps",
             f"exposure {s['exposure_us']} us" if s["exposure_us"] is not None else "",
             f"iso {s['iso']}" if s["iso"] is not None else "",
             "focus fixed (no lens control)" if focus is None else
             ("autofocus" if focus == "auto" else f"focus lens position {focus}")]
    if s["socket"]:
        parts.append(f"socket {s['socket']}")
    if s["device_id"] is not None:
        parts.append(f"device {s['device_id'] or 'first found'}")
    return ", ".join(p for p in parts if p)
