"""``cell bench loops``: servo and IBVS to a view taught by showing, with the camera's mount off
the hand-eye calibration, against the simulator's truth.

The simulated cell runs with the ideal world but for the camera's true mount: 1.5 / -1.0 / 2.0
mm and 0.5 deg about [1, 1, 0] from ``[hand_eye]``. ``arm="ur"`` (the default) drives it as
``make run`` serves it, through the UR adapter, ur_rtde and the simulated controller in their
own processes; ``arm="sim"`` uses the in-process arm (no controller, no pose pushes).

A view is taught at home (``teach``, ``teach_samples`` samples of ``[teach]
frames_per_sample`` frames, as an operator's ``POST /teach``), and taught again for every
repeat: the taught view's own error is shared by every run from it, so one teach would make a
set of runs one draw. The repeats take the teach poses in turn (``TEACH_POSES``: home, 456 mm
from the plate and square to it, and a pose 150 mm nearer and tilted 8 deg). Each run jogs the
arm by one of the jogs (base frame: translation mm, rotation deg) and approaches the taught
view with no standoff. For every run: the job's state and time, the true error (the
simulator's TCP against the true TCP at teaching) and the error the job claims
(``estimated_error_mm`` / ``_deg``), and whether the claim bounds the truth; per mode, how
often it did and how many runs ended within the mode's target (``TARGETS``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from cell.bench.ibvs import jog_to
from cell.config.schema import load_config, parse_config
from cell.errors import CellError
from cell.runtime import start_cell
from cell.vision.frames import step_goal
from estimator.transforms import pose_distance
from fakes.ur_controller.process import free_loopback_host

CALLER = "bench:loops"
MOUNT_ERROR_MM = (1.5, -1.0, 2.0)
MOUNT_ERROR_AXIS = (1.0, 1.0, 0.0)
MOUNT_ERROR_DEG = 0.5
# (translation mm, rotation deg), base frame: the jog first, then others a user makes
JOGS: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = (
    ((25.0, -15.0, 10.0), (0.0, 0.0, 6.0)),
    ((10.0, 0.0, 0.0), (2.0, 0.0, 0.0)),
    ((0.0, 40.0, -20.0), (0.0, 8.0, 0.0)),
    ((-60.0, 20.0, 0.0), (0.0, 0.0, 15.0)),
)
# where the view is taught, from home (base frame: translation mm, rotation deg about the TCP)
TEACH_POSES: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = (
    ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
    ((20.0, -15.0, -150.0), (8.0, 0.0, 0.0)),
)
MODES = ("servo", "ibvs")
ARMS = ("ur", "sim")
# the true error each mode is to end within (mm, deg)
TARGETS = {"servo": (0.1, 0.05), "ibvs": (0.05, 0.02)}


def _config(tmp: Path, arm: str = "ur") -> Any:
    data = load_config().model_dump(mode="python")
    if arm == "ur":
        data["robot"]["kind"] = "ur"
        data["robot"]["host"] = free_loopback_host()
        data["sim"]["ur_controller"] = True
    else:
        data["robot"]["kind"] = "sim"
        data["sim"]["ur_controller"] = False
    data["gripper"]["kind"] = "none"
    data["api"]["job_db"] = str(tmp / "jobs.db")
    data["api"]["calibration_dir"] = str(tmp / "calibration")
    data["modbus"]["port"] = 0
    data["opcua"]["enabled"] = False
    he = data["hand_eye"]["T_flange_camera"]
    axis = np.asarray(MOUNT_ERROR_AXIS) / np.linalg.norm(MOUNT_ERROR_AXIS)
    data["sim"]["T_flange_camera"] = {
        "position_mm": (np.asarray(he["position_mm"]) + MOUNT_ERROR_MM).tolist(),
        "rotvec_rad": (axis * np.radians(MOUNT_ERROR_DEG)).tolist()}
    return parse_config(data)


def run_bench_loops(*, repeats: int = 3, modes: tuple[str, ...] = MODES,
                    teach_samples: int = 5, burners: int = 0,
                    arm: str = "ur") -> dict[str, Any]:
    if arm not in ARMS:
        raise ValueError(f"arm must be one of {ARMS}, got {arm!r}")
    rows: list[dict[str, Any]] = []
    with contextlib.ExitStack() as stack:
        if burners > 0:
            from fakes.ur_controller.load import cpu_burners

            stack.enter_context(cpu_burners(burners, max_s=3600.0))
        tmp = stack.enter_context(tempfile.TemporaryDirectory())
        cell = start_cell(_config(Path(tmp), arm))
        try:
            assert cell.sim is not None
            time.sleep(1.0)
            T_home = cell.arm_state().T_base_tcp
            teach_frames: int | None = None
            for repeat in range(repeats):
                pose_i = repeat % len(TEACH_POSES)
                jog_to(cell, step_goal(T_home, *TEACH_POSES[pose_i], frame="base"))
                taught = cell.teach(CALLER, "view", samples=teach_samples)
                T_taught = cell.sim.true_T_base_tcp()
                teach_frames = taught.view.frames if taught.view is not None else None
                for jog_i, (t_mm, r_deg) in enumerate(JOGS):
                    for mode in modes:
                        rows.append({"teach": repeat, "teach_pose": pose_i}
                                    | _run(cell, taught, T_taught, mode, jog_i, t_mm, r_deg))
        finally:
            cell.close()
    return {"teach_samples": teach_samples, "teach_frames": teach_frames,
            "teach_poses": [list(map(list, p)) for p in TEACH_POSES],
            "jogs": [list(map(list, j)) for j in JOGS],
            "runs": rows, "summary": {m: _summary([r for r in rows if r["mode"] == m])
                                      for m in modes},
            "arm": arm, "burners": burners, "load_average": list(os.getloadavg())}


def _run(cell: Any, taught: Any, T_taught: Any, mode: str, jog_i: int,
         t_mm: tuple[float, ...], r_deg: tuple[float, ...]) -> dict[str, Any]:
    row: dict[str, Any] = {"mode": mode, "jog": jog_i, "load_1min": os.getloadavg()[0]}
    try:
        cell.jog_step(CALLER, frame="base", translation_mm=list(t_mm),
                      rotation_deg=list(r_deg), speed_mm_s=100.0)
        time.sleep(0.3)
        t0 = time.monotonic()
        kw: dict[str, Any] = {"view": taught.view} if mode == "ibvs" else {"standoff_mm": 0.0}
        job = cell.approach(CALLER, T_target_tcp=taught.T_target_tcp, mode=mode, wait=True,
                            wait_timeout_s=120.0, **kw)
    except CellError as err:
        return row | {"state": "refused", "error": f"{err.code}: {err.message}"}
    row["time_s"] = time.monotonic() - t0
    time.sleep(0.2)
    d_mm, d_deg = pose_distance(cell.sim.true_T_base_tcp(), T_taught)
    row.update(state=job.state, true_mm=d_mm, true_deg=d_deg)
    if job.state == "succeeded":
        r = job.result
        row.update(claimed_mm=r.estimated_error_mm, claimed_deg=r.estimated_error_deg,
                   resolution_mm=getattr(r, "resolution_mm", None),
                   reach_error_mm=getattr(r, "reach_error_mm", None),
                   goal_frames_averaged=getattr(r, "goal_frames_averaged", None))
        row["bound_held"] = d_mm <= r.estimated_error_mm and d_deg <= r.estimated_error_deg
    else:
        row["error"] = f"{job.error_code}: {job.error_message}"
        for step in (lambda: cell.stop(CALLER, reason="bench: run failed"),
                     lambda: cell.unlock(CALLER)):
            with contextlib.suppress(CellError):
                step()
    # back to the taught pose for the next jog (a failed run may have left it anywhere)
    with contextlib.suppress(CellError):
        jog_to(cell, T_taught)
    return row


def _summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    ok = [r for r in rows if r["state"] == "succeeded"]
    return {"runs": len(rows), "succeeded": len(ok),
            "within_target": sum(1 for r in ok if _within(r)),
            "bound_held": sum(1 for r in ok if r["bound_held"]),
            "median_true_mm": float(np.median([r["true_mm"] for r in ok])) if ok else None,
            "worst_true_mm": max((r["true_mm"] for r in ok), default=None),
            "median_claimed_mm": float(np.median([r["claimed_mm"] for r in ok])) if ok else None,
            "median_time_s": float(np.median([r["time_s"] for r in ok])) if ok else None}


def _within(row: dict[str, Any]) -> bool:
    mm, deg = TARGETS[row["mode"]]
    return bool(row["true_mm"] <= mm and row["true_deg"] <= deg)


def format_report(r: dict[str, Any]) -> list[str]:
    arm = {"ur": "through the UR adapter", "sim": "in-process arm"}[r.get("arm", "ur")]
    lines = [f"{arm}, to a view taught at {len(r['teach_poses'])} poses in turn "
             f"({r['teach_samples']} "
             f"samples, {r['teach_frames']} frames, taught again every repeat), mount off by "
             f"{np.linalg.norm(MOUNT_ERROR_MM):.1f} mm / {MOUNT_ERROR_DEG} deg:"]
    for row in r["runs"]:
        if row["state"] == "succeeded":
            lines.append(f"  teach pose {row['teach_pose']} {row['mode']:5s} jog {row['jog']} "
                         f"succeeded {row['time_s']:.2f} s "
                         f"true {row['true_mm']:.3f} mm / {row['true_deg']:.3f} deg, claimed "
                         f"{row['claimed_mm']:.3f} mm / {row['claimed_deg']:.3f} deg "
                         f"{'held' if row['bound_held'] else 'NOT held'} "
                         f"(load {row['load_1min']:.1f})")
        else:
            lines.append(f"  teach pose {row['teach_pose']} {row['mode']:5s} jog {row['jog']} "
                         f"{row['state']}: "
                         f"{row.get('error')} (load {row['load_1min']:.1f})")
    for mode, s in r["summary"].items():
        lines.append(f"  {mode}: {s['succeeded']}/{s['runs']} succeeded, "
                     f"{s['within_target']} within {TARGETS[mode][0]} mm / {TARGETS[mode][1]} "
                     f"deg, the claim bounded the truth in {s['bound_held']}; "
                     f"median true {s['median_true_mm']} mm, "
                     f"claimed {s['median_claimed_mm']} mm, {s['median_time_s']} s")
    return lines


def main(args: argparse.Namespace) -> int:
    if args.repeats < 1 or args.burners < 0 or not 1 <= args.teach_samples <= 20:
        print("--repeats must be at least 1, --burners not negative and --teach-samples "
              "1..20")
        return 2
    report = run_bench_loops(repeats=args.repeats, burners=args.burners,
                             teach_samples=args.teach_samples, arm=args.arm)
    if args.json:
        print(json.dumps(report, indent=1, default=float))
    else:
        print("\n".join(format_report(report)))
    return 0
