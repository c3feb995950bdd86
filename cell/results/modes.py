"""How an approach reaches its goal: the one spelling of the modes every interface accepts."""

from __future__ import annotations

from enum import StrEnum


class ApproachMode(StrEnum):
    """``look_and_move``: locate from still views and move, correcting until the correction
    is small; ``servo``: position-based visual servoing on every frame; ``ibvs``: image-based
    servoing to a taught view."""

    look_and_move = "look_and_move"
    servo = "servo"
    ibvs = "ibvs"
