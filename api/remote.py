"""What the OPC UA server and the URScript XML-RPC endpoint share with the HTTP API.

Both are thin adapters: a caller with one of the API's roles (:data:`api.auth.PERMISSIONS`),
one call on the :class:`cell.service.Cell` facade (so the same guard, job runner and audit log
as HTTP), and the cell's own error codes. A refusal by role is audited here, because it never
reaches the facade; everything else is audited by the facade or by :func:`audited`.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from api.auth import ALWAYS, PERMISSIONS
from api.status import STATUS
from cell.actions.approach import JobLayout
from cell.actions.approach_rules import check_speed, check_standoff
from cell.calibration.check import CHECK_KIND
from cell.error_codes import ErrorCode
from cell.errors import CellError, ForbiddenError, LimitError
from cell.features.recipes import Recipe, RecipeTarget
from cell.jobs.audit import AuditNote
from cell.jobs.store import Job
from cell.results.check import CheckResult
from cell.results.modes import ApproachMode
from cell.service import Cell
from cell.vision.frames import approach_tcp
from cell.vision.locate import Located
from cell.vision.parts import LocatedParts
from estimator.transforms import pose_from_T

Matrix4 = NDArray[np.float64]
T = TypeVar("T")

@dataclass(frozen=True)
class RemoteCaller:
    """A caller of one of the non-HTTP interfaces, with one of the API's roles."""

    interface: str  # "opcua" or "xmlrpc": kept in the audit log
    name: str
    role: str

    @property
    def label(self) -> str:
        """As in the audit log, the same on every door: ``<door>:<name>(<role>)``, e.g.
        ``opcua:plc(plc)``, ``modbus:plc(plc)``, HTTP's ``http:plc(plc)``."""
        return f"{self.interface}:{self.name}({self.role})"

    def may(self, permission: str) -> bool:
        return permission in (PERMISSIONS.get(self.role, frozenset()) | ALWAYS)


def require(cell: Cell, caller: RemoteCaller, permission: str, command: str,
            params: dict[str, Any]) -> None:
    """Refuse (and audit the refusal) when the caller's role lacks ``permission``."""
    if caller.may(permission):
        return
    with cell.core.audit.command(caller.label, command, params):
        raise ForbiddenError(ErrorCode.forbidden, f"role {caller.role!r} may not {permission}")


@contextmanager
def audited(cell: Cell, caller: RemoteCaller, command: str,
            params: dict[str, Any]) -> Iterator[AuditNote]:
    """An audit row for a command the facade does not audit itself (approach_pose, ...)."""
    with cell.core.audit.command(caller.label, command, params) as note:
        yield note


def http_status(err: CellError) -> int:
    """The HTTP status the API would answer for ``err`` (XML-RPC fault codes use it)."""
    return STATUS.get(err.kind, 409)


def finite(name: str, value: Any, *, minimum: float | None = None) -> float:
    """A float argument, or ``invalid_request`` (bools, NaN and infinities are refused)."""
    if isinstance(value, bool) or not isinstance(value, int | float) \
            or not math.isfinite(float(value)):
        raise LimitError(ErrorCode.invalid_request,
                         f"{name} must be a finite number, got {value!r}")
    if minimum is not None and value < minimum:
        raise LimitError(ErrorCode.invalid_request, f"{name} must be >= {minimum:g}, got {value!r}")
    return float(value)


def text(name: str, value: Any) -> str:
    """A string argument (None: empty), or ``invalid_request``: a number or a flag where a
    name is expected is refused, not turned into one."""
    if value is None:
        return ""
    if not isinstance(value, str):
        raise LimitError(ErrorCode.invalid_request,
                         f"{name} must be a string, got {type(value).__name__} {value!r}")
    return value


# -- poses ------------------------------------------------------------------------------------
def pose_mm_rad(T_base: Matrix4) -> tuple[list[float], list[float]]:
    """(position_mm, rotvec_rad) of a pose, the project's JSON form."""
    position_mm, rotvec_rad = pose_from_T(T_base)
    return [float(v) for v in position_mm], [float(v) for v in rotvec_rad]


def ur_pose(T_base: Matrix4) -> list[float]:
    """A UR pose ``p[x, y, z, rx, ry, rz]``: metres and a rotation vector in radians."""
    position_mm, rotvec_rad = pose_mm_rad(T_base)
    return [v / 1000.0 for v in position_mm] + rotvec_rad


# -- commands ---------------------------------------------------------------------------------
def locate(cell: Cell, caller: RemoteCaller) -> Located:
    require(cell, caller, "locate", "locate", {"n_frames": 1})
    return cell.locate(caller.label)


def locate_all(cell: Cell, caller: RemoteCaller, recipe: Any = "") -> LocatedParts:
    """Every part in view: of the layout in use, or of the targets of ``recipe`` (a name or
    a number; "" for none)."""
    require(cell, caller, "locate", "locate", {"all": True, "recipe": recipe})
    return cell.locate_all(caller.label, None if recipe in ("", None) else recipe_ref(recipe))


def approach(cell: Cell, caller: RemoteCaller, standoff_mm: Any, mode: Any,
             taught: Any = "") -> Job:
    """An approach job (not waited for). ``mode`` "" is the cell's default; ``taught`` (may
    be empty) names a taught pose, whose view an ``ibvs`` approach converges on."""
    params = {"standoff_mm": standoff_mm, "mode": mode, "taught": taught}
    require(cell, caller, "approach", "approach", params)
    try:
        mode = text("mode", mode)
        taught = text("taught", taught)
        standoff = check_standoff(finite("standoff_mm", standoff_mm, minimum=0.0))
        how = approach_mode(cell, mode)
        T_target_tcp, view = cell.taught.for_job(taught or None, how)
    except CellError:
        with audited(cell, caller, "approach", params):
            raise
    if how == ApproachMode.ibvs:  # to the taught view itself: a standoff of 0 is none
        return cell.approach(caller.label, standoff_mm=standoff or None, mode=how,
                             T_target_tcp=T_target_tcp, view=view)
    return cell.approach(caller.label, standoff_mm=standoff, mode=how, T_target_tcp=T_target_tcp)


def pick(cell: Cell, caller: RemoteCaller, recipe: Any = "", target: Any = "",
         place: Any = "") -> Job:
    """A pick job (not waited for): the next part of the recipe's target (``recipe`` "": the
    cell's own target), placed at the base-frame pose taught as ``place`` ("": kept in the
    gripper)."""
    params = {"recipe": recipe, "target": target, "place": place}
    require(cell, caller, "pick", "pick", params)
    try:
        ref = None if recipe in ("", None) else recipe_ref(recipe)
        chosen_target = text("target", target)
        place_name = text("place", place) or None
    except CellError:
        with audited(cell, caller, "pick", params):
            raise
    return cell.pick(caller.label, recipe=ref, target=chosen_target, place=place_name)


def check_calibration(cell: Cell, caller: RemoteCaller) -> Job:
    """A calibration check job (not waited for): the arm revisits the reference's views."""
    require(cell, caller, "check_calibration", "calibration_check", {})
    return cell.check_calibration(caller.label)


def record_reference(cell: Cell, caller: RemoteCaller) -> Job:
    """Record the calibration reference around the arm's pose (a job, not waited for): the
    operator's, as the hand-eye calibration it belongs to."""
    require(cell, caller, "calibrate", "calibration_reference", {})
    return cell.record_reference(caller.label)


def last_check(cell: Cell, scan: int = 20) -> tuple[Job, CheckResult] | None:
    """The newest calibration check that ended with a verdict, among the newest ``scan``
    checks (a PLC door shows it from its start, so a restart keeps the last verdict)."""
    for job in cell.jobs.list_jobs(scan, kind=CHECK_KIND):
        if isinstance(job.result, CheckResult):
            return job, job.result
    return None


def approach_mode(cell: Cell, name: str) -> ApproachMode:
    """The approach mode a PLC names ("": the cell's ``[approach] mode``), or
    ``invalid_request`` listing the modes."""
    if not name:
        return cell.config.approach.mode
    try:
        return ApproachMode(name)
    except ValueError:
        raise LimitError(ErrorCode.invalid_request,
                         f"mode must be one of {', '.join(ApproachMode)} (or empty), got "
                         f"{name!r}") from None


# -- recipes ----------------------------------------------------------------------------------
def recipe_ref(value: Any) -> str | int:
    """A recipe named by its name or its number (a digit string is a number)."""
    if isinstance(value, bool) or not isinstance(value, str | int) or value in ("", 0):
        raise LimitError(ErrorCode.invalid_request,
                         f"recipe must be a name or a number, got {value!r}")
    if isinstance(value, str) and value.isdigit():
        return int(value)
    return value


def find_recipe(cell: Cell, ref: str | int, target: Any = "",
                version: int | None = None) -> tuple[Recipe, RecipeTarget]:
    """The recipe and its target (``""``: the first); nothing is changed."""
    recipe = cell.recipes.get(ref, version)
    return recipe, recipe.target(text("target", target))


def prepare_recipe(cell: Cell, ref: str | int, target: str = "",
                   version: int | None = None) -> tuple[Recipe, RecipeTarget]:
    """The recipe's target, its dot layout now the one the locator looks for (a recipe
    selected for what follows: Machine Vision's PrepareRecipe, a Modbus locate with a recipe).
    A job with a recipe does not need this: it looks for the layout while it runs only."""
    recipe, chosen = find_recipe(cell, ref, target, version)
    cell.core.locator.use_target(chosen.model())
    return recipe, chosen


@contextmanager
def recipe_selected(cell: Cell, ref: str | int, target: Any = "") -> Iterator[
        tuple[Recipe, RecipeTarget]]:
    """:func:`prepare_recipe` for what the block does with it (a locate, a program's goal),
    undone when the block is refused: the locator's layout and last locate as they were."""
    recipe, chosen = find_recipe(cell, ref, target)
    lent = JobLayout(cell.core, chosen.model())
    lent.apply()
    try:
        yield recipe, chosen
    except BaseException:
        lent.refused()
        raise


def approach_recipe(cell: Cell, caller: RemoteCaller, ref: Any, target: Any = "",
                    standoff_mm: Any = None, *, speed_mm_s: Any = None,
                    use_last_locate: bool = False, wait: bool = False) -> Job:
    """An approach job with a recipe's target: its layout, taught pose, standoff and speed
    (unless given: by the same rules as a plain approach), and mode; the job records the
    recipe, its version and the target. The layout is looked for during the job only; a
    refusal changes nothing."""
    params = {"recipe": ref, "target": target, "standoff_mm": standoff_mm}
    if speed_mm_s is not None:
        params["speed_mm_s"] = speed_mm_s
    require(cell, caller, "approach", "approach", params)
    try:
        recipe, chosen = find_recipe(cell, recipe_ref(ref), target)
        standoff = chosen.standoff_mm if standoff_mm is None \
            else check_standoff(finite("standoff_mm", standoff_mm, minimum=0.0))
        speed = chosen.speed_mm_s if speed_mm_s is None \
            else check_speed(cell.config.limits, finite("speed_mm_s", speed_mm_s))
        T_target_tcp, _ = cell.taught.for_job(chosen.taught or None, chosen.mode)
    except CellError:
        with audited(cell, caller, "approach", params):
            raise
    return cell.approach(caller.label, standoff_mm=standoff, speed_mm_s=speed,
                         T_target_tcp=T_target_tcp, mode=chosen.mode,
                         use_last_locate=use_last_locate, wait=wait,
                         recipe=recipe.record(chosen), layout=chosen.model())


def track_recipe(cell: Cell, caller: RemoteCaller, ref: Any, target: Any = "",
                 duration_s: float | None = None) -> Job:
    """A track job with a recipe's target: its layout, taught pose and standoff, for
    ``duration_s`` (None: ``[servo] max_track_s``, i.e. until stopped); the job records the
    recipe, its version and the target. The layout is looked for during the job only."""
    params = {"recipe": ref, "target": target, "duration_s": duration_s}
    require(cell, caller, "track", "track", params)
    try:
        recipe, chosen = find_recipe(cell, recipe_ref(ref), target)
        duration = cell.config.servo.max_track_s if duration_s is None \
            else finite("duration_s", duration_s, minimum=0.0)
        T_target_tcp, _ = cell.taught.for_job(chosen.taught or None, None)
    except CellError:
        with audited(cell, caller, "track", params):
            raise
    return cell.track(caller.label, standoff_mm=chosen.standoff_mm, duration_s=duration,
                      T_target_tcp=T_target_tcp, recipe=recipe.record(chosen),
                      layout=chosen.model())


def track(cell: Cell, caller: RemoteCaller, standoff_mm: Any, duration_s: Any) -> Job:
    params = {"standoff_mm": standoff_mm, "duration_s": duration_s}
    require(cell, caller, "track", "track", params)
    try:
        standoff = finite("standoff_mm", standoff_mm, minimum=0.0)
        duration = finite("duration_s", duration_s, minimum=0.0)
    except CellError:
        with audited(cell, caller, "track", params):
            raise
    return cell.track(caller.label, standoff_mm=standoff, duration_s=duration)


def stop(cell: Cell, caller: RemoteCaller) -> dict[str, Any]:
    """Always allowed for a known caller; the cell's own stop path (audited there)."""
    return cell.stop(caller.label, reason=f"{caller.interface} Stop")


def home(cell: Cell, caller: RemoteCaller) -> Job:
    require(cell, caller, "home", "home", {})
    return cell.home(caller.label)


def gripper(cell: Cell, caller: RemoteCaller, action: Any, width_mm: Any) -> dict[str, Any]:
    params = {"action": action, "width_mm": width_mm}
    require(cell, caller, "gripper", "gripper", params)
    position = None
    try:
        action = text("action", action)
        if action == "move":
            position = finite("width_mm", width_mm, minimum=0.0)
    except CellError:
        with audited(cell, caller, "gripper", params):
            raise
    return cell.gripper(caller.label, action, position_mm=position)


def tcp_goal(cell: Cell, caller: RemoteCaller, command: str, *, standoff_mm: Any,
             taught: str | None = None) -> tuple[Matrix4, Located]:
    """Robot-program-driven mode: locate now and return the TCP goal for the program's own
    move; nothing is commanded. The goal passes the cell's envelope and tilt checks (from the
    current TCP), so a program gets the same refusal a cell-driven approach would."""
    params: dict[str, Any] = {"standoff_mm": standoff_mm}
    if taught is not None:
        params["taught"] = taught
    require(cell, caller, "locate", command, params)
    with audited(cell, caller, command, params) as note:
        standoff = finite("standoff_mm", standoff_mm, minimum=0.0)
        T_taught, _ = cell.taught.for_job(taught, None)
        T_target_tcp = cell.config.approach.T_target_tcp.T() if T_taught is None else T_taught
        loc = cell.locate(caller.label)
        goal = approach_tcp(loc.T_base_target, T_target_tcp, standoff)
        st = cell.arm_state()
        cell.arm.guard.check_goal(st.T_base_tcp, goal, "the program's goal", st)
        position_mm, _ = pose_mm_rad(goal)
        note.detail = "goal " + ", ".join(f"{v:.2f}" for v in position_mm) + " mm"
        return goal, loc
