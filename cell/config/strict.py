"""The base of every config table: an unknown key is an error, values are frozen once loaded,
and NaN or infinity is refused."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
