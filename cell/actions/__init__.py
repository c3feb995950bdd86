"""What moves the arm, each through the guarded arm of :mod:`cell.motion`.

- :mod:`~cell.actions.approach`: look-and-move, or the closed-loop servo, to the target;
  :mod:`~cell.actions.approach_rules` the standoff and speed rules every door shares (the
  HTTP bodies, recipes when saved, the PLC interfaces);
- :mod:`~cell.actions.track`: hold the TCP at a standoff from a moving target;
- :mod:`~cell.actions.servo`: the servo loop; :mod:`~cell.actions.servo_law` its control law;
  :mod:`~cell.actions.target_filter` the target's constant-velocity filter;
- :mod:`~cell.actions.jog`: Cartesian steps and dead-man continuous jogs;
- :mod:`~cell.actions.recovery`: home, unlock a protective stop, power;
- :mod:`~cell.actions.stop`: the stop path, one thread that does nothing else.
"""
