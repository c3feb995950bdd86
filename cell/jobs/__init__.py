"""Jobs and their record: the store, the one lifecycle, the audit log and the event bus.

- :mod:`~cell.jobs.store`: jobs and audit rows in SQLite (WAL);
- :mod:`~cell.jobs.runner`: one lifecycle for every long-running command;
- :mod:`~cell.jobs.audit`: the one way a command reaches the audit log;
- :mod:`~cell.jobs.events`: fan-out of state, job and jog events to many listeners.
"""

from cell.jobs.store import Job, JobStore

__all__ = ["Job", "JobStore"]
