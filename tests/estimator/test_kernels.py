"""The compiled kernels: one machine-code variant each, whatever arrays the callers pass.

A numba kernel compiles a new variant (seconds) for every new argument type, and an array's
type includes its layout and writability. So read-only frames, Fortran-ordered or strided
points and distorted cameras must all reach the kernels as the variant ``make install``
compiled -- otherwise the first such call of a running cell would stall for seconds.
"""

from __future__ import annotations

import inspect

import numpy as np
from numba.core.registry import CPUDispatcher

import estimator
from estimator import Estimator, Target, posit, solve_pose
from estimator.arrays import kernel_array
from estimator.correspondence import match_blobs
from estimator.kernels import warm_up
from fakes.render import render_target
from tests.support.pose_scenes import CAM, CAM_DISTORTED


def _dispatchers() -> dict[str, CPUDispatcher]:
    import importlib
    import pkgutil

    out = {}
    for info in pkgutil.iter_modules(estimator.__path__):
        module = importlib.import_module(f"estimator.{info.name}")
        for name, obj in inspect.getmembers(module):
            if isinstance(obj, CPUDispatcher) and obj.__module__ == module.__name__:
                out[f"{module.__name__}.{name}"] = obj
    return out


def test_kernel_array_passes_kernel_ready_arrays_and_copies_the_rest() -> None:
    a = np.zeros((3, 2))
    assert kernel_array(a) is a
    readonly = np.zeros((3, 2))
    readonly.flags.writeable = False
    for other in (readonly, np.zeros((2, 3)).T, np.zeros((3, 4))[:, ::2], np.zeros((3, 2), int),
                  [[0.0, 0.0]]):
        out = kernel_array(other)
        assert out.flags.c_contiguous and out.flags.writeable and out.dtype == np.float64
        assert np.array_equal(out, np.asarray(other, dtype=float))


def test_odd_inputs_compile_no_second_variant() -> None:
    warm_up()
    points = np.array([[0, 0, 0], [70, 0, 0], [70, 50, 0], [0, 50, 0], [25, 18, 0],
                       [50, 35, 0]], float)
    target = Target(points, 10.0)
    T = np.eye(4)
    T[:3, 3] = (-30.0, -20.0, 450.0)
    for camera in (CAM, CAM_DISTORTED):
        frame = render_target(camera, target, T, rng=np.random.default_rng(1))
        frame.flags.writeable = False
        pipeline = Estimator(camera, target)
        pipeline.estimate(frame)
        pipeline.estimate(frame)
        assert pipeline.last_mode == "tracking"
        img = camera.project(points @ T[:3, :3].T + T[:3, 3])
        fortran = np.asfortranarray(img)
        readonly = img.copy()
        readonly.flags.writeable = False
        solve_pose(np.asfortranarray(points), fortran, camera, dot_diameter_mm=10.0)
        posit(points[::1], readonly, camera)
        match_blobs(readonly, target, camera)
    variants = {name: len(d.signatures) for name, d in _dispatchers().items()}
    assert variants and all(n <= 1 for n in variants.values()), variants
