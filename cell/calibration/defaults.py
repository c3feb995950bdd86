"""The hand-eye routine's defaults, in a module without imports so the CLI's parser can read
them without loading the solver."""

# The routine's default number of views, including the start pose: the one default of the
# routine, the API's request, the CLI's ``--views`` and the operator page. From 16 views on, a
# camera on the hand has its arm's geometry fitted with the mount; the commissioning figures
# were measured with 24 (docs/calibration.md).
DEFAULT_VIEWS = 24
