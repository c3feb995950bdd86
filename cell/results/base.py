"""The base every result model shares: immutable, closed, and one way to publish it.

A result lists every key a client may see. Keys a result always carries are required fields
(``None`` where the value may be missing); a key that only some results carry (a fixed
camera's occlusion fields, the closing steps of an approach at rest) has the default ``None``
and is published only when its producer set it. So :meth:`Result.json_dict` dumps with
``exclude_unset``: a key a producer did not set stays absent, an explicit ``None`` is ``null``.
No other field has a default, since an unset default would vanish from the published JSON.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict


class Result(BaseModel):
    """A closed, frozen pydantic model: an unknown key is an error where a result is built,
    and NaN survives a round trip through the job store's JSON."""

    model_config = ConfigDict(extra="forbid", frozen=True, ser_json_inf_nan="constants")

    def json_dict(self) -> dict[str, Any]:
        """The JSON object every interface publishes (plain lists, numbers and strings)."""
        return self.model_dump(mode="json", exclude_unset=True)
