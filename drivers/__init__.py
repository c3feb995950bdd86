"""Hardware interfaces (Protocols) and the real adapters: UR arm, OAK camera, serial gripper.

Drivers know nothing of the cell or the API; they may use ``estimator`` for camera models and
transforms.
"""
