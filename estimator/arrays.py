"""Arrays as the compiled kernels take them.

A numba kernel compiles one machine-code variant per argument type, and an array's type
includes its layout and whether it is writable. The kernels are compiled (and cached) for
C-contiguous, writable arrays; anything else would compile another variant -- seconds, inside
whatever call first passes it. So arguments go through :func:`kernel_array`, which passes
such arrays through untouched and copies the rest. (``np.require`` does the same, at ten
times the cost per call, which matters at a dozen calls per frame.)
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray


def kernel_array(a: Any, dtype: type = np.float64) -> NDArray[Any]:
    """``a`` as a C-contiguous, writable array of ``dtype`` (no copy when it already is)."""
    if isinstance(a, np.ndarray) and a.dtype == dtype:
        flags = a.flags
        if flags.c_contiguous and flags.writeable:
            return a
    return np.array(a, dtype=dtype, order="C")
