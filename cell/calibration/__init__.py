"""Calibration as the cell runs it: datasets on disk, the solve-and-judge pipeline, the report,
writing the result into the cell config, and the guided routine on a live arm and camera."""
