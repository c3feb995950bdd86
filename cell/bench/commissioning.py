"""``cell bench commissioning``: the hand-eye routine in the realistic world, judged by its truth.

On the built-in simulated cell with ``[sim] world = "realistic"`` (camera mount 2.1 mm /
0.45 deg off ``[hand_eye]``, lens ~0.8 % off ``[camera]``; cell/devices/sim_truth.py), the
in-process simulated arm, through the Cell facade and the calibration job as the API runs them:

1. before: ``placements`` seeded look-and-move approaches (+-30 mm, +-15 deg about z), each
   job's own estimated error and consistency verdict beside the true TCP's error against the
   true goal;
2. the lens from a circle grid's views into ``[camera]``, the cell restarted on it, then the
   hand-eye routine (``views`` views, the calibration job of the HTTP API), every method's
   result against the true mount, and ``apply`` (the running cell, as the page's Apply):
   :mod:`cell.bench.commission`, the procedure of docs/commissioning.md;
3. after: the same placements again.

The truth (``SimWorld.truth_values``, the true target and TCP) is read only to score; nothing
the cell does sees it. Failures (a job that did not succeed) are counted, not skipped.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.bench.approach import placement
from cell.bench.commission import hand_eye, measure_intrinsics, with_intrinsics
from cell.config.schema import CellConfig, load_config, parse_config
from cell.devices.hardware import SimWorld
from cell.results import ApproachMode, LookAndMoveApproach
from cell.runtime import start_cell
from cell.service import Cell
from cell.vision.frames import approach_tcp
from estimator.transforms import pose_distance

Matrix4 = NDArray[np.float64]
CALLER = "bench"
STANDOFF_MM = 50.0


def bench_config(state_dir: Path, world: str) -> CellConfig:
    data = load_config().model_dump(mode="python")
    data["robot"]["kind"] = "sim"
    data["sim"]["ur_controller"] = False
    data["sim"]["world"] = world
    data["gripper"]["kind"] = "none"
    data["approach"]["mode"] = "look_and_move"
    data["api"]["job_db"] = str(state_dir / "jobs.db")
    data["api"]["calibration_dir"] = str(state_dir / "calibration")
    data["modbus"]["port"] = 0
    return parse_config(data)


def _sim(cell: Cell) -> SimWorld:
    assert cell.sim is not None, "the benchmark runs on the simulated cell"
    return cell.sim


def _settled_tcp(cell: Cell) -> Matrix4:
    prev = _sim(cell).true_T_base_tcp()
    deadline = time.monotonic() + 5.0
    while True:
        time.sleep(0.1)
        now = _sim(cell).true_T_base_tcp()
        if np.abs(now - prev).max() < 1e-4 or time.monotonic() > deadline:
            return now
        prev = now


def approaches(cell: Cell, targets: list[Matrix4]) -> list[dict[str, Any]]:
    """One look-and-move approach per placement: the job's own figures and the truth's."""
    T_target_tcp = cell.config.approach.T_target_tcp.T()
    runs: list[dict[str, Any]] = []
    for T_target in targets:
        home = cell.home(CALLER, wait=True)
        if home.state != "succeeded":
            raise RuntimeError(f"home failed: {home.error_code} {home.error_message}")
        _sim(cell).set_target(T_target)
        time.sleep(0.15)  # frames exposed before the placement are not this run's
        job = cell.approach(CALLER, standoff_mm=STANDOFF_MM, wait=True,
                            mode=ApproachMode.look_and_move)
        r = job.result
        if job.state != "succeeded" or not isinstance(r, LookAndMoveApproach):
            runs.append({"ok": False, "error": job.error_code})
            continue
        goal = approach_tcp(_sim(cell).true_T_base_target(), T_target_tcp, STANDOFF_MM)
        err_mm, err_deg = pose_distance(_settled_tcp(cell), goal)
        c = r.consistency
        runs.append({"ok": True, "true_mm": err_mm, "true_deg": err_deg,
                     "estimated_mm": r.estimated_error_mm, "verdict": c.verdict,
                     "target_moved_mm": c.motion.max_target_moved_mm,
                     "target_moved_deg": c.motion.max_target_moved_deg})
    return runs


def _summary(name: str, runs: list[dict[str, Any]]) -> None:
    ok = [r for r in runs if r["ok"]]
    failed = len(runs) - len(ok)
    verdicts = {v: sum(r["verdict"] == v for r in ok) for v in ("inconsistent", "consistent",
                                                                 "unchecked")}
    print(f"{name}: {len(runs)} approaches, {failed} failed; consistency "
          + ", ".join(f"{v} {n}" for v, n in verdicts.items()))
    if not ok:
        return
    for key, label in (("true_mm", "true error mm"), ("true_deg", "true error deg"),
                       ("estimated_mm", "job's estimated error mm"),
                       ("target_moved_mm", "target seen moving mm (base frame)"),
                       ("target_moved_deg", "target seen moving deg")):
        vals = np.array([r[key] for r in ok if r[key] is not None], dtype=float)
        if vals.size:
            print(f"  {label:36s} max {vals.max():7.3f}  median {np.median(vals):7.3f}")


def run(placements: int, views: int, seed: int, world: str) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    with tempfile.TemporaryDirectory() as tmp:
        config = bench_config(Path(tmp), world)
        T_home_target = config.sim.T_base_target.T()
        targets = [placement(rng, T_home_target) for _ in range(placements)]
        cell = start_cell(config)
        try:
            truth = _sim(cell).truth_values()
            mount_mm, mount_deg = pose_distance(cell.frames.T_flange_camera,
                                                truth.T_flange_camera)
            print(f"world {world}: [hand_eye] is {mount_mm:.2f} mm / {mount_deg:.3f} deg from "
                  "the true mount")
            before = approaches(cell, targets)
            _summary("before calibration", before)
        finally:
            cell.close()
        lens = measure_intrinsics(config)
        m, t = lens["camera"], lens["truth"]
        print(f"lens: {lens['views']} grid views in {lens['routine_s']:.0f} s, rms "
              f"{lens['rms_px']:.3f} px, coverage {100 * lens['coverage']:.0f} %; fx "
              f"{m['fx']:.2f} fy {m['fy']:.2f} cx {m['cx']:.2f} cy {m['cy']:.2f} (true "
              f"{t['fx']:.2f} {t['fy']:.2f} {t['cx']:.2f} {t['cy']:.2f}); written into [camera], "
              "the cell restarted")
        cell = start_cell(with_intrinsics(config, m))
        try:
            home = cell.home(CALLER, wait=True)
            if home.state != "succeeded":
                raise RuntimeError(f"home failed: {home.error_code}")
            _sim(cell).set_target(T_home_target)
            h = hand_eye(cell, views)
            print(f"hand-eye routine: {h['views']} views in {h['routine_s']:.0f} s, "
                  f"{h['failed_views']} failed; verdict "
                  f"{'consistent' if h['verdict_consistent'] else 'inconsistent'}; each method "
                  "against the true mount: " + ", ".join(
                      f"{k} {v['mm']:.3f} mm / {v['deg']:.4f} deg"
                      for k, v in h["methods_vs_truth"].items()))
            if not h["applied"]:
                print(f"Apply refused: {h.get('apply_refused')}")
                return {"before": before, "lens": lens, "hand_eye": h}
            print(f"applied {h['applied']}: the mount is {h['mount_error_after_mm']:.3f} mm / "
                  f"{h['mount_error_after_deg']:.4f} deg from the truth (requirement 0.2 mm / "
                  "0.05 deg)")
            after = approaches(cell, targets)
            _summary("after applying it", after)
            return {"before": before, "lens": lens, "hand_eye": h, "after": after}
        finally:
            cell.close()


def main(a: argparse.Namespace) -> int:
    import os

    load = os.getloadavg()
    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} on {os.cpu_count()} cores")
    run(a.placements, a.views, a.seed, a.world)
    return 0
