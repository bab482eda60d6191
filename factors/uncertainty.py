"""Uncertain rotations and rotated vectors, after Barfoot (as presented in reference 001).

Perturbations (the three rows of the slides' table). A random rotation ``C`` about a nominal
``C_bar`` is written with a zero-mean Gaussian ``eps ~ N(0, Sigma)`` in one of three charts:

=========  ===============================  ==============================================
chart      random rotation                   in this project
=========  ===============================  ==============================================
left       ``C = exp(eps^) C_bar``           the primer's ``C_bar [+] eps`` (``so3.boxplus``);
                                             ``eps`` in the world frame ``I`` for ``Phi_IB``
right      ``C = C_bar exp(eps^)``           GTSAM's ``Rot3.retract``; ``eps`` in the body frame
middle     ``C = exp((mu + eps)^)``          ``mu = so3.log(C_bar)``: noise added to the rotation
                                             vector itself
=========  ===============================  ==============================================

The slides' ``^`` is the skew (hat) operator, the same matrix as ``so3.skew`` (the lecture in
reference 004 prints it entrywise, and the slides' second-order moment ``E[eps^ eps^] =
Sigma - tr(Sigma) I`` holds for exactly that matrix), and their ``exp`` is Rodrigues' formula, so
the slides' left perturbation is *exactly* the primer's ``[+]``; no sign flips are needed.

Chart conversions. ``exp(eps_l^) C = C exp((C^T eps_l)^)``, so ``eps_r = C^T eps_l`` EXACTLY
(for every sample, not only to first order): ``Sigma_r = C^T Sigma_l C``. The middle chart is
related to the others only to first order, through the SO(3) Jacobians
(``exp((mu + d)^) ~= exp((Gamma(mu) d)^) exp(mu^) = exp(mu^) exp((Gamma(-mu) d)^)`` with
``Gamma = so3.gamma``, the left Jacobian): ``eps_l ~= Gamma(mu) eps_m``, ``eps_r ~= Gamma(-mu) eps_m``.
Note on the slides: their struck-out so(3) column reads ``phi ~= mu + J_l(mu) eps_l``; with ``J_l``
the left Jacobian the first-order relation is ``phi ~= mu + J_l(mu)^-1 eps_l`` (the inverse), and
likewise ``J_r(mu)^-1`` in the right row. Monte Carlo (tests/factors/test_uncertainty.py,
``test_slides_struck_out_jacobian_would_be_wrong``) confirms the inverse and rejects the printed
form by hundreds of standard errors.

Rotated vector ``y = C x`` with the left chart (``z = C_bar x``, ``t = tr Sigma``):
expanding ``exp(eps^) = I + eps^ + eps^2/2 + eps^3/6 + eps^4/24 + ...``, odd moments vanish and
``eps^2 = eps eps^T - |eps|^2 I``, ``eps^4 = -|eps|^2 eps^2``, and Isserlis' theorem gives
``E[eps^2] = Sigma - t I`` and ``E[eps^4] = (t^2 + 2 tr(Sigma^2)) I - Sigma (t I + 2 Sigma)``:

* mean, 2nd order: ``(I + (Sigma - t I)/2) z``;
* mean, 4th order: ``(I + (Sigma - t I)/2 + ((t^2 + 2 tr Sigma^2) I - t Sigma - 2 Sigma^2)/24) z``.
  This is the slides' expression; as typeset, its bracket closes before the 1/24 term, so that
  ``C_bar x`` would multiply that term alone. The terms themselves are right (Monte Carlo and
  quadrature agree); the bracket belongs around all three.
* covariance, 2nd order (the linearisation ``y ~= z - z^ eps``): ``z^ Sigma z^T``;
* covariance, 4th order (derived here, not on the slides, checked against Monte Carlo and
  quadrature): ``z^ Sigma z^T - z^ (t Sigma + 2 Sigma^2) z^T / 3
  + [ (z^T Sigma z) Sigma + Sigma z z^T Sigma - 2 (Sigma^2 z z^T + z z^T Sigma^2)
  + 2 tr(Sigma^2) z z^T ] / 4``.

The truncation errors are of order ``|Sigma|^2`` (2nd order) and ``|Sigma|^3`` (4th order) times
``|x|``: the series is useful while the standard deviations stay well below 1 rad (at 1 rad the
2nd-order mean of an isotropic Sigma is already zero where the true mean is ``x/3``).

Every function is vectorised: rotations ``(..., 3, 3)``, covariances ``(..., n, n)``, vectors
``(..., 3)``, with NumPy broadcasting over the leading dimensions.
"""
from __future__ import annotations

import numpy as np

from factors import euler, so3
from factors.axis_angle import check_matrix, check_rotation_matrix, check_vector
from factors.chart import primer_from_gtsam
from factors.errors import InputError

#: The chart names accepted by the functions of this module.
CHARTS = ("left", "right", "middle")

#: Relative asymmetry ``max|S - S^T| / max|S|`` accepted in a covariance.
SYMMETRY_TOLERANCE = 1e-8


def _check_chart(chart, name: str, allowed=CHARTS) -> str:
    if chart not in allowed:
        raise InputError(f"{name}: expected one of {', '.join(map(repr, allowed))}, got {chart!r}")
    return chart


def check_covariance(Sigma, name: str = "Sigma", size: int | None = None) -> np.ndarray:
    """Return ``Sigma`` as a float array of shape ``(..., n, n)`` (``n = size`` if given, else
    any ``n >= 3``) after checking it is finite, symmetric (to :data:`SYMMETRY_TOLERANCE`
    relative) and positive semi-definite (eigenvalues >= ``-1e-12`` times the largest); raise
    ``ValueError`` naming ``name`` otherwise."""
    try:
        S = np.asarray(Sigma, dtype=float)
    except (TypeError, ValueError) as err:
        raise InputError(f"{name}: expected a covariance matrix (..., n, n): {err}") from None
    if S.ndim < 2 or S.shape[-1] != S.shape[-2] or (size is not None and S.shape[-1] != size):
        want = f"{size}, {size}" if size is not None else "n, n"
        raise InputError(f"{name}: expected a covariance of shape (..., {want}), got {S.shape}")
    if size is None and S.shape[-1] < 3:
        raise InputError(f"{name}: expected n >= 3 (it must hold a rotation block), got {S.shape}")
    S = check_matrix(S, name, S.shape[-1])
    scale = np.abs(S).max(axis=(-2, -1), initial=0.0)
    asym = np.abs(S - np.swapaxes(S, -1, -2)).max(axis=(-2, -1))
    if np.any(asym > SYMMETRY_TOLERANCE * np.maximum(scale, 1e-300)):
        raise InputError(f"{name}: expected a symmetric matrix; max|S - S^T| = {np.max(asym):.3g}")
    S = 0.5 * (S + np.swapaxes(S, -1, -2))
    low = np.linalg.eigvalsh(S)[..., 0]
    if np.any(low < -1e-12 * np.maximum(scale, 1e-300)):
        raise InputError(
            f"{name}: expected a positive semi-definite matrix; smallest eigenvalue {np.min(low):.3g}"
        )
    return S


# ----------------------------------------------------------------------------------------------
# The three charts
# ----------------------------------------------------------------------------------------------


def perturb(C_bar, eps, chart: str = "left") -> np.ndarray:
    """The rotation ``C`` that the perturbation ``eps`` (shape ``(..., 3)``) makes of ``C_bar``:
    ``exp(eps) C_bar`` (left), ``C_bar exp(eps)`` (right) or ``exp(log(C_bar) + eps)`` (middle)."""
    C_bar = check_rotation_matrix(C_bar, "C_bar")
    eps = check_vector(eps, "eps")
    _check_chart(chart, "chart")
    if chart == "left":
        return so3.exp(eps) @ C_bar
    if chart == "right":
        return C_bar @ so3.exp(eps)
    return so3.exp(so3.log(C_bar) + eps)


def perturbation_of(C, C_bar, chart: str = "left") -> np.ndarray:
    """Inverse of :func:`perturb`: ``log(C C_bar^T)`` (left, the primer's ``C [-] C_bar``),
    ``log(C_bar^T C)`` (right) or ``log(C) - log(C_bar)`` (middle), each exact (on the ball of
    radius pi of ``log``)."""
    C = check_rotation_matrix(C, "C")
    C_bar = check_rotation_matrix(C_bar, "C_bar")
    _check_chart(chart, "chart")
    if chart == "left":
        return so3.log(C @ np.swapaxes(C_bar, -1, -2))
    if chart == "right":
        return so3.log(np.swapaxes(C_bar, -1, -2) @ C)
    return so3.log(C) - so3.log(C_bar)


def chart_jacobian(C, source: str, target: str) -> np.ndarray:
    """``J = d eps_target / d eps_source`` at the nominal rotation ``C`` (shape ``(..., 3, 3)``).

    left -> right ``C^T`` and right -> left ``C`` are exact linear maps (``eps_r = C^T eps_l`` for
    every sample). Conversions involving the middle chart, with ``mu = so3.log(C)``, are first
    order: middle -> left ``Gamma(mu)``, left -> middle ``Gamma(mu)^-1``, middle -> right
    ``Gamma(-mu)``, right -> middle ``Gamma(-mu)^-1`` (``Gamma = so3.gamma``). The middle chart
    is singular where ``|mu|`` reaches pi (``log`` wraps there)."""
    C = check_rotation_matrix(C)
    _check_chart(source, "source")
    _check_chart(target, "target")
    if source == target:
        return np.broadcast_to(np.eye(3), C.shape).copy()
    if {source, target} == {"left", "right"}:
        left_from_right = primer_from_gtsam(C)  # the one chart adapter (factors.chart)
        return (np.swapaxes(left_from_right, -1, -2) if source == "left" else left_from_right).copy()
    mu = so3.log(C)
    if target == "middle":
        return so3.gamma_inv(mu if source == "left" else -mu)
    return so3.gamma(mu if target == "left" else -mu)


def convert_covariance(Sigma, C, source: str, target: str, index: int = 0) -> np.ndarray:
    """Covariance of the rotation perturbation in chart ``target`` given it in chart ``source``,
    ``J Sigma J^T`` with ``J = chart_jacobian(C, source, target)``.

    ``Sigma`` is ``(..., n, n)`` with ``n >= 3``; the rotation block is rows and columns
    ``index : index + 3`` and the rest (vector-valued variables, which need no conversion) is left
    as it is, cross-covariances included: ``T Sigma T^T`` with ``T = I`` except ``J`` on that
    block. So a full state covariance (e.g. the 15-dim ``(r, v, Phi, b_f, b_w)``, attitude at
    index 6) converts in one call. ``C`` is the nominal rotation (a 3x3 array, a stack of them
    broadcasting against ``Sigma``'s leading dimensions, or a ``gtsam.Rot3``)."""
    Sigma = check_covariance(Sigma)
    n = Sigma.shape[-1]
    if not isinstance(index, (int, np.integer)) or isinstance(index, bool) or not 0 <= index <= n - 3:
        raise InputError(f"index: expected an integer in [0, {n - 3}] (start of the rotation block), got {index!r}")
    J = chart_jacobian(C, source, target)
    lead = np.broadcast_shapes(J.shape[:-2], Sigma.shape[:-2])
    T = np.broadcast_to(np.eye(n), lead + (n, n)).copy()
    T[..., index:index + 3, index:index + 3] = J
    out = T @ Sigma @ np.swapaxes(T, -1, -2)
    return 0.5 * (out + np.swapaxes(out, -1, -2))


def covariance_left_to_right(Sigma, C, index: int = 0) -> np.ndarray:
    """Primer (left, world-frame) covariance -> GTSAM (right, body-frame): ``C^T Sigma C`` on the
    rotation block. Exact. See :func:`convert_covariance` for ``index`` and larger ``Sigma``."""
    return convert_covariance(Sigma, C, "left", "right", index)


def covariance_right_to_left(Sigma, C, index: int = 0) -> np.ndarray:
    """GTSAM (right, body-frame; e.g. ``gtsam.Marginals.marginalCovariance`` of a ``Rot3``) ->
    primer (left, world-frame): ``C Sigma C^T`` on the rotation block. Exact."""
    return convert_covariance(Sigma, C, "right", "left", index)


def state_covariance_to_primer(cov_rpvb: np.ndarray, rotation) -> np.ndarray:
    """A keyframe's joint covariance from GTSAM -- variables ``(Rot3, Point3, velocity, bias)`` in
    that order, the ``Rot3`` block in GTSAM's right chart -- as the primer's 15x15 error-state
    covariance ``(dr, dv, dphi, db_f, db_w)`` with the LEFT attitude increment ``dphi = C d``
    (``rotation``: the 3x3 matrix ``C`` or a ``gtsam.Rot3``)."""
    order = np.r_[3:6, 6:9, 0:3, 9:15]  # (Rot3, Point3, V, bias) -> (r, v, phi, b_f, b_w)
    cov = np.asarray(cov_rpvb, dtype=float)[np.ix_(order, order)]
    return covariance_right_to_left(cov, primer_from_gtsam(rotation), index=6)


def covariance_middle_to_left(Sigma, C, index: int = 0) -> np.ndarray:
    """Middle -> left: ``Gamma(mu) Sigma Gamma(mu)^T``, ``mu = log C``. First order."""
    return convert_covariance(Sigma, C, "middle", "left", index)


# ----------------------------------------------------------------------------------------------
# Rotated vectors
# ----------------------------------------------------------------------------------------------


def _rotated_inputs(C_bar, Sigma, x, order, chart, orders):
    C_bar = check_rotation_matrix(C_bar, "C_bar")
    Sigma = check_covariance(Sigma, "Sigma", size=3)
    x = check_vector(x, "x")
    if isinstance(order, bool) or order not in orders:
        raise InputError(f"order: expected one of {orders}, got {order!r}")
    _check_chart(chart, "chart", ("left", "right"))
    if chart == "right":  # exact: eps_l = C_bar eps_r
        Sigma = C_bar @ Sigma @ np.swapaxes(C_bar, -1, -2)
    z = (C_bar @ x[..., None])[..., 0]
    t = np.trace(Sigma, axis1=-2, axis2=-1)[..., None, None]
    S2 = Sigma @ Sigma
    return z, Sigma, t, S2


def rotated_vector_mean(C_bar, Sigma, x, order: int = 4, chart: str = "left") -> np.ndarray:
    """``E[C x]`` for ``C = exp(eps^) C_bar`` (``chart='left'``, the primer's / the slides') or
    ``C = C_bar exp(eps^)`` (``'right'``, GTSAM's), ``eps ~ N(0, Sigma)``, truncated at ``order``
    0 (``C_bar x``), 2 or 4 in ``eps``; formulas in the module docstring. ``x`` is in the frame
    ``C`` maps from (body), the result in the frame it maps to (world)."""
    z, Sigma, t, S2 = _rotated_inputs(C_bar, Sigma, x, order, chart, (0, 2, 4))
    if order == 0:
        return z
    eye = np.eye(3)
    M = eye + 0.5 * (Sigma - t * eye)
    if order == 4:
        tr2 = np.trace(S2, axis1=-2, axis2=-1)[..., None, None]
        M = M + ((t * t + 2.0 * tr2) * eye - t * Sigma - 2.0 * S2) / 24.0
    return (M @ z[..., None])[..., 0]


def rotated_vector_covariance(C_bar, Sigma, x, order: int = 4, chart: str = "left") -> np.ndarray:
    """``Cov[C x]`` for ``C`` as in :func:`rotated_vector_mean`, to ``order`` 2 (the linearised
    ``z^ Sigma z^T``, ``z = C_bar x``) or 4 in ``eps``; formulas in the module docstring.
    In the world frame (the frame ``C`` maps to)."""
    z, Sigma, t, S2 = _rotated_inputs(C_bar, Sigma, x, order, chart, (2, 4))
    W = so3.skew(z)
    Wt = np.swapaxes(W, -1, -2)
    cov = W @ Sigma @ Wt
    if order == 4:
        zc = z[..., :, None]
        Z = zc @ np.swapaxes(zc, -1, -2)
        Sz = Sigma @ zc
        zSz = (np.swapaxes(zc, -1, -2) @ Sz)
        S2Z = S2 @ Z
        tr2 = np.trace(S2, axis1=-2, axis2=-1)[..., None, None]
        cov = (
            cov
            - W @ (t * Sigma + 2.0 * S2) @ Wt / 3.0
            + 0.25 * (zSz * Sigma + Sz @ np.swapaxes(Sz, -1, -2)
                      - 2.0 * (S2Z + np.swapaxes(S2Z, -1, -2)) + 2.0 * tr2 * Z)
        )
    return 0.5 * (cov + np.swapaxes(cov, -1, -2))


# ----------------------------------------------------------------------------------------------
# Euler angles
# ----------------------------------------------------------------------------------------------


def covariance_to_euler(Sigma, C, convention: str = euler.ROLL_PITCH_YAW, chart: str = "left") -> np.ndarray:
    """First-order covariance of the Euler angles ``euler.from_matrix(C, convention)`` of a
    rotation with perturbation covariance ``Sigma`` (3x3) in ``chart`` ('left', 'right' or
    'middle'): ``E^-1 Sigma E^-T`` with ``E = euler.perturbation_jacobian``. For reports, e.g.
    roll-pitch-yaw standard deviations ``sqrt(diag)`` of the default ``'sxyz'``.

    Entries are NaN where the angles are singular (``|det E| < euler.SINGULAR_TOLERANCE``:
    gimbal lock / degenerate middle angle), where no finite covariance exists."""
    C = check_rotation_matrix(C)
    Sigma = check_covariance(Sigma, size=3)
    _check_chart(chart, "chart")
    if chart == "middle":
        Sigma = convert_covariance(Sigma, C, "middle", "left")
        chart = "left"
    angles = euler.from_matrix(C, convention)
    E = euler.perturbation_jacobian(angles, convention, chart)
    det = np.linalg.det(E)
    singular = np.abs(det) < euler.SINGULAR_TOLERANCE
    E = np.where(singular[..., None, None], np.eye(3), E)
    Einv = np.linalg.inv(E)
    out = Einv @ Sigma @ np.swapaxes(Einv, -1, -2)
    out = 0.5 * (out + np.swapaxes(out, -1, -2))
    return np.where(singular[..., None, None], np.nan, out)


def covariance_from_euler(Sigma_angles, angles, convention: str = euler.ROLL_PITCH_YAW,
                          chart: str = "left") -> np.ndarray:
    """First-order covariance, in ``chart``, of the rotation perturbation given a covariance of
    its Euler ``angles``: ``E Sigma_angles E^T`` (``E = euler.perturbation_jacobian``; for
    ``'middle'`` converted from the left chart). Finite everywhere, gimbal lock included (there
    it is rank-deficient)."""
    Sigma_angles = check_covariance(Sigma_angles, "Sigma_angles", size=3)
    _check_chart(chart, "chart")
    E = euler.perturbation_jacobian(angles, convention, "left" if chart == "middle" else chart)
    out = E @ Sigma_angles @ np.swapaxes(E, -1, -2)
    out = 0.5 * (out + np.swapaxes(out, -1, -2))
    if chart == "middle":
        out = convert_covariance(out, euler.to_matrix(angles, convention), "left", "middle")
    return out
