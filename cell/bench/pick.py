"""``cell bench pick``: pick and place against the simulator's truth, missed grasps, stops.

On the built-in simulated cell through the real UR adapter and ur_rtde (the simulated
controller in its own process on a free loopback address), through the Cell facade as the API
drives it, with the simulated 2F-85 gripper; every figure is scored against the simulated
world's truth (its parts, its arm's true geometry), which nothing the cell does reads.

The scene: ``parts`` parts of two layouts, the config's six-dot plate and a smaller five-dot
plate (:data:`FIVE_DOT`), both targets of one recipe, on 60 mm blocks in a 3 x 4 grid under the
home view (:func:`scene`: seeded cells, +-5 mm and +-15 deg about the vertical). The grid is a
checkerboard of the two layouts: a six-dot plate's neighbours are five-dot plates, at least
45 mm of free table between two parts' dots. Closer identical plates (about 110 mm apart)
can fall into one blob group for the estimator, which then has to split it.

The place poses (:func:`place_slots`) are a row along each of two sides of the view, off the
camera's field at home (a placed part is not seen again) and within the arm's reach. Each is
taught as an integrator teaches one: the arm moved there, ``teach`` in the base frame; the
true tool pose there (simulator truth) is the place pose's truth.

1. Pick and place: from home, a pick of the recipe's six-dot target until the cell sees none
   left, then of the five-dot target, each to the next place pose; the PLC's cycle (home, then
   pick) timed as a whole for the parts per minute. A placed part's error is its true pose
   against its goal: the taught place pose's truth carrying the part as the recipe's grasp
   holds it (``T_target_tcp``). ``parts`` attempts in all; a failed one counts in every
   figure (its cycle as infinite, its error as measured, a part never reached as not
   picked).
2. Missed grasps: ``missed_runs`` picks, each on a fresh scene of three parts; when the job's
   phase becomes ``grasp`` (the last look is over) the chosen part is moved 8 mm across the
   table. Each must end ``grasp_missed`` with the gripper open, the arm retracted above the
   part and standing still, and every other part where it lay.
3. A stop in each phase (approach, grasp, verify, retract, place): the true TCP stands still
   once settled, and the job ends ``cancelled`` naming the phase.
"""

from __future__ import annotations

import functools
import math
import os
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cell.bench.cells import CALLER, HOME_FAILURES, bench_config, home
from cell.bench.commission import commission_lens, commission_mount
from cell.config.schema import CellConfig, parse_config
from cell.devices.hardware import SimPart, SimWorld
from cell.errors import CellError
from cell.features.recipes import RecipeSpec, RecipeTarget
from cell.jobs.store import Job
from cell.results.pick import PickResult
from cell.runtime import freeze_startup_objects, start_cell
from cell.service import Cell
from estimator import Target
from estimator.transforms import T_from_pose_dict, invert_T, make_T, pose_distance

Progress = Callable[[str, int, int], None]
Matrix4 = NDArray[np.float64]

WORLDS = ("realistic", "ideal")
PHASES = ("locate", "approach", "grasp", "verify", "retract", "place")
STOP_PHASES = ("approach", "grasp", "verify", "retract", "place")
RECIPE = "bench-pick"
SIX, FIVE = "six-dot", "five-dot"
# a second product: five 8 mm dots without symmetry on a 55 x 45 mm plate
FIVE_DOT = Target([[0, 0, 0], [50, 0, 0], [0, 35, 0], [20, 45, 0], [55, 28, 0]], 8.0)
BLOCK_MM = 60.0  # the parts lie on blocks: their grasp poses stay above the box's floor
GRID_ROW_MM = (-125.0, 0.0, 125.0)  # along base x, from the home view's centre
GRID_COL_MM = (-210.0, -70.0, 70.0, 210.0)  # along base y
JITTER_MM, YAW_DEG = 5.0, 15.0
PLACE_Z_MM = 40.0  # the tray's surface
PLACE_CLEARANCE_MM = 80.0  # teaching reaches each place pose from above, as the pick does
MISSED_SHIFT_MM = 8.0
MAX_MOVE_MM = 800.0  # one leg from the far side of the view to the far place pose
PLACE_MM, PLACE_DEG = 0.3, 0.1
SETTLE_S = 0.3
MISSED_PARTS = 3
MAX_PARTS = 10  # the place poses beside the view


@dataclass(frozen=True)
class Slot:
    """A place pose: its name, the taught tool pose and that pose's truth (the true TCP when
    it was taught)."""

    name: str
    T_base_tcp: Matrix4
    T_true_tcp: Matrix4


def _sim(cell: Cell) -> SimWorld:
    if cell.sim is None:
        raise RuntimeError("the pick benchmark needs the simulated cell")
    return cell.sim


def pick_config(state_dir: Path, host: str, world: str) -> CellConfig:
    """The approach benchmarks' cell with the simulated gripper, and one move long enough
    for the leg from a part to a place pose across the cell."""
    data = bench_config(state_dir, host, world=world).model_dump(mode="python")
    data["gripper"]["kind"] = "sim"
    data["limits"]["max_move_mm"] = MAX_MOVE_MM
    return parse_config(data)


def layouts(cell: Cell) -> dict[str, Target]:
    return {SIX: cell.core.locator.target, FIVE: FIVE_DOT}


def save_recipe(cell: Cell) -> None:
    """One product, two targets: the config's plate and the five-dot plate, each approached
    as the cell's ``[approach]`` says."""
    ac = cell.config.approach
    targets = []
    for name, layout in layouts(cell).items():
        targets.append(RecipeTarget(
            name=name, points_mm=[(float(x), float(y), float(z)) for x, y, z in
                                  layout.points_mm],
            dot_diameter_mm=layout.dot_diameter_mm, polarity=layout.polarity,
            standoff_mm=ac.standoff_mm, mode=ac.mode, speed_mm_s=ac.speed_mm_s))
    cell.recipes.save(RecipeSpec(name=RECIPE, number=39, targets=targets), CALLER)


def _flat(T_home_target: Matrix4, yaw_deg: float) -> Matrix4:
    """The home target's orientation (lying flat, dots up) turned about the vertical."""
    R = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    return np.asarray(R @ T_home_target[:3, :3], dtype=float)


def scene(rng: np.random.Generator, n: int, T_home_target: Matrix4, plates: dict[str, Target]
          ) -> list[SimPart]:
    """``n`` parts in the grid's cells (seeded), half of each layout (the six-dot plates one
    more when ``n`` is odd), each on its checkerboard colour, the dots' centre at the cell
    +-5 mm, turned 90 +-15 deg about the vertical (the long side along the view's width)."""
    centre = T_home_target[:3, :3] @ plates[SIX].points_mm.mean(axis=0) + T_home_target[:3, 3]
    cells = [(r, c) for r in range(len(GRID_ROW_MM)) for c in range(len(GRID_COL_MM))]
    by_layout = {SIX: [rc for rc in cells if sum(rc) % 2 == 0],
                 FIVE: [rc for rc in cells if sum(rc) % 2 == 1]}
    want = {SIX: (n + 1) // 2, FIVE: n // 2}
    if any(want[k] > len(v) for k, v in by_layout.items()):
        raise ValueError(f"the grid holds {len(cells)} parts at most, asked for {n}")
    out = []
    for name in (SIX, FIVE):
        chosen = rng.permutation(len(by_layout[name]))[:want[name]]
        for k in chosen.tolist():
            r, c = by_layout[name][k]
            R = _flat(T_home_target, 90.0 + rng.uniform(-YAW_DEG, YAW_DEG))
            at = np.array([centre[0] + GRID_ROW_MM[r], centre[1] + GRID_COL_MM[c], BLOCK_MM])
            at[:2] += rng.uniform(-JITTER_MM, JITTER_MM, 2)
            layout = plates[name]
            out.append(SimPart(name, layout, make_T(R, at - R @ layout.points_mm.mean(axis=0))))
    return out


def place_slots(n: int, T_home_target: Matrix4, T_target_tcp: Matrix4) -> list[Matrix4]:
    """``n`` place tool poses: a row beside the view at x = -670 mm (the part turned
    180 deg: its dots towards -x, outside the camera's field at home), then a row behind it at
    y = 330 mm, 130 mm apart, the part on a tray ``PLACE_Z_MM`` high."""
    rows = [(-670.0, y, 180.0) for y in (-410.0, -280.0, -150.0, -20.0, 110.0, 240.0)]
    rows += [(x, 330.0, 0.0) for x in (-560.0, -430.0, -300.0, -170.0)]
    if n > len(rows):
        raise ValueError(f"{len(rows)} place poses at most, asked for {n}")
    return [make_T(_flat(T_home_target, yaw), np.array([x, y, PLACE_Z_MM])) @ T_target_tcp
            for x, y, yaw in rows[:n]]


def teach_slots(cell: Cell, poses: Sequence[Matrix4]) -> list[Slot]:
    """Each place pose taught as an integrator teaches it: the arm moved there (from home,
    down from above), ``teach`` in the base frame; the true TCP recorded beside it."""
    slots = []
    speed = cell.config.approach.speed_mm_s
    accel = cell.config.approach.accel_mm_s2
    for i, T in enumerate(poses):
        home(cell)
        above = T.copy()
        above[:3, 3] -= T[:3, 2] * PLACE_CLEARANCE_MM
        with cell.core.arm.slot.hold("bench: teaching a place pose"):
            cell.core.arm.move_linear(above, speed, accel, what="above the place pose")
            cell.core.arm.move_linear(T, speed, accel, what="place pose")
        time.sleep(SETTLE_S)
        name = f"bench-place-{i}"
        taught = cell.teach(CALLER, name, samples=5, frame="base")
        T_true, _ = _sim(cell).true_tcp_sample()
        slots.append(Slot(name, np.asarray(taught.T_base_tcp, dtype=float), T_true))
        with cell.core.arm.slot.hold("bench: teaching a place pose"):
            cell.core.arm.move_linear(above, speed, accel, what="above the place pose")
    return slots


def _show(cell: Cell, parts: list[SimPart]) -> None:
    _sim(cell).place_parts(parts)
    time.sleep(0.3)  # frames exposed before the parts were placed are not of this scene


def _open(cell: Cell) -> None:
    """The fingers open before a pick (as a PLC opens them), whatever was left in them."""
    status = cell.gripper_ops.status()
    if status is None or status.get("object_detected") or status.get("position_mm", 0) < 80:
        cell.gripper(CALLER, "open")


def _truth(cell: Cell) -> list[tuple[Matrix4, bool]]:
    return [(np.asarray(p.T_base_part, dtype=float), bool(p.held))
            for p in _sim(cell).parts_truth()]


def _nearest(parts: list[tuple[Matrix4, bool]], T: Matrix4) -> int:
    return int(np.argmin([pose_distance(P, T)[0] for P, _ in parts]))


def _still_tcp(cell: Cell, timeout_s: float = 5.0) -> Matrix4:
    """The true TCP once the arm stands (two reads 0.1 s apart within 0.1 um)."""
    deadline = time.monotonic() + timeout_s
    prev, _ = _sim(cell).true_tcp_sample()
    while True:
        time.sleep(0.1)
        now, _ = _sim(cell).true_tcp_sample()
        if np.abs(now - prev).max() < 1e-4 or time.monotonic() > deadline:
            return np.asarray(now, dtype=float)
        prev = now


def _wait(cell: Cell, job_id: str, phases: set[str], timeout_s: float = 90.0) -> bool:
    """Until the job's progress shows one of ``phases``; False when it ended first."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job = cell.job(job_id)
        if job.progress.get("phase") in phases:
            return True
        if job.state != "running":
            return False
        time.sleep(0.005)
    return False


def _wait_end(cell: Cell, job_id: str, timeout_s: float = 120.0) -> Job:
    deadline = time.monotonic() + timeout_s
    while (job := cell.job(job_id)).state == "running" and time.monotonic() < deadline:
        time.sleep(0.02)
    return job


# -- 1. pick and place ----------------------------------------------------------------------
def _pick_once(cell: Cell, target: str, slot: Slot, T_part_tcp: Matrix4) -> dict[str, Any]:
    """Home, then one pick of ``target`` to ``slot``; the row says what happened and what the
    truth says of the part afterwards."""
    t0 = time.monotonic()
    home(cell)
    _open(cell)
    before = _truth(cell)
    t_pick = time.monotonic()
    row: dict[str, Any] = {"target": target, "place": slot.name}
    try:
        job = cell.pick(CALLER, recipe=RECIPE, target=target, place=slot.name, wait=True,
                        wait_timeout_s=180.0)
    except CellError as err:
        row.update(state="refused", code=err.code, error=err.message, cycle_s=None,
                   wall_s=time.monotonic() - t0)
        return row
    row.update(state=job.state, code=job.error_code, wall_s=time.monotonic() - t0,
               job_s=time.monotonic() - t_pick)
    if job.state != "succeeded" or not isinstance(job.result, PickResult):
        row.update(error=job.error_message, cycle_s=None,
                   phases_s=dict(job.progress.get("phases_s") or {}))
        seen = (job.progress.get("part") or {}).get("T_base_target")
        if seen is not None:  # the chosen part, wherever it is now, against the goal
            T_seen = T_from_pose_dict(seen)
            after = _truth(cell)
            T_part = after[_nearest(before, T_seen)][0]
            row["error_mm"], row["error_deg"] = pose_distance(T_part, slot.T_true_tcp @
                                                              invert_T(T_part_tcp))
        return row
    res = job.result
    row.update(part=res.part.id, layout=res.part.layout, parts_seen=res.part.parts_seen,
               grip=res.grip.verdict, width_mm=res.grip.width_mm, cycle_s=res.cycle_s,
               phases_s=dict(res.phases_s))
    after = _truth(cell)
    moved = [i for i, ((B, _), (A, _)) in enumerate(zip(before, after, strict=True))
             if pose_distance(A, B)[0] > 1.0]
    row["parts_moved"] = len(moved)
    if len(moved) != 1:
        row.update(state="failed", code="bench_truth",
                   error=f"{len(moved)} parts moved in the world, not one")
        return row
    T_part, held = after[moved[0]]
    row["held_after"] = held
    goal = slot.T_true_tcp @ invert_T(T_part_tcp)
    row["error_mm"], row["error_deg"] = pose_distance(T_part, goal)
    assert res.place is not None
    row["error_vs_cell_goal_mm"], row["error_vs_cell_goal_deg"] = pose_distance(
        T_part, res.place.T_base_part_goal.T())
    return row


def _pick_section(cell: Cell, slots: list[Slot], n: int, T_part_tcp: Matrix4,
                  progress: Progress | None) -> tuple[list[dict[str, Any]], float]:
    """The six-dot parts until none is seen, then the five-dot ones; ``n`` attempts at most.
    Returns the rows and the section's wall time (homing included)."""
    rows: list[dict[str, Any]] = []
    placed = 0
    t0 = time.monotonic()
    for target in (SIX, FIVE):
        while placed < n:
            row = _pick_once(cell, target, slots[placed], T_part_tcp)
            if row["state"] == "refused" and row["code"] == "target_not_visible":
                row["attempt"] = False  # none of this layout left in view: the next one
                rows.append(row)
                break
            row["attempt"] = True
            rows.append(row)
            if row["state"] == "succeeded":
                placed += 1
            if progress:
                progress("pick", min(placed, n), n)
            if sum(r["attempt"] for r in rows) >= n:
                break
    return rows, time.monotonic() - t0


# -- 2. missed grasps -----------------------------------------------------------------------
def _missed_once(cell: Cell, rng: np.random.Generator, T_home_target: Matrix4,
                 slot: Slot) -> dict[str, Any]:
    home(cell)
    _open(cell)
    parts = scene(rng, MISSED_PARTS, T_home_target, layouts(cell))
    _show(cell, parts)
    job = cell.pick(CALLER, recipe=RECIPE, target=SIX, place=slot.name)
    if not _wait(cell, job.id, {"grasp"}):
        ended = _wait_end(cell, job.id)
        return {"ok": False, "state": ended.state, "code": ended.error_code,
                "error": f"the pick never reached its grasp: {ended.error_message}"}
    before = _truth(cell)
    chosen = _nearest(before, T_from_pose_dict(cell.job(job.id).progress["part"]
                                               ["T_base_target"]))
    heading = rng.uniform(0.0, 2.0 * math.pi)
    T_shifted = before[chosen][0].copy()
    T_shifted[:3, 3] += MISSED_SHIFT_MM * np.array([math.cos(heading), math.sin(heading), 0.0])
    # the chosen part slips; the others are put back exactly where they lay
    moved = [SimPart(p.layout_name, p.layout, T_shifted if i == chosen else before[i][0])
             for i, p in enumerate(parts)]
    _sim(cell).place_parts(moved)
    ended = _wait_end(cell, job.id)
    still = _still_tcp(cell)
    time.sleep(SETTLE_S)
    drift_mm = pose_distance(_sim(cell).true_tcp_sample()[0], still)[0]
    after = _truth(cell)
    status = cell.gripper_ops.status() or {}
    T_part = moved[chosen].T_base_part
    # the tool's z points into the part: retracted is back along it, above the grasp pose
    above_mm = float((T_part[:3, 3] - still[:3, 3]) @ still[:3, 2])
    others_mm = max((pose_distance(after[i][0], moved[i].T_base_part)[0]
                     for i in range(len(moved))), default=0.0)
    retract_mm = cell.config.pick.retract_mm
    row = {"state": ended.state, "code": ended.error_code, "parts": len(parts),
           "gripper_open": not status.get("object_detected")
           and float(status.get("position_mm", 0.0)) > 80.0,
           "fingers_mm": status.get("position_mm"), "retracted_mm": above_mm,
           "arm_drift_mm": drift_mm, "parts_moved_max_mm": others_mm,
           "held": any(h for _, h in after)}
    row["ok"] = (ended.state == "failed" and ended.error_code == "grasp_missed"
                 and row["gripper_open"] and above_mm >= retract_mm - 1.0
                 and drift_mm < 0.01 and others_mm < 1e-3 and not row["held"])
    if ended.state != "failed" or ended.error_code != "grasp_missed":
        row["error"] = ended.error_message
    return row


# -- 3. a stop in each phase ----------------------------------------------------------------
def _stop_once(cell: Cell, phase: str, rng: np.random.Generator, T_home_target: Matrix4,
               slot: Slot) -> dict[str, Any]:
    home(cell)
    _open(cell)
    _show(cell, scene(rng, 2, T_home_target, layouts(cell)))
    job = cell.pick(CALLER, recipe=RECIPE, target=SIX, place=slot.name)
    # during its approach a pick's progress shows the approach's own steps
    wanted = {"approach", "observe", "locate", "final"} if phase == "approach" else {phase}
    if not _wait(cell, job.id, wanted):
        ended = _wait_end(cell, job.id)
        return {"phase": phase, "ok": False, "state": ended.state, "code": ended.error_code,
                "error": f"the pick never reached {phase}: {ended.error_message}"}
    t_stop = time.monotonic()
    cell.stop(CALLER, reason=f"bench: stop in {phase}")
    still = _still_tcp(cell)
    still_after_s = time.monotonic() - t_stop
    time.sleep(SETTLE_S)
    drift_mm = pose_distance(_sim(cell).true_tcp_sample()[0], still)[0]
    ended = _wait_end(cell, job.id, 15.0)
    message = ended.error_message or ""
    row = {"phase": phase, "state": ended.state, "code": ended.error_code,
           "arm_drift_mm": drift_mm, "still_within_s": still_after_s,
           "phase_named": f"pick phase {phase}" in message,
           "gripper_reported": "gripper left as it was" in message, "message": message}
    row["ok"] = (ended.state == "cancelled" and drift_mm < 0.01 and row["phase_named"]
                 and row["gripper_reported"])
    return row


def _attempt(run: Callable[[], dict[str, Any]], cell: Cell, empty: dict[str, Any]
             ) -> dict[str, Any]:
    """One run; an exception is recorded as the run's failure and the arm stopped."""
    try:
        return run()
    except Exception as err:
        cell.stop(CALLER, reason="bench: run failed")
        return {**empty, "ok": False, "error": f"{type(err).__name__}: {err}"}


def run_bench_pick(*, parts: int = 10, seed: int = 0, world: str = "realistic",
                   commissioned: bool = False, missed_runs: int | None = None,
                   stop_phases: Sequence[str] = STOP_PHASES, host: str | None = None,
                   progress: Progress | None = None) -> dict[str, Any]:
    """The three sections (see the module doc) on one simulated cell; ``missed_runs`` None:
    as many as ``parts``. ``commissioned``: the lens and the mount first
    (cell/bench/commission.py); a step that fails is recorded and the run goes on."""
    from fakes.ur_controller.process import free_loopback_host

    if world not in WORLDS:
        raise ValueError(f"world must be one of {WORLDS}, got {world!r}")
    n_missed = parts if missed_runs is None else missed_runs
    rng = np.random.default_rng(seed)
    HOME_FAILURES.clear()
    load_before = list(os.getloadavg())
    with tempfile.TemporaryDirectory() as tmp:
        config = pick_config(Path(tmp), host or free_loopback_host(), world)
        commissioning: dict[str, Any] | None = None
        if commissioned:
            config, lens = commission_lens(config)
            commissioning = {"intrinsics": lens}
        cell = start_cell(config)
        freeze_startup_objects()  # as cell serve does: no full collection stalls the loop
        try:
            T_home_target = _sim(cell).true_T_base_target()
            if commissioning is not None:
                commissioning["hand_eye"] = commission_mount(cell, T_home_target, home)
            T_tt = cell.config.approach.T_target_tcp.T()
            save_recipe(cell)
            slots = teach_slots(cell, place_slots(parts, T_home_target, T_tt))
            if progress:
                progress("pick", 0, parts)
            _show(cell, scene(rng, parts, T_home_target, layouts(cell)))
            rows, section_s = _pick_section(cell, slots, parts, T_tt, progress)
            missed = []
            for i in range(n_missed):
                missed.append(_attempt(
                    functools.partial(_missed_once, cell, rng, T_home_target, slots[0]), cell,
                    {"state": None, "code": None}))
                if progress:
                    progress("missed grasp", i + 1, n_missed)
            stops = []
            for i, phase in enumerate(stop_phases):
                stops.append(_attempt(
                    functools.partial(_stop_once, cell, phase, rng, T_home_target, slots[0]),
                    cell, {"phase": phase, "state": None, "code": None}))
                if progress:
                    progress("stop per phase", i + 1, len(stop_phases))
        finally:
            cell.close()
    report = _report(rows, section_s, parts, missed, stops, world, seed)
    report.update(commissioned=commissioned, commissioning=commissioning,
                  load_average_before=load_before, load_average_after=list(os.getloadavg()),
                  home_failures=list(HOME_FAILURES))
    HOME_FAILURES.clear()
    return report


# -- the report -----------------------------------------------------------------------------
def quantile(xs: Sequence[float], q: float) -> float | None:
    """The nearest-rank ``q`` quantile (0..1) of ``xs``, an infinite value counted as the
    largest; None when it falls on one (or ``xs`` is empty)."""
    if not xs:
        return None
    s = sorted(xs)
    v = s[max(0, math.ceil(q * len(s)) - 1)]
    return None if math.isinf(v) else float(v)


def _report(rows: list[dict[str, Any]], section_s: float, parts: int,
            missed: list[dict[str, Any]], stops: list[dict[str, Any]], world: str, seed: int
            ) -> dict[str, Any]:
    attempts = [r for r in rows if r.get("attempt")]
    done = [r for r in attempts if r["state"] == "succeeded"]
    # a part never attempted counts as a failed pick: its cycle infinite, its error unknown
    never = parts - len(attempts)
    cycles = [r["cycle_s"] if r["state"] == "succeeded" else math.inf for r in attempts]
    cycles += [math.inf] * never
    errors = [(r.get("error_mm"), r.get("error_deg")) for r in attempts]
    mm = [math.inf if e is None else e for e, _ in errors] + [math.inf] * never
    deg = [math.inf if d is None else d for _, d in errors] + [math.inf] * never
    phases: dict[str, float | None] = {}
    for ph in PHASES:
        xs = [float((r.get("phases_s") or {}).get(ph, math.inf)) for r in attempts]
        phases[ph] = quantile(xs + [math.inf] * never, 0.5)
    within = [r for r in done if r["error_mm"] <= PLACE_MM and r["error_deg"] <= PLACE_DEG]
    missed_ok = sum(bool(m.get("ok")) for m in missed)
    stops_ok = all(s.get("ok") for s in stops) and bool(stops)
    out: dict[str, Any] = {
        "picked_ratio": f"{len(done)}/{parts}",
        "failures": [r for r in rows if r["state"] != "succeeded" and r.get("attempt")],
        "cycle_s_p50": quantile(cycles, 0.5),
        "cycle_s_p95": quantile(cycles, 0.95),
        "place_error_mm_max": quantile(mm, 1.0),
        "place_error_deg_max": quantile(deg, 1.0),
        "place_error_mm_median": quantile(mm, 0.5),
        "place_error_deg_median": quantile(deg, 0.5),
        "phases_s_p50": phases,
        "grasps_missed": sum(r.get("code") == "grasp_missed" for r in attempts),
        "parts_per_minute": 60.0 * len(done) / section_s if section_s > 0 else None,
        "placed_within_tolerance": f"{len(within)}/{parts}",
        "place_error_vs_cell_goal_mm_max": quantile(
            [r.get("error_vs_cell_goal_mm", math.inf) for r in done] or [math.inf], 1.0),
        "missed_grasp": f"{missed_ok}/{len(missed)}",
        "stop_per_phase": {s["phase"]: bool(s.get("ok")) for s in stops},
        "world": world, "seed": seed, "parts": parts, "picked": len(done),
        "attempts": len(attempts), "pick_section_s": section_s,
        "picks": rows, "missed_grasp_runs": missed, "stops": stops,
    }
    out["targets_met"] = {
        "all_picked_and_placed": len(done) == parts,
        "place_within_0.3mm_0.1deg": len(within) == parts,
        "missed_grasp_all": bool(missed) and missed_ok == len(missed),
        "stop_each_phase": stops_ok,
    }
    return out


def format_report(r: dict[str, Any]) -> str:
    def f(x: Any, fmt: str = ".3f") -> str:
        return "n/a" if x is None else format(x, fmt)

    ph = r["phases_s_p50"]
    lines = [
        f"world {r['world']}: picked and placed {r['picked_ratio']}, "
        f"{len(r['failures'])} failed picks ({r['grasps_missed']} missed grasps)",
        f"cycle time p50 {f(r['cycle_s_p50'], '.2f')} s, p95 {f(r['cycle_s_p95'], '.2f')} s "
        f"(p50 per phase: " + ", ".join(f"{k} {f(v, '.2f')}" for k, v in ph.items()) + "); "
        f"{f(r['parts_per_minute'], '.1f')} parts/min with homing",
        f"place error max {f(r['place_error_mm_max'])} mm / {f(r['place_error_deg_max'])} deg "
        f"(median {f(r['place_error_mm_median'])} mm / {f(r['place_error_deg_median'])} deg; "
        f"{r['placed_within_tolerance']} within {PLACE_MM:g} mm / {PLACE_DEG:g} deg)",
        f"part moved {MISSED_SHIFT_MM:g} mm after the last look: {r['missed_grasp']} ended "
        "grasp_missed, gripper open, arm retracted and still, the other parts unmoved",
        "stop in each phase (arm still, job cancelled): " + ", ".join(
            f"{k} {'ok' if v else 'FAILED'}" for k, v in r["stop_per_phase"].items()),
        "targets: " + ", ".join(f"{k} {'yes' if v else 'NO'}"
                                for k, v in r["targets_met"].items()),
    ]
    for fail in r["failures"]:
        lines.append(f"  failed: {fail.get('target')} to {fail.get('place')}: {fail.get('code')}"
                     f" {fail.get('error')}")
    for m in r["missed_grasp_runs"]:
        if not m.get("ok"):
            lines.append(f"  missed-grasp run not as required: {m}")
    for s in r["stops"]:
        if not s.get("ok"):
            lines.append(f"  stop in {s['phase']} not as required: {s}")
    return "\n".join(lines)
