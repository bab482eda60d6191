"""The compiled kernels made ready before they are needed: in this process, when an online smoother
is made (:func:`in_this_process`), and in a second process while this one runs the other
estimators (:func:`start`; the child is ``python -m smoother.online.replay``, which replays a few
seconds of simulated data). Neither imports the smoother it warms up, which imports this module.

Numba compiles a kernel the first time it runs and keeps it on disk (``cache=True``); a first run
-- a fresh install, an edited kernel -- spends most of its time compiling, one kernel after the
other, on one core. When a run asks for the sliding-window fixed-lag smoother after other
estimators and the window's kernels are not on disk yet (:func:`cold`), :func:`start` compiles
them in a child process on another core (:mod:`smoother.online.warm_up_child`): it runs the window
over a few seconds of simulated data and writes nothing but Numba's cache. The fixed-lag smoother
waits for it (:meth:`WarmUp.wait`) and then loads the kernels from disk instead of compiling them
again. Nothing depends on the child: if it fails, is slow or is killed, the smoother compiles what
it still needs itself.

Numba writes each cache file whole under a temporary name and renames it, so a process that reads
the cache while another writes it sees a kernel or none.
"""
from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np

from datasets.kinds import pose
from factors import imu
from factors.threads import thread_count

#: How long the fixed-lag smoother waits for the child [s] before it compiles on its own.
WAIT_S = 300.0


def cold() -> bool:
    """Whether the sliding window's main kernel has no index in Numba's disk cache: Numba names a
    cached kernel's index ``<module>.<function>-<line>.py<version>.nbi``, in the module's
    ``__pycache__`` or, with ``NUMBA_CACHE_DIR`` set, somewhere below that folder. False when it
    cannot be told (Numba's JIT disabled)."""
    from smoother.fixed_lag.sliding import normal_equations

    if os.environ.get("NUMBA_DISABLE_JIT", "0") != "0":
        return False
    source = Path(normal_equations.__file__)
    pattern = f"{source.stem}.linearise-*.nbi"
    folder = os.environ.get("NUMBA_CACHE_DIR")
    found = Path(folder).rglob(pattern) if folder else (source.parent / "__pycache__").glob(pattern)
    return next(iter(found), None) is None


class WarmUp:
    """A running warm-up child (:func:`start`)."""

    def __init__(self, process: subprocess.Popen):
        self._process = process

    def wait(self) -> None:
        """Until the child is done (at most :data:`WAIT_S`; then it is stopped)."""
        try:
            self._process.wait(timeout=WAIT_S)
        except subprocess.TimeoutExpired:
            self.close()

    def close(self) -> None:
        """Stop the child if it still runs."""
        if self._process.poll() is None:
            self._process.kill()
            self._process.wait()


def start(order, fixed_lag_kind: str) -> WarmUp | None:
    """A warm-up child when the estimators in ``order`` run the sliding window after another one,
    its kernels are not on disk (:func:`cold`) and the process may use more than one thread
    (:func:`factors.threads.thread_count`: ``BOXPLUS_THREADS=1`` where processes share the
    cores); else None."""
    if fixed_lag_kind != "sliding" or "fixed-lag" not in order or list(order)[0] == "fixed-lag":
        return None
    if thread_count() < 2 or not cold():
        return None
    root = Path(__file__).resolve().parents[2]
    environment = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    process = subprocess.Popen([sys.executable, "-m", "smoother.online.warm_up_child"], cwd=root, env=environment,
                               stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return WarmUp(process)


_warmed = False


def in_this_process(smoother_class) -> None:
    """Load (or compile) every kernel the loop calls -- the checks of an IMU sample and of a pose,
    the interval's preintegration and prediction, the window's update and marginalisation, the
    per-sample estimate -- once per process, by feeding a throwaway smoother (of ``smoother_class``)
    half a second of a resting IMU and three poses: otherwise the first keyframes and the first
    marginalisation of a robot's run stall by the loading (10-250 ms).
    :class:`smoother.online.smoother.OnlineSmoother` calls it, with itself, when it is made."""
    global _warmed
    if _warmed:
        return
    _warmed = True
    t = np.arange(0.0, 0.8, 0.01)
    start = imu.ImuState.identity()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        warm = smoother_class(start, np.eye(imu.STATE_DIM), imu.ImuNoise(1e-2, 1e-3, 1e-3, 1e-4), lag_s=0.3)
        for k, tk in enumerate(t):
            warm.add_imu(tk, -imu.DEFAULT_GRAVITY, np.zeros(3))
            if k % 10 == 5:
                warm.add(pose.KIND.name, tk, np.zeros(3), np.eye(3), cov=1e-4 * np.eye(6))
            if k > 5:
                warm.estimate()
        warm.finish()
