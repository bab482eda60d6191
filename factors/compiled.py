"""How the per-element kernels are compiled: Numba's decorators, one per kind of kernel.

The per-element mathematics of this package (Rodrigues' formula, ``Gamma``, Shepperd's
quaternion, the IMU recursions) is written once, as scalar Numba kernels. Numba compiles them to
machine code on first use (cached on disk, so later processes start at once; the caches are kept
fresh across edits by :mod:`factors.kernel_caches`); NumPy expressions of the same formulas spend
nearly all their time in Python call overhead on 3x3 arrays. A kernel ``loop(flat_in, flat_out)``
loops over the first axis; :func:`factors.rows.apply_rows` gives it the vectorised interface of a
NumPy function, and :func:`factors.threads.in_parallel` runs work of many pieces on several threads.
"""
from __future__ import annotations

from numba import njit

#: Decorator of the IMU recursions (:mod:`factors.imu`, :mod:`factors.preintegration`): compiled,
#: cached on disk, and allowed to fuse ``a * b + c`` into one fused multiply-add (Numba's
#: ``fastmath={"contract"}``; each fused pair rounds once instead of twice, no other reordering).
#: It makes the recursions about 1.3x faster; their tests compare with independent evaluations at
#: 1e-12 relative, far above the one-ulp differences this allows. The SO(3) kernels keep strict
#: IEEE evaluation (their tests hold them to a few ulps near 0 and pi). They release the GIL
#: (``nogil``), so :func:`factors.threads.in_parallel` can run them on several threads.
recursion = njit(cache=True, nogil=True, fastmath={"contract"})

#: Decorator of the small kernels that allocate nothing (they read and write arrays their caller
#: owns) and run once per sample or per factor inside other kernels: :data:`recursion` without
#: Numba's reference counting. Every compiled call that passes arrays otherwise increments and
#: decrements each array's reference count on entry and exit, atomic operations through the
#: runtime: ten of them per call of ``imu.step_quantities`` when it took five arrays, which doubled
#: its cost (0.13 instead of 0.06 us per sample). The caller keeps the arrays alive for the call,
#: so nothing is lost; a kernel under this decorator that tried to allocate would fail to compile,
#: not misbehave. Even without reference counting each array argument is a dozen words to pass:
#: the per-sample leaves take one array holding all their numbers (``imu.STEP_SIZE``).
leaf = njit(cache=True, nogil=True, fastmath={"contract"}, _nrt=False)

#: :data:`leaf` with strict IEEE evaluation, for the SO(3) and quaternion kernels.
exact_leaf = njit(cache=True, _nrt=False)

#: Decorator of the small block operations inside the recursions (``A = F - I`` applied to a
#: matrix): the same floating-point rules as :data:`recursion`, inlined by Numba into each caller.
#: Inlined, LLVM sees the caller's fixed row widths and distinct work arrays and turns the column
#: loops into SIMD instructions; called, the loops stay scalar (the covariance step ran ~1.6x
#: slower).
block_operation = njit(inline="always", fastmath={"contract"})
