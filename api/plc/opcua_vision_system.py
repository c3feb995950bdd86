"""``VisionSystem`` of OPC 40100-1 in the standard's namespace: the object a generic Machine
Vision client looks for (type ``VisionSystemType``, children by the standard's browse names,
arguments of the standard's structured data types), over the cell's Machine Vision behaviour
(:mod:`api.plc.opcua_machine_vision`): one state machine, one prepared recipe and one set of
results, shown on both objects.

- ``VisionStateMachine``: ``CurrentState`` (with its ``Id``, the state's NodeId on the type),
  ``Halt``, ``Reset``, ``SelectModeAutomatic``; ``AutomaticModeStateMachine``: ``CurrentState``,
  ``StartSingleJob``, ``StartContinuous``, ``Stop``, ``Abort``.
- ``RecipeManagement``: the cell's recipes; an external id is a recipe's name or number, an
  internal id ``name@version``. ``AddRecipe`` finds a recipe the cell has (its content comes
  through the cell's own doors: the HTTP API, the ``AddRecipe`` with content of the cell's
  namespace); ``PrepareRecipe``, ``UnprepareRecipe``, ``RemoveRecipe``,
  ``GetRecipeListFiltered``.
- ``ConfigurationManagement``: one configuration, the hand-eye calibration in use: its id is
  the calibration job that was applied last (``config``: the config file's ``[hand_eye]``), its
  date when that happened.
- ``ResultManagement``: ``GetResultById``, ``GetResultComponentsById``,
  ``GetResultListFiltered``, ``ReleaseResultHandle`` over the newest results; each job's end
  raises ``ResultReadyEventType`` from ``VisionSystem``.

A job's result (``ResultDataType``): ``ResultId`` ``r-<JobId>``; ``ResultState`` 1 when the job
succeeded, -1 when it failed, -2 when it was stopped; ``ResultContent`` the located pose (the
cell's ``Pose`` structure; missing when the job located nothing) and the result as JSON (the job's
kind, error, recipe and, for a pick, the part taken, the grip, the place and each phase's
seconds); ``ProcessingTimes`` from the job's start to its end, its acquisition the first locate.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections import OrderedDict
from collections.abc import Awaitable, Callable
from datetime import UTC, datetime
from typing import Any, TypeVar

from asyncua import Node, ua

from api.plc import machine_vision_model as mvm
from api.plc.machine_vision_model import Arg, Model, node_id
from api.plc.modbus import error_number
from api.plc.opcua_machine_vision import CONTINUOUS, MAX_RESULTS, SINGLE, MachineVision
from cell.jobs.store import Job
from cell.results.approach import ApproachBase
from cell.results.jobs import located_pose
from cell.results.pick import PickResult

log = logging.getLogger(__name__)

I32 = ua.VariantType.Int32
EXT = ua.VariantType.ExtensionObject
STATE_SUCCEEDED, STATE_FAILED, STATE_CANCELLED = 1, -1, -2
T = TypeVar("T")
CONFIG_ID = "config"  # the calibration of the config file, none applied since


def _when(t_s: float | None) -> datetime:
    return datetime.fromtimestamp(t_s, tz=UTC) if t_s else ua.get_win_epoch()


class VisionSystemFacet:
    """The standard's ``VisionSystem`` object: built under Objects, kept in step with the
    Machine Vision behaviour it fronts (``show`` after each state change, ``result`` at each
    job's end)."""

    def __init__(self, mv: MachineVision, model: Model, ns: int) -> None:
        self.mv = mv
        self.model = model
        self.ns = ns  # the cell's namespace: the instance's NodeIds
        self.results: OrderedDict[str, Any] = OrderedDict()  # ResultId -> ResultDataType
        self.started: dict[str, tuple[Any, Any, Any, Any]] = {}  # JobId -> its start's ids
        self._nodes: dict[str, Node] = {}
        self._event: Any = None
        self._configuration: Any = None
        self._shown: tuple[str, str] | None = None  # the states last written

    # -- the address space ----------------------------------------------------------------------
    def _nid(self, path: str) -> ua.NodeId:
        return ua.NodeId(ua.String(f"VisionSystem40100.{path}"), ua.Int16(self.ns))

    async def _object(self, parent: Node, path: str, name: str, type_number: int) -> Node:
        """An object of one of the standard's types, without asyncua copying the type's
        instance declarations (the children are built here, each bound to its behaviour)."""
        item = ua.AddNodesItem()
        item.RequestedNewNodeId = self._nid(path)
        item.BrowseName = self.model.name(name)
        item.NodeClass = ua.NodeClass.Object
        item.ParentNodeId = parent.nodeid
        item.ReferenceTypeId = node_id(ua.ObjectIds.HasComponent)
        item.TypeDefinition = self.model.id(type_number)
        attrs = ua.ObjectAttributes()
        attrs.DisplayName = ua.LocalizedText(name)
        item.NodeAttributes = attrs
        server = self.mv.server
        result = (await server.iserver.isession.add_nodes([item]))[0]
        result.StatusCode.check()
        return server.get_node(result.AddedNodeId)

    async def _current_state(self, machine: Node, path: str, key: str) -> None:
        """``CurrentState`` (FiniteStateVariableType) with its ``Id``."""
        var = await machine.add_variable(self._nid(f"{path}.CurrentState"), "CurrentState",
                                         ua.LocalizedText(""))
        await var.delete_reference(node_id(ua.ObjectIds.BaseDataVariableType),
                                   ua.ObjectIds.HasTypeDefinition, forward=True)
        await var.add_reference(node_id(ua.ObjectIds.FiniteStateVariableType),
                                ua.ObjectIds.HasTypeDefinition, forward=True)
        self._nodes[key] = var
        self._nodes[f"{key}.Id"] = await var.add_property(
            self._nid(f"{path}.CurrentState.Id"), "Id", ua.Variant(ua.NodeId(),
                                                                   ua.VariantType.NodeId))

    async def _methods(self, parent: Node, path: str, type_number: int,
                       handlers: dict[str, Callable[..., Awaitable[list[ua.Variant]]]]) -> None:
        """The type's methods on ``parent``, each answered by its handler."""
        for m in mvm.METHODS[type_number]:
            if m.name not in handlers:
                continue
            await parent.add_method(
                self._nid(f"{path}.{m.name}"), self.model.name(m.name), handlers[m.name],
                [self.model.argument(a) for a in m.inputs],
                [self.model.argument(a) for a in m.outputs])

    async def build(self) -> None:
        model, server = self.model, self.mv.server
        vs = await self._object(server.nodes.objects, "VisionSystem", "VisionSystem",
                                mvm.VISION_SYSTEM_TYPE)
        await vs.set_event_notifier([ua.EventNotifier.SubscribeToEvents])
        sm = await self._object(vs, "VisionStateMachine", "VisionStateMachine",
                                mvm.VISION_STATE_MACHINE_TYPE)
        await self._current_state(sm, "VisionStateMachine", "state")
        await self._methods(sm, "VisionStateMachine", mvm.VISION_STATE_MACHINE_TYPE, {
            "Halt": self._halt, "Reset": self._reset,
            "SelectModeAutomatic": self._select_automatic})
        auto = await self._object(sm, "AutomaticModeStateMachine", "AutomaticModeStateMachine",
                                  mvm.AUTOMATIC_MODE_TYPE)
        await self._current_state(auto, "AutomaticModeStateMachine", "sub_state")
        await self._methods(auto, "AutomaticModeStateMachine", mvm.AUTOMATIC_MODE_TYPE, {
            "StartSingleJob": self._start_single, "StartContinuous": self._start_continuous,
            "Stop": self._stop, "Abort": self._stop})
        recipes = await self._object(vs, "RecipeManagement", "RecipeManagement",
                                     mvm.RECIPE_MANAGEMENT_TYPE)
        await self._methods(recipes, "RecipeManagement", mvm.RECIPE_MANAGEMENT_TYPE, {
            "AddRecipe": self._add_recipe, "GetRecipeListFiltered": self._list_recipes,
            "PrepareRecipe": self.prepare_recipe, "UnprepareRecipe": self.unprepare_recipe,
            "RemoveRecipe": self.remove_recipe})
        configs = await self._object(vs, "ConfigurationManagement", "ConfigurationManagement",
                                     mvm.CONFIGURATION_MANAGEMENT_TYPE)
        self._configuration = self._active_configuration()
        self._nodes["configuration"] = await configs.add_variable(
            self._nid("ConfigurationManagement.ActiveConfiguration"),
            model.name("ActiveConfiguration"), ua.Variant(self._configuration, EXT),
            datatype=model.id(mvm.CONFIGURATION))
        await self._methods(configs, "ConfigurationManagement",
                            mvm.CONFIGURATION_MANAGEMENT_TYPE, {
                                "ActivateConfiguration": self._activate_configuration,
                                "GetConfigurationById": self._get_configuration,
                                "GetConfigurationList": self._list_configurations})
        results = await self._object(vs, "ResultManagement", "ResultManagement",
                                     mvm.RESULT_MANAGEMENT_TYPE)
        await self._methods(results, "ResultManagement", mvm.RESULT_MANAGEMENT_TYPE, {
            "GetResultById": self._get_result, "GetResultComponentsById": self._get_components,
            "GetResultListFiltered": self._list_results,
            "ReleaseResultHandle": self._release_handle})
        self._event = await server.get_event_generator(model.id(mvm.RESULT_READY_EVENT_TYPE),
                                                       vs.nodeid)

    # -- following the behaviour ----------------------------------------------------------------
    async def show(self) -> None:
        """The states of the behaviour's machines, with their ``Id`` (a null NodeId when the
        sub-machine is not active); written when they change."""
        if self._shown == (self.mv.state, self.mv.sub_state):
            return
        self._shown = (self.mv.state, self.mv.sub_state)
        values: dict[Any, ua.Variant] = {}
        for key, type_number, state in (
                ("state", mvm.VISION_STATE_MACHINE_TYPE, self.mv.state),
                ("sub_state", mvm.AUTOMATIC_MODE_TYPE, self.mv.sub_state)):
            number = mvm.STATES[type_number].get(state)
            values[self._nodes[key]] = ua.Variant(ua.LocalizedText(state),
                                                  ua.VariantType.LocalizedText)
            values[self._nodes[f"{key}.Id"]] = ua.Variant(
                ua.NodeId() if number is None else self.model.id(number[0]),
                ua.VariantType.NodeId)
        await self.mv.opc.write_nodes(values)

    async def configuration_changed(self) -> None:
        """The active configuration read again (a calibration was applied) and shown."""
        configuration = await self._off_loop(self._active_configuration)
        if (configuration.InternalId.Id, configuration.LastModified) != \
                (self._configuration.InternalId.Id, self._configuration.LastModified):
            self._configuration = configuration
            await self.mv.opc.write_nodes({self._nodes["configuration"]:
                                           ua.Variant(configuration, EXT)})

    async def result(self, job: dict[str, Any]) -> None:
        """A job's end: its ``ResultDataType`` kept for the result methods, the active
        configuration read again, and ``ResultReadyEventType`` raised."""
        await self.configuration_changed()
        result = self._result_of(job, self.mv.opc.ended_job(job["id"]))
        self.results[result.ResultId.Id] = result
        while len(self.results) > MAX_RESULTS:
            self.results.popitem(last=False)
        self.started.pop(job["id"], None)
        event = self._event.event
        for name in ("CreationTime", "InternalConfigurationId", "InternalRecipeId", "IsPartial",
                     "JobId", "ResultId", "MeasId", "PartId", "ProductId", "ExternalRecipeId",
                     "ProcessingTimes"):
            setattr(event, name, getattr(result, name))
        event.ResultState = result.ResultState
        event.Severity = 100 if result.ResultState > 0 else 500
        await self._event.trigger(message=f"result {result.ResultId.Id} of {job['kind']} job "
                                          f"{job['id']} ({job['state']})")

    def _result_of(self, job: dict[str, Any], record: Job | None) -> Any:
        m = self.model
        params = job.get("params") or {}
        recipe = params.get("recipe") or {}
        meas, part, external, product = self.started.get(job["id"], (None, None, None, None))
        typed = None if record is None else record.result
        located = None if typed is None else located_pose(typed)
        content = [] if located is None else [ua.Variant(self.mv.opc.pose_struct(located), EXT)]
        content.append(ua.Variant(json.dumps(self.mv.results.get(f"r-{job['id']}", {}),
                                             default=str), ua.VariantType.String))
        started_s = float(job.get("created_at") or 0.0)
        ended_s = float(job.get("ended_at") or started_s)
        times = m.new("ProcessingTimesDataType", StartTime=_when(started_s),
                      EndTime=_when(ended_s), ProcessingDuration=1000.0 * (ended_s - started_s))
        acquisition_s = _acquisition_s(typed)
        if acquisition_s is not None:
            times.AcquisitionDuration = 1000.0 * acquisition_s
        state = {"succeeded": STATE_SUCCEEDED, "cancelled": STATE_CANCELLED}.get(
            job["state"], STATE_FAILED)
        return m.new(
            "ResultDataType", ResultId=m.new("ResultIdDataType", Id=f"r-{job['id']}"),
            IsPartial=False, IsSimulated=self.mv.opc.cell.sim is not None, ResultState=state,
            MeasId=meas, PartId=part, ExternalRecipeId=external, ProductId=product,
            InternalRecipeId=m.new("RecipeIdInternalDataType", Id=(
                f"{recipe['name']}@{recipe['version']}" if recipe else "")),
            InternalConfigurationId=self._configuration.InternalId,
            JobId=m.new("JobIdDataType", Id=job["id"]), CreationTime=_when(ended_s),
            ProcessingTimes=times, ResultContent=content)

    def _active_configuration(self) -> Any:
        """The hand-eye calibration in use: the newest applied calibration in the audit log
        (when it was applied), else the config file's (when the file was written; none for a
        built-in config)."""
        m = self.model
        cell = self.mv.opc.cell
        applied = next((e for e in cell.jobs.audit_log(1000)
                        if e.command == "apply_calibration" and e.outcome == "ok"
                        and e.params.get("running")), None)
        when_s: float | None
        if applied is not None:
            cal_id, when_s = str(applied.params.get("job_id")), applied.ended_at
        else:
            path = cell.calibration.config_path
            cal_id = CONFIG_ID
            when_s = path.stat().st_mtime if path is not None and path.exists() else None
        return m.new("ConfigurationDataType",
                     InternalId=m.new("ConfigurationIdDataType", Id=cal_id),
                     LastModified=_when(when_s))

    async def _off_loop(self, work: Callable[[], T]) -> T:
        """``work`` (a read of the cell's stores) in a worker thread, off the server's loop."""
        return await asyncio.get_running_loop().run_in_executor(self.mv.opc.calls, work)

    # -- methods --------------------------------------------------------------------------------
    def _error(self, out: list[ua.Variant]) -> int:
        return int(out[-1].Value)

    def _blank(self, outputs: tuple[Arg, ...]) -> list[ua.Variant]:
        """Every output but ``Error``, empty: what a refused call answers."""
        blanks: list[ua.Variant] = []
        for name, dtype, array in outputs[:-1]:
            if array:
                blanks.append(ua.Variant([], EXT if isinstance(dtype, int)
                                         else ua.VariantType.Variant))
            elif isinstance(dtype, int) and dtype not in (mvm.HANDLE, mvm.RESULT_STATE):
                struct = next(s.name for s in mvm.STRUCTS if s.number == dtype)
                blanks.append(ua.Variant(self.model.new(struct), EXT))
            elif dtype == mvm.HANDLE:
                blanks.append(ua.Variant(0, ua.VariantType.UInt32))
            elif dtype == mvm.RESULT_STATE:
                blanks.append(ua.Variant(0, I32))
            else:
                blanks.append(_null(dtype, name))
        return blanks

    def _outputs(self, type_number: int, method: str) -> tuple[Arg, ...]:
        return next(m.outputs for m in mvm.METHODS[type_number] if m.name == method)

    def _refused(self, type_number: int, method: str, error: int) -> list[ua.Variant]:
        return [*self._blank(self._outputs(type_number, method)), ua.Variant(error, I32)]

    @staticmethod
    def _id(value: Any) -> str:
        """The ``Id`` of one of the standard's id structures (empty when none was given)."""
        return str(getattr(value, "Id", "") or "")

    async def _halt(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        return await self.mv.halt(parent)

    async def _reset(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        return await self.mv.reset(parent)

    async def _select_automatic(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        return await self.mv.select_automatic(parent)

    async def _stop(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        return await self.mv.stop(parent)

    async def _start_single(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        return await self._start(SINGLE, args)

    async def _start_continuous(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        return await self._start(CONTINUOUS, args)

    async def _start(self, kind: str, args: tuple[Any, ...]) -> list[ua.Variant]:
        """A job with the prepared recipe, or with ``RecipeId`` prepared first; its MeasId,
        PartId, RecipeId and ProductId are kept for its result."""
        meas, part, recipe, product = self.mv.opc.method_args(args, 5)[:4]
        out = await self.mv.start_job(kind, (self._id(meas), self._id(part), self._id(recipe),
                                              self._id(product)))
        job_id = str(out[0].Value)
        if self._error(out) == 0:
            self.started[job_id] = (meas, part, recipe, product)
        return [ua.Variant(self.model.new("JobIdDataType", Id=job_id), EXT), out[-1]]

    def _internal_id(self, text: str) -> Any:
        return self.model.new("RecipeIdInternalDataType", Id=text)

    async def _add_recipe(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        """A recipe the cell has, by its name or number: its internal id; the content of a new
        one comes through the cell's own doors, so an unknown one is refused."""
        external, _ = self.mv.opc.method_args(args, 2)
        name = self._id(external)
        match = next((f"{r.name}@{r.version}" for r in await self._off_loop(
                          self.mv.opc.cell.recipes.list)
                      if name and name in (r.name, str(r.number))), None)
        if match is None:
            return self._refused(mvm.RECIPE_MANAGEMENT_TYPE, "AddRecipe",
                                 error_number("recipe_not_found", "not_found"))
        return [ua.Variant(self._internal_id(match), EXT),
                ua.Variant(ua.NodeId(), ua.VariantType.NodeId),
                ua.Variant(ua.NodeId(), ua.VariantType.NodeId),
                ua.Variant(False, ua.VariantType.Boolean), ua.Variant(0, I32)]

    async def _list_recipes(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        external, _, is_prepared, max_results, start, _ = self.mv.opc.method_args(args, 6)
        wanted = self._id(external)
        recipes = [r for r in await self._off_loop(self.mv.opc.cell.recipes.list)
                   if not wanted or wanted in (r.name, str(r.number))]
        if is_prepared in (0, 1):
            recipes = [r for r in recipes if (r.name == self.mv.prepared) == bool(is_prepared)]
        ids = [self._internal_id(f"{r.name}@{r.version}") for r in recipes]
        page = _page(ids, start, max_results)
        return [ua.Variant(len(page) + int(start or 0) >= len(ids), ua.VariantType.Boolean),
                ua.Variant(len(page), ua.VariantType.UInt32),
                ua.Variant(0, ua.VariantType.UInt32), ua.Variant(page, EXT),
                ua.Variant(0, I32)]

    async def prepare_recipe(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        external, internal = self.mv.opc.method_args(args, 2)
        ref = self._id(external) or self._id(internal).split("@")[0]
        out = await self.mv.prepare_recipe(parent, ref)
        return [ua.Variant(self._internal_id(str(out[0].Value)), EXT),
                ua.Variant(self._error(out) == 0, ua.VariantType.Boolean), out[-1]]

    async def unprepare_recipe(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        external, internal = self.mv.opc.method_args(args, 2)
        ref = self._id(external) or self._id(internal).split("@")[0]
        before = self.mv.prepared
        out = await self.mv.unprepare_recipe(parent, ref)
        return [ua.Variant(self._internal_id(before if self._error(out) == 0 else ""), EXT),
                out[-1]]

    async def remove_recipe(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        (external,) = self.mv.opc.method_args(args, 1)
        return await self.mv.remove_recipe(parent, self._id(external))

    async def _activate_configuration(self, parent: ua.NodeId, *args: Any
                                      ) -> list[ua.Variant]:
        """The active configuration is the only one: activating it is done, any other is
        not found (a calibration is applied through the cell's own doors)."""
        (internal,) = self.mv.opc.method_args(args, 1)
        found = self._id(internal) == self._configuration.InternalId.Id
        return [ua.Variant(0 if found else error_number("not_found", "not_found"), I32)]

    async def _get_configuration(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        internal, _ = self.mv.opc.method_args(args, 2)
        if self._id(internal) != self._configuration.InternalId.Id:
            return self._refused(mvm.CONFIGURATION_MANAGEMENT_TYPE, "GetConfigurationById",
                                 error_number("not_found", "not_found"))
        return [ua.Variant(0, ua.VariantType.UInt32), ua.Variant(self._configuration, EXT),
                ua.Variant(0, I32)]

    async def _list_configurations(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        max_results, start, _ = self.mv.opc.method_args(args, 3)
        page = _page([self._configuration], start, max_results)
        return [ua.Variant(True, ua.VariantType.Boolean),
                ua.Variant(len(page), ua.VariantType.UInt32),
                ua.Variant(0, ua.VariantType.UInt32), ua.Variant(page, EXT), ua.Variant(0, I32)]

    def _found(self, args: tuple[Any, ...], method: str) -> tuple[Any, list[ua.Variant]]:
        result_id, _ = self.mv.opc.method_args(args, 2)
        result = self.results.get(self._id(result_id))
        if result is None:
            return None, self._refused(mvm.RESULT_MANAGEMENT_TYPE, method, error_number(
                "result_not_found", "not_found"))
        return result, []

    async def _get_result(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        result, refused = self._found(args, "GetResultById")
        if result is None:
            return refused
        return [ua.Variant(0, ua.VariantType.UInt32), ua.Variant(result, EXT), ua.Variant(0, I32)]

    async def _get_components(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        result, refused = self._found(args, "GetResultComponentsById")
        if result is None:
            return refused
        blanks = self._blank(self._outputs(mvm.RESULT_MANAGEMENT_TYPE,
                                           "GetResultComponentsById"))
        names = [a[0] for a in self._outputs(mvm.RESULT_MANAGEMENT_TYPE,
                                             "GetResultComponentsById")[:-1]]
        out: list[ua.Variant] = []
        for name, blank in zip(names, blanks, strict=True):
            value = getattr(result, name, None) if name != "ResultHandle" else None
            if name == "ResultContent":
                out.append(ua.Variant(list(value or []), ua.VariantType.Variant))
            elif value is None:
                out.append(blank)
            else:
                out.append(ua.Variant(value, blank.VariantType))
        return [*out, ua.Variant(0, I32)]

    async def _list_results(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        """The kept results (newest first) matching every given filter: an id structure with
        an empty ``Id`` and a ``ResultState`` of 0 match any."""
        values = self.mv.opc.method_args(args, 12)
        state, filters, (max_results, start) = values[0], values[1:9], values[9:11]
        names = ("MeasId", "PartId", "ExternalRecipeId", "InternalRecipeId",
                 "ExternalConfigurationId", "InternalConfigurationId", "ProductId", "JobId")
        wanted = {n: self._id(v) for n, v in zip(names, filters, strict=True) if self._id(v)}
        found = [r for r in reversed(self.results.values())
                 if (not state or r.ResultState == state)
                 and all(self._id(getattr(r, n)) == v for n, v in wanted.items())]
        page = _page(found, start, max_results)
        return [ua.Variant(len(page) + int(start or 0) >= len(found), ua.VariantType.Boolean),
                ua.Variant(len(page), ua.VariantType.UInt32),
                ua.Variant(0, ua.VariantType.UInt32), ua.Variant(page, EXT), ua.Variant(0, I32)]

    async def _release_handle(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        """No handles are handed out (every list is answered whole): nothing to release."""
        return [ua.Variant(0, I32)]


def _page(items: list[Any], start: Any, max_results: Any) -> list[Any]:
    first = int(start or 0)
    return items[first:first + int(max_results)] if max_results else items[first:]


def _acquisition_s(result: object) -> float | None:
    """The seconds of the job's first locate: a pick's locate phase, an approach's first
    locate."""
    if isinstance(result, PickResult):
        return result.phases_s.get("locate")
    if isinstance(result, ApproachBase):
        return result.first_locate_s
    return None


def _null(dtype: int | ua.NodeId, name: str) -> ua.Variant:
    """An empty output of a built-in type."""
    kinds = {ua.ObjectIds.Boolean: (False, ua.VariantType.Boolean),
             ua.ObjectIds.UInt32: (0, ua.VariantType.UInt32),
             ua.ObjectIds.Int32: (0, I32),
             ua.ObjectIds.UtcTime: (ua.get_win_epoch(), ua.VariantType.DateTime),
             ua.ObjectIds.NodeId: (ua.NodeId(), ua.VariantType.NodeId),
             ua.ObjectIds.BaseDataType: ([], ua.VariantType.Variant)}
    assert isinstance(dtype, ua.NodeId), name
    value, vtype = kinds[int(dtype.Identifier)]
    return ua.Variant(value, vtype)
