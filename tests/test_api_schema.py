"""Schemathesis over the OpenAPI schema of the simulated cell: whatever the body, no 5xx.

Bounded (a few examples per operation) so it stays well under a minute; the event stream is
left out because it is endless by design.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error

from api.app import create_app
from tests.cell_testing import AUTH, running_cell, sim_config


@pytest.fixture(scope="module")
def api_schema(tmp_path_factory: pytest.TempPathFactory) -> Iterator[object]:
    config = sim_config(Path(tmp_path_factory.mktemp("schema")), gripper="sim",
                        approach={"speed_mm_s": 250.0, "accel_mm_s2": 1500.0, "max_cycles": 1})
    with running_cell(config) as cell:
        yield schemathesis.openapi.from_asgi("/openapi.json", create_app(cell))


schema = schemathesis.pytest.from_fixture("api_schema")


@schema.parametrize()
@settings(max_examples=6, deadline=None, suppress_health_check=list(HealthCheck))
def test_no_server_errors(case: schemathesis.Case) -> None:
    if case.path.endswith("/events"):
        pytest.skip("endless stream")
    case.call_and_validate(headers=AUTH["operator"], checks=[not_a_server_error])
