"""Watching the cell: links that come back, what it reports, the gripper's state, logging.

- :mod:`~cell.supervision.links`: watch the arm and camera, fail what depends on a lost one,
  reconnect;
- :mod:`~cell.supervision.snapshot`: one snapshot behind every read, never much older than a
  camera period;
- :mod:`~cell.supervision.status`: ``/status``, ``/health`` and the state events;
- :mod:`~cell.supervision.gripper`: gripper commands and a cached status;
- :mod:`~cell.supervision.logs`: logging set-up for ``cell serve``.
"""
