"""What the cell's jobs and answers return, as typed objects.

One model per job kind, owned here at the bottom of the cell so that the actions that build
them, the job store that keeps them and every interface that serialises them (HTTP, OPC UA,
Modbus, XML-RPC) share one definition. Pure data: nothing here moves or measures anything.

- :mod:`~cell.results.base`: the base model and how a result is published (``json_dict``);
- :mod:`~cell.results.pose`: the pose object;
- :mod:`~cell.results.approach`, :mod:`~cell.results.track`, :mod:`~cell.results.home`,
  :mod:`~cell.results.routine`: each job kind's result; :mod:`~cell.results.jobs`: which kind
  returns which, and reading one back;
- :mod:`~cell.results.loop`, :mod:`~cell.results.consistency`, :mod:`~cell.results.stats`:
  the blocks they share;
- :mod:`~cell.results.locate`, :mod:`~cell.results.calibration`: the locate answers (one
  target, or every part in view), the hand-eye solution and the answer of applying it;
- :mod:`~cell.results.modes`: the approach modes.
"""

from cell.results.approach import (
    ApproachResult,
    IbvsApproach,
    LookAndMoveApproach,
    ServoApproach,
)
from cell.results.base import Result
from cell.results.home import HomeResult
from cell.results.jobs import JobKind, JobResult, result_from_json, result_json, result_of
from cell.results.locate import LocateAllResult, LocatedInstance, LocateResult
from cell.results.modes import ApproachMode
from cell.results.pose import Pose
from cell.results.routine import HandEyeRoutineResult
from cell.results.track import IbvsTrack, ServoTrack, TrackResult

__all__ = [
    "ApproachMode",
    "ApproachResult",
    "HandEyeRoutineResult",
    "HomeResult",
    "IbvsApproach",
    "IbvsTrack",
    "JobKind",
    "JobResult",
    "LocateAllResult",
    "LocateResult",
    "LocatedInstance",
    "LookAndMoveApproach",
    "Pose",
    "Result",
    "ServoApproach",
    "ServoTrack",
    "TrackResult",
    "result_from_json",
    "result_json",
    "result_of",
]
