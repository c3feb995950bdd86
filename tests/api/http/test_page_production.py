"""The operator page on the simulated cell (``cell serve``) for a production day, in headless
Chromium: the layout keeps camera, state, job and STOP in view while commands are used; a
failed approach raises an alarm banner that stays until acknowledged; job history and alarm
log; teaching a pose and approaching it; camera settings; calibration; the image log; and
``/docs`` / ``/redoc`` rendering with no request leaving the host.

The tests share one simulated cell and run in file order (each leaves the target where it
found it).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from functools import partial
from typing import Any
from urllib.parse import urlsplit

import httpx
import numpy as np
import pytest

from tests.support.browser import (
    browser_context,
    login,
    require_chromium,
    screenshot,
    serve_sim_cell,
)
from tests.support.waiting import wait_until

pytestmark = pytest.mark.timeout(300)

OPERATOR = "sim-operator"
HEAD = {"Authorization": f"Bearer {OPERATOR}"}
MONITOR = ("camera", "state", "job", "stop")


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    require_chromium()
    with serve_sim_cell(tmp_path_factory.mktemp("cell")) as url:
        yield url


@pytest.fixture(scope="module")
def ctx() -> Iterator[Any]:
    with browser_context() as c:
        yield c


@pytest.fixture
def page(ctx: Any) -> Iterator[Any]:
    p = ctx.new_page()
    yield p
    p.close()


def api(url: str, method: str, path: str, **kw: Any) -> Any:
    r = httpx.request(method, f"{url}/api/v1{path}", headers=HEAD, timeout=30.0, **kw)
    assert r.status_code < 300, r.text
    return r.json()


def _ended(url: str, job_id: str) -> str | None:
    """A job's final state, None while it runs."""
    state = str(api(url, "GET", f"/jobs/{job_id}")["state"])
    return None if state == "running" else state


def wait_idle(url: str, timeout_s: float = 60.0) -> None:
    wait_until(lambda: api(url, "GET", "/status")["job"] is None, timeout_s, "no running job")


def in_viewport(page: Any, testid: str) -> bool:
    return bool(page.evaluate(
        """(id) => { const r = document.querySelector(`[data-testid="${id}"]`)
                       .getBoundingClientRect();
                     return r.width > 0 && r.height > 0 && r.top >= 0 && r.left >= 0
                       && r.bottom <= window.innerHeight && r.right <= window.innerWidth; }""",
        testid))


def overlaps(page: Any, a: str, b: str) -> bool:
    return bool(page.evaluate(
        """([a, b]) => { const q = (id) => document.querySelector(`[data-testid="${id}"]`)
                                           .getBoundingClientRect();
                         const r = q(a), s = q(b);
                         return !(r.right <= s.left || s.right <= r.left
                                  || r.bottom <= s.top || s.bottom <= r.top); }""", [a, b]))


@pytest.fixture(scope="module")
def home_target(cell: str) -> dict[str, Any]:
    return dict(api(cell, "GET", "/sim/truth")["T_base_target"])


@pytest.mark.parametrize("size", [(1366, 768), (1024, 768), (390, 844)])
def test_layout_keeps_camera_state_job_and_stop_in_view(
        page: Any, cell: str, home_target: dict[str, Any], size: tuple[int, int]) -> None:
    width, height = size
    page.set_viewport_size({"width": width, "height": height})
    login(page, cell, OPERATOR)
    wait_idle(cell)
    page.get_by_test_id("standoff").fill("80")
    page.get_by_test_id("approach").click()  # fails if anything (STOP) covers it
    if width >= 900:
        for testid in MONITOR:
            assert in_viewport(page, testid), f"{testid} is out of view at {width}x{height}"
    else:  # phone: STOP is always in view and never on top of a control
        assert in_viewport(page, "stop")
        assert not overlaps(page, "approach", "stop")
    wait_until(lambda: "approach" in page.get_by_test_id("job").inner_text(), 10, "job shown")
    if width >= 900:  # the controls scrolled, the monitor did not
        page.get_by_test_id("images").scroll_into_view_if_needed()
        for testid in MONITOR:
            assert in_viewport(page, testid), f"{testid} scrolled away at {width}x{height}"
    screenshot(page, f"operator-page-{width}x{height}")
    page.get_by_test_id("stop").click()
    wait_idle(cell)
    if width < 900:  # every control can be reached without ending up under STOP
        for testid in ("locate", "approach", "jog-rz-minus", "teach", "calib-start",
                       "cam-apply", "history-next"):
            page.get_by_test_id(testid).scroll_into_view_if_needed()
            assert not overlaps(page, testid, "stop"), testid


def test_failed_approach_raises_an_alarm_until_acknowledged(
        page: Any, cell: str, home_target: dict[str, Any]) -> None:
    page.set_viewport_size({"width": 1366, "height": 768})
    login(page, cell, OPERATOR)
    wait_idle(cell)
    page.get_by_test_id("standoff").fill("60")
    page.get_by_test_id("approach").click()
    job_id = wait_until(lambda: (api(cell, "GET", "/status")["job"] or {}).get("id"), 10, "job")
    away = {"position_mm": [-480.0, 320.0, 0.0], "rotvec_rad": [np.pi, 0.0, 0.0]}
    api(cell, "PUT", "/sim/target", json=away)  # the target leaves the view mid-approach
    try:
        ended = wait_until(lambda: (j := api(cell, "GET", f"/jobs/{job_id}"))["state"] != "running"
                         and j, 90, "approach end")
        assert ended["state"] == "failed", ended
        banner = page.get_by_test_id("alarm-banner")
        banner.wait_for(state="visible", timeout=20_000)
        alarm = page.locator(f'[data-testid="alarm"]:has-text("{job_id}")')
        alarm.wait_for(timeout=20_000)
        text = alarm.inner_text()
        assert "failed" in text and ended["error"]["message"][:40] in text, text
        assert page.get_by_test_id("alarm-count").inner_text().endswith(("alarm", "alarms"))
        # the job and the Tasks line say how it ended, not "approach started"
        wait_until(lambda: "failed" in page.get_by_test_id("job").inner_text(), 10, "job failed")
        assert "failed" in page.get_by_test_id("result").inner_text()
        # the history and the alarm log show it
        page.locator(f'[data-testid="history"] tr[data-job-id="{job_id}"][data-state="failed"]'
                     ).wait_for(timeout=10_000)
        page.locator('[data-testid="alarm-log"] tr[data-active="true"]').first.wait_for(
            timeout=10_000)
        time.sleep(3.0)  # it stays
        assert alarm.is_visible()
        screenshot(page, "operator-page-alarm")
        alarm_id = alarm.get_attribute("data-alarm-id")
        alarm.get_by_test_id("alarm-ack").click()
        page.locator(f'[data-testid="alarm"][data-alarm-id="{alarm_id}"]').wait_for(
            state="detached", timeout=10_000)
    finally:
        api(cell, "PUT", "/sim/target", json=home_target)
    acked = [a for a in api(cell, "GET", "/alarms")["alarms"] if str(a["id"]) == alarm_id]
    assert acked and not acked[0]["active"] and acked[0]["acknowledged_by"].startswith(
        "http:operator")
    audit = api(cell, "GET", "/audit")["entries"]
    assert any(e["command"] == "alarm_ack" and e["params"]["id"] == int(alarm_id)
               for e in audit)
    # whatever else is open (the layout test's cancelled approaches): "Acknowledge all"
    if api(cell, "GET", "/alarms", params={"active": "true"})["active"]:
        page.get_by_test_id("alarm-ack-all").click()
    wait_until(lambda: page.get_by_test_id("alarm-banner").is_hidden(), 15, "banner gone")
    assert api(cell, "GET", "/alarms", params={"active": "true"})["active"] == 0
    assert page.get_by_test_id("alarm-count").is_hidden()


def test_operators_own_stop_is_an_info_event_not_an_alarm(
        page: Any, cell: str, home_target: dict[str, Any]) -> None:
    page.set_viewport_size({"width": 1366, "height": 768})
    login(page, cell, OPERATOR)
    wait_idle(cell)
    before = {a["id"] for a in api(cell, "GET", "/alarms")["alarms"]}
    for attempt in range(2):
        page.get_by_test_id("standoff").fill("80")
        page.get_by_test_id("approach").click()
        job_id = wait_until(lambda: (api(cell, "GET", "/status")["job"] or {}).get("id"), 10,
                            "job")
        # while it runs, nothing else that moves the arm can be started from the page
        wait_until(lambda: page.get_by_test_id("approach").is_disabled(), 5, "approach disabled")
        assert page.get_by_test_id("home").is_disabled()
        assert page.get_by_test_id("jog-z-plus").is_disabled()
        page.get_by_test_id("stop").click()
        state = wait_until(partial(_ended, cell, str(job_id)), 20, "the job's end")
        if state == "cancelled":
            break
        # a loaded host let the approach arrive before the stop: home and start again
        assert attempt == 0 and state == "succeeded", state
        wait_idle(cell)
        api(cell, "POST", "/arm/home", json={"wait": True})
    message = page.get_by_test_id("message")
    wait_until(lambda: "Stopped" in message.inner_text(), 5, "info line")
    assert message.get_attribute("data-kind") == "info"
    wait_until(lambda: "cancelled" in page.get_by_test_id("job").inner_text(), 10, "job line")
    time.sleep(2.5)  # several rounds of the alarm watcher
    new = [a for a in api(cell, "GET", "/alarms")["alarms"] if a["id"] not in before]
    assert new == [], new
    assert page.get_by_test_id("alarm-banner").is_hidden()
    page.locator(f'[data-testid="history"] tr[data-job-id="{job_id}"][data-state="cancelled"]'
                 ).wait_for(timeout=10_000)
    wait_until(lambda: page.get_by_test_id("approach").is_enabled(), 10, "approach enabled")
    screenshot(page, "operator-page-stopped")


def test_quality_row_and_overlay_agree(page: Any, cell: str,
                                       home_target: dict[str, Any]) -> None:
    page.set_viewport_size({"width": 1366, "height": 768})
    login(page, cell, OPERATOR)
    wait_idle(cell)
    api(cell, "POST", "/locate", json={})  # a good last locate: rms and "unique"
    away = {"position_mm": [-480.0, 320.0, 0.0], "rotvec_rad": [np.pi, 0.0, 0.0]}
    api(cell, "PUT", "/sim/target", json=away)
    try:
        def frame_says() -> dict[str, str]:
            r = httpx.get(f"{cell}/api/v1/camera/frame.jpg", headers=HEAD, timeout=10.0)
            return {k: v for k, v in r.headers.items() if k.lower().startswith("x-locat")}

        wait_until(lambda: frame_says().get("x-located") == "false", 20, "overlay: not located")
        rms = page.get_by_test_id("quality-rms")
        wait_until(lambda: "not located" in rms.inner_text(), 10, "quality row: not located")
        assert page.get_by_test_id("quality-ambiguity").inner_text() == "–"
        screenshot(page, "operator-page-not-located")
    finally:
        api(cell, "PUT", "/sim/target", json=home_target)
    wait_until(lambda: frame_says().get("x-located") == "true", 20, "overlay: located")
    wait_until(lambda: rms.inner_text().endswith(" px")
             and page.get_by_test_id("quality-ambiguity").inner_text() in (
                 "unique", "AMBIGUOUS: two poses fit"), 10, "quality row: located")


def test_image_log_browser_shows_failed_locate_frames(
        page: Any, cell: str, home_target: dict[str, Any]) -> None:
    away = {"position_mm": [-480.0, 320.0, 0.0], "rotvec_rad": [np.pi, 0.0, 0.0]}
    api(cell, "PUT", "/sim/target", json=away)
    try:
        time.sleep(0.3)  # frames without the target
        r = httpx.post(f"{cell}/api/v1/locate", headers=HEAD, timeout=30.0)
        assert r.status_code == 409, r.text
    finally:
        api(cell, "PUT", "/sim/target", json=home_target)
    login(page, cell, OPERATOR)
    entry = page.get_by_test_id("image-entry").first
    entry.wait_for(timeout=15_000)
    assert "target not located" in entry.inner_text() or "blobs" in entry.inner_text()
    entry.click()
    view = page.get_by_test_id("image-view")
    view.wait_for(state="visible")
    wait_until(lambda: page.evaluate(
        "document.querySelector('[data-testid=image-view]').naturalWidth") == 1280, 10,
        "logged frame shown")


def test_teach_a_pose_and_approach_it(page: Any, cell: str) -> None:
    page.set_viewport_size({"width": 1366, "height": 768})
    login(page, cell, OPERATOR)
    wait_idle(cell)
    # from wherever the arm is, a plain approach puts the target well in view
    api(cell, "POST", "/approach", json={"standoff_mm": 120, "wait": True})
    taught_at = np.asarray(api(cell, "GET", "/sim/truth")["T_base_tcp"]["position_mm"])
    page.get_by_test_id("teach-name").fill("page-pose")
    page.get_by_test_id("teach").click()
    wait_until(lambda: "taught page-pose" in page.get_by_test_id("result").inner_text(), 30,
             "teach done")
    options = page.get_by_test_id("taught").locator("option").all_inner_texts()
    assert "page-pose" in options
    api(cell, "POST", "/jog", json={"mode": "step", "translation_mm": [30, -20, 40]})
    page.get_by_test_id("taught").select_option("page-pose")
    page.get_by_test_id("standoff").fill("0")
    page.get_by_test_id("approach").click()
    job_id = wait_until(lambda: (api(cell, "GET", "/status")["job"] or {}).get("id"), 10, "job")
    job = wait_until(lambda: (j := api(cell, "GET", f"/jobs/{job_id}"))["state"] != "running"
                   and j, 60, "approach end")
    assert job["state"] == "succeeded", job
    reached = np.asarray(api(cell, "GET", "/sim/truth")["T_base_tcp"]["position_mm"])
    print(f"taught-pose approach: back within {np.linalg.norm(reached - taught_at):.2f} mm")
    assert np.linalg.norm(reached - taught_at) < 2.0
    assert job["params"].get("taught") == "page-pose" or "T_target_tcp" in job["params"]


def test_camera_settings_panel(page: Any, cell: str) -> None:
    login(page, cell, OPERATOR)
    exposure = page.get_by_test_id("cam-exposure")
    wait_until(lambda: exposure.input_value() != "", 10, "settings loaded")
    page.get_by_test_id("cam-iso").fill("200")
    page.get_by_test_id("cam-apply").click()
    wait_until(lambda: "ISO 200" in page.get_by_test_id("cam-state").inner_text(), 10, "applied")
    assert api(cell, "GET", "/camera/settings")["iso"] == 200
    page.get_by_test_id("cam-iso").fill("5000")
    page.get_by_test_id("cam-apply").click()
    msg = page.get_by_test_id("message")
    wait_until(lambda: "iso" in msg.inner_text(), 10, "refusal in words")
    assert api(cell, "GET", "/camera/settings")["iso"] == 200
    page.get_by_test_id("cam-iso").fill("100")
    page.get_by_test_id("cam-apply").click()
    wait_until(lambda: "ISO 100" in page.get_by_test_id("cam-state").inner_text(), 10, "reset")


def test_calibration_from_the_page(page: Any, cell: str, home_target: dict[str, Any]) -> None:
    page.set_viewport_size({"width": 1366, "height": 768})
    login(page, cell, OPERATOR)
    wait_idle(cell)
    api(cell, "POST", "/approach", json={"standoff_mm": 150, "wait": True})  # target in view
    page.get_by_test_id("calib-views").fill("4")  # the flow, not the accuracy: few views
    page.get_by_test_id("calib-start").click()
    status = page.get_by_test_id("calib-status")
    seen: set[str] = set()

    def finished() -> bool:
        text = status.inner_text()
        if text.startswith("running"):
            seen.add(text)
        return status.get_attribute("data-state") not in (None, "running")

    wait_until(finished, 180, "calibration end")
    print(f"progress shown: {sorted(seen)}")
    assert status.get_attribute("data-state") == "succeeded", status.inner_text()
    assert any("/ 4" in t for t in seen)
    result = page.get_by_test_id("calib-result").inner_text()
    assert "verdict" in result and "T_flange_camera" in result
    screenshot(page, "operator-page-calibration")
    page.get_by_test_id("calib-apply").click()
    wait_until(lambda: status.get_attribute("data-state") == "applied", 10, "applied")
    audit = api(cell, "GET", "/audit")["entries"]
    assert any(e["command"] == "apply_calibration" and e["outcome"] == "ok" for e in audit)


@pytest.mark.parametrize("path, ready", [("/docs", ".opblock"), ("/redoc", "[role=menuitem], "
                                                                         "li[data-item-id]")])
def test_api_docs_render_with_no_request_leaving_the_host(
        page: Any, cell: str, path: str, ready: str) -> None:
    host = urlsplit(cell).netloc
    requests: list[str] = []

    def gate(route: Any) -> None:
        url = route.request.url
        requests.append(url)
        if urlsplit(url).netloc == host or url.startswith(("data:", "blob:")):
            route.continue_()
        else:
            route.abort()

    page.route("**/*", gate)
    page.goto(cell + path)
    page.locator(ready).first.wait_for(timeout=30_000)
    assert page.locator(ready).count() > 10
    outside = [u for u in requests if urlsplit(u).netloc not in (host, "")]
    print(f"{path}: {len(requests)} requests, outside the host: {outside}")
    assert not outside
    screenshot(page, f"api-docs{path.replace('/', '-')}")
