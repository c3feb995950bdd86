"""Why a command found the control script ended, through drivers.ur.adapter.URArm and the
real ur_rtde client: the controller's RTDE watchdog (the ur_rtde child frozen mid-stream, as a
starved host would be) is its own typed error, and a target the controller refuses ends the
script with a different message, naming the target."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

from api.plc.modbus import ERROR_NUMBERS, error_number
from api.status import STATUS
from cell.error_codes import ErrorCode
from cell.motion.guard import driver_error
from drivers.errors import ControllerWatchdogError, MotionError
from drivers.ur.adapter import URArm
from estimator.transforms import translation_T
from fakes.ur_controller.process import ControllerProcess

pytestmark = pytest.mark.timeout(60)


def _freeze_child(arm: URArm, seconds: float) -> None:
    client = arm._client
    assert client is not None
    pid = client._proc.pid
    os.kill(pid, signal.SIGSTOP)
    try:
        time.sleep(seconds)
    finally:
        os.kill(pid, signal.SIGCONT)


def test_a_watchdog_stop_is_its_own_error(ur_ctl: ControllerProcess, ur_arm: URArm) -> None:
    twist = np.array([5.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    for _ in range(10):  # a streamed motion: the watchdog runs at its streaming rate
        ur_arm.servo_twist(twist, 500.0, 0.2)
        time.sleep(0.02)
    _freeze_child(ur_arm, 0.6)  # no kick for 600 ms: the controller ends the script
    time.sleep(0.3)
    said = ur_ctl.state()["messages"]  # the controller's own record: its watchdog fired
    assert any("watchdog" in m for m in said), said
    with pytest.raises(ControllerWatchdogError) as caught:
        ur_arm._raise_command_failure("speedL")  # what a refused speedL then reports
    message = str(caught.value)
    assert caught.value.code == "controller_watchdog"
    assert "RTDE watchdog ended the control script" in message
    assert "host's load" in message and "unreachable" not in message
    assert "safety NORMAL" in message
    # the cell reports it with its own code
    err = driver_error(caught.value, "servoing")
    assert err.code == ErrorCode.controller_watchdog and err.kind == "conflict"
    assert STATUS[err.kind] == 409
    assert error_number(err.code, err.kind) == ERROR_NUMBERS["motion_failed"]
    # the adapter starts the script again for the next command
    ur_arm.servo_twist(twist, 500.0, 0.2)
    ur_arm.stop()


def test_a_refused_target_names_the_target_not_the_watchdog(ur_ctl: ControllerProcess,
                                                            ur_arm: URArm) -> None:
    T0 = ur_arm.tcp_pose()
    n_said = len(ur_ctl.state()["messages"])
    with pytest.raises(MotionError) as caught:
        ur_arm.move_linear(translation_T(0.0, 0.0, 5000.0) @ T0, 100, 500)
    assert not isinstance(caught.value, ControllerWatchdogError)
    message = str(caught.value)
    assert message.startswith("moveL to [")  # the target it was sent with
    # what was observed: the script ended on this command (or, when the stream showed the end
    # before the command's answer did, that it is not running and the watchdog was kicked)
    assert ("ended the controller's control script: it ran when the command was sent and "
            "stopped on it" in message
            or "its RTDE watchdog kicked in time" in message), message
    assert "RTDE watchdog ended" not in message
    said = ur_ctl.state()["messages"][n_said - 20:]
    assert not any("watchdog" in m for m in said), said
