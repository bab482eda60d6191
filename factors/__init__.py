"""The primer's orientation calculus, numerical differentiation on manifolds, the IMU model and
the custom GTSAM factors. Imports neither ``datasets`` nor ``smoother``."""
