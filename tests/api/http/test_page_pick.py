"""The operator page's Pick controls without a browser: the page the service serves has the
Pick button and the place choice, both gated by the ``pick`` permission that ``GET /me`` grants
operators and PLCs and not viewers (and the page's own fallback agrees); the service refuses a
viewer's pick whatever the page shows. In a browser: ``test_page_browser.py``."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from html.parser import HTMLParser
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from tests.support.cell import AUTH, running_cell, sim_config


class _Controls(HTMLParser):
    """Each ``data-testid`` of the page with its tag and ``data-needs``."""

    def __init__(self) -> None:
        super().__init__()
        self.found: dict[str, tuple[str, str | None]] = {}

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if a.get("data-testid"):
            self.found[str(a["data-testid"])] = (tag, a.get("data-needs"))


@pytest.fixture
def http(tmp_path: Path) -> Iterator[TestClient]:
    with running_cell(sim_config(tmp_path, gripper="sim")) as cell, \
            TestClient(create_app(cell)) as c:
        yield c


def test_the_served_page_has_pick_controls_gated_by_the_pick_permission(http: TestClient
                                                                        ) -> None:
    page = http.get("/")
    assert page.status_code == 200
    controls = _Controls()
    controls.feed(page.text)
    assert controls.found["pick"] == ("button", "pick")
    assert controls.found["place"] == ("select", "pick")
    for role in ("viewer", "operator", "plc"):
        me = http.get("/api/v1/me", headers=AUTH[role]).json()
        assert ("pick" in me["permissions"]) == (role != "viewer"), me
    src = re.search(r'src="([^"]*app\.js)"', page.text)
    assert src is not None
    script = http.get(src[1]).text
    fallback = re.search(r"const ROLE_ACTIONS = (\{.*?\});", script, re.S)
    assert fallback is not None
    roles = json.loads(re.sub(r"(\w+):", r'"\1":', fallback[1]).replace(",\n}", "\n}"))
    assert "pick" in roles["operator"] and "pick" in roles["plc"]
    assert "pick" not in roles["viewer"]


def test_a_viewers_pick_is_refused_by_the_service(http: TestClient) -> None:
    cell = http.app.state.cell  # type: ignore[attr-defined]
    jobs = cell.jobs.count_jobs()
    r = http.post("/api/v1/pick", json={"wait": True}, headers=AUTH["viewer"])
    assert r.status_code == 403 and r.json()["error"]["code"] == "forbidden"
    assert cell.jobs.count_jobs() == jobs and not cell.commanded()
