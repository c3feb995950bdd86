"""The ``ibvs`` section of ``cell bench approach``: IBVS, servo and look-and-move to a taught
view, in the ideal world and with the camera's true mount and focal length off the config.

For each world a simulated cell runs through the real UR adapter and ur_rtde (the simulated
controller in its own process, as the rest of the approach benchmark). The arm is homed, moved
along the camera's axis until the target is ``view_distance_mm`` ahead (250 mm: from home, 456
mm, the image does not resolve 0.05 mm, docs/ibvs.md) and a view taught there (``teach``, the
same averaging an operator's teach does, ``teach_samples`` samples). Then, for each of
``placements`` seeded displacements (translation ``displace_mm`` in a random direction,
rotation ``displace_deg`` about a random axis, about the TCP), the arm is jogged to the
displaced pose and each mode approaches the taught pose from it: ``ibvs`` to the taught view,
``servo`` and ``look_and_move`` to the taught ``T_target_tcp`` with no standoff.

The time is the approach job's wall time (its first locate included); the error is the
simulator's true TCP against the true TCP where the view was taught (the cell never sees
either). While each job runs, a sampler projects the target's dots through the simulator's
true camera (true lens, true mount, true arm pose) and records the smallest distance of any dot
from the image's edge: negative means a dot left the image on the way.
"""

from __future__ import annotations

import contextlib
import os
import statistics
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cell.bench.cells import CALLER, bench_config
from cell.config.schema import CellConfig, parse_config
from cell.errors import CellError
from cell.features.teach import TaughtPose
from cell.results import IbvsApproach
from cell.runtime import start_cell
from cell.service import Cell
from estimator.transforms import T_from_pose, invert_T, pose_distance

Matrix4 = NDArray[np.float64]
MODES = ("ibvs", "servo", "look_and_move")
# the camera mount's error: 2.7 mm and 0.5 deg (a hand-measured bracket), and 1 % in focal
MOUNT_ERROR_MM = (1.2, -1.5, 1.9)
MOUNT_ERROR_AXIS = (0.6, -0.48, 0.64)
MOUNT_ERROR_DEG = 0.5
FOCAL_SCALE = 1.01
TEACH_SAMPLES = 30
VIEW_DISTANCE_MM = 250.0  # where the view is taught (None: at home)
TOL_MM, TOL_DEG, TIME_S = 0.05, 0.02, 2.5  # the IBVS targets


def world_config(base: CellConfig, world: str) -> CellConfig:
    """``base`` with the simulated truth of ``world``: ``ideal`` (the config is the truth)
    or ``mount_focal`` (the true mount 2.7 mm / 0.5 deg and the true focal length 1 % off)."""
    data = base.model_dump(mode="python")
    if world == "mount_focal":
        T_he = base.hand_eye.T_flange_camera.T()
        axis = np.asarray(MOUNT_ERROR_AXIS) / np.linalg.norm(MOUNT_ERROR_AXIS)
        T_true = T_he @ T_from_pose(np.asarray(MOUNT_ERROR_MM), axis * np.radians(MOUNT_ERROR_DEG))
        data["sim"]["T_flange_camera"] = {
            "position_mm": T_true[:3, 3].tolist(),
            "rotvec_rad": Rotation.from_matrix(T_true[:3, :3]).as_rotvec().tolist()}
        data["sim"]["camera"]["fx"] = base.camera.fx * FOCAL_SCALE
        data["sim"]["camera"]["fy"] = base.camera.fy * FOCAL_SCALE
    return parse_config(data)


def _to_view_distance(cell: Cell, distance_mm: float) -> None:
    """Move the camera along its optical axis until the target's centre is ``distance_mm``
    ahead (the cell's own frames: a mount error leaves the view a little off that, as an
    operator's jog would)."""
    T_tcp = cell.arm_state().T_base_tcp
    T_cam = cell.core.frames.T_tcp_camera
    T_base_cam = T_tcp @ T_cam
    centre = np.asarray(cell.config.target.points_mm, dtype=float).mean(axis=0)
    T_bt = cell.config.sim.T_base_target.T()
    c_cam = invert_T(T_base_cam) @ (T_bt @ np.r_[centre, 1.0])
    shift = T_base_cam[:3, 2] * (float(c_cam[2]) - distance_mm)
    for attempt in range(5):  # the controller restarts its program now and then
        try:
            jog_to(cell, T_from_pose(shift, np.zeros(3)) @ T_tcp)
            break
        except CellError:
            if attempt == 4:
                raise
            time.sleep(2.0)


def displacements(rng: np.random.Generator, n: int, displace_mm: float, displace_deg: float
                  ) -> list[tuple[NDArray[np.float64], NDArray[np.float64]]]:
    out = []
    for _ in range(n):
        t = rng.normal(size=3)
        r = rng.normal(size=3)
        out.append((t / np.linalg.norm(t) * displace_mm, r / np.linalg.norm(r) * displace_deg))
    return out


class DotSampler:
    """While a job runs: the smallest margin of the dots to the image's edge in the true
    camera (px; negative: a dot was outside the image)."""

    def __init__(self, cell: Cell) -> None:
        assert cell.sim is not None
        self.sim = cell.sim
        truth = cell.sim.truth_values()
        self.camera, self.T_flange_camera = truth.camera, truth.T_flange_camera
        self.T_tcp_flange = invert_T(cell.config.tool.T_flange_tcp.T())
        self.points = np.asarray(cell.config.target.points_mm, dtype=float)
        self.min_margin_px = float("inf")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="bench-dots")

    def __enter__(self) -> DotSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)

    def _run(self) -> None:
        while not self._stop.is_set():
            T_tcp, t = self.sim.true_tcp_sample()
            T_cam = T_tcp @ self.T_tcp_flange @ self.T_flange_camera
            T_ct = invert_T(T_cam) @ self.sim.true_T_base_target(t)
            Pc = self.points @ T_ct[:3, :3].T + T_ct[:3, 3]
            px = self.camera.project(Pc)
            c = self.camera
            m = float(np.min(np.concatenate([px[:, 0], px[:, 1], c.width - 1 - px[:, 0],
                                             c.height - 1 - px[:, 1]])))
            self.min_margin_px = min(self.min_margin_px, m)
            time.sleep(0.01)


def jog_to(cell: Cell, T_goal: Matrix4) -> None:
    """Jog there in steps of at most 100 mm (a jog step is capped by ``[limits]``)."""
    T_now = cell.arm_state().T_base_tcp
    rot = Rotation.from_matrix(T_goal[:3, :3] @ T_now[:3, :3].T).as_rotvec()
    move = T_goal[:3, 3] - T_now[:3, 3]
    n = max(1, int(np.ceil(np.linalg.norm(move) / 100.0)))
    for _ in range(n):
        cell.jog_step(CALLER, frame="base", translation_mm=move / n,
                      rotation_deg=np.degrees(rot) / n, speed_mm_s=100.0)
        time.sleep(0.3)


def _recover(cell: Cell) -> None:
    """After a failed run: stop, unlock a protective stop, home (each may refuse harmlessly)."""
    for step in (lambda: cell.stop(CALLER, reason="bench: run failed"),
                 lambda: cell.unlock(CALLER),
                 lambda: cell.home(CALLER, wait=True)):
        with contextlib.suppress(CellError):
            step()
        time.sleep(0.3)


def _one(cell: Cell, mode: str, taught: TaughtPose, T_taught_true: Matrix4) -> dict[str, Any]:
    t0 = time.monotonic()
    kw: dict[str, Any] = {"view": taught.view} if mode == "ibvs" else {"standoff_mm": 0.0}
    try:
        with DotSampler(cell) as dots:
            job = cell.approach(CALLER, T_target_tcp=taught.T_target_tcp, mode=mode,  # type: ignore[arg-type]
                                wait=True, wait_timeout_s=120.0, **kw)
    except CellError as err:
        return {"mode": mode, "state": "refused", "time_s": None, "error_mm": None,
                "error_deg": None, "error": f"{err.code}: {err.message}"}
    took = time.monotonic() - t0
    time.sleep(0.2)
    assert cell.sim is not None
    d_mm, d_deg = pose_distance(cell.sim.true_T_base_tcp(), T_taught_true)
    row: dict[str, Any] = {"mode": mode, "state": job.state, "time_s": took, "error_mm": d_mm,
                           "error_deg": d_deg, "min_dot_margin_px": dots.min_margin_px}
    if job.state != "succeeded":
        row["error"] = f"{job.error_code}: {job.error_message}"
    elif isinstance(job.result, IbvsApproach):
        r = job.result
        settle = r.settle_steps_mm_deg
        row.update(time_to_converge_s=r.time_to_converge_s,
                   image_error_px_rms=r.image_error_px_rms,
                   image_error_px_max=r.image_error_px_max,
                   estimated_error_mm=r.estimated_error_mm,
                   estimated_error_deg=r.estimated_error_deg, min_dots_used=r.min_dots_used,
                   view_error_mm=r.view_error_mm,
                   settle_steps_mm_deg=None if settle is None else [list(s) for s in settle],
                   first_locate_s=r.first_locate_s, phases_s=r.phases_s.json_dict())
    return row


def run_world(world: str, placements: int, seed: int, displace_mm: float, displace_deg: float,
              host: str, lost_after_s: float | None = None, *, modes: tuple[str, ...] = MODES,
              view_distance_mm: float | None = None, ibvs: dict[str, Any] | None = None,
              teach_samples: int = TEACH_SAMPLES) -> dict[str, Any]:
    """One world's runs; ``view_distance_mm``: teach there (None: at home, 456 mm);
    ``ibvs``: ``[ibvs]`` settings over the config's."""
    rng = np.random.default_rng(seed)
    with tempfile.TemporaryDirectory() as tmp:
        config = bench_config(Path(tmp), host, lost_after_s)
        if ibvs:
            data = config.model_dump(mode="python")
            data["ibvs"].update(ibvs)
            config = parse_config(data)
        cell = start_cell(world_config(config, world))
        rows: list[dict[str, Any]] = []
        try:
            job = cell.home(CALLER, wait=True)
            if job.state != "succeeded":
                raise RuntimeError(f"home failed: {job.error_code} {job.error_message}")
            time.sleep(0.3)
            if view_distance_mm is not None:
                _to_view_distance(cell, view_distance_mm)
            assert cell.sim is not None
            T_taught_true = cell.sim.true_T_base_tcp()
            taught = cell.teach(CALLER, "bench", samples=teach_samples)
            for i, (dt, dr) in enumerate(displacements(rng, placements, displace_mm,
                                                       displace_deg)):
                T_disp = T_from_pose(dt, np.zeros(3)) @ T_taught_true
                T_disp[:3, :3] = Rotation.from_rotvec(np.radians(dr)).as_matrix() \
                    @ T_taught_true[:3, :3]
                for mode in modes:
                    try:
                        jog_to(cell, T_disp)
                    except CellError as err:  # recorded; the arm is recovered and homed
                        rows.append({"placement": i, "mode": mode, "state": "not_started",
                                     "time_s": None, "error_mm": None, "error_deg": None,
                                     "error": f"jog to the displaced pose: {err.code}: "
                                     f"{err.message}"})
                        _recover(cell)
                        continue
                    rows.append({"placement": i, **_one(cell, mode, taught, T_taught_true)})
                    if rows[-1]["state"] != "succeeded":
                        _recover(cell)
        finally:
            cell.close()
    return {"world": world, "view_distance_mm": view_distance_mm,
            "ibvs_settings": ibvs or {}, "teach_spread_mm": taught.spread_mm,
            "teach_spread_deg": taught.spread_deg, "runs": rows,
            **{mode: _summary([r for r in rows if r["mode"] == mode]) for mode in modes}}


def _summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    ok = [r for r in rows if r["state"] == "succeeded"]
    within = [r for r in ok if r["error_mm"] <= TOL_MM and r["error_deg"] <= TOL_DEG
              and r["time_s"] <= TIME_S]

    def stat(key: str, f: Any) -> float | None:
        xs = [r[key] for r in ok if r.get(key) is not None]
        return float(f(xs)) if xs else None

    return {
        "worst_error_mm": stat("error_mm", max), "worst_error_deg": stat("error_deg", max),
        "worst_time_s": stat("time_s", max),
        "succeeded": len(ok), "runs": len(rows),
        "within_0.05mm_0.02deg_2.5s": len(within),
        "median_error_mm": stat("error_mm", statistics.median),
        "median_error_deg": stat("error_deg", statistics.median),
        "median_time_s": stat("time_s", statistics.median),
        "min_dot_margin_px": stat("min_dot_margin_px", min),
    }


def run_bench_ibvs(*, placements: int = 10, seed: int = 0, displace_mm: float = 30.0,
                   displace_deg: float = 6.0, host: str | None = None,
                   worlds: tuple[str, ...] = ("mount_focal", "ideal"),
                   lost_after_s: float | None = None, modes: tuple[str, ...] = MODES,
                   view_distance_mm: float | None = VIEW_DISTANCE_MM,
                   ibvs: dict[str, Any] | None = None,
                   teach_samples: int = TEACH_SAMPLES) -> dict[str, Any]:
    from fakes.ur_controller.process import free_loopback_host

    out: dict[str, Any] = {"placements": placements, "seed": seed, "displace_mm": displace_mm,
                           "displace_deg": displace_deg, "teach_samples": teach_samples,
                           "view_distance_mm": view_distance_mm,
                           "mount_error_mm": float(np.linalg.norm(MOUNT_ERROR_MM)),
                           "mount_error_deg": MOUNT_ERROR_DEG,
                           "focal_error": FOCAL_SCALE - 1.0, "lost_after_s": lost_after_s}
    for world in worlds:  # the least kind world first
        out[world] = run_world(world, placements, seed, displace_mm, displace_deg,
                               host or free_loopback_host(), lost_after_s, modes=modes,
                               view_distance_mm=view_distance_mm, ibvs=ibvs,
                               teach_samples=teach_samples)
    out["load_average"] = list(os.getloadavg())
    return out


def format_ibvs(r: dict[str, Any]) -> list[str]:
    def f(x: Any, fmt: str = ".3f") -> str:
        return "n/a" if x is None else format(x, fmt)

    where = r.get("view_distance_mm")
    lines = [f"to a view taught {'at home' if where is None else f'{where:g} mm from the target'}"
             f" from {r['displace_mm']:g} mm / {r['displace_deg']:g} deg, "
             f"{r['placements']} displacements (worst first):"]
    for world in ("mount_focal", "ideal"):
        if world not in r:
            continue
        lines.append(f"  {world}:")
        for mode in MODES:
            if mode not in r[world]:
                continue
            s = r[world][mode]
            lines.append(
                f"    {mode:14s} worst {f(s['worst_error_mm'])} mm / "
                f"{f(s['worst_error_deg'])} deg, {f(s['worst_time_s'], '.2f')} s; median "
                f"{f(s['median_error_mm'])} mm / {f(s['median_error_deg'])} deg, "
                f"{f(s['median_time_s'], '.2f')} s; {s['succeeded']}/{s['runs']} succeeded, "
                f"{s['within_0.05mm_0.02deg_2.5s']} within target; dots' least margin "
                f"{f(s['min_dot_margin_px'], '.0f')} px")
    return lines
