"""What an operator does to bring the arm back: home, unlock a protective stop, power.

Each is audited and refused while another motion runs (they take the motion slot). Home is a
job (a joint move to ``[robot] home_joints_deg`` through the guard, so ``stop`` cancels it);
unlock and power are short commands that answer when the controller has done them.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cell.core import CellCore
from cell.error_codes import ErrorCode
from cell.errors import RefusedError
from cell.jobs.store import Job
from cell.motion.guard import Motion, driver_error
from cell.results.home import HomeResult
from cell.results.pose import Pose
from drivers.errors import DriverError, UnlockTooEarlyError


def start_home(core: CellCore, caller: str, *, speed_deg_s: float | None = None,
               wait: bool = False, wait_timeout_s: float = 120.0) -> Job:
    """Joint move to the configured home pose, as a job."""
    limits = core.config.limits
    speed = min(30.0, limits.max_joint_speed_deg_s) if speed_deg_s is None else float(speed_deg_s)
    accel = min(2.0 * speed, limits.max_joint_accel_deg_s2)
    q_home = np.radians(np.asarray(core.config.robot.home_joints_deg, dtype=float))
    params = {"home_joints_deg": list(core.config.robot.home_joints_deg), "speed_deg_s": speed}

    def check(motion: Motion) -> None:
        core.arm.guard.check_joint_speed(np.radians(speed), np.radians(accel))
        core.arm.check_joint_move(q_home, "home pose")

    def work(job_id: str, motion: Motion) -> HomeResult:
        core.runner.progress(job_id, {"phase": "moving"})
        core.arm.move_joint(q_home, np.radians(speed), np.radians(accel), what="home pose")
        st = core.arm.state()
        return HomeResult(joints_deg=np.degrees(st.joints_rad).tolist(),
                          T_base_tcp=Pose.from_T(st.T_base_tcp))

    return core.runner.start("home", caller, params, work, check=check, wait=wait,
                             wait_timeout_s=wait_timeout_s)


def unlock(core: CellCore, caller: str) -> dict[str, Any]:
    """Unlock a protective stop: 409 ``unlock_too_early`` (with the seconds left) while the
    controller still refuses, as a UR does for 5 s after the stop."""
    with core.audit.command(caller, "unlock", {}) as note, core.slot.hold("unlock"):
        try:
            before = core.arm.state()
            core.arm.recover_protective_stop()
        except UnlockTooEarlyError as err:
            raise RefusedError(ErrorCode.unlock_too_early,
                               f"the controller refuses to unlock yet: try "
                               f"again in {err.retry_in_s:.1f} s (inspect the cause of the stop "
                               "meanwhile)") from err
        except DriverError as err:
            raise driver_error(err, "unlocking the protective stop") from err
        st = core.arm.state()
        note.detail = f"{before.safety_status} -> {st.safety_status}"
        return {"unlocked": before.protective_stop, "safety": st.safety_status,
                "ready": st.ready}


def power(core: CellCore, caller: str, on: bool) -> dict[str, Any]:
    """Power on and release the brakes (``on``), or power off. Answers when done."""
    with core.audit.command(caller, "power", {"on": on}) as note, core.slot.hold("power"):
        try:
            if on:
                core.arm.power_on()
                core.arm.set_tcp(core.frames.T_flange_tcp)
            else:
                core.arm.power_off()
        except DriverError as err:
            raise driver_error(err, "power on" if on else "power off") from err
        st = core.arm.state()
        note.detail = st.robot_mode
        return {"robot_mode": st.robot_mode, "safety": st.safety_status, "ready": st.ready}
