"""Recipes (products): what a PLC selects per job instead of sending poses and numbers.

A recipe has a number (what a Modbus PLC writes into its recipe register), a name, and one or
more targets. Each target is a dot layout (centres in mm, dot diameter, dark or light dots) with
the taught tool pose to approach it with (a name in the taught-pose store; empty: the
configured ``[approach] T_target_tcp``), the standoff, the approach mode and its limits (speed,
largest reprojection error accepted), and what a Machine Vision single job does with it
(``job``: approach it, or pick it and put it at the base-frame pose taught as ``place``).
Saving a recipe again makes a new version; every version is kept, so a job's record (recipe
name, number, version, target) says exactly what it ran with, even after the recipe was
changed. One JSON file beside the job database, replaced
atomically; an unreadable file refuses recipe jobs and is never overwritten.

Numbers are numbers (an integer is fine for a float; a string or a boolean is refused) and a
recipe no job could run is refused when it is saved, by the rules an approach checks
(:mod:`cell.actions.approach_rules`: the standoff's range, the configured ``[limits]`` speeds),
with the field named (``targets.0.speed_mm_s``).
"""

from __future__ import annotations

import builtins
import json
import threading
import time
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    Strict,
    ValidationError,
    field_validator,
    model_validator,
)

from cell.actions.approach_rules import check_speed, check_standoff
from cell.config.schema import DotLayout, LimitsConfig
from cell.error_codes import ErrorCode
from cell.errors import CellError, LimitError, NotFoundError, RefusedError
from cell.files import replace_text
from cell.results.modes import ApproachMode, PoseMode

STORE_NAME = "recipes.json"
FORMAT_VERSION = 1
MAX_RECIPE_NUMBER = 65535  # one Modbus register
EXAMPLE: dict[str, Any] = {
    "name": "plate-a", "number": 3, "description": "4-dot plate, dark dots",
    "targets": [{"name": "main", "points_mm": [[0, 0, 0], [40, 0, 0], [0, 30, 0], [40, 30, 0]],
                 "dot_diameter_mm": 6.0, "polarity": "dark", "taught": "",
                 "standoff_mm": 50.0, "mode": "look_and_move", "speed_mm_s": 150.0}],
    "version": 2, "saved_by": "http:operator(operator)", "saved_at": 1760000000.0}


class RecipeStoreError(CellError):
    """The recipe file cannot be read or written; nothing was changed."""

    kind = "unavailable"


Num = Annotated[float, Strict()]  # a JSON number: no strings, no booleans


class RecipeTarget(DotLayout):
    """One target of a product: its dot layout and how the cell approaches it."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    points_mm: list[tuple[Num, Num, Num]] = Field(min_length=4, max_length=100)
    dot_diameter_mm: Num = Field(gt=0)
    name: str = Field(default="main", min_length=1, max_length=64)
    taught: str = ""  # a taught pose's name; "" uses [approach] T_target_tcp
    standoff_mm: Num = Field(default=50.0, ge=0)
    mode: PoseMode = ApproachMode.look_and_move
    speed_mm_s: Num = Field(default=150.0, gt=0)
    # a pick's own values (None: the configured [pick] one)
    grasp_speed_mm_s: Num | None = Field(default=None, gt=0)
    retract_mm: Num | None = Field(default=None, ge=0, le=500)
    grip_min_mm: Num | None = Field(default=None, ge=0)
    grip_max_mm: Num | None = Field(default=None, gt=0)
    retract_taught: str = ""  # a base-frame pose the pick's retract ends at ("": none)
    # what a Machine Vision StartSingleJob runs with this target; a pick's place pose is one
    # taught in the base frame ("": the part stays in the gripper)
    job: Literal["approach", "pick"] = "approach"
    place: str = Field(default="", max_length=64)

    @model_validator(mode="after")
    def _place_is_a_picks(self) -> RecipeTarget:
        if self.place and self.job != "pick":
            raise ValueError(f"place {self.place!r} is where a pick puts the part: set job "
                             "to \"pick\"")
        return self


class RecipeSpec(BaseModel):
    """A recipe as a client sends it (no version: the store gives that)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$")
    number: Annotated[int, Strict()] = Field(ge=1, le=MAX_RECIPE_NUMBER)
    description: str = Field(default="", max_length=500)
    targets: list[RecipeTarget] = Field(min_length=1, max_length=16)

    @field_validator("targets")
    @classmethod
    def _unique_names(cls, v: list[RecipeTarget]) -> list[RecipeTarget]:
        names = [t.name for t in v]
        if len(set(names)) != len(names):
            raise ValueError(f"target names must be unique, got {names}")
        return v


class Recipe(RecipeSpec):
    """One stored version of a recipe."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False,
                              json_schema_extra={"examples": [EXAMPLE]})

    version: int = Field(ge=1)
    saved_by: str = ""
    saved_at: float = 0.0

    def target(self, name: str = "") -> RecipeTarget:
        """The named target ("": the first)."""
        if not name:
            return self.targets[0]
        for t in self.targets:
            if t.name == name:
                return t
        raise NotFoundError(ErrorCode.recipe_target_not_found,
                            f"recipe {self.name!r} has no target {name!r}; it has "
                            f"{', '.join(t.name for t in self.targets)}")

    def record(self, target: RecipeTarget) -> dict[str, Any]:
        """What a job records about the recipe it ran with."""
        return {"name": self.name, "number": self.number, "version": self.version,
                "target": target.name}


def parse_spec(data: Any) -> RecipeSpec:
    """A recipe from JSON-like data, or ``invalid_recipe`` naming the first problem."""
    try:
        return RecipeSpec.model_validate(data)
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise LimitError(ErrorCode.invalid_recipe, f"recipe {where}: {first['msg']}") from err


def check_runnable(spec: RecipeSpec, limits: LimitsConfig | None) -> None:
    """Refuse a recipe no job could run, by the approach's own rules: each target's standoff
    (``invalid_standoff``) and, with the cell's limits, its speed (``speed_limit``); the
    message names the field (``targets.0.speed_mm_s``)."""
    for i, t in enumerate(spec.targets):
        where = f"recipe targets.{i}"
        check_standoff(t.standoff_mm, f"{where}.standoff_mm")
        if limits is not None:
            check_speed(limits, t.speed_mm_s, f"{where}.speed_mm_s")


class RecipeStore:
    """Thread-safe, versioned recipes in one JSON file (``path=None``: in memory only). With
    ``limits``, a recipe those limits would refuse to run is refused when saved."""

    def __init__(self, path: str | Path | None, limits: LimitsConfig | None = None) -> None:
        self.path = None if path is None else Path(path)
        self.limits = limits
        self._lock = threading.Lock()
        self._error: RecipeStoreError | None = None
        self._versions: dict[str, list[Recipe]] = {}
        try:
            self._versions = self._load()
        except RecipeStoreError as err:  # the service still runs; recipe jobs are refused
            self._error = err

    @staticmethod
    def beside_job_db(job_db: str, limits: LimitsConfig | None = None) -> RecipeStore:
        if job_db == ":memory:":
            return RecipeStore(None, limits)
        return RecipeStore(Path(job_db).parent / STORE_NAME, limits)

    def _load(self) -> dict[str, list[Recipe]]:
        if self.path is None or not self.path.exists():
            return {}
        try:
            data = json.loads(self.path.read_text())
            out: dict[str, list[Recipe]] = {}
            for d in data["recipes"]:
                r = Recipe.model_validate(d)
                out.setdefault(r.name, []).append(r)
            return {k: sorted(v, key=lambda r: r.version) for k, v in out.items()}
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise RecipeStoreError(ErrorCode.recipe_store_unreadable,
                                   f"cannot read the recipes in {self.path}: {err!r}; fix or "
                                   "move the file (it is never overwritten while unreadable)"
                                   ) from err

    def _usable(self) -> None:
        if self._error is not None:
            raise self._error

    def list(self) -> list[Recipe]:
        """The newest version of every recipe, by number."""
        self._usable()
        with self._lock:
            return sorted((v[-1] for v in self._versions.values()), key=lambda r: r.number)

    def versions(self, name: str) -> builtins.list[Recipe]:
        self._usable()
        with self._lock:
            found = list(self._versions.get(name, []))
        if not found:
            raise self._missing(name)
        return found

    def get(self, ref: str | int, version: int | None = None) -> Recipe:
        """By name or number; the newest version unless one is asked for."""
        self._usable()
        with self._lock:
            if isinstance(ref, int) and not isinstance(ref, bool):
                found = [v for v in self._versions.values() if v[-1].number == ref]
                history = found[0] if found else []
            else:
                history = self._versions.get(str(ref), [])
        if not history:
            raise self._missing(ref)
        if version is None:
            return history[-1]
        for r in history:
            if r.version == version:
                return r
        raise NotFoundError(ErrorCode.recipe_not_found,
                            f"recipe {ref!r} has no version {version}; it has "
                            f"{', '.join(str(r.version) for r in history)}")

    def save(self, spec: RecipeSpec, saved_by: str) -> Recipe:
        """A new version of ``spec.name`` (version 1 for a new name). A number another recipe
        uses is refused, and so is one that no job could run (:func:`check_runnable`)."""
        self._usable()
        check_runnable(spec, self.limits)
        with self._lock:
            for name, history in self._versions.items():
                if name != spec.name and history[-1].number == spec.number:
                    raise RefusedError(ErrorCode.recipe_number_taken,
                                       f"recipe number {spec.number} belongs to {name!r}")
            history = self._versions.get(spec.name, [])
            recipe = Recipe(**spec.model_dump(), version=len(history) + 1 if not history
                            else history[-1].version + 1, saved_by=saved_by,
                            saved_at=time.time())
            versions = {**self._versions, spec.name: [*history, recipe]}
            self._write(versions)
            self._versions = versions
            return recipe

    def delete(self, name: str) -> Recipe:
        """Removes the recipe and its history (jobs keep their record of it)."""
        self._usable()
        with self._lock:
            history = self._versions.get(name)
            if not history:
                raise self._missing(name)
            versions = {k: v for k, v in self._versions.items() if k != name}
            self._write(versions)
            self._versions = versions
            return history[-1]

    @staticmethod
    def _missing(ref: str | int) -> NotFoundError:
        return NotFoundError(ErrorCode.recipe_not_found,
                             f"no recipe {ref!r}; see GET /api/v1/recipes")

    def _write(self, versions: dict[str, builtins.list[Recipe]]) -> None:
        """Replace the file atomically; on failure the file and the memory stay as they were."""
        if self.path is None:
            return
        rows = [r.model_dump() for name in sorted(versions) for r in versions[name]]
        text = json.dumps({"version": FORMAT_VERSION, "recipes": rows}, indent=2)
        try:
            replace_text(self.path, text + "\n")
        except OSError as err:
            raise RecipeStoreError(ErrorCode.recipe_store_write_failed,
                                   f"cannot write {self.path}: {err}; nothing was changed"
                                   ) from err
