"""The closed loop every streamed motion runs, and the laws it is given.

The approach and the track (:mod:`cell.actions`) decide what to servo on and when a job ends;
this room holds how: the runner (:mod:`~cell.servoing.runner`) owns the frame thread, the
tick, the loss clock, the stop, the statistics and the history; a law
(:mod:`~cell.servoing.law`) says what a frame measures and what twist a tick sends.
Position-based: :mod:`~cell.servoing.position` (its maths in
:mod:`~cell.servoing.servo_law` and :mod:`~cell.servoing.target_filter`); image-based:
:mod:`~cell.servoing.image` (:mod:`~cell.servoing.ibvs`, :mod:`~cell.servoing.ibvs_mount`,
:mod:`~cell.servoing.ibvs_settle`). Every twist goes through the guarded arm of
:mod:`cell.motion`.
"""
