"""What moves the arm, each through the guarded arm of :mod:`cell.motion`.

- :mod:`~cell.actions.approach`: look-and-move, the servo or IBVS, to the target;
  :mod:`~cell.actions.approach_rules` the standoff and speed rules every door shares (the
  HTTP bodies, recipes when saved, the PLC interfaces);
- :mod:`~cell.actions.track`: hold the TCP at a standoff from a moving target;
  both run the closed loop of :mod:`cell.servoing` with a position- or image-based law;
- :mod:`~cell.actions.jog`: Cartesian steps and dead-man continuous jogs;
- :mod:`~cell.actions.recovery`: home, unlock a protective stop, power;
- :mod:`~cell.actions.stop`: the stop path, one thread that does nothing else.
"""
