"""The routes under ``/api/v1``, one module per area: the cell's own (status, locate,
approach, jobs, jog, stop, gripper, camera, events), arm recovery, calibration and teach,
production operations, recipes, and tracking."""
