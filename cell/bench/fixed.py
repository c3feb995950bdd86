"""Benchmark: locate accuracy of a fixed camera at 1 m (``cell bench fixed``).

Renders the cell's dot plate at 1 m from the camera, 30 deg off the optical axis (the
sim-fixed.toml geometry) at random positions and spins, estimates it, and reports the error
against the rendered truth at the plate centre (where the tool goes): the worst case first,
then the median, for one frame and for the 3-frame average look-and-move uses, for the OAK-D's
12 MP colour sensor and its 1280x800 mono sensor. The truth is never shown to the estimator.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from cell.results.modes import ApproachMode
from cell.vision.frames import mean_pose
from estimator import CameraModel, EstimationError, Target
from estimator.pipeline import Estimator
from estimator.transforms import make_T, pose_distance
from fakes.render import motion_smear, render_target, render_target_full_frame

SENSORS = {"12MP colour (4056x3040, f 2950 px)": (4056, 3040, 2950.0),
           "1280x800 mono (f 880 px)": (1280, 800, 880.0)}
POINTS = [[0, 0, 0], [60, 0, 0], [100, 10, 0], [0, 50, 0], [40, 70, 0], [90, 60, 0]]


def run(n_poses: int, tilt_deg: float, distance_mm: float, seed: int) -> None:
    target = Target(POINTS, 10.0, "dark")
    centre = target.points_mm.mean(axis=0)
    for name, (w, h, f) in SENSORS.items():
        cam = CameraModel(f, f, (w - 1) / 2, (h - 1) / 2, (), w, h)
        rng = np.random.default_rng(seed)
        rows, failed = [], 0
        for _ in range(n_poses):
            R = (Rotation.from_rotvec([np.radians(tilt_deg), 0, 0])
                 * Rotation.from_rotvec([0, 0, rng.uniform(-np.pi, np.pi)])).as_matrix()
            t = np.array([*rng.uniform(-100, 100, 2), distance_mm]) - R @ centre
            T = make_T(R, t)
            estimates = []
            for _frame in range(3):
                img = render_target(cam, target, T, noise_std=1.0, blur_sigma_px=0.8, rng=rng)
                try:
                    estimates.append(Estimator(cam, target).estimate(img).T_camera_target)
                except EstimationError:
                    failed += 1
            if len(estimates) < 3:
                continue
            row = []
            for Te in (estimates[0], mean_pose(estimates)):
                d_mm = float(np.linalg.norm((Te[:3, :3] - R) @ centre + Te[:3, 3] - t))
                row += [d_mm, pose_distance(Te, T)[1]]
            rows.append(row)
        e = np.array(rows)
        print(f"{name}: {len(rows)} poses, {failed} failed frames, at {distance_mm:g} mm, "
              f"tilt {tilt_deg:g} deg")
        for label, k in (("1 frame", 0), ("3-frame mean", 2)):
            print(f"  {label:13s} worst {e[:, k].max():.3f} mm / {e[:, k + 1].max():.3f} deg, "
                  f"median {np.median(e[:, k]):.3f} mm / {np.median(e[:, k + 1]):.3f} deg")


def render_cost(n: int) -> None:
    """What one frame costs at each sensor size here: the simulated render and the estimate
    (the servo's pose interval is at least their sum on this host), and the search that runs
    when the track does not explain a frame: the whole frame against the window around the
    last dots (:mod:`cell.vision.search_window`), all dots in view and with one dot hidden
    (the tool over it, the case that costs most: the coarse pass cannot account for every
    dot). The windowed search must give the same pose; the largest difference is printed."""
    import time

    from cell.vision.search_window import SearchWindows

    target = Target(POINTS, 10.0, "dark")
    centre = target.points_mm.mean(axis=0)
    for name, (w, h, f) in SENSORS.items():
        cam = CameraModel(f, f, (w - 1) / 2, (h - 1) / 2, (), w, h)
        rng = np.random.default_rng(0)
        R = Rotation.from_rotvec([np.radians(30.0), 0, 0]).as_matrix()
        T = make_T(R, np.array([0.0, 0.0, 1000.0]) - R @ centre)
        est = Estimator(cam, target)
        t_render, t_est = [], []
        search: dict[str, list[float]] = {}
        worst_diff = (0.0, 0.0)
        for k in range(n):
            t0 = time.perf_counter()
            img = render_target(cam, target, T, noise_std=1.0, blur_sigma_px=0.8, rng=rng)
            t1 = time.perf_counter()
            first = est.estimate(img)
            t_render.append(t1 - t0)
            t_est.append(time.perf_counter() - t1)
            hidden = img.copy()  # the tool (grey 70) over one dot, a different one each frame
            pts = np.asarray(first.image_points_px)
            u, v = np.round(pts[k % len(pts)]).astype(int)
            r = int(np.ceil(max(b.major_axis_px for b in first.matched_blobs)))
            hidden[max(v - r, 0):v + r + 1, max(u - r, 0):u + r + 1] = 70
            # the window the cell would use for the next frame, the arm having moved 20 mm
            # in 0.3 s (the servo's pose interval at 12 MP)
            policy = SearchWindows(True)
            T_tcp = np.eye(4)
            policy.seen(first, target.points_mm, cam, 0.0, T_tcp, np.eye(4))
            moved = T_tcp.copy()
            moved[:3, 3] += [20.0, 0.0, 0.0]
            window = policy.window(0.3, moved, w, h)
            for label, frame in (("all dots", img), ("one hidden", hidden)):
                poses = {}
                for how, win in (("full", None), ("window", window)):
                    # no track, so every estimate searches; the first is the sighting
                    searcher = Estimator(cam, target, tracking=False)
                    searcher.estimate(img)
                    t2 = time.perf_counter()
                    try:
                        poses[how] = searcher.estimate(frame, win).T_camera_target
                    except EstimationError:
                        continue
                    finally:
                        search.setdefault(f"{how}, {label}", []).append(
                            time.perf_counter() - t2)
                if len(poses) == 2:
                    d = pose_distance(poses["full"], poses["window"])
                    worst_diff = (max(worst_diff[0], d[0]), max(worst_diff[1], d[1]))
        print(f"{name}: render median {np.median(t_render) * 1000:.0f} ms (worst "
              f"{max(t_render) * 1000:.0f}), estimate median {np.median(t_est) * 1000:.0f} ms "
              f"(worst {max(t_est) * 1000:.0f}) over {n} frames")
        print("  search after a lost track, median / worst ms: " + "; ".join(
            f"{key} {np.median(ts) * 1000:.1f} / {max(ts) * 1000:.1f}"
            for key, ts in search.items()))
        print(f"  window size {window[2] - window[0] if window else w}x"
              f"{window[3] - window[1] if window else h} px; windowed pose against the full "
              f"search's: {worst_diff[0]:.2e} mm / {worst_diff[1]:.2e} deg")


def render_steps(n: int) -> None:
    """Where a simulated frame's render time goes, step by step, for the two simulated cameras
    as built (their true lens): the fixed 12 MP camera at home (sim-fixed.toml's scene, the
    tool drawn over it) and the 1280x800 eye-in-hand camera at 300 mm (motion smear of 2 px).
    Each step's median ms over ``n`` frames, for the straightforward full-frame computation
    (:func:`fakes.render.render_target_full_frame`) and the render the cameras use
    (:func:`fakes.render.render_target`, the work within the drawn box), the two in turn so
    that both see the same load; then the totals, median and worst, and the largest grey-level
    difference between the two images."""
    import time

    from cell.devices import sim_truth
    from estimator.transforms import invert_T
    from fakes.fixed_camera import draw_tool

    fixed = sim_truth.as_built("fixed")
    hand = sim_truth.as_built("hand")
    assert fixed.hand_eye.T_base_camera is not None  # a fixed mount's config has it
    T_fixed = invert_T(fixed.hand_eye.T_base_camera.T()) @ fixed.sim.T_base_target.T()
    hand_target = hand.target.model()
    centre = hand_target.points_mm.mean(axis=0)
    R = Rotation.from_rotvec([np.radians(20.0), 0, 0]).as_matrix()
    T_hand = make_T(R, np.array([10.0, -5.0, 300.0]) - R @ centre)
    scenes = [
        ("fixed 12 MP", sim_truth.resolve(fixed).camera, fixed.target.model(), T_fixed, fixed.sim),
        ("hand 1280x800", sim_truth.resolve(hand).camera, hand_target, T_hand, hand.sim)]
    load = _load()
    table: dict[str, dict[str, str]] = {}
    totals: list[str] = []
    methods = (("full frame", render_target_full_frame), ("drawn box", render_target))
    for name, cam, target, T, sim in scenes:
        steps: dict[str, list[dict[str, float]]] = {label: [] for label, _ in methods}
        total: dict[str, list[float]] = {label: [] for label, _ in methods}
        worst = 0
        for k in range(n):  # the two in turn, so that both see the same load
            images = []
            for label, fn in methods:
                t: dict[str, float] = {}
                t0 = time.perf_counter()
                img = fn(cam, target, T, noise_std=sim.noise_std, blur_sigma_px=sim.blur_sigma_px,
                         lighting_gradient=0.1, rng=np.random.default_rng(k), timings=t)
                t1 = time.perf_counter()
                if name.startswith("fixed"):
                    img = draw_tool(img, np.array([[1900.0, 1000.0], [1990.0, 1000.0],
                                                   [1990.0, 1300.0], [1900.0, 1300.0]]))
                    t["tool (fixed camera)"] = time.perf_counter() - t1
                else:
                    img = motion_smear(img, (2.0, 1.0))
                    t["motion smear (hand camera)"] = time.perf_counter() - t1
                total[label].append(time.perf_counter() - t0)
                steps[label].append(t)
                images.append(img)
            worst = max(worst, int(np.abs(images[0].astype(int) - images[1]).max()))
        for label, _ in methods:
            col = f"{name}, {label}"
            for key in steps[label][0]:
                table.setdefault(key, {})[col] = \
                    f"{np.median([s[key] for s in steps[label]]) * 1000:.1f}"
            table.setdefault("total", {})[col] = (f"{np.median(total[label]) * 1000:.0f} "
                                                  f"(worst {max(total[label]) * 1000:.0f})")
        totals.append(f"{name}: largest difference {worst} grey level(s)")
    cols = [f"{name}, {label}" for name, *_ in scenes for label, _ in methods]
    print(f"render steps, median ms over {n} frames, the full frame and the drawn box in turn:")
    print(f"  {'step':28s}" + "".join(f"{c:>26s}" for c in cols))
    order = ["geometry + discs", "background fill", "noise", "lit background",
             "plate + frame (frame)", "plate + frame (box)", "discs (paint)", "gradient (frame)",
             "gradient (box)", "blur (frame)", "blur (box)", "add box", "clip + uint8",
             "tool (fixed camera)", "motion smear (hand camera)", "total"]
    rank = {key: i for i, key in enumerate(order)}
    for key, row in sorted(table.items(), key=lambda kv: rank.get(kv[0], len(order))):
        print(f"  {key:28s}" + "".join(f"{row.get(c, '-'):>26s}" for c in cols))
    print("  " + "; ".join(totals) + f"; load {load} to {_load()}")


def _load() -> str:
    try:
        with open("/proc/loadavg") as f:
            return " ".join(f.read().split()[:3])
    except OSError:
        return "unknown"



def _fixed_cell_data(state_dir: Path) -> dict[str, Any]:
    """sim-fixed.toml as a dict, with the in-process arm, no gripper, no PLC servers and its
    job database in ``state_dir``: the benchmark's cell, to adjust before parsing."""
    from cell.config.schema import load_config

    d = load_config(Path(__file__).parents[1] / "configs" / "sim-fixed.toml").model_dump(
        mode="python")
    d["robot"]["kind"], d["sim"]["ur_controller"], d["gripper"]["kind"] = "sim", False, "none"
    d["api"]["job_db"] = str(state_dir / "jobs.db")
    d["opcua"]["enabled"], d["urscript"]["xmlrpc_port"] = False, 0
    return d

def approach(n: int, seed: int, servo: bool = False, lost_after_s: float | None = None,
             stall_after_s: float | None = None, preview: bool = False) -> None:
    """``n`` approaches on the simulated fixed-camera cell (sim-fixed.toml, in-process arm),
    look-and-move or (``servo``) the closed loop, each to a new random placement, homing
    between; the error is the true TCP against the true goal (simulated truth the cell does
    not see). Failed jobs are counted first; the time is the job's, start to end.
    ``preview``: the colour sensor's image scaled 1/3 by the camera's ISP (1352x1013), a
    ninth of the pixels to render and search."""
    import tempfile
    import time
    from pathlib import Path

    from cell.actions.approach import start_approach
    from cell.config.schema import parse_config
    from cell.errors import CellError
    from cell.results import LookAndMoveApproach, ServoApproach
    from cell.runtime import start_cell
    from cell.vision.frames import approach_tcp

    flat = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])
    rng = np.random.default_rng(seed)
    with tempfile.TemporaryDirectory() as tmp:
        d = _fixed_cell_data(Path(tmp))
        if preview:
            c = d["camera"]
            c.update(fx=c["fx"] / 3, fy=c["fy"] / 3, cx=(c["cx"] + 0.5) / 3 - 0.5,
                     cy=(c["cy"] + 0.5) / 3 - 0.5, width=c["width"] // 3,
                     height=c["height"] // 3)
        if lost_after_s is not None:
            d["servo"]["lost_after_s"] = lost_after_s
        if stall_after_s is not None:
            d["servo"]["stall_after_s"] = stall_after_s
        cell = start_cell(parse_config(d))
        try:
            assert cell.sim is not None
            errors, good, times, failures, notes = [], 0, [], [], []
            mode = ApproachMode.servo if servo else ApproachMode.look_and_move
            for _ in range(n):
                R = (Rotation.from_rotvec([*rng.normal(size=2) * 0.15, 0])
                     * Rotation.from_rotvec([0, 0, rng.uniform(-0.6, 0.6)])).as_matrix() @ flat
                c = np.array([-432.0, -132.0, 0.0]) + np.r_[rng.uniform(-40, 40, 2),
                                                             rng.uniform(0, 30)]
                T = make_T(R, c - R @ np.array([48.0, 32.0, 0.0]))
                cell.sim.set_target(T)
                time.sleep(0.3)
                t0 = time.monotonic()
                try:
                    job = start_approach(cell.core, "bench", wait=True, mode=mode)
                except CellError as err:  # refused before anything moved
                    failures.append(f"refused {err.code}")
                    continue
                times.append(time.monotonic() - t0)
                rec = cell.core.jobs.get(job.id)
                goal = approach_tcp(T, np.eye(4), cell.config.approach.standoff_mm)
                d_mm, d_deg = pose_distance(cell.sim.true_T_base_tcp(), goal)
                ok = rec is not None and rec.state == "succeeded"
                if ok:
                    errors.append((d_mm, d_deg))
                    r = rec.result if rec is not None else None
                    loop = r if isinstance(r, ServoApproach) else None
                    source = (r.pose_source if isinstance(r, LookAndMoveApproach | ServoApproach)
                              else None)
                    interval = None if loop is None else loop.pose_interval_ms
                    notes.append((source or "live", None if loop is None else loop.frames,
                                  None if interval is None else interval.median))
                else:
                    failures.append(f"failed {rec.error_code if rec is not None else '?'}")
                    if rec is not None and rec.error_message and len(failures) == 1:
                        print(f"  first failure: {rec.error_message}")
                good += int(ok and d_mm < 0.1)
                cell.home("bench", wait=True)
            size = f"{cell.config.camera.width}x{cell.config.camera.height}"
            print(f"approach ({mode}, {size}): {good}/{n} succeeded within 0.1 mm of the true "
                  f"goal; {len(failures)} failed ({', '.join(failures) or 'none'})")
            if errors:
                e = np.array(errors)
                print(f"  error vs truth: worst {e[:, 0].max():.3f} mm / {e[:, 1].max():.4f} "
                      f"deg, median {np.median(e[:, 0]):.3f} mm / {np.median(e[:, 1]):.4f} deg")
            if times:
                print(f"  job time: median {np.median(times):.2f} s, worst {max(times):.2f} s")
            if servo and notes:
                held = sum(1 for src, _, _ in notes if src == "last_seen")
                frames = [f for _, f, _ in notes if f is not None]
                gaps = [g for _, _, g in notes if g is not None]
                print(f"  ended on the last pose seen (arm hiding the target): {held}/"
                      f"{len(notes)}; poses per run median {np.median(frames):.0f}"
                      + (f", pose interval median {np.median(gaps):.0f} ms" if gaps else ""))
        finally:
            cell.close()


def main(a: argparse.Namespace) -> int:
    if a.poses:
        run(a.poses, a.tilt_deg, a.distance_mm, a.seed)
    if a.render:
        render_steps(a.render)
        render_cost(a.render)
    if a.approaches:
        approach(a.approaches, a.seed, a.servo, a.lost_after_s, a.stall_after_s, a.preview)
    if a.ibvs:
        ibvs(a.ibvs, a.seed, stall_after_s=a.stall_after_s)
    return 0


# The dot plate clamped to the tool, facing the camera at home (the calibration test's).
TOOL_BOARD = {"position_mm": [48.0, 27.7128, 134.0], "rotvec_rad": [0.0, -0.813104, -3.034545]}
# The true camera off the configured [hand_eye] T_base_camera (2.1 mm / 0.46 deg).
TRUE_CAMERA_OFFSET = ((1.5, -1.0, 1.2), (0.004, -0.003, 0.005))  # position mm, rotvec rad


def ibvs(n: int, seed: int, displace_mm: float = 30.0, displace_deg: float = 6.0,
         teach_samples: int = 10, stall_after_s: float | None = None) -> None:
    """IBVS with the fixed camera: the plate on the tool (``TOOL_BOARD``) taught at home
    (``POST /teach``'s routine), then ``n`` seeded displacements (``displace_mm`` in a random
    direction, ``displace_deg`` about a random axis through the TCP), each jogged to and
    approached back by ``mode = "ibvs"``; the simulated camera stands ``TRUE_CAMERA_OFFSET``
    away from the configured one. Error: the true TCP against the true TCP where the view was
    taught (simulated truth the cell does not see)."""
    import tempfile
    import time
    from pathlib import Path

    from cell.bench.ibvs import _recover, displacements, jog_to
    from cell.config.schema import parse_config
    from cell.errors import CellError
    from cell.results import IbvsApproach
    from cell.runtime import start_cell
    from estimator.transforms import T_from_pose, T_from_pose_dict, pose_dict

    rng = np.random.default_rng(seed)
    with tempfile.TemporaryDirectory() as tmp:
        d = _fixed_cell_data(Path(tmp))
        guess = T_from_pose_dict(d["hand_eye"]["T_base_camera"])
        truth = guess @ T_from_pose(*TRUE_CAMERA_OFFSET)
        d["sim"].update(T_base_camera=pose_dict(truth), T_flange_board=TOOL_BOARD)
        if stall_after_s is not None:
            d["servo"]["stall_after_s"] = stall_after_s
        cell = start_cell(parse_config(d))
        try:
            assert cell.sim is not None
            off_mm, off_deg = pose_distance(guess, truth)
            T_taught = cell.sim.true_T_base_tcp()
            taught = cell.teach("bench", "plate", samples=teach_samples)
            print(f"IBVS, fixed camera (12 MP), the tool's plate taught at home ({teach_samples} "
                  f"samples, spread {taught.spread_mm:.3f} mm); camera {off_mm:.1f} mm / "
                  f"{off_deg:.2f} deg off the config; {n} displacements of {displace_mm:g} mm / "
                  f"{displace_deg:g} deg; stall_after_s {cell.config.servo.stall_after_s:g} s")
            rows, failures = [], []
            for dt, dr in displacements(rng, n, displace_mm, displace_deg):
                T_disp = T_from_pose(dt, np.zeros(3)) @ T_taught
                T_disp[:3, :3] = Rotation.from_rotvec(np.radians(dr)).as_matrix() \
                    @ T_taught[:3, :3]
                try:
                    jog_to(cell, T_disp)
                except CellError as err:
                    failures.append(f"jog {err.code}")
                    _recover(cell)
                    continue
                t0 = time.monotonic()
                try:
                    job = cell.approach("bench", T_target_tcp=taught.T_target_tcp,
                                        mode=ApproachMode.ibvs, view=taught.view, wait=True,
                                        wait_timeout_s=120.0)
                except CellError as err:
                    failures.append(f"refused {err.code}")
                    continue
                took = time.monotonic() - t0
                time.sleep(0.2)
                d_mm, d_deg = pose_distance(cell.sim.true_T_base_tcp(), T_taught)
                if job.state != "succeeded":
                    failures.append(f"failed {job.error_code}")
                    if len(failures) == 1:
                        print(f"  first failure: {job.error_message}")
                    _recover(cell)
                    continue
                r = job.result
                assert isinstance(r, IbvsApproach)
                rows.append((d_mm, d_deg, took, r.estimated_error_mm, r.image_error_px_rms))
            good = sum(1 for row in rows if row[0] < 0.1)
            print(f"  {len(rows)}/{n} converged, {good} within 0.1 mm of the taught true TCP; "
                  f"{len(failures)} failed ({', '.join(failures) or 'none'})")
            if rows:
                e = np.array([row[:3] for row in rows])
                est = [row[3] for row in rows if row[3] is not None]
                print(f"  true error: worst {e[:, 0].max():.3f} mm / {e[:, 1].max():.4f} deg, "
                      f"median {np.median(e[:, 0]):.3f} mm / {np.median(e[:, 1]):.4f} deg; "
                      f"time median {np.median(e[:, 2]):.2f} s, worst {e[:, 2].max():.2f} s"
                      + (f"; pose-based estimate of the error median {np.median(est):.3f} mm"
                         if est else ""))
        finally:
            cell.close()
