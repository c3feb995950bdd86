"""``cell bench approach``: servo against look-and-move, conveyor tracking, lost-target stop.

On the built-in simulated cell through the real UR adapter and ur_rtde (the simulated
controller in its own process on a free loopback address), through the Cell facade like the
API, so every command passes the guarded motion path. Errors are against simulator truth.

1. The same ``placements`` seeded random target placements (+-30 mm, +-15 deg about z, +-3 deg
   tilt) for both modes, both at the cell's speed and acceleration limits: home, place,
   approach to a 50 mm standoff; the time is the approach
   job's wall time (its initial locate included), the error is the true TCP against the true
   goal once the job has ended.
2. Conveyor tracking at each speed along base -x for 3 s: the arm first holds the still target
   (placed where home sees it), then the target drifts; the RMS of the true error from the
   first second on.
3. Lost target: tracking at 50 mm/s, the lens is covered; the headline
   ``lost_target_cover_to_still_ms`` is from covering the lens to the simulated arm standing
   still (the simulated controller's own state, never the cell's declaration); beside it the
   same from the cell's declaration, and the job's own figure.

``commissioned``: before anything is measured, the cell is commissioned as an integrator does
it on a real cell (cell/bench/commission.py): the lens from a circle-grid plate's views into
``[camera]``, then the hand-eye routine on the running cell and Apply; each result is scored
against the simulated truth, which nothing the cell does reads.

``world`` (``realistic`` by default) is the simulated truth the cell does not share
(cell/devices/sim_truth.py): its lens, mount, arm geometry, camera latency and timestamps,
motion blur and light differ from what the cell's config believes. The report starts with the
least kind figures: the success ratio of each mode (a failed approach counts in every median:
its time as infinite, its error as measured after the job ended), the cover-to-still time,
then the tracking errors.
"""

from __future__ import annotations

import functools
import math
import os
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cell.bench.cells import CALLER, HOME_FAILURES, bench_config, home
from cell.bench.commission import commission_lens, commission_mount
from cell.bench.ibvs import format_ibvs, run_bench_ibvs
from cell.config.schema import parse_config
from cell.devices.hardware import SimWorld
from cell.errors import CellError
from cell.results import ServoApproach
from cell.runtime import freeze_startup_objects, start_cell
from cell.service import Cell
from cell.vision.frames import approach_tcp
from estimator.transforms import make_T, pose_dict, pose_distance

Progress = Callable[[str, int, int], None]
Matrix4 = NDArray[np.float64]
STANDOFF_MM = 50.0


WORLDS = ("realistic", "ideal")


def placement(rng: np.random.Generator, T_home_target: Matrix4) -> Matrix4:
    """The home target moved in the base frame and turned about its own origin."""
    rot = np.radians([*rng.uniform(-3.0, 3.0, 2), rng.uniform(-15.0, 15.0)])
    R = Rotation.from_rotvec(rot).as_matrix()
    return make_T(R @ T_home_target[:3, :3],
                  T_home_target[:3, 3] + np.r_[rng.uniform(-30, 30, 2), 0.0])


def _sim(cell: Cell) -> SimWorld:
    if cell.sim is None:
        raise RuntimeError("the approach benchmark needs the simulated cell")
    return cell.sim


def _true_error(cell: Cell, T_target_tcp: Matrix4) -> tuple[float, float]:
    T_tcp, t = _sim(cell).true_tcp_sample()
    return pose_distance(T_tcp, approach_tcp(_sim(cell).true_T_base_target(t), T_target_tcp,
                                             STANDOFF_MM))


def _true_offset_mm(cell: Cell, T_target_tcp: Matrix4) -> NDArray[np.float64]:
    """True TCP position minus the true goal's (base frame, mm)."""
    T_tcp, t = _sim(cell).true_tcp_sample()
    goal = approach_tcp(_sim(cell).true_T_base_target(t), T_target_tcp, STANDOFF_MM)
    return np.asarray(T_tcp[:3, 3] - goal[:3, 3], dtype=float)


def _approach(cell: Cell, mode: str, T_target: Matrix4, T_target_tcp: Matrix4
              ) -> dict[str, Any]:
    home(cell)
    _sim(cell).set_target(T_target)
    time.sleep(0.15)  # frames exposed before the placement are not this run's
    t0 = time.monotonic()
    try:
        job = cell.approach(CALLER, standoff_mm=STANDOFF_MM,
                            mode=mode,  # type: ignore[arg-type]
                            wait=True, wait_timeout_s=120.0)
    except CellError as err:  # refused before it started (recorded, the run goes on)
        return {"mode": mode, "state": "refused", "time_s": None, "error_mm": None,
                "error_deg": None, "error": f"{err.code}: {err.message}",
                "placement_T_base_target": pose_dict(T_target)}
    took = time.monotonic() - t0
    time.sleep(0.2)
    d_mm, d_deg = _true_error(cell, T_target_tcp)
    row: dict[str, Any] = {"mode": mode, "state": job.state, "time_s": took,
                           "error_mm": d_mm, "error_deg": d_deg}
    if job.state != "succeeded":
        row["error"] = f"{job.error_code}: {job.error_message}"
    elif isinstance(job.result, ServoApproach):
        row["time_to_converge_s"] = job.result.time_to_converge_s
        interval = job.result.pose_interval_ms
        row["pose_interval_ms"] = None if interval is None else interval.json_dict()
    return row


def _wait_end(cell: Cell, job_id: str, timeout_s: float) -> str:
    deadline = time.monotonic() + timeout_s
    while (state := cell.job(job_id).state) == "running" and time.monotonic() < deadline:
        time.sleep(0.02)
    return state


def _hold(cell: Cell, T_target_tcp: Matrix4, duration_s: float) -> str:
    """Start tracking the still target and wait until the arm holds it: within 1 mm and
    0.5 deg of the true goal, or, in a world whose calibration the cell does not share, where
    that goal is out of its reach, standing still (the true TCP within 0.05 mm over 0.5 s)."""
    job = cell.track(CALLER, standoff_mm=STANDOFF_MM, duration_s=duration_s)
    deadline = time.monotonic() + 15.0
    window: list[tuple[float, NDArray[np.float64]]] = []
    while any(e > lim for e, lim in zip(_true_error(cell, T_target_tcp), (1.0, 0.5),
                                            strict=True)):
        if cell.job(job.id).state != "running" or time.monotonic() > deadline:
            raise RuntimeError(f"tracking did not settle: {cell.job(job.id).error_message}")
        T, t = _sim(cell).true_tcp_sample()
        window.append((t, T[:3, 3].copy()))
        while window and window[-1][0] - window[0][0] > 0.5:
            window.pop(0)
        if (time.monotonic() - (deadline - 15.0) > 1.0 and window[-1][0] - window[0][0] >= 0.45
                and max(float(np.linalg.norm(p - window[-1][1])) for _, p in window) < 0.05):
            break
        time.sleep(0.02)
    return job.id


def _track(cell: Cell, speed_mm_s: float, T_target_tcp: Matrix4, T_home_target: Matrix4,
           follow_s: float) -> dict[str, Any]:
    home(cell)
    sim = _sim(cell)
    sim.set_target(T_home_target)  # in view from home; it then drifts along -x
    time.sleep(0.15)
    job_id = _hold(cell, T_target_tcp, follow_s + 20.0)
    sim.set_target(sim.true_T_base_target(), np.array([-speed_mm_s, 0.0, 0.0]))
    t_move = time.monotonic()
    samples: list[tuple[float, float, float]] = []
    offsets: list[NDArray[np.float64]] = []
    while time.monotonic() < t_move + follow_s:
        d_mm, d_deg = _true_error(cell, T_target_tcp)
        samples.append((time.monotonic() - t_move, d_mm, d_deg))
        if samples[-1][0] >= 1.0:
            offsets.append(_true_offset_mm(cell, T_target_tcp))
        time.sleep(0.01)
    state = cell.job(job_id).state
    cell.stop(CALLER, reason="bench: tracking done")
    sim.set_target(sim.true_T_base_target())
    _wait_end(cell, job_id, 10.0)
    job = cell.job(job_id)
    tail = [s for s in samples if s[0] >= 1.0]
    out: dict[str, Any] = {"speed_mm_s": speed_mm_s, "state_while_following": state,
           "rms_error_mm": float(np.sqrt(np.mean([s[1] ** 2 for s in tail]))),
           "max_error_mm": max(s[1] for s in tail),
           "rms_error_deg": float(np.sqrt(np.mean([s[2] ** 2 for s in tail])))}
    if offsets:  # a constant offset (calibration) apart from the error that moves (dynamics)
        arr = np.array(offsets)
        bias = arr.mean(axis=0)
        out["bias_mm"] = [float(x) for x in bias]
        out["bias_norm_mm"] = float(np.linalg.norm(bias))
        out["rms_about_bias_mm"] = float(np.sqrt(np.mean(np.sum((arr - bias) ** 2, axis=1))))
    if state != "running":
        out["error"] = f"{job.error_code}: {job.error_message}"
    return out


def _still_at(cell: Cell, since_s: float, timeout_s: float = 3.0) -> float:
    """Monotonic time from which the true TCP stands still (< 0.01 mm over 20 ms)."""
    sim = _sim(cell)
    window: list[tuple[float, Matrix4]] = []
    deadline = since_s + timeout_s
    while time.monotonic() < deadline:
        T, t = sim.true_tcp_sample()
        window.append((t, T))
        while len(window) > 2 and window[-1][0] - window[1][0] >= 0.02:
            window.pop(0)
        if window[-1][0] - window[0][0] >= 0.02 and all(
                np.linalg.norm(T_[:3, 3] - T[:3, 3]) < 0.01 for _, T_ in window):
            return window[0][0]
        time.sleep(0.002)
    raise RuntimeError("the arm did not come to rest")


def _lost_target(cell: Cell, T_target_tcp: Matrix4, T_home_target: Matrix4) -> dict[str, Any]:
    home(cell)
    sim = _sim(cell)
    speed = 50.0
    sim.set_target(T_home_target)
    time.sleep(0.15)
    job_id = _hold(cell, T_target_tcp, 30.0)
    sim.set_target(sim.true_T_base_target(), np.array([-speed, 0.0, 0.0]))
    time.sleep(1.5)
    moving_mm_s = _true_speed_mm_s(cell)
    t_cover = time.monotonic()
    sim.set_camera_blocked(True)
    try:
        t_still = _still_at(cell, t_cover)
        state = _wait_end(cell, job_id, 10.0)
    finally:
        sim.set_camera_blocked(False)
        sim.set_target(sim.true_T_base_target())
    job = cell.job(job_id)
    lost_after_ms = cell.config.servo.lost_after_s * 1000.0
    lost_at = job.progress.get("lost_at_monotonic_s")
    last_pose = job.progress.get("last_pose_exposure_s")
    cover_ms = (t_still - t_cover) * 1000.0
    # the figure counts only when the arm was following the target when the lens was
    # covered and stood still after the cell declared the loss (not stopped for another reason)
    valid = moving_mm_s >= 0.5 * speed and lost_at is not None and t_still >= lost_at - 0.005
    return {"speed_mm_s": speed, "state": state, "code": job.error_code,
            "arm_speed_at_cover_mm_s": moving_mm_s, "valid": valid,
            "job_stopped_in_ms": job.progress.get("stopped_in_ms"),
            # where the time went, each from the cover: the camera time of the last frame
            # that showed the target, the loss declared, the arm standing (simulator truth)
            "last_pose_exposure_ms": None if last_pose is None
            else (last_pose - t_cover) * 1000.0,
            "cover_to_declared_ms": None if lost_at is None else (lost_at - t_cover) * 1000.0,
            "declared_to_still_ms": None if lost_at is None else (t_still - lost_at) * 1000.0,
            "cover_to_still_ms": cover_ms if valid else None,
            "cover_to_still_measured_ms": cover_ms,
            "lost_after_ms": lost_after_ms,
            "truth_stop_ms": cover_ms - lost_after_ms}


def _true_speed_mm_s(cell: Cell, span_s: float = 0.03) -> float:
    """The true TCP's speed over ``span_s`` (simulator truth)."""
    T0, t0 = _sim(cell).true_tcp_sample()
    time.sleep(span_s)
    T1, t1 = _sim(cell).true_tcp_sample()
    return float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]) / max(t1 - t0, 1e-6))


def run_bench_approach(*, placements: int = 10, seed: int = 0,
                       speeds: tuple[float, ...] = (25.0, 50.0, 100.0, 150.0),
                       follow_s: float = 3.0, host: str | None = None,
                       progress: Progress | None = None, lost_after_s: float | None = None,
                       world: str = "realistic", ibvs: bool = True,
                       sim_overrides: dict[str, Any] | None = None,
                       commissioned: bool = False) -> dict[str, Any]:
    """The approach, tracking and lost-target sections in ``world``; ``sim_overrides`` sets
    ``[sim]`` keys over the world's preset (to take one effect out and see what it costs);
    ``commissioned``: the cell is commissioned first (cell/bench/commission.py: intrinsics into
    ``[camera]``, then the hand-eye routine and Apply); a step that fails is recorded and the
    run goes on without it."""
    from fakes.ur_controller.process import free_loopback_host

    if world not in WORLDS:
        raise ValueError(f"world must be one of {WORLDS}, got {world!r}")
    rng = np.random.default_rng(seed)
    HOME_FAILURES.clear()
    load_before = list(os.getloadavg())
    with tempfile.TemporaryDirectory() as tmp:
        config = bench_config(Path(tmp), host or free_loopback_host(), lost_after_s, world)
        if sim_overrides:
            data = config.model_dump(mode="python")
            data["sim"].update(sim_overrides)
            config = parse_config(data)
        commissioning: dict[str, Any] | None = None
        if commissioned:
            config, lens = commission_lens(config)
            commissioning = {"intrinsics": lens}
        cell = start_cell(config)
        freeze_startup_objects()  # as cell serve does: no full collection stalls the loop
        lost_after_s = cell.config.servo.lost_after_s
        try:
            T_tt = cell.config.approach.T_target_tcp.T()
            T_home_target = _sim(cell).true_T_base_target()
            if commissioning is not None:
                commissioning["hand_eye"] = commission_mount(cell, T_home_target, home)
            rows: list[dict[str, Any]] = []
            steps = 2 * placements + len(speeds) + 1
            for i in range(placements):
                T = placement(rng, T_home_target)
                for mode in ("servo", "look_and_move"):
                    try:
                        row = _approach(cell, mode, T, T_tt)
                    except Exception as err:  # counted as a failure; the run goes on
                        cell.stop(CALLER, reason="bench: approach failed")
                        row = {"mode": mode, "state": "failed", "time_s": None,
                               "error_mm": None, "error_deg": None,
                               "error": f"{type(err).__name__}: {err}",
                               "placement_T_base_target": pose_dict(T)}
                    rows.append({"placement": i, **row})
                    if progress:
                        progress("approach", len(rows), steps)
            tracks: list[dict[str, Any]] = []
            for speed in speeds:
                # the drift stays within TRACK_TRAVEL_MM: at 150 mm/s a 3 s follow would carry
                # the target out of the workspace box
                follow = min(follow_s, TRACK_TRAVEL_MM / speed)
                run = functools.partial(_track, cell, speed, T_tt, T_home_target, follow)
                tracks.append(_attempt(run, cell, {"speed_mm_s": speed, "rms_error_mm": None}))
                if progress:
                    progress("approach", len(rows) + len(tracks), steps)
            lost = _attempt(lambda: _lost_target(cell, T_tt, T_home_target), cell,
                            {"job_stopped_in_ms": None, "truth_stop_ms": None})
            if progress:
                progress("approach", steps, steps)
            _sim(cell).set_target(T_home_target)
        finally:
            cell.close()
    report = _report(rows, tracks, lost, placements, seed, lost_after_s, world)
    report["commissioned"] = commissioned
    report["commissioning"] = commissioning
    report["load_average_before"] = load_before
    report["sim_overrides"] = sim_overrides or {}
    report["home_failures"] = list(HOME_FAILURES)
    HOME_FAILURES.clear()
    if ibvs:
        report["ibvs"] = _ibvs_section(placements, seed, lost_after_s)
    return report


def _ibvs_section(placements: int, seed: int, lost_after_s: float) -> dict[str, Any]:
    """IBVS, servo and look-and-move to a taught view (cell/bench/ibvs.py), its own cells."""
    try:
        return run_bench_ibvs(placements=placements, seed=seed, lost_after_s=lost_after_s)
    except Exception as err:  # recorded, as every other section's failure
        return {"failed": f"{type(err).__name__}: {err}"}


def _attempt(run: Callable[[], dict[str, Any]], cell: Cell, empty: dict[str, Any]
             ) -> dict[str, Any]:
    """One bench section; a failure (e.g. a false target_lost on an overloaded machine) is
    recorded with its reason instead of ending the run."""
    try:
        return run()
    except Exception as err:
        cell.stop(CALLER, reason="bench: section failed")
        sim = _sim(cell)
        sim.set_camera_blocked(False)
        sim.set_target(sim.true_T_base_target())
        return {**empty, "failed": f"{type(err).__name__}: {err}"}


def _median(rows: list[dict[str, Any]], mode: str, key: str) -> float | None:
    """The median over every run of ``mode``: a failed one counts with the value measured
    after it ended (a final error) or, where it has none (a time), as infinitely bad; None
    when no run has the value at all. Each median's ``_n`` in the report says how many."""
    xs: list[float] = []
    for r in rows:
        if r["mode"] != mode:
            continue
        value = r.get(key)
        if r["state"] == "succeeded":
            if value is not None:
                xs.append(float(value))
        elif key.startswith("error_") and value is not None:
            xs.append(float(value))
        else:
            xs.append(math.inf)
    if not xs:
        return None
    m = float(statistics.median(xs))
    return None if math.isinf(m) else m


def _ratio(rows: list[dict[str, Any]], mode: str) -> str:
    runs = [r for r in rows if r["mode"] == mode]
    return f"{sum(r['state'] == 'succeeded' for r in runs)}/{len(runs)}"


def _report(rows: list[dict[str, Any]], tracks: list[dict[str, Any]], lost: dict[str, Any],
            placements: int, seed: int, lost_after_s: float, world: str = "ideal"
            ) -> dict[str, Any]:
    servo_t = _median(rows, "servo", "time_s")
    lam_t = _median(rows, "look_and_move", "time_s")
    n_servo = sum(r["mode"] == "servo" for r in rows)
    n_lam = sum(r["mode"] == "look_and_move" for r in rows)
    cover_ms = lost.get("cover_to_still_ms")
    out: dict[str, Any] = {
        "world": world,
        "servo_success_ratio": _ratio(rows, "servo"),
        "look_and_move_success_ratio": _ratio(rows, "look_and_move"),
        "lost_target_cover_to_still_ms": cover_ms,
        "track_rms_error_mm": {f"{t['speed_mm_s']:g}": t["rms_error_mm"] for t in tracks},
        "servo_time_s_median": servo_t,
        "look_and_move_time_s_median": lam_t,
        "servo_final_error_mm_median": _median(rows, "servo", "error_mm"),
        "servo_final_error_deg_median": _median(rows, "servo", "error_deg"),
        "look_and_move_final_error_mm_median": _median(rows, "look_and_move", "error_mm"),
        "look_and_move_final_error_deg_median": _median(rows, "look_and_move", "error_deg"),
        "servo_time_to_converge_s_median": _median(rows, "servo", "time_to_converge_s"),
        "medians_n": {"servo": n_servo, "look_and_move": n_lam},  # every run, failures too
        "speedup": (lam_t / servo_t) if servo_t and lam_t else None,
        "lost_after_s": lost_after_s,
        "lost_target_declared_to_still_ms": lost.get("declared_to_still_ms"),
        "lost_target_job_stop_ms": lost["job_stopped_in_ms"],
        "lost_target_truth_stop_ms": lost["truth_stop_ms"],
        "failures": [r for r in rows if r["state"] != "succeeded"],
        "placements": placements, "seed": seed, "approaches": rows, "tracking": tracks,
        "lost_target": lost, "load_average": list(os.getloadavg()),
    }
    e_mm, e_deg = out["servo_final_error_mm_median"], out["servo_final_error_deg_median"]
    rms = out["track_rms_error_mm"]
    succeeded = [r for r in rows if r["state"] == "succeeded"]
    out["targets_met"] = {
        "every_approach_succeeded": bool(rows) and len(succeeded) == len(rows),
        "lost_target_cover_to_still_le_250ms": cover_ms is not None and cover_ms <= 250.0,
        "track_100_le_1.5mm": (rms.get("100") or 1e9) <= 1.5,
        "track_150_le_2.5mm": (rms.get("150") or 1e9) <= 2.5,
        "servo_median_time_le_3s": servo_t is not None and servo_t <= 3.0,
        "servo_4x_faster": bool(out["speedup"] and out["speedup"] >= 4.0),
        "servo_final_error_le_0.1mm_0.05deg": e_mm is not None and e_deg is not None
        and e_mm <= 0.1 and e_deg <= 0.05,
        "track_50_le_0.5mm": (rms.get("50") or 1e9) <= 0.5,
    }
    return out


def format_report(r: dict[str, Any]) -> str:
    def f(x: Any, fmt: str = ".3f") -> str:
        return "n/a" if x is None else format(x, fmt)

    comm = _commissioning_lines(r.get("commissioning"))
    lines = [
        f"world {r.get('world', 'ideal')}: servo succeeded {r['servo_success_ratio']}, "
        f"look-and-move {r['look_and_move_success_ratio']}; lens covered -> arm still "
        f"{f(r['lost_target_cover_to_still_ms'], '.0f')} ms",
        *comm,
        "conveyor tracking, RMS error after the first second:",
        *(f"  {k} mm/s: {f(v)} mm" for k, v in r["track_rms_error_mm"].items()),
        f"approach from home to a {STANDOFF_MM:g} mm standoff, {r['placements']} placements "
        f"(seed {r['seed']}; medians over every run, a failure's time counted as infinite):",
        f"  servo          median {f(r['servo_time_s_median'], '.2f')} s, final error "
        f"{f(r['servo_final_error_mm_median'])} mm / {f(r['servo_final_error_deg_median'])} deg",
        f"  look-and-move  median {f(r['look_and_move_time_s_median'], '.2f')} s, final error "
        f"{f(r['look_and_move_final_error_mm_median'])} mm / "
        f"{f(r['look_and_move_final_error_deg_median'])} deg",
        f"  speed-up {f(r['speedup'], '.1f')}x; failures: {len(r['failures'])}",
        f"  homings that failed and were retried: {len(r.get('home_failures', []))}",
        f"lost target: arm still {f(r['lost_target_declared_to_still_ms'], '.0f')} ms after it "
        f"was declared lost (the job's own figure {f(r['lost_target_job_stop_ms'], '.0f')} ms)",
        _lost_line(r.get("lost_target") or {}),
        "targets: " + ", ".join(f"{k} {'yes' if v else 'NO'}"
                                for k, v in r["targets_met"].items()),
    ]
    for fail in r["failures"]:
        lines.append(f"  failed: placement {fail.get('placement')} {fail['mode']}: "
                     f"{fail.get('error')}")
    return "\n".join(lines + _ibvs_lines(r.get("ibvs")))


def _commissioning_lines(c: dict[str, Any] | None) -> list[str]:
    if c is None:
        return ["uncommissioned: [camera] and [hand_eye] as configured"]
    out = []
    i = c.get("intrinsics") or {}
    if "failed" in i:
        out.append(f"intrinsics FAILED ({i['failed']}): [camera] as configured")
    elif i:
        m, t = i["camera"], i["truth"]
        out.append(f"intrinsics: {i['views']} board views, rms {i['rms_px']:.3f} px, coverage "
                   f"{100 * i['coverage']:.0f} %; fx {m['fx']:.2f} (true {t['fx']:.2f}) fy "
                   f"{m['fy']:.2f} ({t['fy']:.2f}) cx {m['cx']:.2f} ({t['cx']:.2f}) cy "
                   f"{m['cy']:.2f} ({t['cy']:.2f})")
    h = c.get("hand_eye") or {}
    if "failed" in h:
        out.append(f"hand-eye FAILED ({h['failed']}): [hand_eye] as configured")
    elif h:
        out.append(
            f"hand-eye: {h['views']} views in {h['routine_s']:.0f} s, verdict "
            f"{'consistent' if h['verdict_consistent'] else 'INCONSISTENT'}, "
            f"{('applied ' + str(h['applied'])) if h['applied'] else 'Apply refused'}; mount "
            f"{h['mount_error_before_mm']:.2f} mm / {h['mount_error_before_deg']:.3f} deg -> "
            f"{h['mount_error_after_mm']:.3f} mm / {h['mount_error_after_deg']:.4f} deg from "
            "the truth; each method: " + ", ".join(
                f"{k} {v['mm']:.2f} mm / {v['deg']:.3f} deg"
                for k, v in h["methods_vs_truth"].items()))
    return out


def _lost_line(lost: dict[str, Any]) -> str:
    """Where the cover-to-still time went, from the cover (ms)."""
    def f(x: Any) -> str:
        return "n/a" if x is None else f"{x:+.0f}"

    if "failed" in lost:
        return f"  lens covered: the section failed: {lost['failed']}"
    speed = lost.get("arm_speed_at_cover_mm_s")
    return (f"  lens covered (0): last frame showing the target exposed at "
            f"{f(lost.get('last_pose_exposure_ms'))}, lost declared "
            f"{f(lost.get('cover_to_declared_ms'))}, "
            f"arm still {f(lost.get('cover_to_still_measured_ms'))}; arm at "
            f"{'n/a' if speed is None else f'{speed:.0f}'} mm/s when covered"
            + ("" if lost.get("valid") else " (NOT counted: the arm was not following, or had "
               "stopped before the loss was declared)"))


def _ibvs_lines(section: dict[str, Any] | None) -> list[str]:
    if section is None:
        return []
    if "failed" in section:
        return [f"ibvs section failed: {section['failed']}"]
    return format_ibvs(section)


# -- the tracking section: false losses first -----------------------------------------------
TRACK_RUNS: dict[float, int] = {25.0: 5, 50.0: 5, 100.0: 10, 150.0: 10}  # 30 runs
TRACK_TRAVEL_MM = 300.0  # the drift's length at most: the target stays in the workspace
COVER_RUNS = 5
COVER_SPEED_MM_S = 100.0


def _track_run(cell: Cell, speed_mm_s: float, T_target_tcp: Matrix4, T_home_target: Matrix4,
               follow_s: float) -> dict[str, Any]:
    """One tracking run; ``false_loss`` when the job ended ``target_lost`` while every frame
    showed the target (it is never covered here)."""
    follow = min(follow_s, TRACK_TRAVEL_MM / speed_mm_s)
    row = _attempt(functools.partial(_track, cell, speed_mm_s, T_target_tcp, T_home_target,
                                     follow),
                   cell, {"speed_mm_s": speed_mm_s, "rms_error_mm": None})
    text = str(row.get("error") or row.get("failed") or "")
    row["follow_s"] = follow
    row["false_loss"] = "target_lost" in text or "no target pose" in text \
        or "did not show the target" in text or "no frame examined" in text
    row["ok"] = row.get("state_while_following") == "running" and not text
    return row


def _cover_run(cell: Cell, speed_mm_s: float, T_target_tcp: Matrix4, T_home_target: Matrix4
               ) -> dict[str, Any]:
    """Tracking at ``speed_mm_s``, then the lens is covered: from the cover to the simulated
    arm standing still (the simulator's own state), and the job's end code."""
    home(cell)
    sim = _sim(cell)
    sim.set_target(T_home_target)
    time.sleep(0.15)
    job_id = _hold(cell, T_target_tcp, 30.0)
    sim.set_target(sim.true_T_base_target(), np.array([-speed_mm_s, 0.0, 0.0]))
    time.sleep(1.0)
    t_cover = time.monotonic()
    sim.set_camera_blocked(True)
    try:
        t_still = _still_at(cell, t_cover)
        state = _wait_end(cell, job_id, 10.0)
    finally:
        sim.set_camera_blocked(False)
        sim.set_target(sim.true_T_base_target())
    job = cell.job(job_id)
    lost_at = job.progress.get("lost_at_monotonic_s")
    return {"speed_mm_s": speed_mm_s, "state": state, "code": job.error_code,
            "cover_to_still_ms": (t_still - t_cover) * 1000.0,
            "cover_to_declared_ms": None if lost_at is None else (lost_at - t_cover) * 1000.0,
            "declared_to_still_ms": None if lost_at is None else (t_still - lost_at) * 1000.0}


def run_bench_tracking(*, runs: dict[float, int] | None = None, cover_runs: int = COVER_RUNS,
                       follow_s: float = 3.0, host: str | None = None,
                       progress: Progress | None = None) -> dict[str, Any]:
    """Tracking runs per speed (a false ``target_lost`` counted first), then covered-lens
    stops timed to the simulated arm standing still."""
    from fakes.ur_controller.process import free_loopback_host

    plan = TRACK_RUNS if runs is None else runs
    load_before = list(os.getloadavg())
    with tempfile.TemporaryDirectory() as tmp:
        cell = start_cell(bench_config(Path(tmp), host or free_loopback_host()))
        freeze_startup_objects()
        try:
            T_tt = cell.config.approach.T_target_tcp.T()
            T_home_target = _sim(cell).true_T_base_target()
            total = sum(plan.values()) + cover_runs
            rows: list[dict[str, Any]] = []
            for speed, n in plan.items():
                for _ in range(n):
                    rows.append(_track_run(cell, speed, T_tt, T_home_target, follow_s))
                    if progress:
                        progress("tracking", len(rows), total)
            covers: list[dict[str, Any]] = []
            for _ in range(cover_runs):
                covers.append(_attempt(
                    functools.partial(_cover_run, cell, COVER_SPEED_MM_S, T_tt, T_home_target),
                    cell, {"speed_mm_s": COVER_SPEED_MM_S, "cover_to_still_ms": None}))
                if progress:
                    progress("tracking", len(rows) + len(covers), total)
            _sim(cell).set_target(T_home_target)
            lost_after_s = cell.config.servo.lost_after_s
        finally:
            cell.close()
    return _tracking_report(rows, covers, lost_after_s, load_before)


def _tracking_report(rows: list[dict[str, Any]], covers: list[dict[str, Any]],
                     lost_after_s: float, load_before: list[float]) -> dict[str, Any]:
    speeds = sorted({r["speed_mm_s"] for r in rows})
    per_speed: dict[str, dict[str, Any]] = {}
    for s in speeds:
        rs = [r for r in rows if r["speed_mm_s"] == s]
        rms = [r["rms_error_mm"] for r in rs if r["ok"] and r["rms_error_mm"] is not None]
        per_speed[f"{s:g}"] = {
            "runs": len(rs), "false_target_lost": sum(r["false_loss"] for r in rs),
            "other_failures": sum((not r["ok"]) and not r["false_loss"] for r in rs),
            "rms_error_mm_max": max(rms) if rms else None,
            "rms_error_mm_median": float(statistics.median(rms)) if rms else None}
    still = [c["cover_to_still_ms"] for c in covers if c.get("cover_to_still_ms") is not None]
    lost_codes = [c.get("code") for c in covers]
    false_total = sum(r["false_loss"] for r in rows)
    return {
        "false_target_lost": false_total, "tracking_runs": len(rows),
        "other_failures": sum((not r["ok"]) and not r["false_loss"] for r in rows),
        "per_speed": per_speed,
        "cover_to_still_ms_max": max(still) if still else None,
        "cover_to_still_ms_median": float(statistics.median(still)) if still else None,
        "cover_runs": len(covers), "cover_ended_target_lost": lost_codes.count("target_lost"),
        "lost_after_s": lost_after_s,
        "targets_met": {"no_false_target_lost": false_total == 0,
                        "covered_stops": bool(covers) and lost_codes.count("target_lost")
                        == len(covers)},
        "runs": rows, "covers": covers,
        "load_average_before": load_before, "load_average_after": list(os.getloadavg()),
    }


def format_tracking_report(r: dict[str, Any]) -> str:
    def f(x: Any, fmt: str = ".2f") -> str:
        return "n/a" if x is None else format(x, fmt)

    lines = [f"tracking: {r['false_target_lost']} false target_lost in {r['tracking_runs']} "
             f"runs ({r['other_failures']} other failures)"]
    for k, v in r["per_speed"].items():
        lines.append(f"  {k:>4} mm/s: {v['false_target_lost']} false losses, "
                     f"{v['other_failures']} other failures in {v['runs']} runs; RMS error "
                     f"max {f(v['rms_error_mm_max'])} mm (median "
                     f"{f(v['rms_error_mm_median'])})")
    lines.append(f"covered lens at {COVER_SPEED_MM_S:g} mm/s: arm still after max "
                 f"{f(r['cover_to_still_ms_max'], '.0f')} ms (median "
                 f"{f(r['cover_to_still_ms_median'], '.0f')}) of the cover; "
                 f"{r['cover_ended_target_lost']}/{r['cover_runs']} ended target_lost")
    lines.append(f"load average before {r['load_average_before'][0]:.2f}, after "
                 f"{r['load_average_after'][0]:.2f}")
    return "\n".join(lines)
