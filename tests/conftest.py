"""Shared fixtures and the opt-in hardware switches (--ur-host, --oak)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from drivers.ur import URArm
from fakes.ur_controller.process import ControllerProcess

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--ur-host", default=None, help="IP of a real UR controller (opt-in)")
    parser.addoption("--oak", action="store_true", default=False, help="run real OAK tests")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    skip_ur = pytest.mark.skip(reason="needs a real UR controller: pass --ur-host IP")
    skip_oak = pytest.mark.skip(reason="needs a real OAK camera: pass --oak")
    for item in items:
        if "ur_hardware" in item.keywords and not config.getoption("--ur-host"):
            item.add_marker(skip_ur)
        if "oak_hardware" in item.keywords and not config.getoption("--oak"):
            item.add_marker(skip_oak)


@pytest.fixture(scope="session", autouse=True)
def _estimator_kernels() -> None:
    """Compile (or load) the estimator's numba kernels once, before any test times a request:
    a first compile inside an HTTP locate would take ~15 s (make install normally did it)."""
    from estimator.kernels import warm_up

    warm_up()


@pytest.fixture
def ur_host(request: pytest.FixtureRequest) -> str:
    host = request.config.getoption("--ur-host")
    if not host:
        pytest.skip("needs --ur-host")
    return str(host)


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """``../shared`` beside the checkout; tests that need it skip when it is absent."""
    if not SHARED.is_dir():
        pytest.skip(f"{SHARED} is absent")
    return SHARED


@pytest.fixture(scope="session")
def visp_dir(shared_dir: Path) -> Path:
    d = shared_dir / "data" / "visp-eye-in-hand"
    if not d.is_dir():
        pytest.skip(f"{d} is absent")
    return d


@pytest.fixture
def ur_ctl() -> Iterator[ControllerProcess]:
    """A simulated UR controller in its own process on its own loopback address."""
    with ControllerProcess() as proc:
        yield proc


@pytest.fixture
def ur_arm(ur_ctl: ControllerProcess) -> Iterator[URArm]:
    """The real UR adapter (ur_rtde) connected to ``ur_ctl``, powered and brakes released."""
    arm = URArm(ur_ctl.host)
    arm.connect()
    arm.power_on()
    yield arm
    arm.disconnect()
