"""Commission a simulated cell as an integrator commissions a real one (docs/commissioning.md).

Two steps, each through the cell's own tools, none reading the simulated truth (it is read
here only to score the result afterwards):

1. intrinsics (:func:`measure_intrinsics`): the circle-grid plate of the procedure (10 x 7
   dots of 14 mm at 35 mm pitch) under the home pose, the arm's views of it collected by the
   routine (``cell calibrate routine --board circles``), ``calibrate_intrinsics`` on their
   images (``cell calibrate intrinsics``); the result goes into ``[camera]``, as the
   integrator copies it, and takes effect when the cell starts;
2. hand-eye (:func:`hand_eye`): the routine on the cell's own dot plate (the HTTP API's
   calibration job) and Apply on the running cell. Apply refuses a result whose verdict says
   the data disagree with themselves, as the page does; the cell then stays as it was.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.config.schema import CellConfig, parse_config
from cell.results import HandEyeRoutineResult
from cell.service import Cell
from estimator.transforms import pose_distance

Matrix4 = NDArray[np.float64]
CALLER = "bench"
# as docs/commissioning.md runs the routine: enough views, tilts and rolls for the arm's
# geometry to be fitted with the mount
HAND_EYE_VIEWS = 24
HAND_EYE_TILT_DEG = 30.0
HAND_EYE_ROLL_DEG = 60.0
BOARD_VIEWS = 14
BOARD_TILT_DEG, BOARD_ROLL_DEG = 18.0, 35.0  # the lens's views: the whole grid stays in view
AX_XB_FALLBACK = "tsai"
BOARD_COLS, BOARD_ROWS, BOARD_PITCH_MM = 10, 7, 35.0  # circles: a third of the image or more
BOARD_DOT_MM = 14.0
BOARD_AT = {"position_mm": [-587.0, -30.0, 0.0], "rotvec_rad": [np.pi, 0.0, 0.0]}


def measure_intrinsics(config: CellConfig) -> dict[str, Any]:
    """Step 1 on ``config``'s simulated world with the in-process simulated arm: the lens
    from the board's views. Returns the camera values and the scores; RuntimeError when the
    routine or the calibration fails."""
    from cell.calibration.observe import board_observer
    from cell.calibration.routine import RoutineSettings, run_hand_eye_routine
    from cell.devices import sim_truth
    from cell.runtime import start_cell
    from estimator.calib.board import Board
    from estimator.calib.intrinsics import calibrate_intrinsics

    cols, rows, pitch = BOARD_COLS, BOARD_ROWS, BOARD_PITCH_MM
    data = config.model_dump(mode="python")
    data["robot"]["kind"], data["sim"]["ur_controller"] = "sim", False
    data["gripper"]["kind"] = "none"
    data["target"]["points_mm"] = [[c * pitch, r * pitch, 0.0] for r in range(rows)
                                   for c in range(cols)]
    data["target"]["dot_diameter_mm"] = BOARD_DOT_MM
    data["sim"]["T_base_target"] = BOARD_AT
    cfg = parse_config(data)
    board = Board("circles", cols, rows, pitch)
    limits = cfg.limits
    speed = min(200.0, limits.max_speed_mm_s)
    settings = RoutineSettings(n_views=BOARD_VIEWS, tilt_deg=BOARD_TILT_DEG,
                               roll_deg=BOARD_ROLL_DEG, speed_mm_s=speed,
                               accel_mm_s2=min(4.0 * speed, limits.max_accel_mm_s2))
    t0 = time.monotonic()
    cell = start_cell(cfg)  # the cell's guarded arm, as `cell calibrate routine` uses it
    try:
        core = cell.core
        with core.arm.slot.hold("calibration"):
            result = run_hand_eye_routine(core.arm, core.camera, board_observer(board),
                                          core.frames.T_flange_tcp, core.frames.T_camera_mount,
                                          settings)
    finally:
        cell.close()
    cal = calibrate_intrinsics(board, list(result.images), dot_diameter_mm=BOARD_DOT_MM)
    cam, true = cal.camera, sim_truth.resolve(cfg).camera
    return {"views": len(result.images), "routine_s": time.monotonic() - t0,
            "rms_px": cal.rms_px, "coverage": cal.coverage,
            "camera": {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
                       "dist": [float(d) for d in cam.dist]},
            "truth": {"fx": true.fx, "fy": true.fy, "cx": true.cx, "cy": true.cy,
                      "dist": [float(d) for d in true.dist]}}


def with_intrinsics(config: CellConfig, camera: dict[str, Any]) -> CellConfig:
    """``config`` with the measured lens in ``[camera]`` (what the integrator copies there)."""
    data = config.model_dump(mode="python")
    data["camera"].update({k: camera[k] for k in ("fx", "fy", "cx", "cy", "dist")})
    return parse_config(data)


def hand_eye(cell: Cell, views: int = HAND_EYE_VIEWS) -> dict[str, Any]:
    """Step 2 on the running cell, the target at rest in view of the arm's current pose: the
    routine and Apply. Every method's result and the mount before and after are scored
    against the simulated mount. RuntimeError when the routine itself fails."""
    from cell.calibration.routine import RoutineSettings
    from cell.errors import CellError

    assert cell.sim is not None, "commissioning is scored on the simulated cell"
    truth = cell.sim.truth_values()
    before = pose_distance(cell.core.frames.T_flange_camera, truth.T_flange_camera)
    service = cell.calibration
    t0 = time.monotonic()
    settings = RoutineSettings(n_views=views, tilt_deg=HAND_EYE_TILT_DEG,
                               roll_deg=HAND_EYE_ROLL_DEG)
    job = service.wait(service.start(CALLER, settings).id, 600.0)
    took = time.monotonic() - t0
    r = job.result
    if job.state != "succeeded" or not isinstance(r, HandEyeRoutineResult):
        raise RuntimeError(f"hand-eye routine {job.state}: {job.error_code} {job.error_message}")
    results = {name: m.T_flange_camera for name, m in r.methods.items()}
    refined = {"joint": r.joint, "hybrid": r.hybrid, "kinematic": r.kinematic}
    results.update({name: fit.T_flange_camera for name, fit in refined.items()
                    if fit is not None})
    scored = {name: dict(zip(("mm", "deg"), pose_distance(pose.T(), truth.T_flange_camera),
                             strict=True))
              for name, pose in results.items()}
    out: dict[str, Any] = {
        "views": views, "failed_views": len(r.failed_views), "routine_s": took,
        "chosen": r.chosen, "verdict_consistent": r.verdict.consistent,
        "verdict": r.verdict.text, "methods_vs_truth": scored,
        "mount_error_before_mm": before[0], "mount_error_before_deg": before[1]}
    try:
        service.apply(CALLER, job.id)
        out["applied"] = r.chosen
    except CellError as err:  # an inconsistent verdict: the page refuses Apply too
        out["apply_refused"] = f"{err.code}: {err.message}"
        # docs/commissioning.md: when the verdict blames the robot's reported poses, the
        # AX = XB result (rotation from the motions' rotations alone) is applied, forced
        if err.code == "calibration_inconsistent" and "flange poses" in r.verdict.text:
            service.apply(CALLER, job.id, method=AX_XB_FALLBACK, force=True)
            out["applied"] = f"{AX_XB_FALLBACK} (forced: the verdict blames the arm's poses)"
        else:
            out["applied"] = None
    after = pose_distance(cell.core.frames.T_flange_camera, truth.T_flange_camera)
    out.update(mount_error_after_mm=after[0], mount_error_after_deg=after[1])
    return out


def commission_lens(config: CellConfig) -> tuple[CellConfig, dict[str, Any]]:
    """Step 1 as a bench runs it: ``config`` with the measured lens and the step's record; a
    failure is recorded and the lens stays the configured one."""
    try:
        measured = measure_intrinsics(config)
    except Exception as err:  # recorded; the bench goes on with the configured lens
        return config, {"failed": f"{type(err).__name__}: {err}"}
    return with_intrinsics(config, measured["camera"]), measured


def commission_mount(cell: Cell, T_base_target: Matrix4, go_home: Callable[[Cell], None]
                     ) -> dict[str, Any]:
    """Step 2 as a bench runs it: home (``go_home``), the plate alone at ``T_base_target``,
    the routine and Apply; a failure stops the arm and is recorded, and the mount stays the
    configured one."""
    assert cell.sim is not None, "commissioning is scored on the simulated cell"
    try:
        go_home(cell)
        cell.sim.set_target(T_base_target)
        time.sleep(0.15)  # frames exposed before the placement are not of this scene
        return hand_eye(cell)
    except Exception as err:  # recorded; the mount stays the configured one
        cell.stop(CALLER, reason="bench: commissioning failed")
        return {"failed": f"{type(err).__name__}: {err}"}
