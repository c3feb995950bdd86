"""``cell bench drift``: does the calibration check see a knocked camera, and how well?

On the built-in simulated cell through the UR adapter and ur_rtde (as ``cell bench
approach``), commissioned first unless ``--no-commission`` (the lens into ``[camera]``, the
hand-eye routine and Apply), the reference recorded at home with the target in view. Then:

1. False alarms: ``clean_checks`` checks with nothing changed (beside ``burners``
   CPU-burning processes when asked): every ``drifted`` is a false alarm, a failed check a
   failure.
2. Bumps: the simulated camera mount is knocked by each translation (mm) and rotation (deg)
   in a random direction (seeded), ``repeats`` times each, the cell not told. For each: the
   check's verdict and its figure at the tool; then an approach (look-and-move, the configured
   standoff) from home to the target, and the true error it makes against the simulator's
   truth, which is what the check's figure should predict; the approach's own consistency
   verdict beside it (does a job's own evidence see the knock?). The knock is then undone.

The report starts with the least kind figures: false alarms and failures, then the share of
bumps of each size detected, then how the check's figure compares with the true error.
"""

from __future__ import annotations

import contextlib
import math
import os
import statistics
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cell.bench.approach import STANDOFF_MM, _sim
from cell.bench.cells import CALLER, HOME_FAILURES, bench_config, home
from cell.bench.commission import hand_eye, measure_intrinsics, with_intrinsics
from cell.devices.hardware import SimFaults
from cell.errors import CellError
from cell.results.approach import ApproachBase
from cell.results.check import CheckResult
from cell.runtime import freeze_startup_objects, start_cell
from cell.service import Cell
from cell.vision.frames import approach_tcp
from estimator.transforms import make_T, pose_distance

Progress = Callable[[str, int, int], None]
Matrix4 = NDArray[np.float64]
TRANSLATIONS_MM = (0.2, 0.5, 1.0, 2.0)
ROTATIONS_DEG = (0.1, 0.2, 0.3, 1.0)
# the detection targets: these bumps are drifted every time
MUST_DETECT = (("translation", 0.5), ("rotation", 0.2))
PREDICTION_TOLERANCE = 0.30  # the check's tool figure within 30 % of the true approach error


@contextlib.contextmanager
def _burning(burners: int) -> Iterator[None]:
    if burners <= 0:
        yield
        return
    from fakes.ur_controller.load import cpu_burners

    with cpu_burners(burners, max_s=3600.0):
        yield


def _check(cell: Cell) -> tuple[str, CheckResult | None, str | None]:
    """(job state, result, error) of one check, waited for."""
    try:
        job = cell.check_calibration(CALLER, wait=True)
    except CellError as err:
        return "refused", None, f"{err.code}: {err.message}"
    result = job.result if isinstance(job.result, CheckResult) else None
    error = None if job.state == "succeeded" else f"{job.error_code}: {job.error_message}"
    return job.state, result, error


def _bump(rng: np.random.Generator, kind: str, size: float) -> Matrix4:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    if kind == "translation":
        return make_T(np.eye(3), axis * size)
    return make_T(Rotation.from_rotvec(axis * math.radians(size)).as_matrix(), np.zeros(3))


def _approach_truth(cell: Cell) -> dict[str, Any]:
    """An approach from home and its true error against the true goal."""
    home(cell)
    time.sleep(0.15)
    try:
        job = cell.approach(CALLER, standoff_mm=STANDOFF_MM, mode="look_and_move",  # type: ignore[arg-type]
                            wait=True, wait_timeout_s=120.0)
    except CellError as err:
        return {"approach_state": "refused", "approach_error": f"{err.code}: {err.message}"}
    time.sleep(0.2)
    sim = _sim(cell)
    T_tcp, t = sim.true_tcp_sample()
    goal = approach_tcp(sim.true_T_base_target(t), cell.config.approach.T_target_tcp.T(),
                        STANDOFF_MM)
    d_mm, d_deg = pose_distance(T_tcp, goal)
    out: dict[str, Any] = {"approach_state": job.state, "true_tcp_error_mm": d_mm,
                           "true_tcp_error_deg": d_deg}
    if isinstance(job.result, ApproachBase):
        c = job.result.consistency
        out["approach_consistency"] = c.verdict
        out["approach_disagreement_mm"] = c.motion.max_target_moved_mm
    if job.state != "succeeded":
        out["approach_error"] = f"{job.error_code}: {job.error_message}"
    return out


def run_bench_drift(*, repeats: int = 3, clean_checks: int = 10, seed: int = 0,
                    world: str = "realistic", commissioned: bool = True, burners: int = 0,
                    translations_mm: tuple[float, ...] = TRANSLATIONS_MM,
                    rotations_deg: tuple[float, ...] = ROTATIONS_DEG,
                    progress: Progress | None = None) -> dict[str, Any]:
    from fakes.ur_controller.process import free_loopback_host

    rng = np.random.default_rng(seed)
    HOME_FAILURES.clear()
    load_before = list(os.getloadavg())
    bumps = [("translation", s) for s in translations_mm] + [("rotation", s)
                                                             for s in rotations_deg]
    steps = 1 + clean_checks + repeats * len(bumps)
    with tempfile.TemporaryDirectory() as tmp:
        config = bench_config(Path(tmp), free_loopback_host(), world=world)
        commissioning: dict[str, Any] | None = None
        if commissioned:
            commissioning = {}
            try:
                commissioning["intrinsics"] = measure_intrinsics(config)
                config = with_intrinsics(config, commissioning["intrinsics"]["camera"])
            except Exception as err:  # recorded; the lens stays the configured one
                commissioning["intrinsics"] = {"failed": f"{type(err).__name__}: {err}"}
        cell = start_cell(config)
        freeze_startup_objects()
        try:
            sim = _sim(cell)
            T_home_target = sim.true_T_base_target()
            home(cell)
            if commissioning is not None:
                try:
                    commissioning["hand_eye"] = hand_eye(cell)
                except Exception as err:  # recorded; the mount stays the configured one
                    cell.stop(CALLER, reason="bench: commissioning failed")
                    commissioning["hand_eye"] = {"failed": f"{type(err).__name__}: {err}"}
                home(cell)
            reference = cell.record_reference(CALLER, wait=True)
            if reference.state != "succeeded":
                raise RuntimeError(f"the reference was not recorded: {reference.error_code} "
                                   f"{reference.error_message}")
            if progress:
                progress("drift", 1, steps)
            clean: list[dict[str, Any]] = []
            with _burning(burners):
                for _ in range(clean_checks):
                    state, result, error = _check(cell)
                    clean.append({"state": state, "error": error,
                                  **({} if result is None else {
                                      "verdict": result.verdict,
                                      "tcp_error_mm": result.tcp_error_mm,
                                      "tcp_error_deg": result.tcp_error_deg,
                                      "took_s": result.took_s})})
                    if progress:
                        progress("drift", 1 + len(clean), steps)
            rows: list[dict[str, Any]] = []
            for kind, size in bumps:
                for _ in range(repeats):
                    delta = _bump(rng, kind, size)
                    row: dict[str, Any] = {"kind": kind, "size": size}
                    try:
                        home(cell)
                        sim.set_faults(SimFaults(T_mount_delta=delta))
                        time.sleep(0.2)
                        state, result, error = _check(cell)
                        row.update(state=state, error=error)
                        if result is not None:
                            row.update(verdict=result.verdict, cause=result.cause,
                                       tcp_error_mm=result.tcp_error_mm,
                                       tcp_error_deg=result.tcp_error_deg,
                                       spread_mm=result.spread_mm, took_s=result.took_s)
                        row.update(_approach_truth(cell))
                    except Exception as err:  # counted as a failure; the run goes on
                        cell.stop(CALLER, reason="bench: bump failed")
                        row.update(state="failed", error=f"{type(err).__name__}: {err}")
                    finally:
                        sim.clear_faults()
                        sim.set_target(T_home_target)
                        for alarm in cell.alarms.list(active_only=True, limit=100)[0]:
                            cell.alarms.acknowledge(alarm.id, CALLER)
                    rows.append(row)
                    if progress:
                        progress("drift", 1 + clean_checks + len(rows), steps)
        finally:
            cell.close()
    report = _report(clean, rows, repeats, burners, seed, world)
    report["commissioned"] = commissioned
    report["commissioning"] = commissioning
    report["load_average_before"] = load_before
    report["home_failures"] = list(HOME_FAILURES)
    return report


def _prediction(row: dict[str, Any]) -> float | None:
    """|check's tool figure - true approach error| / true error (mm), for a bump whose
    approach succeeded and whose true error is not lost in the approach's own noise."""
    true_mm, said_mm = row.get("true_tcp_error_mm"), row.get("tcp_error_mm")
    if true_mm is None or said_mm is None or row.get("approach_state") != "succeeded":
        return None
    return abs(said_mm - true_mm) / max(true_mm, 1e-9)


def _report(clean: list[dict[str, Any]], rows: list[dict[str, Any]], repeats: int,
            burners: int, seed: int, world: str) -> dict[str, Any]:
    false_alarms = sum(c.get("verdict") == "drifted" for c in clean)
    clean_failed = sum(c["state"] != "succeeded" for c in clean)
    by_bump: dict[str, dict[str, Any]] = {}
    for kind, size in sorted({(r["kind"], r["size"]) for r in rows}):
        runs = [r for r in rows if r["kind"] == kind and r["size"] == size]
        unit = "mm" if kind == "translation" else "deg"
        predicted = [p for r in runs if (p := _prediction(r)) is not None]
        inconsistent = sum(r.get("approach_consistency") == "inconsistent" for r in runs)
        by_bump[f"{kind}_{size:g}{unit}"] = {
            "detected": f"{sum(r.get('verdict') == 'drifted' for r in runs)}/{len(runs)}",
            "failed": sum(r["state"] != "succeeded" for r in runs),
            "check_tcp_error_mm_median": _median([r.get("tcp_error_mm") for r in runs]),
            "true_tcp_error_mm_median": _median([r.get("true_tcp_error_mm") for r in runs]),
            "prediction_error_ratio_median": _median(list(predicted)),
            "within_30_percent": f"{sum(p <= PREDICTION_TOLERANCE for p in predicted)}/"
                                 f"{len(runs)}",
            "approach_inconsistent": f"{inconsistent}/{len(runs)}",
        }
    took = [c["took_s"] for c in clean if "took_s" in c] + [r["took_s"] for r in rows
                                                            if "took_s" in r]
    targets = {
        "no_false_drifted": false_alarms == 0 and clean_failed == 0,
        "check_within_15_s": bool(took) and max(took) <= 15.0,
    }
    for kind, size in MUST_DETECT:
        unit = "mm" if kind == "translation" else "deg"
        key = f"{kind}_{size:g}{unit}"
        if key in by_bump:
            d = by_bump[key]
            n = int(d["detected"].split("/")[1])
            targets[f"{key}_detected_every_time"] = d["detected"] == f"{n}/{n}" and n > 0
            targets[f"{key}_predicted_within_30_percent"] = d["within_30_percent"] == f"{n}/{n}"
    return {
        "false_drifted": f"{false_alarms}/{len(clean)}", "clean_checks_failed": clean_failed,
        "bumps": by_bump, "check_s_max": max(took) if took else None,
        "check_s_p50": _median(list(took)), "burners": burners, "repeats": repeats,
        "seed": seed, "world": world, "clean": clean, "rows": rows, "targets_met": targets}


def _median(xs: list[Any]) -> float | None:
    vals = [float(x) for x in xs if x is not None]
    return float(statistics.median(vals)) if vals else None


def format_report(r: dict[str, Any]) -> str:
    lines = [f"false drifted with nothing changed: {r['false_drifted']} "
             f"({r['clean_checks_failed']} checks failed; {r['burners']} CPU burners)",
             f"check time: p50 {r['check_s_p50']} s, max {r['check_s_max']} s",
             "bump                  detected  check mm  true mm  |check-true|/true  "
             "within 30 %  approach inconsistent"]
    for name, d in r["bumps"].items():
        lines.append(f"{name:20s}  {d['detected']:>8s}  {_fmt(d['check_tcp_error_mm_median'])}"
                     f"  {_fmt(d['true_tcp_error_mm_median'])}  "
                     f"{_fmt(d['prediction_error_ratio_median'])}  {d['within_30_percent']:>11s}"
                     f"  {d['approach_inconsistent']}")
    lines.append("targets: " + ", ".join(f"{k} {'met' if v else 'MISSED'}"
                                         for k, v in r["targets_met"].items()))
    return "\n".join(lines)


def _fmt(v: float | None) -> str:
    return "    -   " if v is None else f"{v:8.3f}"
