"""The warm-up child of :func:`smoother.online.warm_up.start`: ``python -m
smoother.online.warm_up_child`` runs the sliding window over 3 s of the simulator's default run
(every kernel an update, a marginalisation and the covariances call) and writes nothing but
Numba's cache. A module of its own: it drives the online smoother, which warms its kernels up
through :mod:`smoother.online.warm_up` in turn."""
from __future__ import annotations

import warnings


def compile_window() -> None:
    """The sliding window over 3 s of the simulator's default run, its warnings silenced."""
    from datasets.simulate import simulate
    from smoother.online.replay import replay

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        replay(simulate("gentle", duration=3.0, seed=0), 1.0, "sliding", covariances=True, progress=False)


if __name__ == "__main__":
    compile_window()
