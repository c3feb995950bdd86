"""The hardware behind its interfaces, and the one place that builds it from the config.

- :mod:`~cell.devices.factory`: one builder per device kind (:mod:`cell.config.devices`), the
  simulated parts from one call to ``fakes.sim_cell`` (the only importer of ``fakes`` at run
  time);
- :mod:`~cell.devices.hardware`: what the factory hands to the cell, and the simulated world
  as the cell may see it;
- :mod:`~cell.devices.sim_truth`: the simulated world's own truth, resolved from ``[sim]``: the
  simulated devices are built to it; of the cell only the benchmarks and the ``/sim`` routes
  read it.
"""

from cell.devices.hardware import Hardware, SimWorld

__all__ = ["Hardware", "SimWorld"]
