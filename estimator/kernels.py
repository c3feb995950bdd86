"""Compile the estimator's numba kernels ahead of the first frame: ``python -m estimator.kernels``.

The kernels (:mod:`estimator.regions`, :mod:`estimator.coplanar`, and small ones in
:mod:`estimator.correspondence`, :mod:`estimator.solve`, :mod:`estimator.ambiguity`; the
warm-up's estimate runs every one of them) compile on first use, which
takes ~15 s on a 2-core machine, and cache the machine code next to their sources, after which
loading them takes ~0.3 s. A cell must not spend those 15 s inside its first locate, so
``make install`` runs this module once and the cell calls :func:`warm_up` when it starts.
"""

from __future__ import annotations

import time

import numpy as np

from estimator.camera import CameraModel
from estimator.pipeline import Estimator
from estimator.target import Target


def _scene() -> tuple[CameraModel, Target, np.ndarray]:
    """A tiny synthetic frame of a 5-dot plate: enough to run every kernel once."""
    camera = CameraModel(400.0, 400.0, 159.5, 119.5, (), 320, 240)
    points = np.array([[0, 0, 0], [80, 0, 0], [80, 60, 0], [0, 60, 0], [30, 24, 0]], float)
    target = Target(points, 12.0)
    image = np.full((240, 320), 200, np.uint8)
    yy, xx = np.mgrid[0:240, 0:320]
    for x_mm, y_mm, _ in points:  # the plate seen head-on at 400 mm, centred
        u = 159.5 + 400.0 * (x_mm - 40.0) / 400.0
        v = 119.5 + 400.0 * (y_mm - 30.0) / 400.0
        image[(xx - u) ** 2 + (yy - v) ** 2 <= 6.0**2] = 40
    return camera, target, image


def warm_up() -> float:
    """Run every kernel once (compiling it, or loading it from the cache); returns seconds."""
    t0 = time.perf_counter()
    camera, target, image = _scene()
    estimator = Estimator(camera, target)
    estimator.estimate(image)  # detection, correspondence, coplanar POSIT, refinement
    estimator.estimate(image)  # tracking windows
    return time.perf_counter() - t0


if __name__ == "__main__":
    print(f"estimator kernels ready in {warm_up():.1f} s")
