"""Seeing the target: the frame chain, locate, and the image log of failed frames.

- :mod:`~cell.vision.frames`: base -> flange -> (tcp, camera) and camera -> target;
- :mod:`~cell.vision.locate`: the freshest frame's target pose, paired with the arm pose at
  its capture time;
- :mod:`~cell.vision.imagelog`: a bounded ring on disk of frames whose locate failed.
"""

from cell.vision.frames import CellFrames, cell_frames

__all__ = ["CellFrames", "cell_frames"]
