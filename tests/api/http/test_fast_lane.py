"""The fast lane answers plain ``/status`` and ``/stop`` requests the way the routes would,
and hands everything else (every refusal) to the routes with the body intact."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

import api.http.fast_lane as fast_lane
from api.app import create_app
from tests.support.cell import AUTH, running_cell, sim_config


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    with running_cell(sim_config(tmp_path)) as cell, TestClient(create_app(cell)) as c:
        yield c


def code(r: Any) -> str:
    return str(r.json()["error"]["code"])


class Spy:
    """Counts the requests the fast lane answered itself."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.answered = 0
        original = fast_lane._answer

        async def counting(*args: Any) -> None:
            self.answered += 1
            await original(*args)

        monkeypatch.setattr(fast_lane, "_answer", counting)


def test_status_from_the_lane_equals_the_routes_answer(client: TestClient,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    spy = Spy(monkeypatch)
    fast = client.get("/api/v1/status", headers=AUTH["viewer"])
    assert fast.status_code == 200 and spy.answered == 1
    assert fast.headers["content-type"] == "application/json"
    assert fast.headers["cache-control"] == "no-store"
    routed = client.get("/api/v1/status?via=route", headers=AUTH["viewer"])  # a query: routed
    assert routed.status_code == 200 and spy.answered == 1
    a, b = fast.json(), routed.json()
    assert set(a) == set(b) and a["state"] == b["state"] == "idle"
    assert a["robot"]["mode"] == b["robot"]["mode"] and 0 <= a["snapshot_age_s"] < 0.2
    metrics = client.get("/api/v1/metrics", headers=AUTH["viewer"]).text
    assert 'route="/api/v1/status",status="200"' in metrics


def test_refused_status_reads_go_to_the_route(client: TestClient,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    spy = Spy(monkeypatch)
    r = client.get("/api/v1/status")
    assert r.status_code == 401 and code(r) == "unauthorized"
    r = client.get("/api/v1/status", headers={"Authorization": "Bearer wrong"})
    assert r.status_code == 401
    r = client.get("/api/v1/status?token=sim-viewer")  # the header only, as on the route
    assert r.status_code == 401
    assert spy.answered == 0


def test_a_plain_stop_is_answered_by_the_lane(client: TestClient,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    spy = Spy(monkeypatch)
    for kwargs in ({"json": {"reason": "lane test"}}, {}):  # with a body, and without one
        r = client.post("/api/v1/stop", headers=AUTH["plc"], **kwargs)
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["stopped"] is True and body["commanded_monotonic_s"] > 0
    assert spy.answered == 2
    cell = client.app.state.cell  # type: ignore[attr-defined]
    rows = [(e.caller, e.outcome, e.params) for e in cell.jobs.audit_log(10)
            if e.command == "stop"]
    assert rows == [("http:plc(plc)", "ok", {"reason": "requested"}),
                    ("http:plc(plc)", "ok", {"reason": "lane test"})], rows
    metrics = client.get("/api/v1/metrics", headers=AUTH["viewer"]).text
    assert "cell_stop_seconds_count 2.0" in metrics


@pytest.mark.parametrize(("kwargs", "status", "error"), [
    ({"content": b'{"reason": 5}', "headers": {"Content-Type": "application/json"}}, 422,
     "invalid_request"),
    ({"content": b'{"reason": "x", "extra": 1}',
      "headers": {"Content-Type": "application/json"}}, 422, "invalid_request"),
    ({"content": b"{not json", "headers": {"Content-Type": "application/json"}}, 422,
     "invalid_request"),
    ({"content": b"reason=x", "headers": {"Content-Type": "application/x-www-form-urlencoded"}},
     415, "unsupported_media_type"),
    ({"content": b'{"reason": "x"}', "headers": {}}, 415, "unsupported_media_type"),
])
def test_malformed_stops_get_the_routes_answers(client: TestClient,
                                                monkeypatch: pytest.MonkeyPatch,
                                                kwargs: dict[str, Any], status: int,
                                                error: str) -> None:
    spy = Spy(monkeypatch)
    headers = {**AUTH["operator"], **kwargs.pop("headers")}
    r = client.post("/api/v1/stop", headers=headers, **kwargs)
    assert r.status_code == status and code(r) == error, r.text
    assert spy.answered == 0


def stops(client: TestClient) -> list[tuple[str, str]]:
    cell = client.app.state.cell  # type: ignore[attr-defined]
    return [(e.caller, e.outcome) for e in cell.jobs.audit_log(20) if e.command == "stop"]


def test_a_stop_without_a_token_stops_as_anonymous(client: TestClient,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """STOP is the safe direction: with no credential at all it is taken (by the lane, and by
    the route when the lane passes it on) and audited with the caller's address."""
    spy = Spy(monkeypatch)
    r = client.post("/api/v1/stop", json={"reason": "anon"})
    assert r.status_code == 200 and r.json()["stopped"] is True, r.text
    assert spy.answered == 1
    r = client.post("/api/v1/stop?via=route")  # a query: the regular route answers
    assert r.status_code == 200 and r.json()["stopped"] is True, r.text
    assert spy.answered == 1
    # the cell's own page: its Origin is the host it was served from
    r = client.post("/api/v1/stop", headers={"Origin": "http://testserver"})
    assert r.status_code == 200, r.text
    assert stops(client) == [("http:anonymous@testclient(anonymous)", "ok")] * 3


@pytest.mark.parametrize("headers", [
    {"Authorization": "Bearer wrong"},  # an invalid token stays refused
    {"Authorization": "Bearer "},
    {"Authorization": "Basic c2ltOnNpbQ=="},  # another scheme is a credential too
    {"Origin": "https://elsewhere.example"},  # another site's page, through a browser
    {"Origin": "null"},
])
def test_a_stop_with_a_bad_credential_or_from_another_site_is_refused(
        client: TestClient, monkeypatch: pytest.MonkeyPatch, headers: dict[str, str]) -> None:
    spy = Spy(monkeypatch)
    for path in ("/api/v1/stop", "/api/v1/stop?via=route"):
        r = client.post(path, json={"reason": "anon"}, headers=headers)
        assert r.status_code == 401 and code(r) == "unauthorized", r.text
    assert spy.answered == 0 and stops(client) == []
    cell = client.app.state.cell  # type: ignore[attr-defined]
    assert any(e.caller == "anonymous" and e.outcome == "refused:unauthorized"
               for e in cell.jobs.audit_log(10))


def test_a_query_token_is_no_way_around_the_header(client: TestClient) -> None:
    for token in ("sim-viewer", "wrong"):
        r = client.post(f"/api/v1/stop?token={token}")
        assert r.status_code == 401 and code(r) == "unauthorized", r.text
    assert stops(client) == []


def test_stops_without_a_token_can_be_switched_off(tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    config = sim_config(tmp_path, api={"anonymous_stop": False})
    with running_cell(config) as cell, TestClient(create_app(cell)) as c:
        spy = Spy(monkeypatch)
        for path in ("/api/v1/stop", "/api/v1/stop?via=route"):
            r = c.post(path, json={"reason": "anon"})
            assert r.status_code == 401 and code(r) == "unauthorized", r.text
        assert spy.answered == 0 and stops(c) == []
        assert c.post("/api/v1/stop", headers=AUTH["viewer"]).status_code == 200
