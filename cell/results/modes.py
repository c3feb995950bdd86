"""How an approach reaches its goal: the one spelling of the modes every interface accepts, and
the fields that take only some of them."""

from __future__ import annotations

from enum import StrEnum
from typing import Annotated, Any

from pydantic import GetCoreSchemaHandler, GetJsonSchemaHandler
from pydantic.json_schema import JsonSchemaValue
from pydantic_core import CoreSchema, PydanticCustomError, core_schema


class ApproachMode(StrEnum):
    """``look_and_move``: locate from still views and move, correcting until the correction
    is small; ``servo``: position-based visual servoing on every frame; ``ibvs``: image-based
    servoing to a taught view."""

    look_and_move = "look_and_move"
    servo = "servo"
    ibvs = "ibvs"


# pydantic's error type for a value a Literal does not list
_LITERAL_ERROR = "literal_error"


class _Only:
    """Field metadata for an :class:`ApproachMode` that takes only some of the modes: any
    other is refused as a literal is (``Input should be 'servo' or 'ibvs'``), and the JSON
    schema (the OpenAPI, a recipe's schema) lists exactly the modes it takes."""

    def __init__(self, *modes: ApproachMode) -> None:
        self.modes = modes

    def __get_pydantic_core_schema__(self, source: Any,
                                     handler: GetCoreSchemaHandler) -> CoreSchema:
        return core_schema.no_info_before_validator_function(self._check, handler(source))

    def __get_pydantic_json_schema__(self, schema: CoreSchema,
                                     handler: GetJsonSchemaHandler) -> JsonSchemaValue:
        return {"type": "string", "enum": [m.value for m in self.modes]}

    def _check(self, value: Any) -> Any:
        if value not in self.modes:
            raise PydanticCustomError(_LITERAL_ERROR, "Input should be {expected}",
                                      {"expected": " or ".join(f"'{m}'" for m in self.modes)})
        return value


# The modes that approach the located target's pose. IBVS converges on a taught view, which
# a config's default mode or a recipe's target does not name.
PoseMode = Annotated[ApproachMode, _Only(ApproachMode.look_and_move, ApproachMode.servo)]
# The closed loops, which can also follow a moving target (track).
TrackMode = Annotated[ApproachMode, _Only(ApproachMode.servo, ApproachMode.ibvs)]
