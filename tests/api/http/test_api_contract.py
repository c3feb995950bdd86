"""The API as a contract a PLC programmer can read offline: every operation answers a typed,
documented body with an example, every status it returns is documented, error codes are an
enum that covers every code the project raises, and ``wait=true`` says what it means. Plus the
Prometheus metrics (histograms, process metrics, the ``metrics_public`` switch)."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, Any

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from cell.error_codes import ErrorCode
from cell.errors import NotFoundError
from cell.results.modes import ApproachMode
from tests.support.cell import AUTH, running_cell, sim_config
from tests.support.paths import REPO

VIEW, OP = AUTH["viewer"], AUTH["operator"]
BINARY = {"image/png", "image/jpeg", "text/event-stream", "text/plain",
          "multipart/x-mixed-replace"}


@pytest.fixture(scope="module")
def app_and_schema(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Any, dict]]:
    with running_cell(sim_config(tmp_path_factory.mktemp("contract"))) as cell:
        app = create_app(cell)
        yield app, app.openapi()


def _ref(schema: dict[str, Any]) -> list[str]:
    if "$ref" in schema:
        return [schema["$ref"].rsplit("/", 1)[-1]]
    return [r for part in schema.get("anyOf", []) + schema.get("oneOf", []) for r in _ref(part)]


def operations(schema: dict[str, Any]) -> Iterator[tuple[str, str, dict[str, Any]]]:
    for path, item in schema["paths"].items():
        for method, op in item.items():
            yield path, method.upper(), op


def test_every_operation_answers_a_typed_documented_body(
        app_and_schema: tuple[Any, dict]) -> None:
    _, schema = app_and_schema
    components = schema["components"]["schemas"]
    untyped = []
    n = 0
    for path, method, op in operations(schema):
        n += 1
        ok = {s: r for s, r in op["responses"].items() if s.startswith("2")}
        assert ok, f"{method} {path} documents no success status"
        for status, resp in ok.items():
            content = resp.get("content", {})
            assert content, f"{method} {path} {status} has no content type"
            for media, body in content.items():
                if media in BINARY:
                    continue
                refs = _ref(body.get("schema", {}))
                if not refs:
                    untyped.append(f"{method} {path}")
                for name in refs:
                    assert components[name].get("examples"), f"{name} has no example"
        for status in ("401", "403", "422"):
            if path != "/api/v1/health":
                assert status in op["responses"], f"{method} {path} does not document {status}"
    print(f"{n} operations, untyped: {untyped}")
    assert n >= 30 and not untyped


def test_statuses_and_wait_semantics_are_documented(app_and_schema: tuple[Any, dict]) -> None:
    _, schema = app_and_schema
    paths = schema["paths"]
    assert "404" in paths["/api/v1/jobs/{job_id}"]["get"]["responses"]
    approach = paths["/api/v1/approach"]["post"]
    assert {"404", "409", "422", "503"} <= set(approach["responses"])
    assert "wait=true" in approach["description"] and "failed" in approach["description"]
    wait = schema["components"]["schemas"]["ApproachRequest"]["properties"]["wait"]
    assert "200" in wait["description"] and "cancelled" in wait["description"]
    for path in ("/api/v1/locate", "/api/v1/approach", "/api/v1/jog", "/api/v1/gripper"):
        assert {"409", "503"} <= set(paths[path]["post"]["responses"]), path
    assert {"413", "415"} <= set(approach["responses"])


def test_the_schema_lists_the_approach_modes_each_request_takes(
        app_and_schema: tuple[Any, dict]) -> None:
    _, schema = app_and_schema
    comps = schema["components"]["schemas"]

    def modes(model: str) -> list[str]:
        prop = comps[model]["properties"]["mode"]
        found = _ref(prop)
        return list(comps[found[0]]["enum"] if found else prop["enum"])

    assert modes("ApproachRequest") == [m.value for m in ApproachMode]
    assert modes("TrackRequest") == ["servo", "ibvs"]
    assert modes("RecipeTarget") == ["look_and_move", "servo"]


def test_error_codes_are_an_enum_that_covers_every_raised_code(
        app_and_schema: tuple[Any, dict]) -> None:
    _, schema = app_and_schema
    comps = schema["components"]["schemas"]
    code = comps["ErrorDetail"]["properties"]["code"]
    enum = comps[_ref(code)[0]]["enum"] if _ref(code) else code["enum"]
    assert set(enum) == {c.value for c in ErrorCode}
    raised: set[str] = set()
    for folder in ("cell", "api", "drivers", "estimator"):
        for path in (REPO / folder).rglob("*.py"):
            text = path.read_text()
            raised |= set(re.findall(r'(?:Error|Cancelled)\(\s*"([a-z_]+)"', text, re.S))
            raised |= set(re.findall(r'^\s+code = "([a-z_]+)"', text, re.M))
            raised |= set(re.findall(r'error_body\(\s*"([a-z_]+)"', text))
    missing = sorted(raised - set(enum))
    print(f"{len(raised)} codes raised in the source, {len(enum)} in the enum")
    assert not missing, f"codes raised but not in cell.error_codes.ErrorCode: {missing}"


def test_docs_pages_use_local_assets(app_and_schema: tuple[Any, dict]) -> None:
    app, _ = app_and_schema
    with TestClient(app) as client:
        for page in ("/docs", "/redoc"):
            html = client.get(page).text
            assert "http://" not in html and "https://" not in html, page
            for asset in re.findall(r'(?:src|href)="(/docs-assets/[^"]+)"', html):
                r = client.get(asset)
                assert r.status_code == 200 and len(r.content) > 1000, asset


def test_metrics_histograms_and_process_metrics(app_and_schema: tuple[Any, dict]) -> None:
    app, _ = app_and_schema
    with TestClient(app) as client:
        assert client.post("/api/v1/locate", headers=OP).status_code == 200
        assert client.post("/api/v1/stop", headers=OP).status_code == 200
        client.get("/api/v1/jobs/nope", headers=VIEW)
        text = client.get("/metrics", headers=VIEW).text
        assert client.get("/metrics").status_code == 401  # the default: a token is needed
    for needle in (
            'cell_http_request_duration_seconds_bucket{le="0.005",method="GET",'
            'route="/api/v1/jobs/{job_id}",status="404"}',
            'cell_locate_request_seconds_count{outcome="ok"} 1.0',
            "cell_stop_seconds_count 1.0",
            "process_cpu_seconds_total", "process_resident_memory_bytes", "python_info",
            'cell_locate_total{outcome="ok"}', "cell_arm_connected 1.0"):
        assert needle in text, needle


def test_metrics_public_switch_and_job_durations(tmp_path: Path) -> None:
    config = sim_config(tmp_path, api={"metrics_public": True},
                        approach={"speed_mm_s": 250.0, "accel_mm_s2": 1500.0, "max_cycles": 1})
    with running_cell(config) as cell, TestClient(create_app(cell)) as client:
        r = client.post("/api/v1/approach", json={"standoff_mm": 80, "wait": True}, headers=OP)
        assert r.status_code == 200, r.text
        state = r.json()["state"]  # whatever the outcome, its duration is counted under it
        assert state != "running"
        text = client.get("/metrics").text  # no token needed now
        assert f'cell_job_duration_seconds_count{{kind="approach",outcome="{state}"}} 1.0' \
            in text, text[-2000:]
        assert client.get("/api/v1/metrics").status_code == 200
        assert client.get("/api/v1/status").status_code == 401  # only the metrics are open


NOT_UTF8 = b'{"reason": "\xff\xfe caf\xe9"}'  # JSON punctuation around bytes that are not UTF-8
BODY_ROUTES = [("POST", "/api/v1/locate"), ("POST", "/api/v1/approach"),
               ("POST", "/api/v1/jog"), ("POST", "/api/v1/stop"), ("POST", "/api/v1/gripper"),
               ("PUT", "/api/v1/sim/target"), ("PUT", "/api/v1/camera/settings"),
               ("PUT", "/api/v1/recipes")]


def test_a_body_that_is_not_utf8_is_an_invalid_request(
        app_and_schema: tuple[Any, dict]) -> None:
    app, schema = app_and_schema
    client = TestClient(app)
    for method, path in BODY_ROUTES:
        assert "422" in schema["paths"][path][method.lower()]["responses"], (method, path)
        r = client.request(method, path, content=NOT_UTF8,
                           headers={**OP, "Content-Type": "application/json"})
        assert r.status_code == 422, (method, path, r.status_code, r.text)
        error = r.json()["error"]
        assert error["code"] == "invalid_request" and "UTF-8" in error["message"], error


def test_a_body_the_framework_cannot_decode_is_the_documented_422() -> None:
    """Behind the guard too: FastAPI's own 400 for an undecodable body becomes the 422."""
    from fastapi import Body, FastAPI

    from api.http import errors

    app = FastAPI()
    errors.install(app)

    @app.post("/echo")
    def echo(body: Annotated[dict[str, Any], Body()]) -> dict[str, Any]:
        return body

    r = TestClient(app).post("/echo", content=NOT_UTF8,
                             headers={"Content-Type": "application/json"})
    assert r.status_code == 422 and r.json()["error"]["code"] == "invalid_request", r.text


SQLITE_MAX = 2**63 - 1


def test_integer_parameters_are_bounded_to_what_sqlite_stores(tmp_path: Path) -> None:
    with running_cell(sim_config(tmp_path)) as cell, TestClient(create_app(cell)) as client:
        _integers_bounded(client)


def _integers_bounded(client: TestClient) -> None:
    app: Any = client.app
    schema = app.openapi()
    unbounded = [(path, method, p["name"]) for path, item in schema["paths"].items()
                 for method, op in item.items() for p in op.get("parameters", [])
                 for branch in p["schema"].get("anyOf", [p["schema"]])
                 if branch.get("type") == "integer"
                 and branch.get("maximum", SQLITE_MAX + 1) > SQLITE_MAX]
    assert not unbounded, unbounded
    for alarm_id in ("246149399008181101789184", str(SQLITE_MAX + 1), "0", "-1"):
        r = client.post(f"/api/v1/alarms/{alarm_id}/ack", headers=OP)
        assert r.status_code == 422 and r.json()["error"]["code"] == "invalid_request", r.text
    r = client.post(f"/api/v1/alarms/{SQLITE_MAX}/ack", headers=OP)
    assert r.status_code == 404 and r.json()["error"]["code"] == "alarm_not_found", r.text
    for query in ("limit=246149399008181101789184", "offset=246149399008181101789184",
                  "offset=-1"):
        for path in ("/api/v1/jobs", "/api/v1/alarms", "/api/v1/images"):
            r = client.get(f"{path}?{query}", headers=VIEW)
            assert r.status_code == 422, (path, query, r.text)
    r = client.get("/api/v1/audit?limit=246149399008181101789184", headers=VIEW)
    assert r.status_code == 422, r.text
    # the alarm log itself, for any other door: an id SQLite cannot hold is simply unknown
    with pytest.raises(NotFoundError):
        app.state.cell.alarms.acknowledge(10**23, "test")
