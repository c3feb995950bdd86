"""The OPC UA Machine Vision subset (OPC 40100-1) a guided-robot cell fits, next to ``Cell``.

The behaviour of the vision system (its state machines, the prepared recipe, the results) and
its first face: an object in the cell's namespace with the standard's browse names, the id data
types of the standard carried as strings, every method answering the standard's ``Error``
(Int32, 0: done) last. The same behaviour in the standard's namespace, NodeIds and structured
data types, for a generic OPC 40100 client, is :mod:`api.plc.opcua_vision_system` (a
:class:`Facet`, told of every state change and result):

- ``VisionSystem/VisionStateMachine``: ``CurrentState`` (Preoperational, Halted, Error,
  Operational), the methods ``SelectModeAutomatic``, ``Halt`` (stops the arm), ``Reset``, and
  the sub-machine ``VisionAutomaticModeStateMachine`` with ``CurrentState`` (Initialized,
  Ready, SingleExecution, ContinuousExecution), ``StartSingleJob(MeasId, PartId, RecipeId,
  ProductId)`` -> ``JobId`` (an approach, or a pick), ``StartContinuousJob`` (same arguments;
  tracking until stopped), ``Stop``, ``Abort``;
- ``VisionSystem/RecipeManagement``: ``AddRecipe(ExternalId, ProductId, Content)`` ->
  ``InternalId``, ``PrepareRecipe(ExternalId)`` -> ``InternalId``, ``UnprepareRecipe``,
  ``RemoveRecipe``, ``GetRecipeListFiltered`` -> ``RecipeIds``, and ``PreparedRecipe``;
- ``VisionSystem/ResultManagement``: ``GetResultById(ResultId)`` -> ``Result`` (JSON), and the
  last result's ``ResultId``, ``JobId``, ``RecipeId``, ``Result``.

A single job is an approach with the prepared recipe (its target, taught pose, standoff, mode),
or a pick when the recipe's target says ``job: "pick"`` (placed at its ``place``, a pose taught
in the base frame; none: kept in the gripper); its result (``ResultId`` = ``r-<JobId>``) carries
the JobId, the job's kind, the recipe and its version, the located pose, the job's error and,
for a pick, the part taken, the grip, where the part should end and each phase's seconds. A
continuous job is tracking with the prepared recipe (its target, taught pose, standoff) for up
to ``[servo] max_track_s``: ContinuousExecution while it runs, Ready again when it ends (Stop,
Abort, a lost target, the time cap). The error numbers are those of the Modbus table
(:data:`api.plc.modbus.ERROR_NUMBERS`), so both PLC doors speak the same numbers.

The selected mode and the prepared recipe survive a restart
(:mod:`api.plc.machine_vision_memory`): the system starts Preoperational with the remembered recipe
prepared again, and enters Operational (Initialized, or Ready with the recipe) by itself once
the arm and the camera are connected, if automatic mode was the last choice.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Callable
from concurrent.futures import Executor
from typing import Any, Protocol

from asyncua import Server, ua

from api import remote
from api.plc.machine_vision_memory import MachineVisionMemory, Remembered
from api.plc.modbus import UNKNOWN_ERROR, error_number
from api.remote import RemoteCaller
from cell.error_codes import ErrorCode
from cell.errors import CellError, NotFoundError, RefusedError
from cell.features.recipes import parse_spec
from cell.jobs.store import Job
from cell.results.jobs import located_pose
from cell.results.pick import PickResult
from cell.results.pose import Pose
from cell.service import Cell


class OpcHost(Protocol):
    """What the Machine Vision object needs of the OPC UA server it lives in (the server in
    :mod:`api.plc.opcua` is one); naming only this keeps the two modules from importing each
    other."""

    @property
    def cell(self) -> Cell: ...

    @property
    def calls(self) -> Executor: ...

    async def write_nodes(self, values: dict[Any, ua.Variant]) -> list[bool]: ...

    async def show_started(self, job_id: str) -> None: ...

    def ended_job(self, job_id: str) -> Job | None: ...

    def current_caller(self) -> RemoteCaller | None: ...

    def method_args(self, args: tuple[Any, ...], n: int) -> list[Any]: ...

    def pose_struct(self, pose: Pose) -> Any: ...


class Facet(Protocol):
    """Another object that shows this behaviour (the standard's ``VisionSystem``): told of
    every state change, of every job's end and of every calibration applied."""

    async def show(self) -> None: ...

    async def result(self, job: dict[str, Any]) -> None: ...

    async def configuration_changed(self) -> None: ...


log = logging.getLogger(__name__)

PREOPERATIONAL, HALTED, ERROR, OPERATIONAL = "Preoperational", "Halted", "Error", "Operational"
INITIALIZED, READY, SINGLE, CONTINUOUS = ("Initialized", "Ready", "SingleExecution",
                                          "ContinuousExecution")
MAX_RESULTS = 100  # kept for GetResultById
ARM_FAULTS = ("protective_stop", "emergency_stop")


def _arg(name: str, vtype: ua.VariantType, description: str, array: bool = False
         ) -> ua.Argument:
    a = ua.Argument()
    a.Name = name
    a.DataType = ua.NodeId(ua.Int32(vtype.value))
    a.ValueRank = 1 if array else -1
    a.ArrayDimensions = [0] if array else []
    a.Description = ua.LocalizedText(description)
    return a


S, I32 = ua.VariantType.String, ua.VariantType.Int32
ERROR_OUT = _arg("Error", I32, "0: done; else the cell's error number (docs/plc.md)")


def _pick_summary(result: object) -> dict[str, Any] | None:
    """What a PLC reads of a pick in its Machine Vision result: the part taken, the grip,
    where the part should end, each phase's seconds; None for any other job."""
    if not isinstance(result, PickResult):
        return None
    out = result.json_dict()
    return {k: out[k] for k in ("part", "grip", "place", "phases_s", "cycle_s")}


class MachineVision:
    """The VisionSystem object, its state machines and its recipe and result management."""

    def __init__(self, opc: OpcHost, server: Server, idx: int) -> None:
        self.opc = opc
        self.server = server
        self.idx = idx
        self.state = PREOPERATIONAL
        self.sub_state = ""
        self.prepared: str = ""  # the prepared recipe's name
        self.running_job = ""
        self.results: dict[str, dict[str, Any]] = {}
        self._nodes: dict[str, Any] = {}
        self.facets: list[Facet] = []
        self.automatic = False  # automatic mode was selected (and not halted or reset since)
        self.memory = MachineVisionMemory.beside_job_db(opc.cell.config.api.job_db)
        remembered = self.memory.load()
        self._resume_automatic = remembered.automatic  # once the arm and camera are up
        if remembered.prepared:
            self._prepare_again(remembered.prepared)

    def _prepare_again(self, name: str) -> None:
        """The remembered recipe, prepared again (its layout loaded); gone: none prepared."""
        try:
            recipe, _ = remote.prepare_recipe(self.opc.cell, name)
            self.prepared = recipe.name
        except CellError as err:
            log.warning("the remembered recipe %r cannot be prepared again (%s): none is "
                        "prepared", name, err)

    def _remember(self) -> None:
        """Writes the mode and the prepared recipe for the next start (after each change)."""
        self.memory.save(Remembered(self.automatic, self.prepared))

    # -- the address space ----------------------------------------------------------------------
    async def build(self) -> None:
        idx = self.idx
        vs = await self.server.nodes.objects.add_object(idx, "VisionSystem")
        sm = await vs.add_object(idx, "VisionStateMachine")
        auto = await sm.add_object(idx, "VisionAutomaticModeStateMachine")
        recipes = await vs.add_object(idx, "RecipeManagement")
        results = await vs.add_object(idx, "ResultManagement")
        for key, parent, name, value in (
                ("state", sm, "CurrentState", ua.LocalizedText(self.state)),
                ("sub_state", auto, "CurrentState", ua.LocalizedText("")),
                ("prepared", recipes, "PreparedRecipe", ""),
                ("result_id", results, "ResultId", ""), ("result_job", results, "JobId", ""),
                ("result_recipe", results, "RecipeId", ""), ("result", results, "Result", "{}")):
            self._nodes[key] = await parent.add_variable(idx, name, value)
        methods: list[tuple[Any, str, Callable[..., Any], list[ua.Argument],
                            list[ua.Argument]]] = [
            (sm, "SelectModeAutomatic", self.select_automatic, [], [ERROR_OUT]),
            (sm, "Halt", self.halt, [], [ERROR_OUT]),
            (sm, "Reset", self.reset, [], [ERROR_OUT]),
            (auto, "StartSingleJob", self._start_single_job, [
                _arg("MeasId", S, "the PLC's measurement id (kept in the result)"),
                _arg("PartId", S, "the part's id (kept in the result)"),
                _arg("RecipeId", S, "empty: the prepared recipe; else one to prepare first"),
                _arg("ProductId", S, "the product's id (kept in the result)")],
             [_arg("JobId", S, "the job started"), ERROR_OUT]),
            (auto, "StartContinuousJob", self._start_continuous_job, [
                _arg("MeasId", S, "the PLC's measurement id (kept in the result)"),
                _arg("PartId", S, "the part's id (kept in the result)"),
                _arg("RecipeId", S, "empty: the prepared recipe; else one to prepare first"),
                _arg("ProductId", S, "the product's id (kept in the result)")],
             [_arg("JobId", S, "the tracking job started"), ERROR_OUT]),
            (auto, "Stop", self.stop, [], [ERROR_OUT]),
            (auto, "Abort", self.stop, [], [ERROR_OUT]),
            (recipes, "AddRecipe", self._add_recipe, [
                _arg("ExternalId", S, "the recipe's name"),
                _arg("ProductId", S, "the recipe number (1..65535)"),
                _arg("Content", S, "the recipe as JSON (targets, ...; see docs/plc.md)")],
             [_arg("InternalId", S, "name@version"), ERROR_OUT]),
            (recipes, "PrepareRecipe", self.prepare_recipe, [
                _arg("ExternalId", S, "the recipe's name or number")],
             [_arg("InternalId", S, "name@version"), ERROR_OUT]),
            (recipes, "UnprepareRecipe", self.unprepare_recipe, [
                _arg("ExternalId", S, "the prepared recipe's name")], [ERROR_OUT]),
            (recipes, "RemoveRecipe", self.remove_recipe, [
                _arg("ExternalId", S, "the recipe's name")], [ERROR_OUT]),
            (recipes, "GetRecipeListFiltered", self._list_recipes, [],
             [_arg("RecipeIds", S, "name@version of every recipe", array=True), ERROR_OUT]),
            (results, "GetResultById", self._get_result, [
                _arg("ResultId", S, "a result's id")],
             [_arg("Result", S, "the result as JSON"), ERROR_OUT]),
        ]
        for parent, name, func, inputs, outputs in methods:
            await parent.add_method(idx, name, func, inputs, outputs)

    async def _show(self) -> None:
        await self._nodes["state"].write_value(ua.LocalizedText(self.state))
        await self._nodes["sub_state"].write_value(ua.LocalizedText(self.sub_state))
        await self._nodes["prepared"].write_value(self.prepared)
        for facet in self.facets:
            await facet.show()

    async def calibration_applied(self) -> None:
        """A hand-eye calibration was applied: the faces that show it as a configuration."""
        for facet in self.facets:
            await facet.configuration_changed()

    async def update(self, status: dict[str, Any], job: dict[str, Any] | None) -> None:
        """Follows the cell: automatic mode resumes once the devices are up after a restart;
        an arm fault is Error; a single or continuous job's end is its result."""
        robot = status.get("robot", {})
        if self._resume_automatic and self.state == PREOPERATIONAL \
                and robot.get("connected") and (status.get("camera") or {}).get("connected"):
            self._resume_automatic = False
            self.automatic, self.state = True, OPERATIONAL
            self.sub_state = READY if self.prepared else INITIALIZED
            log.info("the vision system resumed automatic mode (%s)", self.sub_state)
        fault = bool(robot.get("protective_stop")) \
            or "EMERGENCY_STOP" in str(robot.get("safety", ""))
        if fault and self.state == OPERATIONAL:
            self.state, self.sub_state = ERROR, ""
        ended = job if job is not None and job["id"] == self.running_job \
            and job.get("ended_at") else None
        if ended is not None:
            await self._result(ended)
            self.running_job = ""
            if self.state == OPERATIONAL:
                self.sub_state = READY if self.prepared else INITIALIZED
        await self._show()
        if ended is not None:  # the other faces once this one shows the result and the state
            for facet in self.facets:
                await facet.result(ended)

    async def _result(self, job: dict[str, Any]) -> None:
        params = job.get("params") or {}
        error = job.get("error") or {}
        result_id = f"r-{job['id']}"
        record = self.opc.ended_job(job["id"])
        located = None if record is None else located_pose(record.result)
        recipe = params.get("recipe") or {}
        body = {"result_id": result_id, "job_id": job["id"], "kind": job["kind"],
                "state": job["state"], "recipe": recipe, "meas_id": params.get("meas_id", ""),
                "located": None if located is None else located.json_dict(),
                "error": error.get("code") or "", "error_number":
                    error_number(error["code"]) if error.get("code") else 0,
                "message": error.get("message") or "",
                "pick": None if record is None else _pick_summary(record.result)}
        self.results[result_id] = body
        while len(self.results) > MAX_RESULTS:
            self.results.pop(next(iter(self.results)))
        recipe_id = f"{recipe.get('name', '')}@{recipe.get('version', '')}" if recipe else ""
        # the result's id and the job's id are written together with it
        await self.opc.write_nodes({
            self._nodes["result_id"]: ua.Variant(result_id, S),
            self._nodes["result_job"]: ua.Variant(job["id"], S),
            self._nodes["result_recipe"]: ua.Variant(recipe_id, S),
            self._nodes["result"]: ua.Variant(json.dumps(body, default=str), S)})

    # -- calls ----------------------------------------------------------------------------------
    async def _change_state(self, work: Callable[[RemoteCaller], list[ua.Variant]]
                            ) -> list[ua.Variant]:
        """A state-machine method without outputs: ``work`` changes the state, then the
        state variables show it, whether the call was taken or refused."""
        out = await self._call(work, [])
        await self._show()
        return out

    async def _call(self, work: Callable[[RemoteCaller], list[ua.Variant]],
                    blanks: list[ua.Variant]) -> list[ua.Variant]:
        """The outputs then ``Error``; a refusal is blanks and its error number."""
        caller = self.opc.current_caller()
        if caller is None:
            return [*blanks, ua.Variant(error_number("unauthorized", "forbidden"), I32)]
        try:
            out = await asyncio.get_running_loop().run_in_executor(self.opc.calls, work,
                                                                   caller)
            return [*out, ua.Variant(0, I32)]
        except CellError as err:
            return [*blanks, ua.Variant(error_number(err.code, err.kind), I32)]
        except Exception:
            log.exception("Machine Vision call failed")
            return [*blanks, ua.Variant(UNKNOWN_ERROR, I32)]

    def _need(self, *states: str) -> None:
        if self.state not in states:
            raise RefusedError(ErrorCode.not_ready,
                               f"the vision system is {self.state}; this needs "
                               f"{' or '.join(states)}")

    async def select_automatic(self, parent: ua.NodeId) -> list[ua.Variant]:
        def work(caller: RemoteCaller) -> list[ua.Variant]:
            remote.require(self.opc.cell, caller, "approach", "select_mode_automatic", {})
            self._need(PREOPERATIONAL, OPERATIONAL)
            if self.state == PREOPERATIONAL:
                self.sub_state = READY if self.prepared else INITIALIZED
            self.state, self.automatic, self._resume_automatic = OPERATIONAL, True, False
            self._remember()
            return []

        return await self._change_state(work)

    async def halt(self, parent: ua.NodeId) -> list[ua.Variant]:
        def work(caller: RemoteCaller) -> list[ua.Variant]:
            remote.stop(self.opc.cell, caller)
            self.state, self.sub_state = HALTED, ""
            self.automatic = self._resume_automatic = False
            self._remember()
            return []

        return await self._change_state(work)

    async def reset(self, parent: ua.NodeId) -> list[ua.Variant]:
        def work(caller: RemoteCaller) -> list[ua.Variant]:
            remote.require(self.opc.cell, caller, "recover", "reset", {})
            self._need(HALTED, ERROR, PREOPERATIONAL)
            self.state, self.sub_state = PREOPERATIONAL, ""
            self.automatic = self._resume_automatic = False
            self._remember()
            return []

        return await self._change_state(work)

    async def stop(self, parent: ua.NodeId) -> list[ua.Variant]:
        def work(caller: RemoteCaller) -> list[ua.Variant]:
            remote.stop(self.opc.cell, caller)
            return []

        return await self._call(work, [])

    async def _start_single_job(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        return await self.start_job(SINGLE, args)

    async def _start_continuous_job(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        return await self.start_job(CONTINUOUS, args)

    async def start_job(self, kind: str, args: tuple[Any, ...]) -> list[ua.Variant]:
        """A single job (an approach) or a continuous one (tracking until stopped) with the
        prepared recipe, or with ``RecipeId`` prepared first."""
        meas_id, part_id, recipe_id, product_id = self.opc.method_args(args, 4)

        def work(caller: RemoteCaller) -> list[ua.Variant]:
            self._need(OPERATIONAL)
            if self.sub_state in (SINGLE, CONTINUOUS):
                raise RefusedError(ErrorCode.busy, f"the vision system is in {self.sub_state}")
            if recipe_id:
                recipe, _ = remote.prepare_recipe(self.opc.cell, remote.recipe_ref(recipe_id))
                if recipe.name != self.prepared:
                    self.prepared = recipe.name
                    self._remember()
            if not self.prepared:
                raise RefusedError(ErrorCode.not_ready,
                                   "no recipe is prepared: PrepareRecipe first")
            job = self._single_job(caller) if kind == SINGLE \
                else remote.track_recipe(self.opc.cell, caller, self.prepared)
            self.running_job, self.sub_state = job.id, kind
            log.info("%s job %s (meas %s, part %s, product %s)", kind, job.id, meas_id,
                     part_id, product_id)
            return [ua.Variant(job.id, S)]

        out = await self._call(work, [ua.Variant("", S)])
        if out[-1].Value == 0:
            await self.opc.show_started(str(out[0].Value))
        await self._show()
        return out

    def _single_job(self, caller: RemoteCaller) -> Job:
        """The prepared recipe's single job: an approach of its target, or a pick of it when
        the target's ``job`` is ``pick`` (placed at the target's ``place``)."""
        _, chosen = remote.find_recipe(self.opc.cell, self.prepared)
        if chosen.job == "pick":
            return remote.pick(self.opc.cell, caller, self.prepared, chosen.name, chosen.place)
        return remote.approach_recipe(self.opc.cell, caller, self.prepared)

    async def _add_recipe(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        external_id, product_id, content = self.opc.method_args(args, 3)

        def work(caller: RemoteCaller) -> list[ua.Variant]:
            remote.require(self.opc.cell, caller, "edit_recipes", "add_recipe",
                           {"name": external_id})
            try:
                data = json.loads(str(content or "{}"))
            except ValueError as err:
                raise remote.LimitError(ErrorCode.invalid_recipe,
                                        f"Content is not JSON: {err}") from err
            if not isinstance(data, dict):
                raise remote.LimitError(ErrorCode.invalid_recipe, "Content must be a JSON object")
            data.setdefault("name", external_id)
            if product_id:
                data.setdefault("number", int(product_id) if str(product_id).isdigit()
                                else product_id)
            recipe = self.opc.cell.recipes.save(parse_spec(data), caller.label)
            return [ua.Variant(f"{recipe.name}@{recipe.version}", S)]

        return await self._call(work, [ua.Variant("", S)])

    async def prepare_recipe(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        (external_id,) = self.opc.method_args(args, 1)

        def work(caller: RemoteCaller) -> list[ua.Variant]:
            remote.require(self.opc.cell, caller, "approach", "prepare_recipe",
                           {"recipe": external_id})
            recipe, _ = remote.prepare_recipe(self.opc.cell, remote.recipe_ref(external_id))
            self.prepared = recipe.name
            if self.state == OPERATIONAL and self.sub_state == INITIALIZED:
                self.sub_state = READY
            self._remember()
            return [ua.Variant(f"{recipe.name}@{recipe.version}", S)]

        out = await self._call(work, [ua.Variant("", S)])
        await self._show()
        return out

    async def unprepare_recipe(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        (external_id,) = self.opc.method_args(args, 1)

        def work(caller: RemoteCaller) -> list[ua.Variant]:
            if external_id not in ("", self.prepared):
                raise NotFoundError(ErrorCode.recipe_not_found,
                                    f"recipe {external_id!r} is not prepared")
            self.prepared = ""
            if self.state == OPERATIONAL and self.sub_state == READY:
                self.sub_state = INITIALIZED
            self._remember()
            return []

        return await self._change_state(work)

    async def remove_recipe(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        (external_id,) = self.opc.method_args(args, 1)

        def work(caller: RemoteCaller) -> list[ua.Variant]:
            remote.require(self.opc.cell, caller, "edit_recipes", "remove_recipe",
                           {"name": external_id})
            if external_id == self.prepared:
                raise RefusedError(ErrorCode.recipe_prepared, "UnprepareRecipe first")
            self.opc.cell.recipes.delete(remote.text("ExternalId", external_id))
            return []

        return await self._call(work, [])

    async def _list_recipes(self, parent: ua.NodeId) -> list[ua.Variant]:
        def work(caller: RemoteCaller) -> list[ua.Variant]:
            ids = [f"{r.name}@{r.version}" for r in self.opc.cell.recipes.list()]
            return [ua.Variant(ids, S)]

        return await self._call(work, [ua.Variant([], S)])

    async def _get_result(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        (result_id,) = self.opc.method_args(args, 1)
        body = self.results.get(str(result_id or ""))
        if body is None:
            return [ua.Variant("", S), ua.Variant(error_number("result_not_found", "not_found"),
                                                 I32)]
        return [ua.Variant(json.dumps(body, default=str), S), ua.Variant(0, I32)]
