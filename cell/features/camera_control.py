"""Camera settings (exposure, gain, focus) of the running cell, for the API and the page.

Through the ``Camera`` interface only, so the simulated camera and the OAK behave alike. A
value the camera refuses is a LimitError ``invalid_camera_setting`` whose message names the
setting, and nothing changes; every change is audited.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from typing import Any

from cell.core import CellCore
from cell.error_codes import ErrorCode
from cell.errors import LimitError, UnavailableError
from drivers.camera import CameraSettings, FocusSetting
from drivers.errors import DriverError


def camera_settings(core: CellCore) -> dict[str, Any]:
    """The settings in force (None for a control this camera does not have)."""
    try:
        return asdict(core.camera.get_settings())
    except DriverError as err:
        raise UnavailableError(ErrorCode.camera_lost,
                               f"reading the camera settings: {err}") from err


def apply_camera_settings(core: CellCore, caller: str, *, exposure_us: int | None = None,
                          iso: int | None = None,
                          focus: FocusSetting | None = None) -> dict[str, Any]:
    """Change the given settings (None: leave as is); returns those in force."""
    params = {"exposure_us": exposure_us, "iso": iso, "focus": focus}
    t0 = time.time()
    try:
        try:
            applied = core.camera.apply_settings(
                CameraSettings(exposure_us=exposure_us, iso=iso, focus=focus))
        except ValueError as err:
            raise LimitError(ErrorCode.invalid_camera_setting, str(err)) from err
        except DriverError as err:
            raise UnavailableError(ErrorCode.camera_lost, f"changing the camera settings: {err}") \
                from err
    except (LimitError, UnavailableError) as err:
        core.jobs.audit(caller, "camera_settings", params, f"refused:{err.code}", err.message,
                        None, t0)
        raise
    out = asdict(applied)
    core.jobs.audit(caller, "camera_settings", params, "ok", "", None, t0)
    core.events.publish("camera_settings", {"settings": out})
    return out
