"""The OPC UA server for a cell PLC (asyncua), configured by ``[opcua]``.

One object ``Cell`` under Objects holds the variables (``State``, ``RobotMode``,
``SafetyStatus``, ``TcpPose``/``TcpPoseUR``, ``LastLocatePose``/``LastLocatePoseUR``,
``LastLocateQuality``, ``PartsSeen``, ``PartIds``, ``JobId``, ``JobKind``, ``JobState``,
``JobPhase``, ``JobProgress``, ``CameraConnected``, ``Alarms``, ``JobResult``, ``JobErrorCode``)
and the methods ``Locate()``, ``LocateAll(recipe)``, ``Approach(standoff_mm, mode, taught)``,
``ApproachRecipe(recipe, target, standoff_mm)``, ``Track(standoff_mm, duration_s)``,
``Pick(recipe, target, place)``, ``CheckCalibration()``, ``RecordReference()`` (the
operator's), ``Stop()``, ``Home()``, ``Gripper(action, width_mm)``. Every
method answers ``Code`` ("ok" or the HTTP API's error code) and ``Message`` first; a refusal is
an answer, not an OPC UA fault, so a PLC reads one place. Poses are the structure ``Pose``
(``position_mm``, ``rotvec_rad``) and, as ``...UR``, a UR pose (m, rotation vector).

Jobs are consistent at a method's return: before the answer of a method that starts a job is
sent, ``JobId``, ``JobKind`` and ``JobState`` (``running``) hold that job. A job's end is
written in one service call with its result (``JobResult``, JSON carrying the ``job_id``) and
``JobErrorCode``, and raised as a ``JobEndedEventType`` event (``JobId``, ``JobState``,
``ErrorCode``) from the ``Cell`` object. ``PartsSeen`` and ``PartIds`` follow the last locate of
every part, from any door (the cell's ``parts`` event); ``LocateAll`` writes them before it
answers. The object ``Cell/LastCheck`` holds the newest calibration check that ended with a
verdict, from any door or the schedule (``Verdict``, ``Cause``, ``TcpErrorMm``,
``TcpErrorDeg``, ``Time``, ``JobId``); a check's end changes them in the same write as its
``JobResult``. The OPC UA Machine Vision subset (``VisionSystem``)
is built by :mod:`api.plc.opcua_machine_vision`; the same behaviour in the standard's
namespace and types (``VisionSystem`` of type ``VisionSystemType``) by
:mod:`api.plc.opcua_vision_system`.

The server runs its own asyncio loop in its own thread, so the HTTP server's load does not
delay a PLC's Stop; cell calls run in worker threads. The calling user reaches the method
through a context variable set by the permission ruleset, which asyncua runs for every request
in the task that then executes it (``uaprocessor``: check, then the service call).

A refused login (an unknown user, a wrong password, a session without a user name: anonymous
or certificate login, which ``[opcua]`` does not offer) is logged here once, at WARNING, in one
line; asyncua's own ERROR lines about it are dropped and its loggers stay at WARNING
(``cell.supervision.logs``).
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import hmac
import json
import logging
import socket
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

from asyncua import Server, ua
from asyncua.common.callback import CallbackType
from asyncua.common.structures104 import new_struct, new_struct_field
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.permission_rules import USER_TYPES, SimpleRoleRuleset, User, UserRole
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions
from asyncua.server.user_managers import UserManager
from cryptography.x509.oid import ExtendedKeyUsageOID

from api import remote
from api.plc.loop_thread import LoopThread
from api.plc.machine_vision_model import build_model
from api.plc.opcua_address_space import cached_shelf
from api.plc.opcua_machine_vision import MachineVision
from api.plc.opcua_vision_system import VisionSystemFacet
from api.remote import RemoteCaller
from cell.calibration.check import CHECK_KIND
from cell.config.schema import OpcUaConfig
from cell.errors import CellError
from cell.jobs.store import Job
from cell.results.check import CheckResult
from cell.results.locate import LocateQuality
from cell.results.modes import ApproachMode
from cell.results.pose import Pose
from cell.service import Cell
from cell.supervision.logs import drop_library_records, quiet_library_loggers

log = logging.getLogger(__name__)

IDLE_CHECK_S = 1.0  # with nobody subscribed, the variables are updated this often
NO_TIME = datetime(1601, 1, 1, tzinfo=UTC)  # OPC UA's null DateTime: no check yet
_CURRENT_USER: contextvars.ContextVar[User | None] = contextvars.ContextVar(
    "opcua_user", default=None)
# Read, browse, subscribe, call: what an authenticated user may send. Writes are not allowed
# (every variable is the cell's to set), nor is changing the address space.
_ALLOWED = frozenset(ua.NodeId(ua.Int32(t)) for t in USER_TYPES) - {
    ua.NodeId(ua.Int32(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary))}

_POLICIES: dict[str, list[ua.SecurityPolicyType]] = {
    "None": [ua.SecurityPolicyType.NoSecurity],
    "Basic256Sha256": [ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
                       ua.SecurityPolicyType.Basic256Sha256_Sign],
}


def job_result(job: Job) -> dict[str, Any]:
    """``JobResult``: the ended job, its typed result as every interface publishes it, its
    error and the recipe it ran with."""
    return {"job_id": job.id, "kind": job.kind, "state": job.state,
            "result": None if job.result is None else job.result.json_dict(),
            "error": job.error(), "recipe": job.params.get("recipe")}


def _has_subscriptions(server: Server) -> bool:
    """Whether a client monitors anything (its data changes come from the update's
    writes); an asyncua without the table counts as yes, so updates never stop silently."""
    service = getattr(server.iserver, "subscription_service", None)
    subscriptions = getattr(service, "subscriptions", None)
    return subscriptions is None or bool(subscriptions)


class _Users(UserManager):
    """The configured users; a session's user name is how its calls are audited."""

    def __init__(self, config: OpcUaConfig) -> None:
        self._users = {u.name: u for u in config.users}

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> User | None:
        u = self._users.get(username or "")
        if u is None:
            log.warning("OPC UA login refused: %s is not a user in [opcua] users",
                        repr(username) if username else "a login without a user name")
            return None
        if password is None or not hmac.compare_digest(u.password.encode(), password.encode()):
            log.warning("OPC UA login of user %r refused: wrong password", u.name)
            return None
        return User(role=UserRole.User, name=u.name)


# asyncua's server loggers whose lines about a refused login are replaced by the server's own
_SESSION_LOG = "asyncua.server.internal_session"
_PROCESSOR_LOG = "asyncua.server.uaprocessor"
_LOGIN_FAULTS = frozenset({"BadIdentityTokenRejected", "BadIdentityTokenInvalid",
                           "BadUserAccessDenied"})


def _token_refused(record: logging.LogRecord) -> bool:
    """asyncua's ERROR on a session that offers no user name and password (anonymous or a
    certificate as identity): dropped, and said once at WARNING in the server's words."""
    if "UserIdentityToken not supported" not in str(record.msg):
        return False
    log.warning("OPC UA login refused: anonymous (or certificate) logins are not offered; "
                "[opcua] accepts only its users, by name and password")
    return True


def _login_fault(record: logging.LogRecord) -> bool:
    """asyncua's ERROR "sending service fault response" for a refused login, which
    ``_Users`` or ``_token_refused`` has logged already."""
    return "service fault" in str(record.msg) and any(
        str(arg) in _LOGIN_FAULTS for arg in (record.args or ()))


class _Rules(SimpleRoleRuleset):
    """Lets authenticated users read, browse, subscribe and call; remembers who is asking."""

    def check_validity(self, user: User | None, action_type: ua.NodeId, body: Any) -> bool:
        _CURRENT_USER.set(user)
        return user is not None and user.role == UserRole.User and action_type in _ALLOWED


def _arg(name: str, vtype: ua.VariantType, description: str, array: bool = False,
         datatype: ua.NodeId | None = None) -> ua.Argument:
    a = ua.Argument()
    a.Name = name
    a.DataType = datatype if datatype is not None else ua.NodeId(ua.Int32(vtype.value))
    a.ValueRank = 1 if array else -1
    a.ArrayDimensions = [0] if array else []
    a.Description = ua.LocalizedText(description)
    return a


class OpcUaServer(LoopThread):
    """``start()`` listens (raises OSError when the endpoint cannot be bound), ``close()``."""

    thread_name = "opcua"
    what = "the OPC UA server"

    def __init__(self, cell: Cell, config: OpcUaConfig, cert_dir: Path) -> None:
        super().__init__()
        self.cell = cell
        self.config = config
        self.cert_dir = cert_dir
        self.roles = {u.name: u.role for u in config.users}
        self._stop: asyncio.Event | None = None
        self._wake: asyncio.Event | None = None
        self._last_job_id = ""
        self._ended_job: dict[str, Any] | None = None  # the last job, as it ended
        self._ended_record: Job | None = None  # its record, read from the job store once
        self._nodes: dict[str, Any] = {}
        self._written: dict[str, ua.Variant] = {}  # the last value written to each node
        self._updated_s = 0.0  # time.monotonic() of the last variable update
        self._types: dict[str, Any] = {}
        self._server: Server | None = None
        self._job_created_at = 0.0  # of the job _last_job_id names
        self._ended_sent: str = ""  # the last job whose JobEnded event was raised
        self._event_gen: Any = None
        self._parts: list[int] | None = None  # the ids of the last locate of every part
        self._calibration_applied = False  # the next update shows the configuration anew
        self._last_check: tuple[Job, CheckResult] | None = None  # LastCheck's check
        self.machine_vision: Any = None
        self.calls = ThreadPoolExecutor(4, thread_name_prefix="opcua-call")
        self._stops = ThreadPoolExecutor(2, thread_name_prefix="opcua-stop")

    @property
    def endpoint(self) -> str:
        return self.config.endpoint

    def start(self, timeout_s: float = 60.0) -> None:
        quiet_library_loggers()  # asyncua logs every request at INFO
        drop_library_records(_SESSION_LOG, _token_refused)
        drop_library_records(_PROCESSOR_LOG, _login_fault)
        super().start(timeout_s)

    def close(self) -> None:
        loop, stop, wake = self._loop, self._stop, self._wake
        if loop is not None and stop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):  # the loop has ended meanwhile
                loop.call_soon_threadsafe(stop.set)
                if wake is not None:
                    loop.call_soon_threadsafe(wake.set)
        self._join(10.0)
        self.calls.shutdown(wait=False, cancel_futures=True)
        self._stops.shutdown(wait=False, cancel_futures=True)

    # -- the server's thread --------------------------------------------------------------------
    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        server = await self._build()
        self._server = server
        self._last_check = remote.last_check(self.cell)
        self._wake = wake = asyncio.Event()  # set by close(), a new subscription, a job event
        threading.Thread(target=self._watch_jobs, name="opcua-jobs", daemon=True).start()
        server.subscribe_server_callback(CallbackType.PreRead, self._before_read)
        server.subscribe_server_callback(CallbackType.ItemSubscriptionCreated,
                                         self._subscribed)
        await server.start()
        try:
            await self._refresh()  # the first values before anyone reads
            self._ready.set()
            while not self._stop.is_set():
                # with nobody subscribed the update slows to IDLE_CHECK_S (a Read refreshes
                # for itself first), so an idle cell PC builds almost nothing for nobody
                subscribed = _has_subscriptions(server)
                wake.clear()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(wake.wait(), self.config.update_period_s
                                           if subscribed else IDLE_CHECK_S)
                if not self._stop.is_set():
                    await self._refresh()
        finally:
            await server.stop()

    def _watch_jobs(self) -> None:
        """Wakes the update at every job start and end and every applied calibration, so an
        end (and its event) or the new configuration is shown at once rather than at the
        next period."""
        with self.cell.events.subscribe() as sub:
            while self._stop is not None and not self._stop.is_set():
                event = sub.get(timeout_s=0.5)
                if event is None or event.get("type") not in ("job", "parts", "calibration"):
                    continue
                if event["type"] == "parts":
                    self._parts = [int(p["id"]) for p in event.get("parts", [])]
                elif event["type"] == "calibration":
                    if event.get("state") != "applied":
                        continue
                    self._calibration_applied = True
                else:
                    self._saw_job(event.get("job") or {})
                loop, wake = self._loop, self._wake
                if loop is not None and wake is not None and not loop.is_closed():
                    with contextlib.suppress(RuntimeError):
                        loop.call_soon_threadsafe(wake.set)

    def _saw_job(self, job: dict[str, Any]) -> None:
        """A check that ended with a verdict becomes ``LastCheck`` (read back from the job
        store, the record every door publishes)."""
        if job.get("kind") == CHECK_KIND and job.get("ended_at"):
            record = self.cell.jobs.get(str(job.get("id", "")))
            if record is not None:
                self._show_check(record)

    def _show_check(self, record: Job) -> None:
        if not isinstance(record.result, CheckResult):
            return
        shown = self._last_check
        if shown is None or (record.ended_at or 0.0) >= (shown[0].ended_at or 0.0):
            self._last_check = (record, record.result)

    async def _refresh(self) -> None:
        self._updated_s = time.monotonic()
        try:
            await self._update()
        except Exception:
            log.exception("OPC UA variable update failed")

    async def _subscribed(self, event: Any, dispatcher: Any) -> None:
        """A new monitored item: fresh values now, and the periodic update back to its
        rate."""
        await self._before_read(event, dispatcher)
        if self._wake is not None:
            self._wake.set()

    async def _before_read(self, event: Any, dispatcher: Any) -> None:
        """A client's Read finds the variables at most one update period old: with nobody
        subscribed the periodic update rests (an idle cell PC builds nothing for nobody),
        so a polling PLC's read refreshes them first."""
        if time.monotonic() - self._updated_s >= self.config.update_period_s:
            await self._refresh()

    async def _build(self) -> Server:
        cfg = self.config
        server = Server(user_manager=_Users(cfg))
        await server.init(cached_shelf())  # namespace 0 read from its shelf when prepared
        server.set_endpoint(cfg.endpoint)
        server.set_server_name("ur-vision-cell")
        await server.set_application_uri(f"{cfg.namespace}:server")
        policies = [p for name in cfg.security_policies for p in _POLICIES[name]]
        server.set_security_policy(policies, permission_ruleset=_Rules())
        server.set_identity_tokens([ua.UserNameIdentityToken])
        if "Basic256Sha256" in cfg.security_policies:
            cert, key = await self._key_pair()
            await server.load_certificate(str(cert))
            await server.load_private_key(str(key))
        if cfg.trusted_client_certs_dir:
            store = TrustStore([Path(cfg.trusted_client_certs_dir)], [])
            await store.load()
            server.set_certificate_validator(CertificateValidator(
                CertificateValidatorOptions.TRUSTED_VALIDATION
                | CertificateValidatorOptions.PEER_CLIENT, store))
        idx = await server.register_namespace(cfg.namespace)
        await self._model(server, idx)
        self.machine_vision = MachineVision(self, server, idx)
        await self.machine_vision.build()
        facet = VisionSystemFacet(self.machine_vision, await build_model(server), idx)
        await facet.build()
        self.machine_vision.facets.append(facet)
        return server

    async def _key_pair(self) -> tuple[Path, Path]:
        if self.config.certificate:
            return Path(self.config.certificate), Path(self.config.private_key)
        self.cert_dir.mkdir(parents=True, exist_ok=True)
        cert, key = self.cert_dir / "server-cert.der", self.cert_dir / "server-key.pem"
        # the machine's name, which asyncua (and some clients) look for among the DNS names
        host = socket.gethostname() or urlparse(self.config.endpoint).hostname or "localhost"
        await setup_self_signed_certificate(
            key, cert, f"{self.config.namespace}:server", host,
            [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH],
            {"commonName": "ur-vision-cell", "organizationName": "ur-vision-cell"})
        key.chmod(0o600)
        return cert, key

    async def _model(self, server: Server, idx: int) -> None:
        D = ua.VariantType.Double
        pose_type, _ = await new_struct(server, idx, "Pose", [
            new_struct_field("position_mm", D, array=True),
            new_struct_field("rotvec_rad", D, array=True)])
        quality_type, _ = await new_struct(server, idx, "LocateQuality", [
            new_struct_field("valid", ua.VariantType.Boolean),
            new_struct_field("rms_px", D), new_struct_field("max_residual_px", D),
            new_struct_field("ambiguous", ua.VariantType.Boolean),
            new_struct_field("n_points", ua.VariantType.Int32), new_struct_field("age_s", D)])
        loaded = await server.load_data_type_definitions()
        # asyncua registers each structure's class in ``ua`` once per process; a second server
        # in the same process (tests) finds them there instead of in the returned dict.
        self._types = {name: loaded.get(name) or getattr(ua, name)
                       for name in ("Pose", "LocateQuality")}
        obj = await server.nodes.objects.add_object(idx, "Cell")
        S, B = ua.VariantType.String, ua.VariantType.Boolean
        zero = self._pose([0.0] * 3, [0.0] * 3)
        variables: list[tuple[str, Any, ua.VariantType, ua.NodeId | None]] = [
            ("State", "starting", S, None), ("RobotMode", "", S, None),
            ("SafetyStatus", "", S, None),
            ("TcpPose", zero, ua.VariantType.ExtensionObject, pose_type.nodeid),
            ("TcpPoseUR", [0.0] * 6, D, None),
            ("LastLocatePose", zero, ua.VariantType.ExtensionObject, pose_type.nodeid),
            ("LastLocatePoseUR", [0.0] * 6, D, None),
            ("LastLocateQuality", self._quality(None), ua.VariantType.ExtensionObject,
             quality_type.nodeid),
            ("JobId", "", S, None), ("JobKind", "", S, None), ("JobState", "", S, None),
            ("JobPhase", "", S, None), ("JobProgress", "{}", S, None),
            ("CameraConnected", False, B, None), ("Alarms", [], S, None),
            ("JobResult", "{}", S, None), ("JobErrorCode", "", S, None),
            ("PartsSeen", 0, ua.VariantType.Int32, None),
            ("PartIds", [], ua.VariantType.Int32, None),
        ]
        self._written = {}
        for name, value, vtype, datatype in variables:
            node = await obj.add_variable(idx, name, ua.Variant(value, vtype), datatype=datatype)
            self._nodes[name] = node
        last_check = await obj.add_object(idx, "LastCheck")
        for name, variant in self._check_values(None).items():
            self._nodes[name] = await last_check.add_variable(idx, name.split(".")[1], variant)
        event_type = await server.create_custom_event_type(
            idx, "JobEndedEventType", ua.ObjectIds.BaseEventType,
            [("JobId", ua.VariantType.String), ("JobState", ua.VariantType.String),
             ("ErrorCode", ua.VariantType.String)])
        self._event_gen = await server.get_event_generator(event_type, obj.nodeid)
        pose_arg = pose_type.nodeid
        code = [_arg("Code", S, '"ok" or the error code of the HTTP API'),
                _arg("Message", S, "what happened, in words")]
        job = [*code, _arg("JobId", S, "the job started (empty when refused)")]
        methods: list[tuple[str, Callable[..., Any], list[ua.Argument], list[ua.Argument]]] = [
            ("Locate", self._locate, [], [
                *code, _arg("Pose", S, "T_base_target", datatype=pose_arg),
                _arg("PoseUR", D, "T_base_target as a UR pose (m, rotation vector)", array=True),
                _arg("RmsPx", D, "reprojection error")]),
            ("LocateAll", self._locate_all, [
                _arg("recipe", S, "the recipe whose targets' layouts are looked for (empty: "
                     "the layout in use)")], [
                *code, _arg("Count", ua.VariantType.Int32, "the parts in view"),
                _arg("PartIds", ua.VariantType.Int32, "their ids, in the pick order",
                     array=True),
                _arg("Instances", S, "the parts as JSON: id, layout, T_base_target, quality, "
                     "flags, pickable, ... (as POST /locate {\"all\": true})")]),
            ("Approach", self._approach, [
                _arg("standoff_mm", D, "distance back from the taught tool pose"),
                _arg("mode", S, f"{', '.join(ApproachMode)} (empty: the cell's [approach] "
                     "mode); ibvs goes to the taught view, standoff 0"),
                _arg("taught", S, "a taught pose's name (empty: the config's tool pose); "
                     "required for ibvs")], job),
            ("ApproachRecipe", self._approach_recipe, [
                _arg("recipe", S, "the recipe's name or number"),
                _arg("target", S, "the recipe's target (empty: its first)"),
                _arg("standoff_mm", D, "distance back from the taught pose (< 0: the "
                     "recipe's)")], job),
            ("Track", self._track, [
                _arg("standoff_mm", D, "distance kept from the target"),
                _arg("duration_s", D, "how long to follow it")], job),
            ("Pick", self._pick, [
                _arg("recipe", S, "the recipe's name or number (empty: the cell's target)"),
                _arg("target", S, "the recipe's target (empty: its first)"),
                _arg("place", S, "a pose taught in the base frame to place the part at "
                     "(empty: keep it in the gripper)")], job),
            ("CheckCalibration", self._check_calibration, [], job),
            ("RecordReference", self._record_reference, [], job),
            ("Stop", self._stop_call, [], job),
            ("Home", self._home, [], job),
            ("Gripper", self._gripper, [
                _arg("action", S, "open, close, move or activate"),
                _arg("width_mm", D, "finger opening for move")], code),
        ]
        for name, func, inputs, outputs in methods:
            await obj.add_method(idx, name, func, inputs, outputs)

    # -- values ---------------------------------------------------------------------------------
    def _pose(self, position_mm: list[float], rotvec_rad: list[float]) -> Any:
        pose = self._types["Pose"]()
        pose.position_mm = list(position_mm)
        pose.rotvec_rad = list(rotvec_rad)
        return pose

    def pose_struct(self, pose: Pose) -> Any:
        return self._pose(list(pose.position_mm), list(pose.rotvec_rad))

    @staticmethod
    def _ur(pose: Pose) -> list[float]:
        return [v / 1000.0 for v in pose.position_mm] + list(pose.rotvec_rad)

    def _quality(self, q: LocateQuality | None) -> Any:
        out = self._types["LocateQuality"]()
        out.valid = q is not None
        if q is not None:
            out.rms_px = q.rms_px
            out.max_residual_px = q.max_residual_px
            out.ambiguous = q.ambiguous
            out.n_points = q.n_points
            out.age_s = q.frame_age_s
        return out

    def _snapshot(self) -> dict[str, Any]:
        """What the variables show: the cell's snapshot (built from cached device state, it
        never waits on a device, so it is read on the server's loop) and the job running,
        or the last one as it ended (read from the job store once)."""
        st = self.cell.status()
        health = self.cell.health()
        job = st.get("job")
        if job is not None and job["id"] != self._last_job_id \
                and float(job.get("created_at") or 0.0) < self._job_created_at:
            job = None  # an older snapshot than the job a method has just started
        if job is not None:
            self._last_job_id, self._ended_job = job["id"], None
            self._job_created_at = float(job.get("created_at") or 0.0)
        elif self._last_job_id:
            job = self._ended_job
            if job is None or job["id"] != self._last_job_id:
                j = self.cell.jobs.get(self._last_job_id)
                job = None if j is None else j.as_dict()
                # kept once its record has ended (the slot may be free a moment before)
                self._ended_job = job if job is not None and job.get("ended_at") else None
        robot = st.get("robot", {})
        alarms = [f"{name}_disconnected" for name in health.get("missing", [])]
        if robot.get("protective_stop"):
            alarms.append("protective_stop")
        if "EMERGENCY_STOP" in str(robot.get("safety", "")):
            alarms.append("emergency_stop")
        gripper = st.get("gripper") or {}
        if isinstance(gripper, dict) and gripper.get("error"):
            alarms.append("gripper_fault")
        return {"status": st, "job": job, "alarms": alarms}

    async def _update(self) -> None:
        snap = self._snapshot()
        st, job = snap["status"], snap["job"]
        robot = st.get("robot", {})
        S, D = ua.VariantType.String, ua.VariantType.Double
        values: dict[str, ua.Variant] = {
            "State": ua.Variant(str(st.get("state", "")), S),
            "RobotMode": ua.Variant(str(robot.get("mode", "DISCONNECTED")), S),
            "SafetyStatus": ua.Variant(str(robot.get("safety", "")), S),
            "CameraConnected": ua.Variant(bool(st["camera"]["connected"]),
                                          ua.VariantType.Boolean),
            "Alarms": ua.Variant(snap["alarms"], S),
            "JobId": ua.Variant("" if job is None else job["id"], S),
            "JobKind": ua.Variant("" if job is None else job["kind"], S),
            "JobState": ua.Variant("" if job is None else job["state"], S),
            "JobPhase": ua.Variant("" if job is None else
                                   str((job.get("progress") or {}).get("phase", "")), S),
            "JobProgress": ua.Variant("{}" if job is None else
                                      json.dumps(job.get("progress") or {}, default=str), S),
            **self._job_end_values(job),
        }
        values.update(self._check_values(self._last_check))
        if "T_base_tcp" in robot:
            tcp = Pose.model_validate(robot["T_base_tcp"])
            values["TcpPose"] = ua.Variant(self.pose_struct(tcp), ua.VariantType.ExtensionObject)
            values["TcpPoseUR"] = ua.Variant(self._ur(tcp), D)
        located = self.cell.last_locate
        last = None if located is None else located.answer(time.monotonic())
        if last is not None:
            values["LastLocatePose"] = ua.Variant(self.pose_struct(last.T_base_target),
                                                  ua.VariantType.ExtensionObject)
            values["LastLocatePoseUR"] = ua.Variant(self._ur(last.T_base_target), D)
        values["LastLocateQuality"] = ua.Variant(
            self._quality(None if last is None else last.quality),
            ua.VariantType.ExtensionObject)
        if self._parts is not None:
            values.update(self._parts_values(self._parts))
        await self._write(values)
        if job is not None and job.get("ended_at") and job["id"] != self._ended_sent:
            await self._job_ended(job)
        if self.machine_vision is not None:
            if self._calibration_applied:
                self._calibration_applied = False
                await self.machine_vision.calibration_applied()
            await self.machine_vision.update(st, job)

    @staticmethod
    def _parts_values(ids: list[int]) -> dict[str, ua.Variant]:
        I32 = ua.VariantType.Int32
        return {"PartsSeen": ua.Variant(len(ids), I32), "PartIds": ua.Variant(ids, I32)}

    @staticmethod
    def _check_values(last: tuple[Job, CheckResult] | None) -> dict[str, ua.Variant]:
        """``LastCheck``'s variables: the check's verdict and its figures at the tool (empty
        and zero before any check)."""
        S, D = ua.VariantType.String, ua.VariantType.Double
        job, result = last if last is not None else (None, None)
        ended = NO_TIME if job is None or not job.ended_at \
            else datetime.fromtimestamp(job.ended_at, tz=UTC)
        return {
            "LastCheck.Verdict": ua.Variant("" if result is None else result.verdict, S),
            "LastCheck.Cause": ua.Variant("" if result is None else result.cause, S),
            "LastCheck.TcpErrorMm": ua.Variant(0.0 if result is None else result.tcp_error_mm,
                                               D),
            "LastCheck.TcpErrorDeg": ua.Variant(
                0.0 if result is None else result.tcp_error_deg, D),
            "LastCheck.Time": ua.Variant(ended, ua.VariantType.DateTime),
            "LastCheck.JobId": ua.Variant("" if job is None else job.id, S),
        }

    def ended_job(self, job_id: str) -> Job | None:
        """The record of a job that has ended, read from the job store once: what the result
        variables (``JobResult``, the Machine Vision result) serialise."""
        record = self._ended_record
        if record is None or record.id != job_id:
            record = self.cell.jobs.get(job_id)
            self._ended_record = record if record is not None and record.finished else None
        return record

    def _job_end_values(self, job: dict[str, Any] | None) -> dict[str, ua.Variant]:
        """The job's result and error code: empty while it runs, set with its end state."""
        S = ua.VariantType.String
        record = None if job is None or not job.get("ended_at") else self.ended_job(job["id"])
        if record is None:
            return {"JobResult": ua.Variant("{}", S), "JobErrorCode": ua.Variant("", S)}
        self._show_check(record)  # a check's end shows in LastCheck in this same write
        return {"JobResult": ua.Variant(json.dumps(job_result(record), default=str), S),
                "JobErrorCode": ua.Variant(record.error_code or "", S)}

    async def _write(self, values: dict[str, ua.Variant]) -> None:
        """Every changed value in ONE write service call, so a client's Read (served on this
        loop) sees all of them or none: a job's end never without its result. Unchanged values
        are not written (no data-change notification, OPC UA's way)."""
        changed = {n: v for n, v in values.items() if self._written.get(n) != v}
        if not changed:
            return
        results = await self.write_nodes({self._nodes[n]: v for n, v in changed.items()})
        for (name, value), good in zip(changed.items(), results, strict=True):
            if good:
                self._written[name] = value

    async def write_nodes(self, values: dict[Any, ua.Variant]) -> list[bool]:
        """One Write service call for all of ``values`` (node -> value); which were written."""
        params = ua.WriteParameters()
        for node, value in values.items():
            wv = ua.WriteValue()
            wv.NodeId = node.nodeid
            wv.AttributeId = ua.AttributeIds.Value
            wv.Value = ua.DataValue(value)
            params.NodesToWrite.append(wv)
        assert self._server is not None
        results = await self._server.iserver.isession.write(params)
        for node, status in zip(values, results, strict=True):
            if not status.is_good():
                log.warning("OPC UA write of %s failed: %s", node.nodeid, status)
        return [status.is_good() for status in results]

    async def _job_ended(self, job: dict[str, Any]) -> None:
        self._ended_sent = job["id"]
        if self._event_gen is None:
            return
        error = job.get("error") or {}
        gen = self._event_gen
        gen.event.JobId = job["id"]
        gen.event.JobState = job["state"]
        gen.event.ErrorCode = str(error.get("code") or "")
        gen.event.Severity = 100 if job["state"] == "succeeded" else 500
        await gen.trigger(message=f"{job['kind']} job {job['id']} {job['state']}")

    async def show_started(self, job_id: str) -> None:
        """Before a method's answer leaves: the job it started in JobId/JobKind/JobState."""
        if not job_id:
            return
        j = self.cell.jobs.get(job_id)
        if j is None:
            return
        job = j.as_dict()
        self._last_job_id, self._job_created_at = job["id"], float(job["created_at"])
        self._ended_job = job if job.get("ended_at") else None
        S = ua.VariantType.String
        await self._write({
            "JobId": ua.Variant(job["id"], S), "JobKind": ua.Variant(job["kind"], S),
            "JobState": ua.Variant(job["state"], S),
            "JobPhase": ua.Variant(str((job.get("progress") or {}).get("phase", "")), S),
            "JobProgress": ua.Variant(json.dumps(job.get("progress") or {}, default=str), S),
            **self._job_end_values(job)})

    # -- methods --------------------------------------------------------------------------------
    def current_caller(self) -> RemoteCaller | None:
        user = _CURRENT_USER.get()
        if user is None or user.name not in self.roles:
            return None
        return RemoteCaller("opcua", user.name, self.roles[user.name])

    async def _answer(self, work: Callable[[RemoteCaller], list[ua.Variant]],
                      refused_tail: list[ua.Variant], *,
                      pool: ThreadPoolExecutor | None = None) -> list[ua.Variant]:
        """``Code``, ``Message`` and the method's outputs; a refusal fills them with blanks."""
        S = ua.VariantType.String
        caller = self.current_caller()
        if caller is None:
            return [ua.Variant("unauthorized", S), ua.Variant("no known user", S), *refused_tail]
        try:
            loop = asyncio.get_running_loop()
            return await loop.run_in_executor(pool or self.calls, work, caller)
        except CellError as err:
            return [ua.Variant(err.code, S), ua.Variant(err.message, S), *refused_tail]
        except Exception as err:
            log.exception("OPC UA call failed")
            return [ua.Variant("internal_error", S), ua.Variant(f"unexpected error: {err!r}", S),
                    *refused_tail]

    @staticmethod
    def _ok(message: str, *tail: ua.Variant) -> list[ua.Variant]:
        S = ua.VariantType.String
        return [ua.Variant("ok", S), ua.Variant(message, S), *tail]

    @staticmethod
    def method_args(args: tuple[Any, ...], n: int) -> list[Any]:
        """The method's input values; missing ones are None (refused by the checks)."""
        vals = [a.Value if isinstance(a, ua.Variant) else a for a in args]
        return (vals + [None] * n)[:n]

    def _job_answer(self, job_id: str, state: str) -> list[ua.Variant]:
        return self._ok(f"job {job_id} {state}" if job_id else state,
                        ua.Variant(job_id, ua.VariantType.String))

    async def _job_call(self, work: Callable[[RemoteCaller], list[ua.Variant]]
                        ) -> list[ua.Variant]:
        """A method that starts a job: its answer leaves once the variables show the job."""
        out = await self._answer(work, [ua.Variant("", ua.VariantType.String)])
        if out[0].Value == "ok":
            await self.show_started(str(out[2].Value))
        return out

    async def _locate(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        D = ua.VariantType.Double

        def work(caller: RemoteCaller) -> list[ua.Variant]:
            loc = remote.locate(self.cell, caller)
            position_mm, rotvec_rad = remote.pose_mm_rad(loc.T_base_target)
            return self._ok(
                f"located, rms {loc.result.rms_px:.3f} px",
                ua.Variant(self._pose(position_mm, rotvec_rad), ua.VariantType.ExtensionObject),
                ua.Variant(remote.ur_pose(loc.T_base_target), D),
                ua.Variant(float(loc.result.rms_px), D))

        blank = [ua.Variant(self._pose([0.0] * 3, [0.0] * 3), ua.VariantType.ExtensionObject),
                 ua.Variant([0.0] * 6, D), ua.Variant(0.0, D)]
        return await self._answer(work, blank)

    async def _locate_all(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        (recipe,) = self.method_args(args, 1)
        S, I32 = ua.VariantType.String, ua.VariantType.Int32

        def work(caller: RemoteCaller) -> list[ua.Variant]:
            found = remote.locate_all(self.cell, caller, recipe or "")
            parts = found.answer(time.monotonic())
            ids = [p.id for p in parts.instances]
            self._parts = ids
            pickable = sum(p.pickable for p in parts.instances)
            return self._ok(
                f"{len(ids)} part(s) in view, {pickable} pickable",
                ua.Variant(len(ids), I32), ua.Variant(ids, I32),
                ua.Variant(json.dumps([p.json_dict() for p in parts.instances]), S))

        out = await self._answer(work, [ua.Variant(0, I32), ua.Variant([], I32),
                                        ua.Variant("[]", S)])
        if out[0].Value == "ok":  # the variables agree with the answer when it leaves
            await self._write(self._parts_values(list(out[3].Value or [])))
        return out

    async def _approach(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        standoff_mm, mode, taught = self.method_args(args, 3)

        def work(caller: RemoteCaller) -> list[ua.Variant]:
            job = remote.approach(self.cell, caller, standoff_mm, mode, taught)
            return self._job_answer(job.id, job.state)

        return await self._job_call(work)

    async def _approach_recipe(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        recipe, target, standoff_mm = self.method_args(args, 3)

        def work(caller: RemoteCaller) -> list[ua.Variant]:
            standoff = None if isinstance(standoff_mm, float) and standoff_mm < 0 \
                else standoff_mm
            job = remote.approach_recipe(self.cell, caller, recipe, target, standoff)
            return self._job_answer(job.id, job.state)

        return await self._job_call(work)

    async def _track(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        standoff_mm, duration_s = self.method_args(args, 2)

        def work(caller: RemoteCaller) -> list[ua.Variant]:
            job = remote.track(self.cell, caller, standoff_mm, duration_s)
            return self._job_answer(job.id, job.state)

        return await self._job_call(work)

    async def _pick(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        recipe, target, place = self.method_args(args, 3)

        def work(caller: RemoteCaller) -> list[ua.Variant]:
            job = remote.pick(self.cell, caller, recipe, target, place)
            return self._job_answer(job.id, job.state)

        return await self._job_call(work)

    async def _check_calibration(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        def work(caller: RemoteCaller) -> list[ua.Variant]:
            job = remote.check_calibration(self.cell, caller)
            return self._job_answer(job.id, job.state)

        return await self._job_call(work)

    async def _record_reference(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        def work(caller: RemoteCaller) -> list[ua.Variant]:
            job = remote.record_reference(self.cell, caller)
            return self._job_answer(job.id, job.state)

        return await self._job_call(work)

    async def _stop_call(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        S = ua.VariantType.String

        def work(caller: RemoteCaller) -> list[ua.Variant]:
            t0 = time.monotonic()
            out = remote.stop(self.cell, caller)
            job_id = out.get("job_id") or ""
            if not out.get("stopped"):  # the arm, or a moving gripper, did not take it
                which = "arm_error" if out.get("arm_error") else "gripper_error"
                return [ua.Variant(which, S), ua.Variant(str(out.get(which)), S),
                        ua.Variant(job_id, S)]
            what = f"cancelled {out['cancelled']}" if out.get("cancelled") else "nothing running"
            return self._ok(f"stopped ({what}) in {1000 * (time.monotonic() - t0):.0f} ms",
                            ua.Variant(job_id, S))

        # Its own threads: a Stop never queues behind locates and approaches being started.
        return await self._answer(work, [ua.Variant("", S)], pool=self._stops)

    async def _home(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        def work(caller: RemoteCaller) -> list[ua.Variant]:
            job = remote.home(self.cell, caller)
            return self._job_answer(job.id, job.state)

        return await self._job_call(work)

    async def _gripper(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        action, width_mm = self.method_args(args, 2)

        def work(caller: RemoteCaller) -> list[ua.Variant]:
            st = remote.gripper(self.cell, caller, action, width_mm)
            return self._ok(json.dumps(st, default=str))

        return await self._answer(work, [])
