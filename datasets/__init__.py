"""Data types (NumPy arrays in dataclasses), the simulator and the loaders. Depends on ``factors``
at most."""
