"""Cell configuration: one TOML file, validated with pydantic; errors name the offending key.

Tables: ``[camera]`` and ``[target]`` (estimator), later ``[robot]``, ``[hand_eye]``, ``[tool]``,
``[approach]``, ``[limits]``, ``[api]``, ``[sim]``. Keys of existing tables stay stable.
Without a file every command uses the built-in simulated cell (``cell/configs/sim.toml``).
"""

from __future__ import annotations

import tomllib
from importlib import resources
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from estimator import CameraModel, Target


class ConfigError(Exception):
    """The configuration file is missing, unreadable or invalid; the message names the key."""

    code = "config_invalid"


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class CameraConfig(_Strict):
    """Intrinsics for the configured output size (OpenCV model)."""

    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    width: int = Field(gt=0)
    height: int = Field(gt=0)
    dist: list[float] = Field(default_factory=list)

    @field_validator("dist")
    @classmethod
    def _dist_len(cls, v: list[float]) -> list[float]:
        if len(v) not in (0, 4, 5, 8, 12, 14):
            raise ValueError("dist must have 0, 4, 5, 8, 12 or 14 coefficients")
        return v

    def model(self) -> CameraModel:
        return CameraModel(self.fx, self.fy, self.cx, self.cy, tuple(self.dist),
                           self.width, self.height)


class TargetConfig(_Strict):
    """Dot centres in the target frame (mm), dot diameter, dark or light dots."""

    points_mm: list[tuple[float, float, float]] = Field(min_length=4, max_length=12)
    dot_diameter_mm: float = Field(gt=0)
    polarity: Literal["dark", "light"] = "dark"

    def model(self) -> Target:
        return Target(self.points_mm, self.dot_diameter_mm, self.polarity)


class CellConfig(BaseModel):
    """The whole file. Tables added by later features are optional with sane defaults."""

    model_config = ConfigDict(extra="forbid")

    camera: CameraConfig
    target: TargetConfig


SIM_CONFIG_NAME = "sim.toml"


def _format_validation_error(err: ValidationError, source: str) -> str:
    lines = [f"invalid configuration in {source}:"]
    for e in err.errors():
        key = ".".join(str(p) for p in e["loc"])
        lines.append(f"  {key}: {e['msg']}")
    return "\n".join(lines)


def parse_config(data: dict[str, Any], source: str = "<config>") -> CellConfig:
    try:
        return CellConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_format_validation_error(err, source)) from err


def load_config(path: str | Path | None = None) -> CellConfig:
    """Load and validate a config file; ``None`` gives the built-in simulated cell."""
    if path is None:
        text = resources.files("cell.configs").joinpath(SIM_CONFIG_NAME).read_text()
        source = f"built-in {SIM_CONFIG_NAME}"
    else:
        p = Path(path)
        try:
            text = p.read_text()
        except OSError as err:
            raise ConfigError(f"cannot read config file {p}: {err.strerror}") from err
        source = str(p)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{source} is not valid TOML: {err}") from err
    return parse_config(data, source)
