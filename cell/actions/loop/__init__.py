"""The closed loop every streamed motion runs (:mod:`~cell.actions.loop.runner`) and the laws it
is given (:mod:`~cell.actions.loop.law`): position-based (:mod:`~cell.actions.loop.position`)
and image-based (:mod:`~cell.actions.loop.image`)."""
