"""The hardware behind its interfaces, and the one place that builds it from the config.

- :mod:`~cell.devices.factory`: builds the real adapters or the simulated devices (the only
  importer of ``fakes`` at run time);
- :mod:`~cell.devices.hardware`: what the factory hands to the cell;
- :mod:`~cell.devices.sim_truth`: the simulated world's own truth, which the cell never reads.
"""

from cell.devices.hardware import Hardware, SimWorld

__all__ = ["Hardware", "SimWorld"]
