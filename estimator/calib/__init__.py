"""Camera and hand-eye calibration: board models and detection, intrinsics, AX = XB solvers.

Pure like the rest of ``estimator``: images, poses and intrinsics in, transforms and residuals
out. Reading datasets, judging results and driving a robot live in ``cell.calibration``.
"""
