"""Shared fixtures, the opt-in hardware switches (--ur-host, --oak) and the size of the API's
fuzzing run (--schema-examples)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from drivers.ur.adapter import URArm
from fakes.ur_controller.process import ControllerProcess
from tests.support.paths import SHARED


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--ur-host", default=None, help="IP of a real UR controller (opt-in)")
    parser.addoption("--oak", action="store_true", default=False, help="run real OAK tests")
    parser.addoption("--schema-examples", type=int, default=5, metavar="N",
                     help="schemathesis examples per API operation (default 5; ~70 per "
                          "operation make 20,000 cases: docs/performance.md)")


# ``make test`` runs the suite on two xdist workers (``--dist loadgroup``): each file is one
# unit of work, so its module fixtures, servers and CPU burners stay in one process.
# The files in ``tests/realtime/`` drive the simulated UR controller in real time through
# ur_rtde (some with CPU burners or a dozen pollers); they form one group and run one after
# another on one worker: together they would load both cores far past the "loaded 2-core host"
# their bounds are written for (measured: a 0.4 s late speedL, 1.6 s without RTDE data, with
# two of them at once).
REALTIME_DIR = Path(__file__).resolve().parent / "realtime"


def _realtime(item: pytest.Item) -> bool:
    return item.path.parent == REALTIME_DIR

# The other files that take longest (seconds of simulated motion in real time, measured with
# ``--durations``), longest first, after the real-time group: handing out the long work first
# (``--no-loadscope-reorder`` keeps this order) keeps one worker from starting a 2-minute file
# while the other has nothing left to do. A module not listed runs after these, in collection
# order; the lists only group and order, never skip.
LONGEST_FIRST = (
    "test_page_production.py",
    "test_plc_interfaces.py",
    "test_calibrate_cli.py",
    "test_servo_ur.py",
    "test_ur_engine.py",
    "test_guard.py",
    "test_calibration_api.py",
    "test_api_cell.py",
    "test_cli_hardware.py",
    "test_page_browser.py",
)


def _module_rank(item: pytest.Item) -> int:
    name = item.path.name
    if _realtime(item):
        return 0
    return 1 + (LONGEST_FIRST.index(name) if name in LONGEST_FIRST else len(LONGEST_FIRST))


def pytest_itemcollected(item: pytest.Item) -> None:
    """The xdist group, set as each test is collected (xdist reads it when collection ends)."""
    name = item.path.name
    item.add_marker(pytest.mark.xdist_group("realtime_ur" if _realtime(item) else name))


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    items.sort(key=_module_rank)  # stable: each module's tests keep their order
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
