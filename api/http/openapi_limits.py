"""The OpenAPI schema states the configured limits, not only the schema's static bounds.

Pydantic models are written once, but a cell's speed limits come from its config: a client
generated from ``/openapi.json`` must see ``[limits]`` as the bounds of every speed field, so
that what the schema allows is what the cell accepts (the cell still refuses with the limit's
code, e.g. ``speed_limit``, whatever a client sends).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from fastapi import FastAPI

from cell.actions.approach_rules import MAX_STANDOFF_MM
from cell.config.schema import LimitsConfig

# (schema, property) -> (minimum, maximum) from the limits
Bounds = Callable[[LimitsConfig], tuple[float, float]]
FIELDS: dict[tuple[str, str], Bounds] = {
    ("ApproachRequest", "speed_mm_s"): lambda lim: (lim.min_speed_mm_s, lim.max_speed_mm_s),
    ("JogStep", "speed_mm_s"): lambda lim: (lim.min_speed_mm_s, lim.max_jog_speed_mm_s),
    ("HomeRequest", "speed_deg_s"): lambda lim: (0.1, lim.max_joint_speed_deg_s),
    ("RecipeApproachRequest", "speed_mm_s"): lambda lim: (lim.min_speed_mm_s,
                                                          lim.max_speed_mm_s),
    # what a recipe is checked against when saved (cell.actions.approach_rules)
    ("RecipeTarget", "speed_mm_s"): lambda lim: (lim.min_speed_mm_s, lim.max_speed_mm_s),
    ("RecipeTarget", "standoff_mm"): lambda lim: (0.0, MAX_STANDOFF_MM),
}


def _bound(prop: dict[str, Any], lo: float, hi: float) -> None:
    for branch in prop.get("anyOf", [prop]):
        if branch.get("type") in ("number", "integer"):
            branch.pop("exclusiveMinimum", None)
            branch.pop("exclusiveMaximum", None)
            branch["minimum"], branch["maximum"] = lo, hi


def install(app: FastAPI, limits: LimitsConfig) -> None:
    base = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is not None:
            return app.openapi_schema
        schema = base()
        components = schema.get("components", {}).get("schemas", {})
        for (model, field), bounds in FIELDS.items():
            prop = components.get(model, {}).get("properties", {}).get(field)
            if prop is not None:
                _bound(prop, *bounds(limits))
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]
