"""What an operator or a PLC builds a production day from. The Cell (:mod:`cell.service`)
holds the taught poses, the recipes and the alarms, built and closed with it; every interface
uses those.

- :mod:`~cell.features.alarms`: every failed job and every fault, until acknowledged;
- :mod:`~cell.features.teach`: taught reference poses and the view they were taught from;
- :mod:`~cell.features.recipes`: products (targets, taught poses, standoff, mode), versioned;
- :mod:`~cell.features.camera_control`: exposure, gain and focus of the running cell.
"""
