"""What a finished tracking job returns, discriminated by ``mode``: ``track`` (pose-based)
or ``ibvs_track`` (holding a taught view)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from cell.results.loop import IbvsLoop, ServoLoop


class ServoTrack(ServoLoop):
    """The pose-based loop held the standoff pose for ``duration_s``; ``rms_error_mm`` over
    the run after its first second."""

    mode: Literal["track"]
    duration_s: float
    rms_error_mm: float | None


class IbvsTrack(IbvsLoop):
    """The image-based loop held the taught view for ``duration_s``."""

    mode: Literal["ibvs_track"]
    duration_s: float


TrackResult = Annotated[ServoTrack | IbvsTrack, Field(discriminator="mode")]
