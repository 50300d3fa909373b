"""Non-linear least squares: the one batched Levenberg–Marquardt."""
