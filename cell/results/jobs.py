"""Which result each kind of job returns, and reading one back by its kind.

A job's kind names its result's model: an approach returns an :data:`ApproachResult` (by its
mode), a track a :data:`TrackResult`, home a :class:`HomeResult`, the hand-eye routine a
:class:`HandEyeRoutineResult`, a pick a :class:`PickResult`, the calibration reference and
its check a :class:`ReferenceResult` and a :class:`CheckResult`. The job store keeps a result as
its JSON and reads it back through :func:`result_of` with the job's kind.
"""

from __future__ import annotations

from typing import Any, Literal, get_args

from pydantic import TypeAdapter

from cell.results.approach import (
    AnyApproach,
    ApproachResult,
    IbvsApproach,
    LookAndMoveApproach,
    ServoApproach,
)
from cell.results.check import CheckResult, ReferenceResult
from cell.results.home import HomeResult
from cell.results.pick import PickResult
from cell.results.pose import Pose
from cell.results.routine import HandEyeRoutineResult
from cell.results.track import IbvsTrack, ServoTrack, TrackResult

JobKind = Literal["approach", "track", "home", "hand_eye_calibration", "pick",
                  "calibration_reference", "calibration_check"]
JOB_KINDS: tuple[JobKind, ...] = get_args(JobKind)

JobResult = (LookAndMoveApproach | ServoApproach | IbvsApproach | ServoTrack | IbvsTrack
             | HomeResult | HandEyeRoutineResult | PickResult | ReferenceResult | CheckResult)

_ADAPTERS: dict[str, TypeAdapter[Any]] = {
    "approach": TypeAdapter(ApproachResult),
    "track": TypeAdapter(TrackResult),
    "home": TypeAdapter(HomeResult),
    "hand_eye_calibration": TypeAdapter(HandEyeRoutineResult),
    "pick": TypeAdapter(PickResult),
    "calibration_reference": TypeAdapter(ReferenceResult),
    "calibration_check": TypeAdapter(CheckResult),
}


def _adapter(kind: str) -> TypeAdapter[Any]:
    try:
        return _ADAPTERS[kind]
    except KeyError:
        raise ValueError(f"no result model for jobs of kind {kind!r}") from None


def located_pose(result: JobResult | None) -> Pose | None:
    """The target pose a job's result reports (an approach's or a track's ``T_base_target``),
    as the PLC doors publish it; None for other kinds, or an IBVS run that saw no view."""
    if isinstance(result, AnyApproach | ServoTrack | IbvsTrack):
        return result.T_base_target
    if isinstance(result, PickResult):
        return result.part.T_base_target
    return None


def result_of(kind: str, data: Any) -> JobResult:
    """A result of a job of ``kind`` from its model, or from its JSON object as a dict;
    pydantic's ValidationError when it is not one."""
    result: JobResult = _adapter(kind).validate_python(data)
    return result


def result_from_json(kind: str, text: str | bytes) -> JobResult:
    """A result of a job of ``kind`` from the JSON text the job store keeps."""
    result: JobResult = _adapter(kind).validate_json(text)
    return result


def result_json(result: JobResult) -> str:
    """The JSON text the job store keeps (keys a producer did not set stay absent)."""
    return result.model_dump_json()
