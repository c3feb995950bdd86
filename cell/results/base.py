"""The base every result model shares: immutable, closed, and publishing only what was set.

A result lists every key a client may see. Keys a result always carries are required fields
(``None`` where the value may be missing); a key that only some results carry (a fixed
camera's occlusion fields, a hand camera's look-and-move closing steps) has the default ``None``
and is published only when its producer set it: every dump of a result (``json_dict``, the job
store's JSON, FastAPI's response) leaves out the fields its producer did not set, and an
explicit ``None`` is ``null``. No other field has a default, since an unset default would
vanish from the published JSON.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, SerializerFunctionWrapHandler, model_serializer


class Result(BaseModel):
    """A closed, frozen pydantic model: an unknown key is an error where a result is built,
    and NaN survives a round trip through the job store's JSON."""

    model_config = ConfigDict(extra="forbid", frozen=True, ser_json_inf_nan="constants")

    @model_serializer(mode="wrap")
    def _only_set(self, handler: SerializerFunctionWrapHandler):  # type: ignore[no-untyped-def]
        # no return annotation: the serialised schema stays the model's own (OpenAPI)
        data = handler(self)
        return {name: value for name, value in data.items() if name in self.model_fields_set}

    def json_dict(self) -> dict[str, Any]:
        """The JSON object every interface publishes (plain lists, numbers and strings)."""
        return self.model_dump(mode="json")

    def set_values(self) -> dict[str, Any]:
        """The fields its producer set, by name, as they are: to build a result that carries
        this one's fields flat (the routine's result from the solution's)."""
        return {name: getattr(self, name) for name in self.model_fields_set}
