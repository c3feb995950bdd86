"""The OPC UA server and the URScript XML-RPC endpoint on the simulated cell (in-process arm),
checked against the HTTP API and the simulated ground truth: browse, read, Locate, Approach,
Stop mid-approach, roles, malformed calls, audit rows, and ``cell serve`` serving both."""

from __future__ import annotations

import asyncio
import socket
import subprocess
import sys
import threading
import time
import xmlrpc.client
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from asyncua import ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography.x509.oid import ExtendedKeyUsageOID
from fastapi.testclient import TestClient

from api.app import create_app
from api.plc.opcua import OpcUaServer
from api.plc.xmlrpc import XmlRpcServer
from cell.config.endpoints import opcua_cert_dir
from cell.features.teach import TaughtPose
from cell.service import Cell
from cell.supervision.status import still_starting
from cell.vision.frames import approach_tcp
from estimator.transforms import T_from_pose, T_from_pose_dict, T_from_ur_pose, pose_distance
from tests.support.cell import AUTH, running_cell, settled_tcp, sim_config, tcp
from tests.support.net import free_port
from tests.support.opcua import Opc, opc_client
from tests.support.waiting import wait_until

METHODS = ("Locate", "Approach", "Track", "Stop", "Home", "Gripper")
VARIABLES = ("State", "RobotMode", "SafetyStatus", "TcpPose", "TcpPoseUR", "LastLocatePose",
             "LastLocatePoseUR", "LastLocateQuality", "JobId", "JobKind", "JobState",
             "JobPhase", "JobProgress", "CameraConnected", "Alarms")


@dataclass
class Served:
    cell: Cell
    http: TestClient
    opcua_url: str
    xmlrpc_url: str  # /RPC2 without a token (as the simulated cell)
    xmlrpc_token_url: str  # the same cell with require_token, http://.../{token}/RPC2


@pytest.fixture
def served(tmp_path: Path) -> Iterator[Served]:
    opcua_port, rpc_port, token_port = free_port(), free_port(), free_port()
    config = sim_config(
        tmp_path, approach={"speed_mm_s": 250.0, "accel_mm_s2": 1200.0},
        opcua={"endpoint": f"opc.tcp://127.0.0.1:{opcua_port}"},
        urscript={"xmlrpc_port": rpc_port})
    assert config.opcua.enabled and not config.urscript.require_token  # as sim.toml says
    with running_cell(config) as cell, TestClient(create_app(cell)) as http:
        opcua = OpcUaServer(cell, config.opcua, opcua_cert_dir(config))
        rpc = XmlRpcServer(cell, config.urscript)
        rpc_tokens = XmlRpcServer(cell, config.urscript.model_copy(
            update={"xmlrpc_port": token_port, "require_token": True}))
        opcua.start()
        rpc.start()
        rpc_tokens.start()
        try:
            yield Served(cell, http, f"opc.tcp://127.0.0.1:{opcua_port}",
                         f"http://127.0.0.1:{rpc_port}/RPC2",
                         f"http://127.0.0.1:{token_port}/{{token}}/RPC2")
        finally:
            opcua.close()
            rpc.close()
            rpc_tokens.close()


def run(coro: Any) -> Any:
    return asyncio.run(coro)


def truth(s: Served) -> dict[str, Any]:
    r = s.http.get("/api/v1/sim/truth", headers=AUTH["viewer"])
    assert r.status_code == 200, r.text
    return dict(r.json())


def audit(s: Served) -> list[dict[str, Any]]:
    r = s.http.get("/api/v1/audit", params={"limit": 500}, headers=AUTH["viewer"])
    return list(r.json()["entries"])


def close_to(T_a: np.ndarray, T_b: np.ndarray, mm: float = 0.5, deg: float = 0.1) -> bool:
    d_mm, d_deg = pose_distance(T_a, T_b)
    return d_mm <= mm and d_deg <= deg


# -- OPC UA --------------------------------------------------------------------------------------
def test_opcua_browse_read_and_locate_against_truth(served: Served) -> None:
    async def go() -> None:
        opc = await Opc(opc_client(served.opcua_url, "plc")).open()
        try:
            names = {(await n.read_browse_name()).Name for n in await opc.cell.get_children()}
            assert set(METHODS) | set(VARIABLES) <= names, names
            assert await opc.read("State") == "idle"
            assert await opc.read("RobotMode") == "RUNNING"
            assert await opc.read("SafetyStatus") == "NORMAL"
            assert await opc.read("CameraConnected") is True
            assert await opc.read("Alarms") in ([], None)
            t = truth(served)
            T_tcp = T_from_pose_dict(t["T_base_tcp"])
            pose = await opc.read("TcpPose")
            assert close_to(T_from_pose(pose.position_mm, pose.rotvec_rad), T_tcp, 1.0, 0.2)
            assert close_to(T_from_ur_pose(await opc.read("TcpPoseUR")), T_tcp, 1.0, 0.2)
            assert not (await opc.read("LastLocateQuality")).valid

            code, message, pose, pose_ur, rms = await opc.call("Locate")
            assert code == "ok", message
            T_true = T_from_pose_dict(t["T_base_target"])
            T_opc = T_from_pose(pose.position_mm, pose.rotvec_rad)
            assert close_to(T_opc, T_true), pose_distance(T_opc, T_true)
            assert close_to(T_from_ur_pose(pose_ur), T_opc, 1e-6, 1e-6)
            assert 0 <= rms < 0.5
            quality = await opc.wait_for("LastLocateQuality", lambda q: q.valid, 10)
            assert quality.n_points == 6 and not quality.ambiguous
            last = await opc.read("LastLocatePose")
            assert close_to(T_from_pose(last.position_mm, last.rotvec_rad), T_opc, 1e-6, 1e-6)
        finally:
            await opc.close()

    run(go())
    rows = [e for e in audit(served) if e["caller"] == "opcua:plc(plc)"]
    assert [e["command"] for e in rows] == ["locate"] and rows[0]["outcome"] == "ok"


def test_opcua_approach_succeeds_then_stop_mid_approach_leaves_the_arm_still(
        served: Served) -> None:
    async def go() -> None:
        opc = await Opc(opc_client(served.opcua_url, "plc")).open()
        try:
            code, message, job_id = await opc.call("Approach", 40.0, "")
            assert code == "ok", message
            assert await opc.wait_for("JobId", lambda v: v == job_id, 10)
            assert await opc.wait_for("JobKind", lambda v: v == "approach", 10)
            await opc.wait_for("JobState", lambda v: v != "running", 120)
            assert await opc.read("JobState") == "succeeded"
            job = served.http.get(f"/api/v1/jobs/{job_id}", headers=AUTH["viewer"]).json()
            assert job["state"] == "succeeded" and job["caller"] == "opcua:plc(plc)"
            goal = approach_tcp(T_from_pose_dict(truth(served)["T_base_target"]), np.eye(4), 40)
            assert close_to(settled_tcp(served.cell), goal, 0.5, 0.1)

            # a second approach from a pose away from the target, stopped while moving
            r = served.http.post("/api/v1/arm/home", json={"wait": True},
                                 headers=AUTH["operator"], timeout=120)
            assert r.status_code == 200 and r.json()["state"] == "succeeded", r.text
            code, message, job_id = await opc.call("Approach", 40.0, "look_and_move")
            assert code == "ok", message
            start = tcp(served.cell)
            deadline = time.monotonic() + 60
            while pose_distance(tcp(served.cell), start)[0] < 5.0:
                assert time.monotonic() < deadline, "the arm did not start moving"
                await asyncio.sleep(0.02)
            code, message, stopped_job = await opc.call("Stop")
            assert code == "ok", message
            assert stopped_job == job_id
            still = settled_tcp(served.cell)
            await asyncio.sleep(1.0)
            assert pose_distance(tcp(served.cell), still)[0] < 0.01
            assert pose_distance(still, goal)[0] > 5.0  # it stopped short of the goal
            state = await opc.wait_for("JobState", lambda v: v != "running", 30)
            assert state in ("cancelled", "failed")
            assert await opc.read("State") == "idle"
        finally:
            await opc.close()

    run(go())
    rows = [(e["command"], e["outcome"]) for e in audit(served)
            if e["caller"] == "opcua:plc(plc)"]
    assert ("stop", "ok") in rows and rows.count(("approach", "ok")) >= 2


def test_opcua_rests_without_subscribers_and_subscribers_see_the_arm_move(
        served: Served, monkeypatch: pytest.MonkeyPatch) -> None:
    builds: list[float] = []  # the OPC UA thread's status reads
    status = served.cell.status

    def counted() -> dict[str, Any]:
        if threading.current_thread().name == "opcua":
            builds.append(time.monotonic())
        return status()

    monkeypatch.setattr(served.cell, "status", counted)
    time.sleep(1.5)
    # nobody subscribed: once a second (api.plc.opcua.IDLE_CHECK_S), not 10 times
    assert len(builds) <= 2, f"{len(builds)} updates in 1.5 s with nobody connected"

    class Changes:
        def __init__(self) -> None:
            self.poses: list[Any] = []

        def datachange_notification(self, node: Any, value: Any, data: Any) -> None:
            self.poses.append(value)

    async def go() -> None:
        async with Opc(opc_client(served.opcua_url, "plc")) as opc:
            # a read is fresh although nothing ran periodically: the read refreshed first
            t = T_from_pose_dict(truth(served)["T_base_tcp"])
            pose = await opc.read("TcpPose")
            assert close_to(T_from_pose(pose.position_mm, pose.rotvec_rad), t, 1.0, 0.2)
            changes = Changes()
            sub = await opc.client.create_subscription(50, changes)
            await sub.subscribe_data_change(await opc.cell.get_child(f"{opc.idx}:TcpPose"))
            r = served.http.post("/api/v1/jog", headers=AUTH["operator"], json={
                "mode": "continuous", "linear_mm_s": [40.0, 0.0, 0.0]})
            assert r.status_code == 200, r.text
            for _ in range(10):  # the dead-man heartbeat keeps the jog going for a second
                await asyncio.sleep(0.1)
                assert served.http.post("/api/v1/jog/heartbeat",
                                        headers=AUTH["operator"]).status_code == 200
            assert served.http.post("/api/v1/stop", headers=AUTH["operator"],
                                    json={"reason": "test"}).status_code == 200
            still = settled_tcp(served.cell)
            await asyncio.sleep(0.5)
            xs = [p.position_mm[0] for p in changes.poses]
            assert len(xs) >= 5 and xs[-1] - xs[0] > 20.0, xs  # ~40 mm in the jog's second
            last = changes.poses[-1]
            assert close_to(T_from_pose(last.position_mm, last.rotvec_rad), still, 0.5, 0.1)
            await sub.delete()

    run(go())


def test_opcua_roles_users_and_refusals(served: Served) -> None:
    async def go() -> None:
        viewer = await Opc(opc_client(served.opcua_url, "viewer")).open()
        plc = await Opc(opc_client(served.opcua_url, "plc")).open()
        try:
            assert await viewer.read("State") == "idle"  # a viewer reads
            before = tcp(served.cell)
            for name, args in (("Locate", ()), ("Approach", (40.0, "")),
                               ("Track", (40.0, 1.0)), ("Home", ()),
                               ("Gripper", ("open", 0.0))):
                out = await viewer.call(name, *args)
                assert out[0] == "forbidden", (name, out)
            # a PLC homes and uses the gripper (a production cycle); this cell has no gripper
            assert (await plc.call("Gripper", "close", 0.0))[0] == "gripper_unavailable"
            code, message, job_id = await plc.call("Home")
            assert code == "ok" and job_id, message
            await plc.wait_for("JobState", lambda v: v == "succeeded", 60)
            code, _, _ = await viewer.call("Stop")  # every user may stop
            assert code == "ok"
            operator = await Opc(opc_client(served.opcua_url, "operator")).open()
            try:
                code, message, job_id = await operator.call("Home")
                assert code == "ok" and job_id, message
                await operator.wait_for("JobState", lambda v: v == "succeeded", 60)
                # this cell has no gripper: the API's code, in the answer
                assert (await operator.call("Gripper", "open", 0.0))[0] == "gripper_unavailable"
                assert (await operator.call("Gripper", "move", -3.0))[0] == "invalid_request"
            finally:
                await operator.close()
            # bad input: the cell's codes, nothing moves
            assert (await plc.call("Approach", -5.0, ""))[0] == "invalid_request"
            assert (await plc.call("Approach", float("nan"), ""))[0] == "invalid_request"
            assert (await plc.call("Approach", 40.0, "teleport"))[0] == "invalid_request"
            assert (await plc.call("Approach", 40.0, ua.Variant("x", ua.VariantType.String))
                    )[0] == "invalid_request"
            assert pose_distance(tcp(served.cell), before)[0] < 0.01
            # variables belong to the cell
            with pytest.raises(ua.UaStatusCodeError):
                node = await plc.cell.get_child(f"{plc.idx}:State")
                await node.write_value(ua.Variant("hacked", ua.VariantType.String))
            assert await plc.read("State") == "idle"
        finally:
            await viewer.close()
            await plc.close()
        for user, password in (("plc", "wrong"), ("nobody", "sim-plc"), (None, None)):
            with pytest.raises((ua.UaError, ConnectionError, OSError, TimeoutError)):
                c = opc_client(served.opcua_url, user, password)
                await c.connect()
                try:  # anonymous may get a session but must not read
                    await c.nodes.objects.get_children()
                finally:
                    await c.disconnect()

    run(go())
    rows = {(e["command"], e["outcome"]) for e in audit(served)
            if e["caller"] == "opcua:viewer(viewer)"}
    assert ("locate", "refused:forbidden") in rows and ("stop", "ok") in rows
    plc_rows = {(e["command"], e["outcome"]) for e in audit(served)
                if e["caller"] == "opcua:plc(plc)"}
    assert ("approach", "refused:invalid_request") in plc_rows


def test_opcua_basic256sha256_with_the_generated_certificate(served: Served,
                                                             tmp_path: Path) -> None:
    key, cert = tmp_path / "client-key.pem", tmp_path / "client-cert.der"

    async def go() -> None:
        await setup_self_signed_certificate(
            key, cert, "urn:test:client", "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH],
            {"commonName": "test client"})
        client = opc_client(served.opcua_url, "operator")
        client.application_uri = "urn:test:client"
        await client.set_security(SecurityPolicyBasic256Sha256, str(cert), str(key),
                                  mode=ua.MessageSecurityMode.SignAndEncrypt)
        opc = await Opc(client).open()
        try:
            assert await opc.read("State") == "idle"
            code, message, *_ = await opc.call("Locate")
            assert code == "ok", message
        finally:
            await opc.close()

    run(go())
    assert (opcua_cert_dir(served.cell.config) / "server-cert.der").is_file()


def test_opcua_trusted_client_certificates_only(tmp_path: Path) -> None:
    """With ``trusted_client_certs_dir``, Basic256Sha256 admits only the certificates in it."""
    trusted_dir = tmp_path / "trusted"
    trusted_dir.mkdir()
    port = free_port()
    config = sim_config(tmp_path, opcua={"endpoint": f"opc.tcp://127.0.0.1:{port}",
                                         "security_policies": ["Basic256Sha256"],
                                         "trusted_client_certs_dir": str(trusted_dir)})

    async def client_cert(name: str) -> tuple[Path, Path]:
        key, cert = tmp_path / f"{name}-key.pem", tmp_path / f"{name}-cert.der"
        await setup_self_signed_certificate(
            key, cert, f"urn:test:{name}", "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH],
            {"commonName": name})
        return key, cert

    async def read_state(name: str, key: Path, cert: Path) -> str:
        client = opc_client(f"opc.tcp://127.0.0.1:{port}", "plc")
        client.application_uri = f"urn:test:{name}"
        await client.set_security(SecurityPolicyBasic256Sha256, str(cert), str(key),
                                  mode=ua.MessageSecurityMode.SignAndEncrypt)
        opc = await Opc(client).open()
        try:
            return str(await opc.read("State"))
        finally:
            await opc.close()

    key_ok, cert_ok = run(client_cert("known"))
    key_bad, cert_bad = run(client_cert("stranger"))
    (trusted_dir / "known.der").write_bytes(cert_ok.read_bytes())
    with running_cell(config) as cell:
        server = OpcUaServer(cell, config.opcua, opcua_cert_dir(config))
        server.start()
        try:
            assert run(read_state("known", key_ok, cert_ok)) == "idle"
            with pytest.raises((ua.UaError, ConnectionError, OSError, TimeoutError)):
                run(read_state("stranger", key_bad, cert_bad))
        finally:
            server.close()


# -- XML-RPC -------------------------------------------------------------------------------------
def struct_T(p: dict[str, float]) -> np.ndarray:
    return T_from_ur_pose([p["x"], p["y"], p["z"], p["rx"], p["ry"], p["rz"]])


def test_xmlrpc_locate_and_approach_pose_match_the_http_api(served: Served) -> None:
    rpc = xmlrpc.client.ServerProxy(served.xmlrpc_url)
    commanded = len(served.cell.commanded())
    before = tcp(served.cell)
    assert rpc.status() == "idle"
    T_rpc = struct_T(rpc.locate())
    r = served.http.post("/api/v1/locate", headers=AUTH["plc"])
    assert r.status_code == 200, r.text
    T_http = T_from_pose_dict(r.json()["T_base_target"])
    T_true = T_from_pose_dict(truth(served)["T_base_target"])
    assert close_to(T_rpc, T_http) and close_to(T_rpc, T_true), pose_distance(T_rpc, T_true)

    goal = struct_T(rpc.approach_pose(40))
    expected = approach_tcp(T_http, served.cell.config.approach.T_target_tcp.T(), 40.0)
    assert close_to(goal, expected), pose_distance(goal, expected)

    # a taught tool pose, read from the cell's store that HTTP's teach writes
    T_target_tcp = T_from_pose([10.0, -5.0, 0.0], [0.0, 0.0, 0.3])
    served.cell.taught.put(TaughtPose(
        "grasp", T_target_tcp, 1, 0.0, 0.0, T_true, before, "test", time.time()))
    taught = struct_T(rpc.taught_pose("grasp", 25.0))
    assert close_to(taught, approach_tcp(T_http, T_target_tcp, 25.0))
    # the list forms, for programs that branch on a refusal instead of faulting
    tried = rpc.try_approach_pose(40.0)
    assert tried[0] == 0 and close_to(T_from_ur_pose(tried[1:]), expected)
    assert close_to(T_from_ur_pose(rpc.try_locate()[1:]), T_true)
    assert rpc.try_taught_pose("nope") == [404.0] + [0.0] * 6
    assert rpc.try_approach_pose(-1)[0] == 422
    # robot-program-driven: nothing was commanded, the arm did not move
    assert len(served.cell.commanded()) == commanded
    assert pose_distance(tcp(served.cell), before)[0] < 0.01
    rows = [(e["command"], e["outcome"]) for e in audit(served)
            if e["caller"] == "xmlrpc:urscript(plc)"]
    for row in (("locate", "ok"), ("approach_pose", "ok"), ("taught_pose", "ok")):
        assert row in rows, rows


def test_xmlrpc_malformed_calls_get_faults_and_the_endpoint_keeps_serving(
        served: Served) -> None:
    rpc = xmlrpc.client.ServerProxy(served.xmlrpc_url)
    r = httpx.post(served.xmlrpc_url, content=b"<methodCall><methodName>locate",
                   headers={"Content-Type": "text/xml"}, timeout=10)
    assert r.status_code == 200 and b"<fault>" in r.content
    cases: list[tuple[Any, int, str]] = [
        (lambda: rpc.teleport(), 404, "unknown_method"),
        (lambda: rpc.approach_pose(), 422, "invalid_request"),
        (lambda: rpc.approach_pose(1, 2, 3), 422, "invalid_request"),
        (lambda: rpc.approach_pose("forty"), 422, "invalid_request"),
        (lambda: rpc.approach_pose(-1.0), 422, "invalid_request"),
        (lambda: rpc.taught_pose("nope"), 404, "taught_not_found"),
    ]
    for call, fault_code, code in cases:
        with pytest.raises(xmlrpc.client.Fault) as err:
            call()
        assert err.value.faultCode == fault_code, err.value
        assert err.value.faultString.startswith(code), err.value
    assert rpc.status() == "idle"
    assert rpc.locate()["z"] == pytest.approx(0.0, abs=0.001)
    rows = {(e["command"], e["outcome"]) for e in audit(served)
            if e["caller"] == "xmlrpc:urscript(plc)"}
    assert ("approach_pose", "refused:invalid_request") in rows
    assert ("taught_pose", "refused:taught_not_found") in rows


def test_xmlrpc_with_tokens_in_the_path(served: Served) -> None:
    url = served.xmlrpc_token_url
    with pytest.raises(xmlrpc.client.ProtocolError) as err:
        xmlrpc.client.ServerProxy(url.replace("/{token}", "")).status()
    assert err.value.errcode == 404
    with pytest.raises(xmlrpc.client.ProtocolError):
        xmlrpc.client.ServerProxy(url.format(token="not-a-token")).status()
    viewer = xmlrpc.client.ServerProxy(url.format(token="sim-viewer"))
    assert viewer.status() == "idle"
    with pytest.raises(xmlrpc.client.Fault) as fault:
        viewer.locate()
    assert fault.value.faultCode == 403 and fault.value.faultString.startswith("forbidden")
    plc = xmlrpc.client.ServerProxy(url.format(token="sim-plc"))
    assert plc.locate()["z"] == pytest.approx(0.0, abs=0.001)
    callers = {(e["caller"], e["command"], e["outcome"]) for e in audit(served)}
    assert ("xmlrpc:viewer(viewer)", "locate", "refused:forbidden") in callers
    assert ("xmlrpc:plc(plc)", "locate", "ok") in callers


# -- cell serve ----------------------------------------------------------------------------------
def test_cell_serve_prints_and_serves_every_endpoint(tmp_path: Path) -> None:
    from tests.api.http.test_api_serve import _config

    config = _config(tmp_path)  # sim.toml with the interfaces off (their fixed ports) ...
    text = config.read_text()
    config.write_text(text.replace("\nenabled = false", "\nenabled = true", 1)
                      .replace("xmlrpc_port = 0", "xmlrpc_port = 1"))  # ... on, moved below
    http_port, opcua_port, rpc_port = free_port(), free_port(), free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "cell", "serve", "--config", str(config), "--port",
         str(http_port), "--opcua-port", str(opcua_port), "--xmlrpc-port", str(rpc_port),
         "--log-level", "warning"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path)
    lines: list[str] = []
    try:
        assert proc.stdout is not None
        deadline = time.monotonic() + 90
        while True:
            assert proc.poll() is None, "".join(lines) + proc.stdout.read()
            try:
                if xmlrpc.client.ServerProxy(f"http://127.0.0.1:{rpc_port}/RPC2").status():
                    break
            except OSError:
                pass
            assert time.monotonic() < deadline, "XML-RPC did not come up within 90 s"
            time.sleep(0.3)
        wait_until(lambda: not still_starting(httpx.get(
            f"http://127.0.0.1:{http_port}/api/v1/health", timeout=10).json()), 60.0,
            "the start to end (the arm connected and powered on)")

        async def opc_state() -> str:
            opc = await Opc(opc_client(f"opc.tcp://127.0.0.1:{opcua_port}", "viewer")).open()
            try:
                return str(await opc.read("State"))
            finally:
                await opc.close()

        assert run(opc_state()) == "idle"
        assert httpx.get(f"http://127.0.0.1:{http_port}/api/v1/health",
                         timeout=10).status_code == 200
    finally:
        proc.terminate()
        out, _ = proc.communicate(timeout=30)
        lines.append(out)
    text = "".join(lines)
    assert f"serving the cell on http://127.0.0.1:{http_port}" in text, text
    assert f"serving OPC UA on opc.tcp://127.0.0.1:{opcua_port}" in text, text
    assert f"serving URScript XML-RPC on http://127.0.0.1:{rpc_port}/RPC2" in text, text
    # uvicorn re-raises the SIGTERM it handled, after a clean shutdown
    assert proc.returncode in (0, -15), text


def test_an_interface_whose_port_is_taken_is_left_out(tmp_path: Path,
                                                      caplog: pytest.LogCaptureFixture) -> None:
    from api.plc.interfaces import Interfaces

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        busy = taken.getsockname()[1]
        rpc_port = free_port()
        config = sim_config(tmp_path, opcua={"endpoint": f"opc.tcp://127.0.0.1:{busy}",
                                             "security_policies": ["None"]},
                            urscript={"xmlrpc_port": rpc_port})
        with running_cell(config) as cell:
            doors = Interfaces(cell)
            doors.start()
            try:
                assert set(doors.running) == {"xmlrpc"}
                assert "opcua: cannot serve on" in caplog.text
                assert xmlrpc.client.ServerProxy(
                    f"http://127.0.0.1:{rpc_port}/RPC2").status() == "idle"
                # and /health says which server is missing, for as long as it is
                deadline = time.monotonic() + 10.0
                while not (h := cell.health())["reasons"]:
                    assert time.monotonic() < deadline, h
                    time.sleep(0.05)
                assert h["status"] == "degraded", h
                assert [r["code"] for r in h["reasons"]] == ["plc_server_down"], h
                assert f"OPC UA server cannot serve on opc.tcp://127.0.0.1:{busy}" in (
                    h["reasons"][0]["message"]), h
            finally:
                doors.close()
