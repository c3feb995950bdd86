"""``cell bench bias``: the dots' centre bias of the simulated camera, the figure behind
``[ibvs] centroid_bias_px``.

    cell bench bias [--frames 30] [--steps 41] [--json]

A dot's measured centre carries two errors: noise, different in every frame, which averaging
frames removes, and a bias that depends on where in its pixel the dot lies (the pixel grid,
the grey levels' quantisation), the same in every frame of one pose, which averaging does not
remove. The bench shows the simulated cell's target to its camera (``[camera]``, ``[target]``
of the built-in config, 456 mm away, tilted 8 and 5 deg), moves it by ``1 / (steps - 1)``
... 2 px along the image's x, then its y, and at each step takes the mean centre of every dot
over ``frames`` rendered frames (``fakes.render``, with the simulated camera's noise and blur
from ``[sim]``) found by the
estimator's blob detector. Each dot's mean centre minus its ideal image point, less that
difference's mean over the steps (a per-dot constant: the perspective bias, the blur), is the
bias at that step; the report gives its RMS per image coordinate and its worst, for both
sweeps. What is left of the noise after ``frames`` frames is in the figure too (it falls as
``1 / sqrt(frames)``), so it bounds the bias from above.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

DISTANCE_MM = 456.0  # the simulated cell's view from home
TILT_DEG = (8.0, -5.0)  # about the camera's x and y
SWEEP_PX = 2.0
Progress = Callable[[str, int, int], None]


def run_bench_bias(frames: int = 30, steps: int = 41, seed: int = 1,
                   progress: Progress | None = None) -> dict[str, Any]:
    from cell.config.schema import load_config
    from estimator.blobs import detect_dots
    from estimator.transforms import make_T
    from fakes.render import render_target

    config = load_config(None)
    camera, target = config.camera.model(), config.target.model()
    points = np.asarray(target.points_mm, dtype=float)
    R = Rotation.from_euler("xy", TILT_DEG, degrees=True).as_matrix()
    centre = np.array([-points[:, 0].mean(), -points[:, 1].mean(), DISTANCE_MM])
    rng = np.random.default_rng(seed)
    sweeps: dict[str, NDArray[np.float64]] = {}
    missed = 0
    done, total = 0, 2 * steps
    for axis, name in ((0, "x"), (1, "y")):
        residuals = []
        for k in range(steps):
            shift = np.zeros(3)
            shift[axis] = k * SWEEP_PX / (steps - 1) * DISTANCE_MM / camera.fx
            T_camera_target = make_T(R, centre + shift)
            ideal = camera.project(points @ R.T + T_camera_target[:3, 3])
            total_px, n = np.zeros_like(ideal), 0
            for _ in range(frames):
                image = render_target(camera, target, T_camera_target, rng=rng,
                                      noise_std=config.sim.noise_std,
                                      blur_sigma_px=config.sim.blur_sigma_px)
                found = detect_dots(image, target.polarity)[0].centres_px
                if len(found) != len(points):
                    missed += 1
                    continue
                nearest = [int(np.argmin(np.linalg.norm(found - p, axis=1))) for p in ideal]
                total_px += found[nearest]
                n += 1
            if n == 0:
                raise RuntimeError(f"no frame at step {k} along {name} showed every dot")
            residuals.append(total_px / n - ideal)
            done += 1
            if progress is not None:
                progress("bias (steps)", done, total)
        r = np.asarray(residuals)
        sweeps[name] = r - r.mean(axis=0, keepdims=True)
    both = np.concatenate(list(sweeps.values()))
    return {
        # the least kind figure first: what the bound should take per image coordinate
        "bias_px_rms": round(float(np.sqrt(np.mean(both ** 2))), 5),
        "bias_px_worst": round(float(np.abs(both).max()), 5),
        "sweeps": {name: {"u_px_rms": round(float(np.sqrt(np.mean(r[..., 0] ** 2))), 5),
                          "v_px_rms": round(float(np.sqrt(np.mean(r[..., 1] ** 2))), 5),
                          "worst_px": round(float(np.abs(r).max()), 5)}
                   for name, r in sweeps.items()},
        "frames_per_step": frames, "steps": steps, "sweep_px": SWEEP_PX,
        "frames_missing_a_dot": missed, "distance_mm": DISTANCE_MM,
        "noise_std": config.sim.noise_std, "blur_sigma_px": config.sim.blur_sigma_px,
        "tilt_deg": list(TILT_DEG), "dots": len(points), "seed": seed,
    }


def format_report(r: dict[str, Any]) -> str:
    lines = [f"dot centre bias: {r['bias_px_rms']} px RMS per image coordinate, worst "
             f"{r['bias_px_worst']} px ({r['frames_per_step']} frames a step, {r['steps']} "
             f"steps over {r['sweep_px']} px, {r['dots']} dots at {r['distance_mm']} mm; "
             f"{r['frames_missing_a_dot']} frames missing a dot)"]
    for name, s in r["sweeps"].items():
        lines.append(f"  moved along {name}: u {s['u_px_rms']} px, v {s['v_px_rms']} px RMS, "
                     f"worst {s['worst_px']} px")
    return "\n".join(lines)
