"""The package's public names load on first use, and the geometry alone stays light."""

from __future__ import annotations

import subprocess
import sys

import estimator


def test_every_public_name_resolves_to_its_module() -> None:
    for name in estimator.__all__:
        value = getattr(estimator, name)
        assert value.__module__.startswith("estimator."), name
    assert set(estimator.__all__) <= set(dir(estimator))


def test_an_unknown_name_is_an_attribute_error() -> None:
    try:
        estimator.no_such_name  # type: ignore[attr-defined]  # noqa: B018
    except AttributeError as err:
        assert "no_such_name" in str(err)
    else:
        raise AssertionError("no AttributeError")


def test_the_transforms_alone_load_neither_opencv_nor_numba() -> None:
    """The simulated controller's process needs only the geometry: it starts without the
    detection stack (about half a second of imports on a 2-core host)."""
    code = ("import sys, estimator.transforms; "
            "print(sorted(m for m in ('cv2', 'numba', 'estimator.blobs') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "[]"


def test_posit_is_the_function_whichever_module_loaded_first() -> None:
    """The submodule ``estimator.posit`` loaded by another one first must not take the
    package's name ``posit``: it stays the function."""
    code = ("import estimator.pipeline, estimator, sys; from estimator import posit; "
            "print(callable(posit), posit is sys.modules['estimator.seed'].posit)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "True True"
