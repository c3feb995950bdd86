"""Typed estimation failures.

Every failure carries a machine-readable ``code`` (used in JSON errors by the CLI and the API)
and a message a person at the cell can act on.
"""

from __future__ import annotations


class EstimationError(Exception):
    """Base class: the pose could not be estimated."""

    code = "estimation_failed"

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.message = message


class TooFewBlobsError(EstimationError):
    """Fewer usable blobs than the target needs."""

    code = "too_few_blobs"

    def __init__(self, found: int, needed: int, detail: str = "") -> None:
        msg = (
            f"found {found} blob(s), need at least {needed}: check that the target is in view, "
            "lit, in focus, and that the polarity and size filters fit the dots"
        )
        if detail:
            msg += f" ({detail})"
        super().__init__(msg)
        self.found = found
        self.needed = needed


class DegenerateGeometryError(EstimationError):
    """Model or image points are collinear / coincident, so the pose is undetermined."""

    code = "degenerate_geometry"


class NotConvergedError(EstimationError):
    """The iterative solver did not converge within its iteration budget."""

    code = "not_converged"


class BehindCameraError(EstimationError):
    """The solution puts (part of) the target behind the camera."""

    code = "target_behind_camera"


class CorrespondenceError(EstimationError):
    """No assignment of blobs to model dots is geometrically consistent."""

    code = "no_correspondence"
