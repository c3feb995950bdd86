"""``cell detect IMAGE`` and ``cell estimate IMAGE``: the estimator on one image file.

Both read the camera and target from the cell config (the built-in simulated cell without
``--config``). Failures (unreadable image, invalid config, no pose) exit with status 2 and,
with ``--json``, print ``{"error": {"code", "message"}}``.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from cell.commands.common import fail, print_json, read_grey

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    from cell.config.schema import CellConfig


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    for name, func, text in (
        ("detect", _detect, "find the target's dots in an image"),
        ("estimate", _estimate, "estimate the target pose in the camera frame from an image"),
    ):
        p = sub.add_parser(name, help=text, description=text)
        p.add_argument("image", metavar="IMAGE", help="8-bit grey (or colour) image file")
        p.add_argument("--config", metavar="CELL.toml", default=None,
                       help="cell config (default: the built-in simulated cell)")
        p.set_defaults(func=func)


def _load(args: argparse.Namespace) -> tuple[CellConfig, NDArray[np.uint8]] | int:
    """Config and grey image, or the exit status of the failure already reported."""
    import numpy as np

    from cell.config.schema import ConfigError, load_config

    try:
        config = load_config(args.config)
    except ConfigError as err:
        return fail(err.code, str(err), args.json)
    image = read_grey(args.image)
    if isinstance(image, str):
        return fail("image_unreadable", image, args.json)
    return config, np.asarray(image, dtype=np.uint8)


def _detect(args: argparse.Namespace) -> int:
    from estimator import detect_blobs

    loaded = _load(args)
    if isinstance(loaded, int):
        return loaded
    config, image = loaded
    blobs = detect_blobs(image, config.target.polarity)
    if args.json:
        print_json({"blobs": [b.as_dict() for b in blobs]})
    else:
        print(f"{len(blobs)} blob(s)")
        for b in blobs:
            print(f"  u={b.u:9.3f} v={b.v:9.3f} area={b.area:7.1f} "
                  f"circularity={b.circularity:.2f} inertia={b.inertia_ratio:.2f}")
    return 0


def _estimate(args: argparse.Namespace) -> int:
    from estimator import EstimationError, Estimator

    loaded = _load(args)
    if isinstance(loaded, int):
        return loaded
    config, image = loaded
    camera = config.camera.model()
    h, w = image.shape
    if (w, h) != (camera.width, camera.height):
        return fail("image_size_mismatch",
                    f"image is {w}x{h} but the configured camera is {camera.width}x"
                    f"{camera.height}: use the calibration of this resolution", args.json)
    try:
        result = Estimator(camera, config.target.model()).estimate(image)
    except EstimationError as err:
        return fail(err.code, err.message, args.json)
    out = result.as_dict()
    if args.json:
        print_json(out)
    else:
        pose = out["T_camera_target"]
        print(f"position_mm {[round(v, 3) for v in pose['position_mm']]}")
        print(f"rotvec_rad  {[round(v, 5) for v in pose['rotvec_rad']]}")
        print(f"rms {result.rms_px:.3f} px, dots {list(result.matched_ids)}, "
              f"ambiguous {result.ambiguous}")
        for note in result.notes:
            print(f"note: {note}")
    return 0
