"""Recipes (products) over HTTP: list, versions, save (a new version), delete, and an approach
with a recipe's target (a job that records the recipe and its version).

Saving and deleting change what later jobs do: the ``edit_recipes`` permission (operators), as
teaching. An approach with a recipe needs the approach permission (operator, PLC). The store
is the cell's (``Cell.recipes``, :mod:`cell.features.recipes`), the one OPC UA and Modbus use.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request
from pydantic import BaseModel, ConfigDict, Field

from api import remote
from api.auth import Caller, require
from api.http.errors import ERROR_RESPONSES
from api.http.schemas import Flag, Job, Num
from api.remote import RemoteCaller
from cell.actions.approach_rules import MAX_STANDOFF_MM
from cell.features.recipes import EXAMPLE, Recipe, RecipeSpec
from cell.service import Cell

router = APIRouter(prefix="/api/v1", tags=["recipes"], responses=ERROR_RESPONSES)


class RecipeApproachRequest(BaseModel):
    """The options of ``/approach`` that make sense with a recipe (its target gives the
    layout, the taught pose and the mode), under the same rules."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    target: str = Field(default="", description="the recipe's target (empty: its first)")
    standoff_mm: Num | None = Field(default=None, ge=0, le=MAX_STANDOFF_MM,
                                    description="default: the target's standoff")
    speed_mm_s: Num | None = Field(default=None, gt=0, le=2000, description="default: the "
                                   "target's speed; within [limits] like any approach")
    use_last_locate: Flag = Field(
        default=False, description="start from the last /locate result instead of locating "
        "again (refused when older than limits.max_pose_age_s, or when it was of another "
        "dot layout)")
    wait: Flag = Field(default=False, description="as /approach: true answers when the job "
                       "has ended, whatever its end state")


class RecipeList(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{"recipes": [EXAMPLE]}]})

    recipes: list[Recipe] = Field(description="the newest version of every recipe, by number")


class RecipeVersions(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{"versions": [EXAMPLE]}]})

    versions: list[Recipe] = Field(description="every stored version, oldest first")


def _remote(caller: Caller) -> RemoteCaller:
    return RemoteCaller("http", caller.name or caller.role, caller.role)


@router.get("/recipes", response_model=RecipeList)
def list_recipes(request: Request,
                 caller: Annotated[Caller, Depends(require("read"))]) -> dict[str, Any]:
    """The newest version of every recipe, by number."""
    cell: Cell = request.app.state.cell
    return {"recipes": [r.model_dump() for r in cell.recipes.list()]}


@router.get("/recipes/{name}", response_model=RecipeVersions)
def recipe_versions(request: Request, name: str,
                    caller: Annotated[Caller, Depends(require("read"))]) -> dict[str, Any]:
    """Every stored version of one recipe, oldest first."""
    cell: Cell = request.app.state.cell
    return {"versions": [r.model_dump() for r in cell.recipes.versions(name)]}


@router.put("/recipes", response_model=Recipe)
def save_recipe(request: Request, body: RecipeSpec,
                caller: Annotated[Caller, Depends(require("read"))]) -> dict[str, Any]:
    """Save a recipe as its next version (version 1 for a new name); operators only. A recipe
    no job could run is refused (422 ``invalid_standoff`` or ``speed_limit`` against
    ``[limits]``, naming the field, e.g. ``targets.0.speed_mm_s``)."""
    cell: Cell = request.app.state.cell
    rc = _remote(caller)
    remote.require(cell, rc, "edit_recipes", "save_recipe", {"name": body.name})
    with remote.audited(cell, rc, "save_recipe", {"name": body.name}) as note:
        recipe = cell.recipes.save(body, caller.label)
        note.detail = f"version {recipe.version}"
    return recipe.model_dump()


@router.delete("/recipes/{name}", response_model=Recipe)
def delete_recipe(request: Request, name: str,
                  caller: Annotated[Caller, Depends(require("read"))]) -> dict[str, Any]:
    """Remove a recipe and its history (jobs keep their record of it); operators only."""
    cell: Cell = request.app.state.cell
    rc = _remote(caller)
    remote.require(cell, rc, "edit_recipes", "delete_recipe", {"name": name})
    with remote.audited(cell, rc, "delete_recipe", {"name": name}):
        return cell.recipes.delete(name).model_dump()


@router.post("/recipes/{ref}/approach", response_model=Job)
def approach_recipe(request: Request, ref: str, body: RecipeApproachRequest,
                    caller: Annotated[Caller, Depends(require("approach"))]) -> dict[str, Any]:
    """An approach job with the recipe's target (name or number): its dot layout, taught
    pose, standoff, mode and speed; the job records the recipe, version and target. The
    layout is looked for during the job only; a refusal changes nothing. ``wait`` as for
    ``/approach``."""
    cell: Cell = request.app.state.cell
    job = remote.approach_recipe(cell, _remote(caller), ref, body.target, body.standoff_mm,
                                 speed_mm_s=body.speed_mm_s,
                                 use_last_locate=body.use_last_locate, wait=body.wait)
    return job.as_dict()
