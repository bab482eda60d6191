"""Hypothesis strategies shared by the tests: rotation vectors and rotations in the three angle
regimes where SO(3) code breaks (tiny, ordinary, within 1e-3 rad of pi), vectors, IMU states.

Import as ``import strategies`` (``tests/conftest.py`` puts this directory on ``sys.path``).
"""
from __future__ import annotations

import math

import numpy as np
from hypothesis import strategies as st

from factors import so3

#: Unit round-off of float64 (2.2e-16): tolerances below are stated in multiples of it.
EPS = float(np.finfo(float).eps)

#: Largest angle of the "tiny" regime and largest distance to pi of the "near_pi" regime.
TINY = 1e-6
NEAR_PI = 1e-3


def _floats(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False, allow_subnormal=False)


def _log_uniform(lo_exp: float, hi_exp: float) -> st.SearchStrategy[float]:
    """``10**e`` with ``e`` in ``[lo_exp, hi_exp]``: every decade equally likely."""
    return _floats(lo_exp, hi_exp).map(lambda e: 10.0**e)


def unit_vectors() -> st.SearchStrategy[np.ndarray]:
    """Unit 3-vectors (axes), uniform on the sphere: ``z`` uniform in [-1, 1], azimuth uniform."""

    def build(z: float, azimuth: float) -> np.ndarray:
        rho = math.sqrt(max(0.0, 1.0 - z * z))
        return np.array([rho * math.cos(azimuth), rho * math.sin(azimuth), z])

    return st.builds(build, _floats(-1.0, 1.0), _floats(0.0, 2 * math.pi))


def vectors(scale: float = 10.0) -> st.SearchStrategy[np.ndarray]:
    """3-vectors with entries in ``[-scale, scale]``."""
    return st.tuples(_floats(-scale, scale), _floats(-scale, scale), _floats(-scale, scale)).map(np.array)


def tiny_angles() -> st.SearchStrategy[float]:
    """Angles in ``[0, 1e-6]``: exactly 0, Hypothesis' own choices down to 1e-100 (below that the
    squares in a vector norm underflow, which says nothing about rotations), and log-uniform
    between 1e-12 and 1e-6."""
    return st.one_of(st.just(0.0), _floats(1e-100, TINY), _log_uniform(-12, math.log10(TINY)))


def ordinary_angles() -> st.SearchStrategy[float]:
    """Angles in ``[1e-6, pi - 1e-3]``."""
    return _floats(TINY, math.pi - NEAR_PI)


def near_pi_angles(min_distance: float = 0.0) -> st.SearchStrategy[float]:
    """Angles ``pi - d`` with ``d`` in ``[min_distance, 1e-3]`` (``d = 0`` is exactly pi, included
    when ``min_distance == 0``), log-uniform in ``d`` down to 1e-12 as well as Hypothesis' own.

    Use ``min_distance > 0`` where the result would be ambiguous at pi (``log`` returns one of two
    opposite vectors there) or where a numerical step of 1e-6 could cross pi.
    """
    lo = max(min_distance, 1e-12)
    parts = [_floats(min_distance, NEAR_PI).map(lambda d: math.pi - d),
             _log_uniform(math.log10(lo), -3).map(lambda d: math.pi - d)]
    if min_distance == 0.0:
        parts.append(st.just(math.pi))
    return st.one_of(*parts)


def angles(regime: str = "any", min_pi_distance: float = 0.0) -> st.SearchStrategy[float]:
    """Angles of one regime: ``"tiny"``, ``"ordinary"``, ``"near_pi"`` or ``"any"`` (all three)."""
    if regime == "tiny":
        return tiny_angles()
    if regime == "ordinary":
        return ordinary_angles()
    if regime == "near_pi":
        return near_pi_angles(min_pi_distance)
    if regime == "any":
        return st.one_of(tiny_angles(), ordinary_angles(), near_pi_angles(min_pi_distance))
    raise ValueError(f"unknown regime {regime!r}")


def rotation_vectors(regime: str = "any", min_pi_distance: float = 0.0) -> st.SearchStrategy[np.ndarray]:
    """Rotation vectors ``angle * axis`` with the angle drawn from :func:`angles`."""
    return st.builds(lambda t, u: t * u, angles(regime, min_pi_distance), unit_vectors())


def rotations(regime: str = "any", min_pi_distance: float = 0.0) -> st.SearchStrategy[np.ndarray]:
    """Rotation matrices ``so3.exp(phi)`` of :func:`rotation_vectors`."""
    return rotation_vectors(regime, min_pi_distance).map(so3.exp)


def asymmetric_rotations() -> st.SearchStrategy[np.ndarray]:
    """Rotations far from symmetric (``|C - C^T| >= 2 sin(0.5) ~ 0.96`` somewhere): angles in
    [0.5, pi - 0.5], where a transposed C in a formula cannot hide."""
    return st.builds(lambda t, u: so3.exp(t * u), _floats(0.5, math.pi - 0.5), unit_vectors())


def imu_states(attitude_regime: str = "any", attitudes=None):
    """Random :class:`factors.imu.ImuState`: position within 100 m, body velocity within 10 m/s,
    accelerometer bias within 0.5 m/s^2 and gyro bias within 0.2 rad/s per axis; the attitude
    from :func:`rotations` of ``attitude_regime``, or from the strategy ``attitudes``."""
    from factors import imu

    return st.builds(
        imu.ImuState,
        r=vectors(100.0),
        v=vectors(10.0),
        C=attitudes if attitudes is not None else rotations(attitude_regime),
        b_f=vectors(0.5),
        b_w=vectors(0.2),
    )


# ---------------------------------------------------------------------------------------------
# High-precision references (60 significant digits, Python's decimal module). A float argument
# converts to Decimal exactly, so these give the correctly rounded values the float code under
# test should reproduce to a few units of round-off.

from decimal import Decimal, localcontext  # noqa: E402

_DIGITS = 60
_PI = Decimal("3.14159265358979323846264338327950288419716939937510582097494459")


def _series(first: Decimal, ratio) -> Decimal:
    """Sum of a power series given its first term and ``ratio(k, term) -> next term``."""
    total, term, k = Decimal(0), first, 0
    tiny = Decimal(10) ** (-_DIGITS - 5)
    while term != 0:
        total += term
        if abs(term) <= abs(total) * tiny:
            break
        term = ratio(k, term)
        k += 1
    return total


def dec_sin(x: Decimal) -> Decimal:
    with localcontext() as ctx:
        ctx.prec = _DIGITS
        return +_series(x, lambda k, t: -t * x * x / ((2 * k + 2) * (2 * k + 3)))


def dec_cos(x: Decimal) -> Decimal:
    with localcontext() as ctx:
        ctx.prec = _DIGITS
        return +_series(Decimal(1), lambda k, t: -t * x * x / ((2 * k + 1) * (2 * k + 2)))


def dec_atan2(y: Decimal, x: Decimal) -> Decimal:
    """atan2 for ``y >= 0``, ``x >= 0`` (all the quaternion tests need)."""
    with localcontext() as ctx:
        ctx.prec = _DIGITS
        if x == 0:
            return _PI / 2
        z, flip = (y / x, False) if y <= x else (x / y, True)
        # halve the argument twice (atan z = 2 atan(z / (1 + sqrt(1 + z^2)))) so the series is fast
        for _ in range(2):
            z = z / (1 + (1 + z * z).sqrt())
        a = 4 * _series(z, lambda k, t: -t * z * z * (2 * k + 1) / (2 * k + 3))
        return _PI / 2 - a if flip else a


def coefficients(kind: str, t) -> tuple[Decimal, Decimal]:
    """``(a, b)`` with ``M(phi) = I + a phi^x + b phi^x^2`` at angle ``t`` (a float or a Decimal)
    for ``kind`` in ``"exp"`` (Rodrigues, primer eq. 21), ``"gamma"`` (eq. 33), ``"gamma_inv"``."""
    with localcontext() as ctx:
        ctx.prec = _DIGITS
        T = Decimal(t)
        if T == 0:
            return {"exp": (Decimal(1), Decimal(1) / 2), "gamma": (Decimal(1) / 2, Decimal(1) / 6),
                    "gamma_inv": (Decimal(-1) / 2, Decimal(1) / 12)}[kind]
        s, c = dec_sin(T), dec_cos(T)
        if kind == "exp":
            return s / T, (1 - c) / (T * T)
        if kind == "gamma":
            return (1 - c) / (T * T), (T - s) / (T * T * T)
        if kind == "gamma_inv":
            h = T / 2
            return Decimal(-1) / 2, (1 - h * dec_cos(h) / dec_sin(h)) / (T * T)
        raise ValueError(kind)


def reference_matrix(kind: str, phi: np.ndarray) -> np.ndarray:
    """``I + a phi^x + b phi^x^2`` evaluated in 60-digit arithmetic, rounded once to float."""
    with localcontext() as ctx:
        ctx.prec = _DIGITS
        p = [Decimal(float(x)) for x in phi]
        # the angle in high precision too (its float rounding would bias the reference)
        a, b = coefficients(kind, (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt())
        K = [[Decimal(0), -p[2], p[1]], [p[2], Decimal(0), -p[0]], [-p[1], p[0], Decimal(0)]]
        K2 = [[sum(K[i][k] * K[k][j] for k in range(3)) for j in range(3)] for i in range(3)]
        return np.array([[float((1 if i == j else 0) + a * K[i][j] + b * K2[i][j]) for j in range(3)]
                         for i in range(3)])


def reference_quaternion_exp(phi: np.ndarray) -> np.ndarray:
    """``(cos(t/2), sin(t/2)/t phi)`` (primer eq. 38) in 60-digit arithmetic, rounded once."""
    with localcontext() as ctx:
        ctx.prec = _DIGITS
        p = [Decimal(float(x)) for x in phi]
        T = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt()
        if T == 0:
            return np.array([1.0, 0.0, 0.0, 0.0])
        h = T / 2
        k = dec_sin(h) / T
        return np.array([float(dec_cos(h))] + [float(k * x) for x in p])


def reference_quaternion_log(q: np.ndarray) -> np.ndarray:
    """``2 atan2(|qv|, q0) qv / |qv|`` (primer eq. 40) in 60-digit arithmetic, for ``q0 >= 0``."""
    with localcontext() as ctx:
        ctx.prec = _DIGITS
        q0 = Decimal(float(q[0]))
        v = [Decimal(float(x)) for x in q[1:]]
        s = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
        if s == 0:
            return np.zeros(3)
        k = 2 * dec_atan2(s, q0) / s
        return np.array([float(k * x) for x in v])


# ---------------------------------------------------------------------------------------------
# Plain NumPy samplers for batch (vectorisation) tests, where Hypothesis' per-draw cost would
# dominate and shrinking a batch of 12 rotations would not explain anything anyway.


def sample_angles(rng: np.random.Generator, shape) -> np.ndarray:
    """Angles mixing every regime: 0, 1e-12..1e-6 (log-uniform), uniform in [0, pi], pi - 1e-12..
    pi - 1e-3 (log-uniform in the distance) and exactly pi."""
    shape = tuple(np.atleast_1d(shape))
    regime = rng.integers(0, 5, size=shape)
    tiny = 10.0 ** rng.uniform(-12, -6, size=shape)
    ordinary = rng.uniform(0, math.pi, size=shape)
    near_pi = math.pi - 10.0 ** rng.uniform(-12, -3, size=shape)
    return np.choose(regime, [np.zeros(shape), tiny, ordinary, near_pi, np.full(shape, math.pi)])


def sample_rotation_vectors(rng: np.random.Generator, shape) -> np.ndarray:
    """Rotation vectors of shape ``shape + (3,)`` with :func:`sample_angles` and uniform axes."""
    shape = tuple(np.atleast_1d(shape))
    axes = rng.normal(size=shape + (3,))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    return sample_angles(rng, shape)[..., None] * axes


def random_rotation(rng: np.random.Generator, regime: str) -> np.ndarray:
    """A rotation whose angle is tiny (<= 1e-6, 0 included), ordinary, or within 1e-3 of pi."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    if regime == "tiny":
        angle = 0.0 if rng.random() < 0.2 else 10.0 ** rng.uniform(-12, -6)
    elif regime == "near_pi":
        angle = np.pi - (0.0 if rng.random() < 0.2 else 10.0 ** rng.uniform(-12, -3))
    else:
        angle = rng.uniform(1e-6, np.pi - 1e-3)
    return so3.exp(angle * axis)
