"""Analytic motion profiles for the simulator: smooth 3D trajectories with exact derivatives.

A :class:`Profile` gives, at any times ``t``, the world position ``r(t)`` with its first and second
derivatives and the attitude as ZYX Euler angles ``(roll, pitch, yaw)`` (``C = Rz(yaw) Ry(pitch)
Rx(roll)``, :func:`factors.euler.rpy_to_matrix`) with their first derivatives, all in closed
form. :meth:`Profile.evaluate` turns them into :class:`Kinematics`: attitude matrices, the body
angular rate, the body velocity and the specific force of the primer's eq. (42).

Body angular rate of ZYX Euler angles. Differentiating ``C = Rz Ry Rx`` and pulling every rate
back into the body frame (``C^T dC/dt = omega^x``)::

    omega_B = Rx^T Ry^T e_z dyaw + Rx^T e_y dpitch + e_x droll
            = (droll - dyaw sin(pitch),
               dpitch cos(roll) + dyaw sin(roll) cos(pitch),
               -dpitch sin(roll) + dyaw cos(roll) cos(pitch))

This is the body-frame perturbation Jacobian of :mod:`factors.euler` applied to the rates. No
matrix is inverted, so pitch may pass through +-pi/2. ``tests/datasets/test_simulate.py`` checks
it against finite differences of ``C``.

Every profile is a sum of sinusoids and linear ramps (:class:`Sinusoids`) except the heading of
``gentle``, which follows the horizontal velocity; its rate is ``(v_x a_y - v_y a_x) / (v_x^2 +
v_y^2)``, and the figure-eight is chosen so that the horizontal speed never vanishes.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Callable

import numpy as np

from factors import euler

# --------------------------------------------------------------------------------------------
# building blocks


@dataclass(frozen=True)
class Sinusoids:
    """``x(t) = offset + slope t + sum_i amplitude_i sin(frequency_i t + phase_i)`` (one scalar
    function; ``terms`` holds ``(amplitude, angular frequency [rad/s], phase)``)."""

    offset: float = 0.0
    slope: float = 0.0
    terms: tuple = ()

    def derivatives(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(x, dx/dt, d2x/dt2)`` at ``t``."""
        t = np.asarray(t, dtype=float)
        x = self.offset + self.slope * t
        dx = np.full_like(t, self.slope)
        ddx = np.zeros_like(t)
        for amplitude, frequency, phase in self.terms:
            angle = frequency * t + phase
            s, c = np.sin(angle), np.cos(angle)
            x = x + amplitude * s
            dx = dx + amplitude * frequency * c
            ddx = ddx - amplitude * frequency**2 * s
        return x, dx, ddx


def _stack3(functions, t):
    """Evaluate three :class:`Sinusoids` and stack ``(value, d1, d2)`` as ``(..., 3)`` arrays."""
    parts = [f.derivatives(t) for f in functions]
    return tuple(np.stack([p[i] for p in parts], axis=-1) for i in range(3))


def body_rate_from_rpy(rpy: np.ndarray, rpy_rate: np.ndarray) -> np.ndarray:
    """Body angular rate ``omega_B`` (``C^T dC/dt = omega_B^x``) of roll-pitch-yaw angles and their
    rates (the formula of the module docstring): the body-frame (right) perturbation Jacobian of
    :func:`factors.euler.perturbation_jacobian` times the rates. Shapes ``(..., 3)``."""
    E = euler.perturbation_jacobian(rpy, euler.ROLL_PITCH_YAW, "right")
    return np.einsum("...ij,...j->...i", E, np.asarray(rpy_rate, dtype=float))


# --------------------------------------------------------------------------------------------
# kinematics


@dataclass(frozen=True)
class Kinematics:
    """The analytic state of a profile at times ``t`` (leading dimension N).

    ``r``, ``v``, ``a``: world position [m], velocity [m/s], acceleration [m/s^2];
    ``rpy``, ``rpy_rate``: Euler angles and their rates; ``C``: body-to-world attitude
    ``(N, 3, 3)``; ``omega``: body angular rate ``omega_B`` [rad/s]."""

    t: np.ndarray
    r: np.ndarray
    v: np.ndarray
    a: np.ndarray
    rpy: np.ndarray
    rpy_rate: np.ndarray
    C: np.ndarray
    omega: np.ndarray

    def __getitem__(self, index) -> "Kinematics":
        return Kinematics(*(getattr(self, f.name)[index] for f in fields(self)))

    def body_velocity(self) -> np.ndarray:
        """``B_v = C^T I_v``."""
        return np.einsum("...ji,...j->...i", self.C, self.v)

    def specific_force(self, gravity) -> np.ndarray:
        """``B_f = C^T (I_a - I_g)`` (primer eq. 42 without bias and noise)."""
        g = np.asarray(gravity, dtype=float)
        return np.einsum("...ji,...j->...i", self.C, self.a - g)


@dataclass(frozen=True)
class Profile:
    """A named analytic motion: ``position(t) -> (r, dr/dt, d2r/dt2)`` and
    ``attitude(t) -> (rpy, drpy/dt)``, vectorised over ``t`` (arrays of shape ``(..., 3)``)."""

    name: str
    description: str
    position: Callable = field(repr=False)
    attitude: Callable = field(repr=False)

    def evaluate(self, t) -> Kinematics:
        t = np.asarray(t, dtype=float)
        r, v, a = self.position(t)
        rpy, rpy_rate = self.attitude(t)
        r, v, a, rpy, rpy_rate = (np.broadcast_to(x, t.shape + (3,)).astype(float) for x in (r, v, a, rpy, rpy_rate))
        return Kinematics(
            t=t, r=r, v=v, a=a, rpy=rpy, rpy_rate=rpy_rate,
            C=euler.rpy_to_matrix(rpy), omega=body_rate_from_rpy(rpy, rpy_rate),
        )


def sinusoid_profile(name: str, description: str, position: tuple, attitude: tuple) -> Profile:
    """A profile whose three position coordinates and three Euler angles are :class:`Sinusoids`."""

    def pos(t):
        return _stack3(position, t)

    def att(t):
        angles, rates, _ = _stack3(attitude, t)
        return angles, rates

    return Profile(name, description, pos, att)


# --------------------------------------------------------------------------------------------
# the profiles

#: Angular frequency of the figure-eight: one loop in 30 s.
GENTLE_FREQUENCY = 2 * np.pi / 30.0

_GENTLE_POSITION = (
    Sinusoids(terms=((5.0, GENTLE_FREQUENCY, 0.0),)),  # x: 10 m wide
    Sinusoids(terms=((2.5, 2 * GENTLE_FREQUENCY, 0.0),)),  # y: 5 m across the lobes
    Sinusoids(offset=1.0, terms=((0.3, GENTLE_FREQUENCY, 0.5),)),  # z: a slow 0.6 m bob
)
_GENTLE_ROLL_PITCH = (
    Sinusoids(terms=((0.10, 3 * GENTLE_FREQUENCY, 0.3), (0.02, 2 * np.pi * 0.5, 0.0))),
    Sinusoids(terms=((0.05, 5 * GENTLE_FREQUENCY, 1.0), (0.02, 2 * np.pi * 0.3, 0.7))),
)


def _gentle_position(t):
    return _stack3(_GENTLE_POSITION, t)


def _gentle_attitude(t):
    """Yaw along the horizontal velocity (never zero on this figure-eight: ``v_x = 0`` only where
    ``cos(w t) = 0``, and there ``v_y = -2 * 2.5 w``); mild roll and pitch."""
    _, v, a = _gentle_position(t)
    yaw = np.arctan2(v[..., 1], v[..., 0])
    yaw_rate = (v[..., 0] * a[..., 1] - v[..., 1] * a[..., 0]) / (v[..., 0] ** 2 + v[..., 1] ** 2)
    roll, roll_rate, _ = _GENTLE_ROLL_PITCH[0].derivatives(t)
    pitch, pitch_rate, _ = _GENTLE_ROLL_PITCH[1].derivatives(t)
    return np.stack([roll, pitch, yaw], axis=-1), np.stack([roll_rate, pitch_rate, yaw_rate], axis=-1)


GENTLE = Profile(
    "gentle",
    "figure-eight 10 m x 5 m x 0.6 m, one loop in 30 s, 0.7-1.5 m/s (mean 1.0), heading along the "
    "path (yaw rate up to 0.67 rad/s), roll/pitch below 0.12 rad",
    _gentle_position,
    _gentle_attitude,
)

TUMBLING = sinusoid_profile(
    "tumbling",
    "continuous rotation about all axes, peak body rates 5.8/4.6/4.6 rad/s (x/y/z, rms 2 rad/s "
    "each, norm up to 6 rad/s), pitch through +-pi/2, a 3 m x 2 m x 1 m Lissajous translation at up "
    "to 2 m/s",
    position=(
        Sinusoids(terms=((1.5, 0.9, 0.0),)),
        Sinusoids(terms=((1.0, 1.3, 0.7),)),
        Sinusoids(offset=1.0, terms=((0.5, 1.7, 1.1),)),
    ),
    attitude=(
        Sinusoids(slope=1.0, terms=((0.5, 4.1, 0.0),)),  # roll: spins, 1 +- 2 rad/s
        Sinusoids(terms=((1.7, 2.2, 0.4),)),  # pitch: swings through +-pi/2
        Sinusoids(slope=-0.8, terms=((0.6, 3.3, 0.9),)),  # yaw: spins the other way, -0.8 +- 2 rad/s
    ),
)

_STILL = (Sinusoids(), Sinusoids(), Sinusoids(offset=1.0))

STATIC = sinusoid_profile(
    "static",
    "at rest, tilted (roll 0.1, pitch -0.2, yaw 0.7 rad): the IMU measures only gravity",
    position=_STILL,
    attitude=(Sinusoids(offset=0.1), Sinusoids(offset=-0.2), Sinusoids(offset=0.7)),
)

STATIC_LEVEL = sinusoid_profile(
    "static_level",
    "at rest and level (yaw 0.7 rad): the IMU measures only gravity, along the body z axis",
    position=_STILL,
    attitude=(Sinusoids(), Sinusoids(), Sinusoids(offset=0.7)),
)

#: The motion profiles by name.
PROFILES: dict[str, Profile] = {p.name: p for p in (GENTLE, TUMBLING, STATIC, STATIC_LEVEL)}
