"""Schemathesis over the OpenAPI schema of the simulated cell: whatever the request, no 5xx,
no bare 400, and every 422 the cell's error model.

Bounded (a few examples per operation, ``--schema-examples N`` for more) so it stays well
under a minute, and derandomized so every run (and CI) tries the same requests; the number of
requests sent and their statuses are printed (``-s``). The event and MJPEG streams are left
out because they are endless by design. Hypothesis runs per operation inside one test because
schemathesis' pytest fixture loader does not work with this pytest version.
"""

from __future__ import annotations

import re
from collections import Counter
from pathlib import Path
from typing import Any

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import not_a_server_error

from api.app import create_app
from tests.support.cell import AUTH, running_cell, sim_config


def malformed_is_422(ctx: Any, response: Any, case: schemathesis.Case) -> bool:
    """A malformed request is the documented 422 with the error model, never a bare 400 from
    the framework (a body that is not UTF-8, ...)."""
    assert response.status_code != 400, (case.method, case.path, response.text)
    if response.status_code == 422:
        assert set(response.json()["error"]) == {"code", "message"}, response.text
    return True


def test_no_server_errors(tmp_path: Path, pytestconfig: pytest.Config) -> None:
    examples = int(pytestconfig.getoption("--schema-examples"))
    # a teach of one frame per sample: what a teach averages is not what this test checks
    config = sim_config(tmp_path, gripper="sim",
                        approach={"speed_mm_s": 250.0, "accel_mm_s2": 1500.0, "max_cycles": 1},
                        teach={"frames_per_sample": 1})
    with running_cell(config) as cell:
        app = create_app(cell)
        schema = schemathesis.openapi.from_asgi("/openapi.json", app)
        seen = []
        statuses: Counter[int] = Counter()
        for result in schema.get_all_operations():
            operation = result.ok()  # type: ignore[union-attr]
            if operation.path.endswith(("/events", "/stream.mjpg")):  # endless streams
                continue
            seen.append(f"{operation.method.upper()} {operation.path}")

            @given(case=operation.as_strategy())
            @settings(max_examples=examples, deadline=None,
                      suppress_health_check=list(HealthCheck), database=None, derandomize=True)
            def run(case: schemathesis.Case) -> None:
                response = case.call_and_validate(
                    headers=AUTH["operator"], checks=[not_a_server_error, malformed_is_422])
                statuses[response.status_code] += 1

            run()
            cell.stop("test")
        assert "POST /api/v1/approach" in seen and "PUT /api/v1/sim/target" in seen
        print(f"\n{sum(statuses.values())} requests over {len(seen)} operations, "
              f"{examples} examples each; statuses {dict(sorted(statuses.items()))}")
        text = app.state.metrics.render().decode()
        served = re.findall(r'cell_http_request_duration_seconds_count\{.*status="(\d+)"', text)
        assert served and all(int(s) < 500 for s in served), served
