"""Luxonis OAK cameras through depthai v3: the camera adapter and the factory calibration."""
