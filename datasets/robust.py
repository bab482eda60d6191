"""Robust-kernel specs, as ``smoother run --robust`` and a rig file's ``robust`` key write them:
``none``, or a kernel name with an optional threshold, ``huber``, ``cauchy:2.5``, ``tukey:4``.

Parsing needs no GTSAM: the kernels themselves (and their default thresholds) are
``smoother.model.robust.ROBUST_KERNELS``, keyed by :data:`ROBUST_KERNEL_NAMES`. A threshold given must
lie in the range ``sensor.robust`` of :data:`datasets.ranges.RANGES` (in sigmas of the whitened
residual's norm).
"""
from __future__ import annotations

from datasets.ranges import RANGES
from factors.errors import InputError

#: The robust kernels by name.
ROBUST_KERNEL_NAMES = ("huber", "cauchy", "tukey")


def robust_spec(text: str | None):
    """Parse ``none``, ``huber``, ``cauchy:2.5``, ... into ``(name, threshold)`` (threshold None:
    the kernel's dimension-aware default) or None for no kernel; a ``ValueError`` otherwise."""
    if text is None or text == "none":
        return None
    name, _, value = text.partition(":")
    if name not in ROBUST_KERNEL_NAMES:
        raise InputError(f"robust kernel {name!r}: expected one of none, {', '.join(ROBUST_KERNEL_NAMES)}")
    if not value:
        return name, None
    try:
        threshold = float(value)
    except ValueError:
        raise InputError(f"robust kernel threshold {value!r}: expected a number") from None
    if not threshold > 0:
        raise InputError(f"robust kernel threshold must be positive, got {threshold}")
    problem = RANGES["sensor.robust"].problem(threshold)
    if problem is not None:
        raise InputError(f"robust kernel threshold {value!r}: {problem}")
    return name, threshold


def check_robust(name: str, spec) -> None:
    """``spec`` as :func:`robust_spec` returns it -- None, or ``(kernel name, threshold)`` with a
    threshold None or within its range -- or an InputError naming ``name``."""
    if spec is None:
        return
    if not (isinstance(spec, tuple) and len(spec) == 2 and spec[0] in ROBUST_KERNEL_NAMES):
        raise InputError(f"{name}: expected None or (kernel, threshold) with a kernel of "
                         f"{', '.join(ROBUST_KERNEL_NAMES)} (datasets.robust.robust_spec), got {spec!r}")
    threshold = spec[1]
    if threshold is None:
        return
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float)):
        raise InputError(f"{name}: threshold: expected None or a number, got {threshold!r}")
    problem = RANGES["sensor.robust"].problem(threshold)
    if problem is not None:
        raise InputError(f"{name}: threshold: {problem}")
