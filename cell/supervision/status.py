"""What the cell reports about itself: ``/status``, ``/health`` and the ``state`` events
(served from :mod:`cell.supervision.snapshot`, which calls these once per camera period).

Nothing here waits on a slow device: the arm state is the adapter's cached stream sample, the
gripper's status is the last one its poller read, links come from the supervisor.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from cell.core import CellCore
from cell.supervision.gripper import GripperService
from cell.supervision.links import LinkSupervisor
from drivers.arm import ArmState
from drivers.errors import DriverError
from estimator.transforms import pose_dict


def arm_state_name(st: ArmState) -> str:
    return ("disconnected" if not st.connected else
            "emergency_stop" if st.emergency_stop else
            "protective_stop" if st.protective_stop else
            "not_ready" if not st.ready else "idle")


def robot_dict(st: ArmState, now_s: float) -> dict[str, Any]:
    return {
        "connected": st.connected, "mode": st.robot_mode, "safety": st.safety_status,
        "moving": st.moving, "protective_stop": st.protective_stop,
        "T_base_tcp": pose_dict(st.T_base_tcp),
        "joints_deg": [float(np.degrees(q)) for q in st.joints_rad],
        "state_age_s": max(0.0, now_s - st.timestamp_s),
    }


def status(core: CellCore, links: LinkSupervisor, gripper: GripperService) -> dict[str, Any]:
    now = time.monotonic()
    out: dict[str, Any] = {}
    try:
        st = core.arm.state()
        out["robot"] = robot_dict(st, now)
        arm_state = arm_state_name(st)
    except DriverError as err:
        out["robot"] = {"connected": False, "error": str(err)}
        arm_state = "disconnected"
    motion = core.slot.current
    out["state"] = arm_state if arm_state != "idle" or motion is None else motion.name
    frame = core.locator.last_frame
    out["camera"] = {
        "connected": bool(core.camera.is_connected),
        "last_frame_age_s": None if frame is None else max(0.0, now - frame.timestamp_s),
    }
    out["gripper"] = gripper.status()
    job = None
    if motion is not None and motion.job_id is not None:
        j = core.jobs.get(motion.job_id)
        job = None if j is None else j.as_dict()
    out["job"] = job
    last = core.locator.last
    out["last_locate"] = None if last is None else last.answer(now).json_dict()
    out["links"] = links.snapshot()
    return out


MISSING_REASONS = {
    "arm": ("arm_disconnected", "the arm's controller is not connected; the cell reconnects "
            "by itself"),
    "camera": ("camera_lost", "the camera is not delivering frames; the cell reconnects by "
               "itself"),
}

STARTING_REASON = {"code": "starting", "message": "the service is starting: it connects the arm, "
                   "the camera and the gripper (and powers the arm on where configured) and "
                   "opens its PLC servers; commands that need a device are refused until then"}


def still_starting(health: dict[str, Any]) -> bool:
    """A ``/health`` body that says the service's first connect is still running: what a
    client that waits for the service to come up waits out (``ok`` or another reason ends
    it: a start may well leave a device missing)."""
    return any(r.get("code") == "starting" for r in health.get("reasons", []))


def health_from(missing: list[str], robot: dict[str, Any] | None = None,
                storage: list[dict[str, str]] | None = None, starting: bool = False
                ) -> dict[str, Any]:
    """``ok`` when every device is connected, the arm is not safety-stopped and the job
    database and the disk under it can be written, else ``degraded``; ``reasons`` says why
    (``{code, message}`` each) and ``missing`` names the devices that are not connected.
    ``starting``: the service's first connect (and power-on) is still running. The process
    answers either way (a liveness probe must not fail because a device did)."""
    reasons = [STARTING_REASON] if starting else []
    reasons += [{"code": MISSING_REASONS[name][0], "message": MISSING_REASONS[name][1]}
                for name in missing]
    robot = robot or {}
    if robot.get("connected", False):
        safety = str(robot.get("safety", ""))
        if "EMERGENCY_STOP" in safety:
            reasons.append({"code": "emergency_stop", "message": "the arm is emergency-stopped "
                            f"({safety}): release the e-stop, then unlock and power on"})
        elif robot.get("protective_stop") or safety == "PROTECTIVE_STOP":
            reasons.append({"code": "protective_stop", "message": "the arm is in a protective "
                            "stop: clear the cause, then unlock it"})
    reasons += storage or []
    return {"status": "degraded" if reasons else "ok", "missing": missing,
            "arm_connected": "arm" not in missing, "camera_connected": "camera" not in missing,
            "reasons": reasons}


def health(core: CellCore, links: LinkSupervisor) -> dict[str, Any]:
    """Devices only (the snapshot adds the arm's safety state and the storage)."""
    return health_from(links.missing(), starting=links.starting)
