"""``cell calibrate {hand-eye,intrinsics,routine}``: calibrate from images or on the arm.

``hand-eye`` reads ViSP's eye-in-hand folder as it is or the project's dataset.json format,
prints every method's ``T_flange_camera`` with the residuals and a verdict, and can write the
chosen result into a cell config. ``intrinsics`` calibrates the camera from board images.
``routine`` moves the configured arm through views of the target and solves the same way.
A verdict of inconsistent data is a result, not an error: the exit status is 0 with a report.
"""

from __future__ import annotations

import argparse
import sys


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("calibrate", help="camera intrinsics and eye-in-hand hand-eye calibration")
    what = p.add_subparsers(dest="calibration", required=True, metavar="WHAT")

    he = what.add_parser("hand-eye", help="T_flange_camera from board images and robot poses")
    he.add_argument("folder", metavar="DIR", help="ViSP eye-in-hand folder or dataset.json folder")
    he.add_argument("--method", default="tsai", choices=["tsai", "park", "horaud", "joint"],
                    help="the result to choose (all are computed and printed; default tsai)")
    he.add_argument("--no-refine", action="store_true",
                    help="skip the joint reprojection refinement")
    he.add_argument("--write-config", metavar="FILE",
                    help="write the chosen T_flange_camera into FILE's [hand_eye] table")
    he.add_argument("--json", action="store_true", help="print JSON")
    he.set_defaults(func=run_hand_eye)

    it = what.add_parser("intrinsics", help="fx, fy, cx, cy and distortion from board images")
    it.add_argument("folder", metavar="DIR", help="folder of board images")
    it.add_argument("--board", default="chessboard", choices=["chessboard", "circles", "acircles"])
    it.add_argument("--cols", type=int, required=True,
                    help="inner corners (chessboard) or circles along a row")
    it.add_argument("--rows", type=int, required=True, help="inner corners or circles per column")
    it.add_argument("--square-mm", "--pitch-mm", dest="pitch_mm", type=float, required=True,
                    help="square size, or circle spacing along a row, in mm")
    it.add_argument("--no-distortion", action="store_true",
                    help="ideal pinhole: fix all distortion coefficients at zero")
    it.add_argument("--json", action="store_true", help="print JSON")
    it.set_defaults(func=run_intrinsics)

    rt = what.add_parser(
        "routine", help="move the arm around its current pose, collect views and solve hand-eye"
    )
    rt.add_argument("--config", metavar="FILE", help="cell config (default: the simulated cell)")
    rt.add_argument("--views", type=int, default=12, help="number of views (default 12)")
    rt.add_argument("--tilt-deg", type=float, default=18.0, help="camera tilt about the target")
    rt.add_argument("--speed-mm-s", type=float, default=None,
                    help="linear move speed (default: 200 or the config's limits.max_speed_mm_s "
                         "if lower; above that limit is refused)")
    rt.add_argument("--method", default="joint", choices=["tsai", "park", "horaud", "joint"],
                    help="the result to choose (default joint)")
    rt.add_argument("--board", choices=["chessboard", "circles", "acircles"],
                    help="look at a calibration board instead of the cell's dot target")
    rt.add_argument("--cols", type=int, default=9)
    rt.add_argument("--rows", type=int, default=6)
    rt.add_argument("--square-mm", "--pitch-mm", dest="pitch_mm", type=float, default=25.0)
    rt.add_argument("--write-config", metavar="FILE",
                    help="write the chosen T_flange_camera into FILE's [hand_eye] table")
    rt.add_argument("--save-dataset", metavar="DIR",
                    help="write the views (images and flange poses) as a dataset to DIR, for "
                         "`cell calibrate hand-eye DIR` to re-solve")
    rt.add_argument("--json", action="store_true", help="print JSON")
    rt.set_defaults(func=run_routine)


def _progress(stage: str, done: int, total: int) -> None:
    print(f"\r{stage} {done}/{total}", end="\n" if done == total else "", file=sys.stderr,
          flush=True)


def run_hand_eye(args: argparse.Namespace) -> int:
    from cell.calibration.config_writer import ConfigWriteError, write_hand_eye
    from cell.calibration.dataset import DatasetError, load_dataset
    from cell.calibration.solve import solve_dataset
    from cell.commands.common import fail, print_json
    from estimator.calib.handeye import HandEyeError

    try:
        dataset = load_dataset(args.folder)
        report = solve_dataset(dataset, args.method, refine=not args.no_refine,
                               progress=None if args.json else _progress)
    except DatasetError as err:
        return fail(err.code, err.message, args.json)
    except HandEyeError as err:
        return fail(err.code, str(err), args.json)
    written = None
    if args.write_config:
        chosen = report.methods.get(report.chosen)
        note = f"cell calibrate hand-eye {dataset.folder} --method {report.chosen}"
        if chosen is not None:
            note += (f": base-board spread {chosen.spread.mean_mm:.2f} mm / "
                     f"{chosen.spread.mean_deg:.3f} deg")
        if report.joint is not None:
            note += f", joint reprojection rms {report.joint.rms_px:.2f} px"
        try:
            write_hand_eye(args.write_config, report.T_flange_camera, note)
        except ConfigWriteError as err:
            return fail(err.code, str(err), args.json)
        written = args.write_config
    if args.json:
        out = report.as_dict()
        out["dataset"] = {"folder": str(dataset.folder), "format": dataset.source}
        out["written_config"] = written
        print_json(out)
    else:
        print(report.summary())
        if written:
            print(f"wrote [hand_eye] T_flange_camera ({report.chosen}) to {written}")
    return 0


def run_routine(args: argparse.Namespace) -> int:
    from cell.calibration.config_writer import ConfigWriteError, write_hand_eye
    from cell.calibration.dataset import DatasetError, new_dataset_folder
    from cell.calibration.observe import board_observer, dot_target_observer
    from cell.calibration.routine import (
        RoutineError,
        RoutineSettings,
        run_hand_eye_routine,
        save_views,
    )
    from cell.commands.common import fail, print_json
    from cell.config import ConfigError, load_config
    from cell.factory import build_hardware
    from cell.motion import GuardedArm
    from cell.safety import CellError, SafetyGuard
    from drivers.errors import DriverError
    from estimator.calib.board import Board

    try:
        cfg = load_config(args.config)
        limits = cfg.limits
        speed = min(200.0, limits.max_speed_mm_s) if args.speed_mm_s is None else args.speed_mm_s
        accel = min(4.0 * speed, limits.max_accel_mm_s2)
        SafetyGuard(limits).check_speed(speed, accel)  # refused before anything is built
        settings = RoutineSettings(n_views=args.views, tilt_deg=args.tilt_deg,
                                   speed_mm_s=speed, accel_mm_s2=accel,
                                   chosen=args.method, min_views=min(6, args.views))
        pattern = (Board(args.board, args.cols, args.rows, args.pitch_mm) if args.board
                   else cfg.target.model())
        observer = (board_observer(pattern) if isinstance(pattern, Board)
                    else dot_target_observer(pattern))
        if args.save_dataset:  # checked before the arm moves for minutes
            new_dataset_folder(args.save_dataset)
    except ConfigError as err:
        return fail(ConfigError.code, str(err), args.json)
    except DatasetError as err:
        return fail(err.code, err.message, args.json)
    except CellError as err:
        return fail(err.code, err.message, args.json)
    except ValueError as err:
        return fail("invalid_argument", str(err), args.json)
    try:
        hw = build_hardware(cfg)
    except (ConfigError, DriverError) as err:
        return fail(err.code, str(err), args.json)
    try:
        T_flange_tcp = cfg.tool.T_flange_tcp.T()
        arm = GuardedArm(hw.arm, limits)  # every view pose checked, as in the service
        arm.connect()
        arm.power_on()
        arm.set_tcp(T_flange_tcp)
        hw.camera.connect()
        with arm.slot.hold("calibration"):
            result = run_hand_eye_routine(
                arm, hw.camera, observer, T_flange_tcp, cfg.hand_eye.T_flange_camera.T(),
                settings, progress=None if args.json else _progress,
            )
    except RoutineError as err:
        return fail(err.code, err.message, args.json)
    except CellError as err:
        return fail(err.code, err.message, args.json)
    except DriverError as err:
        return fail(err.code, str(err), args.json)
    finally:
        hw.close()
    report = result.report
    saved = None
    if args.save_dataset:
        try:
            saved = str(save_views(args.save_dataset, result, pattern).folder)
        except DatasetError as err:
            return fail(err.code, err.message, args.json)
    written = None
    if args.write_config:
        note = f"cell calibrate routine, {len(report.view_names)} views, --method {report.chosen}"
        try:
            write_hand_eye(args.write_config, report.T_flange_camera, note)
        except ConfigWriteError as err:
            return fail(err.code, str(err), args.json)
        written = args.write_config
    if args.json:
        out = report.as_dict()
        out["failed_views"] = [{"view": k, "reason": r} for k, r in result.failed]
        out["written_config"] = written
        out["dataset"] = saved
        print_json(out)
    else:
        print(report.summary())
        for k, reason in result.failed:
            print(f"view {k} skipped: {reason}")
        if saved:
            print(f"views saved to {saved} (re-solve: cell calibrate hand-eye {saved})")
        if written:
            print(f"wrote [hand_eye] T_flange_camera ({report.chosen}) to {written}")
    return 0


def run_intrinsics(args: argparse.Namespace) -> int:
    from pathlib import Path

    import cv2
    import numpy as np

    from cell.calibration.dataset import IMAGE_SUFFIXES
    from cell.commands.common import fail, print_json
    from estimator.calib.board import Board
    from estimator.calib.intrinsics import IntrinsicsError, calibrate_intrinsics

    folder = Path(args.folder)
    if not folder.is_dir():
        return fail("dataset_not_found", f"{folder} is not a folder", args.json)
    try:
        board = Board(args.board, args.cols, args.rows, args.pitch_mm)
    except ValueError as err:
        return fail("invalid_argument", str(err), args.json)
    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    images = []
    for p in paths:
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            return fail("image_unreadable", f"cannot read image {p}", args.json)
        images.append(np.asarray(img, dtype=np.uint8))
    try:
        result = calibrate_intrinsics(board, images, distortion=not args.no_distortion)
    except IntrinsicsError as err:
        return fail(err.code, str(err), args.json)
    cam = result.camera
    per_image = {paths[i].name: e for i, e in zip(result.used, result.per_image_rms_px,
                                                  strict=True)}
    rejected = [paths[i].name for i in result.rejected]
    if args.json:
        print_json({
            "camera": {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
                       "width": cam.width, "height": cam.height, "dist": list(cam.dist)},
            "rms_px": result.rms_px,
            "per_image_rms_px": per_image,
            "rejected": rejected,
        })
        return 0
    print(f"fx {cam.fx:.2f}  fy {cam.fy:.2f}  cx {cam.cx:.2f}  cy {cam.cy:.2f}  "
          f"({cam.width}x{cam.height}), dist {[round(d, 5) for d in cam.dist]}")
    print(f"rms {result.rms_px:.3f} px over {len(per_image)} image(s)")
    for name, rms in per_image.items():
        print(f"  {name}: {rms:.3f} px")
    if rejected:
        print(f"board not found in: {', '.join(rejected)}")
    return 0
