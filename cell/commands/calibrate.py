"""``cell calibrate {hand-eye,intrinsics,routine}``: calibrate from images or on the arm
(``check`` and ``reference``, on a running service: :mod:`cell.commands.calibration_check`).

``hand-eye`` reads ViSP's eye-in-hand folder as it is or the project's dataset.json format,
prints every method's ``T_flange_camera`` with the residuals and a verdict, and can write the
chosen result into a cell config. ``intrinsics`` calibrates the camera from board images.
``routine`` moves the configured arm through views of the target and solves the same way.
Both choose the same default method (:data:`cell.calibration.solve.DEFAULT_METHOD`), so
re-solving a routine's saved views gives the routine's answer.

Exit status: 0 when the verdict is that the data agree, 1 when it is that they disagree (the
full report is still printed, and nothing is written into a config unless ``--force``), 2 on an
error. ``--write-config`` edits only an existing, valid cell config, keeps a timestamped backup
of it and prints the change.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

from cell.calibration.defaults import DEFAULT_VIEWS
from cell.commands import calibration_check
from cell.commands.common import EXIT_NO, EXIT_OK, fail, print_json, progress_bars

if TYPE_CHECKING:

    from cell.calibration.report import HandEyeReport

METHOD_CHOICES = ["tsai", "park", "horaud", "joint", "hybrid", "auto"]


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("calibrate", help="camera intrinsics and eye-in-hand hand-eye calibration")
    what = p.add_subparsers(dest="calibration", required=True, metavar="WHAT")

    he = what.add_parser("hand-eye", help="T_flange_camera from board images and robot poses")
    he.add_argument("folder", metavar="DIR", help="ViSP eye-in-hand folder or dataset.json folder")
    he.add_argument("--method", default=None, choices=METHOD_CHOICES,
                    help="the result to choose (all are computed and printed; default auto, "
                         "as the routine; tsai with --no-refine)")
    he.add_argument("--no-refine", action="store_true",
                    help="skip the joint reprojection refinement")
    he.add_argument("--write-config", metavar="FILE",
                    help="write the chosen T_flange_camera (T_base_camera for a fixed camera) "
                         "into FILE's [hand_eye] table (an "
                         "existing, valid cell config; a timestamped backup is kept)")
    he.add_argument("--force", action="store_true",
                    help="write the config even when the verdict is that the data disagree")
    he.add_argument("--config", metavar="FILE",
                    help="cell config whose [camera] mount says how to solve (\"fixed\": a "
                         "plate on the tool before a fixed camera, giving T_base_camera); "
                         "default: --write-config's file, else eye-in-hand")
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
    it.add_argument("--dot-mm", type=float, default=None,
                    help="circle grids: the dots' diameter in mm, to correct the perspective "
                         "bias of their centroids (else the focal length comes out ~0.03 %% "
                         "short with dots of 0.4 x the pitch)")
    it.set_defaults(func=run_intrinsics)

    rt = what.add_parser(
        "routine", help="move the arm around its current pose, collect views and solve hand-eye "
                        "(a fixed camera, per --config's mount: the plate on the tool)"
    )
    rt.add_argument("--config", metavar="FILE", help="cell config (default: the simulated cell)")
    rt.add_argument("--views", type=int, default=DEFAULT_VIEWS,
                    help=f"number of views (default {DEFAULT_VIEWS})")
    rt.add_argument("--tilt-deg", type=float, default=30.0,
                    help="camera tilt about the target (default 30)")
    rt.add_argument("--roll-deg", type=float, default=60.0,
                    help="largest roll about the optical axis (default 60); from 16 views on "
                         "the arm's geometry is fitted with the mount")
    rt.add_argument("--speed-mm-s", type=float, default=None,
                    help="linear move speed (default: 200 or the config's limits.max_speed_mm_s "
                         "if lower; above that limit is refused)")
    rt.add_argument("--method", default=None, choices=METHOD_CHOICES,
                    help="the result to choose (default auto: joint, or hybrid when the "
                         "robot's poses are off by more than the images' noise)")
    rt.add_argument("--board", choices=["chessboard", "circles", "acircles"],
                    help="look at a calibration board instead of the cell's dot target")
    rt.add_argument("--cols", type=int, default=9)
    rt.add_argument("--rows", type=int, default=6)
    rt.add_argument("--square-mm", "--pitch-mm", dest="pitch_mm", type=float, default=25.0)
    rt.add_argument("--write-config", metavar="FILE",
                    help="write the chosen T_flange_camera (T_base_camera for a fixed camera) "
                         "into FILE's [hand_eye] table (an "
                         "existing, valid cell config; a timestamped backup is kept)")
    rt.add_argument("--force", action="store_true",
                    help="write the config even when the verdict is that the data disagree")
    rt.add_argument("--save-dataset", metavar="DIR",
                    help="write the views (images and flange poses) as a dataset to DIR, for "
                         "`cell calibrate hand-eye DIR` to re-solve")
    rt.set_defaults(func=run_routine)
    calibration_check.register(what)


def _write(args: argparse.Namespace, report: HandEyeReport, note: str
           ) -> dict[str, Any] | str | int | None:
    """Write the chosen result if asked. Returns the change, why it was not written (the data
    disagree and no ``--force``), the exit status of a reported write error, or None."""
    import sys

    from cell.calibration.config_writer import ConfigWriteError, write_hand_eye

    if not args.write_config:
        return None
    if not report.verdict.consistent and not args.force:
        reason = (f"not written to {args.write_config}: the data disagree with themselves; "
                  "pass --force to write the result anyway")
        if not args.json:
            print(reason, file=sys.stderr)
        return reason
    try:
        change = write_hand_eye(args.write_config, report.T_flange_camera, note)
    except ConfigWriteError as err:
        return fail(err.code, str(err), args.json)
    if not args.json:
        print(f"wrote ({report.chosen}) {change.summary()}")
    return change.record().json_dict()


def _json_write_fields(written: dict[str, Any] | str | None, path: str | None
                       ) -> dict[str, Any]:
    change = written if isinstance(written, dict) else None
    return {"written_config": path if change is not None else None, "config_change": change,
            "not_written": written if isinstance(written, str) else None}


def _verdict_status(report: HandEyeReport) -> int:
    return EXIT_OK if report.verdict.consistent else EXIT_NO


def _method(args: argparse.Namespace) -> str:
    from cell.calibration.solve import DEFAULT_METHOD

    if args.method is not None:
        return str(args.method)
    return "tsai" if getattr(args, "no_refine", False) else DEFAULT_METHOD


def _fixed_mount(args: argparse.Namespace) -> bool:
    """The camera mount of ``--config`` (else ``--write-config``'s file): fixed or on the hand."""
    from cell.config.schema import ConfigError, load_config

    path = getattr(args, "config", None) or getattr(args, "write_config", None)
    if not path:
        return False
    try:
        return load_config(path).fixed_camera
    except ConfigError:
        return False  # the write step reports the file's problem


def run_hand_eye(args: argparse.Namespace) -> int:
    from cell.calibration.dataset import DatasetError, load_dataset
    from cell.calibration.report import mount_fields
    from cell.calibration.solve import solve_dataset
    from estimator.calib.handeye import HandEyeError

    try:
        dataset = load_dataset(args.folder)
        with progress_bars(not args.json) as progress:
            report = solve_dataset(dataset, _method(args), refine=not args.no_refine,
                                   progress=progress, fixed_camera=_fixed_mount(args))
    except DatasetError as err:
        return fail(err.code, err.message, args.json)
    except HandEyeError as err:
        return fail(err.code, str(err), args.json)
    chosen = report.methods.get(report.chosen)
    note = f"cell calibrate hand-eye {dataset.folder} --method {report.chosen}"
    if chosen is not None:
        note += (f": base-board spread {chosen.spread.mean_mm:.2f} mm / "
                 f"{chosen.spread.mean_deg:.3f} deg")
    if report.joint is not None:
        note += f", joint reprojection rms {report.joint.rms_px:.2f} px"
    fixed = _fixed_mount(args)
    if not args.json:
        if fixed:
            print("fixed camera: the result (T_flange_camera below) is T_base_camera")
        print(report.summary())
    written = _write(args, report, note)
    if isinstance(written, int):
        return written
    if args.json:
        out = (report.solution().json_dict()
               | mount_fields(fixed, report.T_flange_camera).json_dict())
        out["dataset"] = {"folder": str(dataset.folder), "format": dataset.source}
        out.update(_json_write_fields(written, args.write_config))
        print_json(out)
    return _verdict_status(report)


def run_routine(args: argparse.Namespace) -> int:
    from cell.calibration.dataset import DatasetError, new_dataset_folder
    from cell.calibration.observe import board_observer, dot_target_observer
    from cell.calibration.report import mount_fields
    from cell.calibration.routine import (
        RoutineError,
        RoutineSettings,
        run_hand_eye_routine,
        save_views,
    )
    from cell.config.schema import ConfigError, load_config
    from cell.devices.factory import build_hardware
    from cell.errors import CellError
    from cell.motion.guard import GuardedArm
    from cell.motion.limits import SafetyGuard
    from cell.vision.frames import cell_frames
    from cell.vision.intrinsics import IntrinsicsPolicy
    from drivers.errors import DriverError
    from estimator.calib.board import Board
    from estimator.kinematics import UR_DH

    try:
        cfg = load_config(args.config)
        limits = cfg.limits
        speed = min(200.0, limits.max_speed_mm_s) if args.speed_mm_s is None else args.speed_mm_s
        accel = min(4.0 * speed, limits.max_accel_mm_s2)
        SafetyGuard(limits).check_speed(speed, accel)  # refused before anything is built
        settings = RoutineSettings(n_views=args.views, tilt_deg=args.tilt_deg,
                                   roll_deg=args.roll_deg, speed_mm_s=speed, accel_mm_s2=accel,
                                   chosen=_method(args), min_views=min(6, args.views))
        pattern = (Board(args.board, args.cols, args.rows, args.pitch_mm) if args.board
                   else cfg.target.model())
        observer = (board_observer(pattern) if isinstance(pattern, Board)
                    else dot_target_observer(pattern))
        if args.save_dataset:  # checked before the arm moves for minutes
            new_dataset_folder(args.save_dataset)
        if args.write_config:  # likewise: a config that cannot take the result
            _check_writable_config(args.write_config)
    except ConfigError as err:
        return fail(err.code, str(err), args.json)
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
        arm = GuardedArm(hw.arm, limits, model=cfg.robot.model)  # checked as in the service
        arm.connect()
        arm.power_on()
        arm.set_tcp(T_flange_tcp)
        hw.camera.connect()
        fixed = cfg.fixed_camera  # then the pattern is on the tool and the result T_base_camera
        guess = cell_frames(cfg).T_camera_mount
        with progress_bars(not args.json) as progress, arm.slot.hold("calibration"):
            result = run_hand_eye_routine(
                arm, hw.camera, observer, T_flange_tcp, guess, settings, progress=progress,
                fixed_camera=fixed,
                intrinsics=IntrinsicsPolicy(cfg.camera.model(), cfg.camera.intrinsics).model_for,
                arm_geometry=UR_DH[cfg.robot.model],
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
            saved = str(save_views(args.save_dataset, result, pattern, cfg.robot.model).folder)
        except DatasetError as err:
            return fail(err.code, err.message, args.json)
    if not args.json:
        if fixed:
            print("fixed camera: the result (T_flange_camera below) is T_base_camera")
        print(report.summary())
        for k, reason in result.failed:
            print(f"view {k} skipped: {reason}")
        if saved:
            print(f"views saved to {saved} (re-solve: cell calibrate hand-eye {saved})")
    note = f"cell calibrate routine, {len(report.view_names)} views, --method {report.chosen}"
    written = _write(args, report, note)
    if isinstance(written, int):
        return written
    if args.json:
        out = (report.solution().json_dict()
               | mount_fields(fixed, report.T_flange_camera).json_dict())
        out["failed_views"] = [{"view": k, "reason": r} for k, r in result.failed]
        out.update(_json_write_fields(written, args.write_config))
        out["dataset"] = saved
        print_json(out)
    return _verdict_status(report)


def _check_writable_config(path: str) -> None:
    """Refuse before the routine moves the arm when ``--write-config`` could not be honoured."""
    from pathlib import Path

    from cell.config.schema import ConfigError, load_config

    if not Path(path).is_file():
        raise ValueError(f"--write-config {path}: no such file; the result is written only into "
                         "an existing cell config")
    try:
        load_config(path)
    except ConfigError as err:
        raise ValueError(f"--write-config {path} is not a valid cell config: {err}") from err


def run_intrinsics(args: argparse.Namespace) -> int:
    from pathlib import Path

    from cell.calibration.dataset import IMAGE_SUFFIXES
    from cell.commands.common import read_grey
    from estimator.calib.board import Board
    from estimator.calib.intrinsics import MIN_COVERAGE, IntrinsicsError, calibrate_intrinsics

    folder = Path(args.folder)
    if not folder.is_dir():
        return fail("dataset_not_found", f"{folder} is not a folder", args.json)
    try:
        board = Board(args.board, args.cols, args.rows, args.pitch_mm)
    except ValueError as err:
        return fail("invalid_argument", str(err), args.json)
    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    images = []
    with progress_bars(not args.json) as progress:
        for k, p in enumerate(paths):
            img = read_grey(p)
            if isinstance(img, str):
                return fail("image_unreadable", img, args.json)
            images.append(img)
            if progress is not None:
                progress("read", k + 1, len(paths))
        if progress is not None:
            progress("calibrate", 0, 1)
        try:
            result = calibrate_intrinsics(board, images, distortion=not args.no_distortion,
                                          dot_diameter_mm=args.dot_mm)
        except IntrinsicsError as err:
            return fail(err.code, str(err), args.json)
        if progress is not None:
            progress("calibrate", 1, 1)
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
            "coverage": result.coverage,
        })
        return 0
    print(f"fx {cam.fx:.2f}  fy {cam.fy:.2f}  cx {cam.cx:.2f}  cy {cam.cy:.2f}  "
          f"({cam.width}x{cam.height}), dist {[round(d, 5) for d in cam.dist]}")
    print(f"rms {result.rms_px:.3f} px over {len(per_image)} image(s)")
    for name, rms in per_image.items():
        print(f"  {name}: {rms:.3f} px")
    if rejected:
        print(f"board not found in: {', '.join(rejected)}")
    print(f"the board's points cover {100 * result.coverage:.0f} % of the image")
    if result.coverage < MIN_COVERAGE:
        print(f"under {100 * MIN_COVERAGE:.0f} %: the distortion is measured only there and "
              "extrapolated beyond; add views with the board near the edges and corners")
    return 0
