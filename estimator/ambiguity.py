"""When is a pose ambiguous: an alternative that is a different pose and fits as well.

Two poses are *different* when a dot moves by more than ``max_dot_mm`` (default 1 mm) or the
rotation differs by more than ``max_deg`` (default 1 deg) between them: an alternative closer
than that is the same answer for any use of the pose. They are *separable* when the measured
points tell them apart at the noise level actually present. sigma^2, the noise variance, is
estimated from the chosen pose's residuals (SSR_best over 2N - 6 degrees of freedom for N
points and 6 pose parameters) pooled with a prior of ``noise_prior_px`` (0.05 px, a good
detector's centre noise) worth PRIOR_DOF = 2 degrees of freedom: a 4-dot plate leaves only 2
of its own, too few to trust alone, while a grid's many dots outweigh the prior. The test is
the likelihood ratio: delta_chi2 = (SSR_alt - SSR_best) / sigma^2 above the 0.999 quantile of
chi^2 with 1 degree of freedom (10.83) rejects the alternative at p = 0.001. ``ambiguous`` =
different and not separable; ``margin`` = delta_chi2 / threshold says by how much (above 1:
separable).

On a symmetric layout the equivalent labellings fit exactly as well (delta_chi2 = 0): a fresh
search on one is always ambiguous, which is what tracking resolves.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray

from estimator.arrays import kernel_array
from estimator.result import AmbiguityTest

MAX_DOT_MM = 1.0
MAX_DEG = 1.0
NOISE_PRIOR_PX = 0.05
PRIOR_DOF = 2.0
CHI2_THRESHOLD = 10.83  # chi^2, 1 dof, 0.999 quantile
TEST_NAME = "likelihood ratio: delta_chi2 = (SSR_alt - SSR_best) / sigma^2 > 10.83 (p 0.001)"


def pose_difference(
    T_a: NDArray[np.float64], T_b: NDArray[np.float64], points_mm: NDArray[np.float64]
) -> tuple[float, float]:
    """(largest dot displacement mm, rotation angle deg) between two poses of the dots."""
    shift, cos_angle = _difference(kernel_array(T_a), kernel_array(T_b), kernel_array(points_mm))
    return shift, math.degrees(math.acos(max(-1.0, min(1.0, cos_angle))))


@numba.njit(cache=True, nogil=True)
def _difference(
    T_a: NDArray[np.float64], T_b: NDArray[np.float64], points_mm: NDArray[np.float64]
) -> tuple[float, float]:
    """(largest dot displacement, cos of the rotation angle): a few 3-vectors, compiled
    because numpy's per-call overhead would be most of the cost on every solve."""
    best = 0.0
    for i in range(points_mm.shape[0]):
        d2 = 0.0
        for r in range(3):
            d = T_b[r, 3] - T_a[r, 3]
            for c in range(3):
                d += (T_b[r, c] - T_a[r, c]) * points_mm[i, c]
            d2 += d * d
        best = max(best, d2)
    trace = 0.0
    for r in range(3):
        for c in range(3):
            trace += T_a[r, c] * T_b[r, c]
    return math.sqrt(best), 0.5 * (trace - 1.0)


def ambiguity_test(
    T_best: NDArray[np.float64], rms_best_px: float, T_alt: NDArray[np.float64],
    rms_alt_px: float, points_mm: NDArray[np.float64], *, max_dot_mm: float = MAX_DOT_MM,
    max_deg: float = MAX_DEG, noise_prior_px: float = NOISE_PRIOR_PX,
) -> AmbiguityTest:
    """The module docstring's test of an alternative pose against the chosen one."""
    n = len(points_mm)
    shift, angle = pose_difference(T_best, T_alt, points_mm)
    different = shift > max_dot_mm or angle > max_deg
    ssr_best, ssr_alt = n * rms_best_px**2, n * rms_alt_px**2
    dof = max(2 * n - 6, 0)
    sigma2 = (ssr_best + PRIOR_DOF * noise_prior_px**2) / (dof + PRIOR_DOF)
    delta = max(ssr_alt - ssr_best, 0.0) / sigma2
    margin = delta / CHI2_THRESHOLD
    return AmbiguityTest(
        ambiguous=bool(different and margin <= 1.0), different=different, dot_shift_mm=shift,
        rotation_deg=angle, delta_chi2=delta, threshold=CHI2_THRESHOLD,
        sigma_px=math.sqrt(sigma2), margin=margin, test=TEST_NAME,
    )
