"""Numerical differentiation on manifolds, and a checker for any GTSAM factor's Jacobians.

Two public tools:

* :func:`numerical_jacobian` differentiates a function whose arguments and value are vectors and/or
  rotations with central differences in the primer's sense (eqs. 19, 20): a rotation argument is
  perturbed with ``Phi [+] (eps e_i) = exp(eps e_i) o Phi`` and a rotation value is compared with
  ``[-]``. It is the numerical twin of every analytic Jacobian the project derives.
* :func:`check_factor` compares any ``gtsam.NonlinearFactor``'s own linearisation (the analytic
  Jacobians its author wrote, whitened by its noise model) with central differences of its
  whitened error in GTSAM's chart (``Values.retract``), key by key. It works on native factors,
  on the project's factors and on a user's ``CustomFactor`` alike.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from factors import so3
from factors.errors import InputError, InputTypeError, MissingKeyError

#: Default central-difference step: truncation O(eps^2) and round-off O(1e-16/eps) balance near 1e-5.
DEFAULT_STEP = 1e-6

VECTOR = "vector"
ROTATION = "rotation"


def _is_rotation(x) -> bool:
    if hasattr(x, "matrix") and hasattr(x, "rpy"):  # gtsam.Rot3
        return True
    x = np.asarray(x)
    return (
        x.shape == (3, 3)
        and np.allclose(x @ x.T, np.eye(3), atol=1e-9)
        and np.linalg.det(x) > 0
    )


def _matrix(x) -> np.ndarray:
    return np.asarray(x.matrix() if hasattr(x, "matrix") else x, dtype=float)


def _like(template, C: np.ndarray):
    """``C`` as the same type as ``template`` (3x3 array or gtsam.Rot3)."""
    if hasattr(template, "matrix"):
        import gtsam

        return gtsam.Rot3(C)
    return C


class Manifold:
    """A manifold for :func:`numerical_jacobian`: ``dim``, ``plus(x, delta)`` and
    ``minus(a, b)`` (with ``minus(plus(x, d), x) == d``). Subclass it, or pass any object with
    these three members as a kind, for composite states such as the IMU state."""

    dim: int

    def plus(self, x, delta: np.ndarray):  # pragma: no cover - interface
        raise NotImplementedError

    def minus(self, a, b) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError


def _perturb(arg, kind, index: int, step: float):
    if kind == ROTATION:
        return _like(arg, so3.boxplus(_matrix(arg), step * np.eye(3)[index]))
    if kind == VECTOR:
        flat = np.array(arg, dtype=float).reshape(-1)
        flat[index] += step
        return flat.reshape(np.shape(arg))
    return kind.plus(arg, step * np.eye(kind.dim)[index])


def _difference(value, reference, kind) -> np.ndarray:
    if kind == ROTATION:
        return so3.boxminus(_matrix(value), _matrix(reference))
    if kind == VECTOR:
        return (np.asarray(value, dtype=float) - np.asarray(reference, dtype=float)).reshape(-1)
    return np.asarray(kind.minus(value, reference), dtype=float)


def _check_kind(kind, role: str) -> None:
    """Raise ``ValueError`` unless ``kind`` is ``"vector"``, ``"rotation"`` or a Manifold-like object."""
    if isinstance(kind, str):
        if kind not in (VECTOR, ROTATION):
            raise InputError(f"unknown {role} kind {kind!r}; expected {VECTOR!r}, {ROTATION!r} or a Manifold")
    elif not all(hasattr(kind, member) for member in ("dim", "plus", "minus")):
        raise InputError(
            f"{role} kind {kind!r} is neither {VECTOR!r}, {ROTATION!r} nor a Manifold (dim, plus, minus)"
        )


def _dim(arg, kind) -> int:
    if kind == ROTATION:
        return 3
    if kind == VECTOR:
        return int(np.size(arg))
    return int(kind.dim)


def numerical_jacobian(
    f: Callable,
    *args,
    step: float = DEFAULT_STEP,
    arg_kinds: Sequence | None = None,
    value_kind=None,
) -> list[np.ndarray]:
    """Central-difference Jacobians of ``f(*args)`` with respect to each argument.

    An argument is a rotation (a 3x3 rotation matrix or a ``gtsam.Rot3``, perturbed with the
    primer's boxplus, 3 columns) or a vector (any array, flattened, one column per entry). The
    value is a rotation (compared with boxminus, 3 rows) or an array (flattened). Kinds are
    detected from the values; pass ``arg_kinds`` / ``value_kind`` (``"vector"`` or ``"rotation"``)
    to override, e.g. for a 3x3 matrix that happens to be orthonormal but is not a rotation; a
    kind may also be a :class:`Manifold` (any object with ``dim``, ``plus``, ``minus``).

    Column ``i`` for a rotation argument is ``(f(Phi [+] eps e_i) [-] f(Phi)
    - f(Phi [+] -eps e_i) [-] f(Phi)) / (2 eps)``, the central form of the primer's eqs. (19, 20),
    accurate to O(eps^2).
    """
    kinds = list(arg_kinds) if arg_kinds is not None else [ROTATION if _is_rotation(a) else VECTOR for a in args]
    if len(kinds) != len(args):
        raise InputError(f"arg_kinds has {len(kinds)} entries for {len(args)} arguments")
    for i, kind in enumerate(kinds):
        _check_kind(kind, f"argument {i}")
    if value_kind is not None:
        _check_kind(value_kind, "value")
    reference = f(*args)
    out_kind = value_kind or (ROTATION if _is_rotation(reference) else VECTOR)
    jacobians = []
    for position, (arg, kind) in enumerate(zip(args, kinds)):
        dim = _dim(arg, kind)
        columns = []
        for i in range(dim):
            shifted = []
            for sign in (1.0, -1.0):
                moved = list(args)
                moved[position] = _perturb(arg, kind, i, sign * step)
                shifted.append(_difference(f(*moved), reference, out_kind))
            columns.append((shifted[0] - shifted[1]) / (2.0 * step))
        jacobians.append(np.stack(columns, axis=-1))
    return jacobians


@dataclass
class Comparison:
    """Analytic versus numerical Jacobian: the worst absolute and relative error and a verdict.

    ``ok`` holds when ``|analytic - numerical| <= atol + rtol |numerical|`` entry by entry;
    ``max_rel_error`` is ``max |difference| / max(max |numerical|, 1)``.
    """

    name: str
    max_abs_error: float
    max_rel_error: float
    ok: bool

    def as_dict(self) -> dict:
        return {
            "name": self.name,
            "max_abs_error": float(self.max_abs_error),
            "max_rel_error": float(self.max_rel_error),
            "ok": bool(self.ok),
        }


def compare(name: str, analytic: np.ndarray, numerical: np.ndarray, atol: float, rtol: float) -> Comparison:
    """Compare two Jacobians of the same shape (see :class:`Comparison`)."""
    analytic = np.asarray(analytic, dtype=float)
    numerical = np.asarray(numerical, dtype=float)
    if analytic.shape != numerical.shape:
        raise InputError(f"{name}: analytic Jacobian has shape {analytic.shape}, numerical {numerical.shape}")
    if not np.all(np.isfinite(analytic)):
        return Comparison(name, np.inf, np.inf, False)
    diff = np.abs(analytic - numerical)
    max_abs = float(diff.max(initial=0.0))
    max_rel = max_abs / max(float(np.abs(numerical).max(initial=0.0)), 1.0)
    ok = bool(np.all(diff <= atol + rtol * np.abs(numerical)))
    return Comparison(name, max_abs, max_rel, ok)


def table(rows: Sequence[Comparison], title: str = "") -> str:
    """A fixed-width text table of comparisons, one line each."""
    width = max([len(r.name) for r in rows] + [5])
    lines = [title] if title else []
    lines.append(f"{'check':<{width}}  {'max abs err':>12}  {'max rel err':>12}  result")
    for r in rows:
        lines.append(
            f"{r.name:<{width}}  {r.max_abs_error:12.3e}  {r.max_rel_error:12.3e}  {'ok' if r.ok else 'FAIL'}"
        )
    return "\n".join(lines)


@dataclass
class FactorCheck:
    """Result of :func:`check_factor`: per key, the factor's whitened Jacobian, its numerical twin
    and their comparison; ``ok`` when every key passes. ``str()`` is a readable table."""

    factor_name: str
    keys: list[int]
    comparisons: list[Comparison]
    analytic: dict = field(repr=False, default_factory=dict)
    numerical: dict = field(repr=False, default_factory=dict)

    @property
    def ok(self) -> bool:
        return all(c.ok for c in self.comparisons)

    @property
    def max_abs_error(self) -> dict:
        return {c.name: c.max_abs_error for c in self.comparisons}

    @property
    def max_rel_error(self) -> dict:
        return {c.name: c.max_rel_error for c in self.comparisons}

    def __str__(self) -> str:
        verdict = "ok" if self.ok else "FAIL"
        return table(self.comparisons, title=f"{self.factor_name}: {verdict}")

    def __bool__(self) -> bool:  # so that `assert check_factor(...)` reads naturally
        return self.ok


def _key_label(key: int) -> str:
    import gtsam

    try:
        return gtsam.DefaultKeyFormatter(key)
    except Exception:  # noqa: BLE001 -- a formatter missing in some builds; the key itself is shown
        return str(key)


def _whitened_error(factor, values, base_model) -> np.ndarray:
    """The factor's error whitened by its Gaussian noise model: ``base_model.whiten`` of the
    unwhitened error for factors with a robust noise model, ``-b`` of the linearisation otherwise."""
    if base_model is not None:
        return np.asarray(base_model.whiten(factor.unwhitenedError(values)), dtype=float)
    return -_linearize(factor, values)[1]


def _robust_base(factor):
    """The Gaussian base of a robust noise model, or None. GTSAM scales a robust factor's
    linearisation ``(A, b)`` by ``sqrt(weight)`` at the current error -- one scalar for the
    ``Block`` reweight scheme, one per row for ``Scalar`` (see :func:`_robust_row_scales`); that
    scaling is not part of the derivative, so the check divides it out and compares against
    differences of the base-whitened error."""
    import gtsam

    model = factor.noiseModel() if hasattr(factor, "noiseModel") else None
    if isinstance(model, gtsam.noiseModel.Robust) and hasattr(factor, "unwhitenedError"):
        return model.noise()
    return None


def _robust_row_scales(factor, b: np.ndarray, e_w: np.ndarray) -> np.ndarray:
    """The factors ``s`` (one per row) with ``b = -s * e_w`` that a robust noise model applied:
    ``sqrt(w(|e_w|))`` for every row (``Block`` reweighting, GTSAM's default) or
    ``sqrt(w(|e_w[i]|))`` for row ``i`` (``Scalar``). The scheme is not exposed to Python, so the
    one that reproduces ``b`` is used."""
    estimator = factor.noiseModel().robust()
    block = np.full(e_w.shape, np.sqrt(estimator.weight(float(np.linalg.norm(e_w)))))
    rows = np.sqrt(np.array([estimator.weight(float(abs(x))) for x in e_w]))
    for s in (block, rows):
        if np.all(s > 0) and np.allclose(b, -s * e_w, rtol=1e-9, atol=1e-300):
            return s
    raise InputTypeError(
        f"check_factor: cannot undo the robust weighting of {type(factor).__name__} "
        "(a weight of 0, or a reweighting scheme other than Block and Scalar)"
    )


def _linearize(factor, values):
    import gtsam

    linear = factor.linearize(values)
    if not isinstance(linear, gtsam.JacobianFactor):
        # pybind11 types a JacobianFactor subclass it does not know (e.g. the fixed-size
        # BinaryJacobianFactor that BetweenFactor returns) as its base GaussianFactor. Convert
        # such a factor; the conversion would Cholesky-factor a HessianFactor, so accept the
        # result only if it has one row per error dimension.
        if isinstance(linear, gtsam.HessianFactor) or not isinstance(linear, gtsam.GaussianFactor):
            linear = None
        else:
            linear = gtsam.JacobianFactor(linear)
            if hasattr(factor, "dim") and linear.rows() != factor.dim():
                linear = None
        if linear is None:
            raise InputTypeError(
                f"check_factor needs a factor that linearises to a JacobianFactor; "
                f"{type(factor).__name__} gave {type(factor.linearize(values)).__name__}"
            )
    return linear.jacobian()


def check_factor(factor, values, atol: float = 1e-6, rtol: float = 1e-5, step: float = DEFAULT_STEP) -> FactorCheck:
    """Check a GTSAM factor's analytic Jacobians against central differences, key by key.

    ``factor`` is any ``gtsam.NonlinearFactor`` that linearises to a ``JacobianFactor``;
    ``values`` holds (at least) its keys. The analytic Jacobian is the factor's own
    ``linearize(values)``; the numerical one differentiates the whitened error ``-b`` of that
    linearisation at ``values.retract(+-step e_i)``, i.e. in GTSAM's chart (a right increment for
    ``Rot3``). Robust noise models are checked through their Gaussian base (see
    :func:`_robust_base`). Both sides are whitened, so ``atol`` is in units of sigma per
    unit of the variable.
    """
    import gtsam

    base = _robust_base(factor)
    keys = list(factor.keys())
    missing = [k for k in keys if not values.exists(k)]
    if missing:
        raise MissingKeyError(f"check_factor: values lack the factor's keys {[_key_label(k) for k in missing]}")
    A, b = _linearize(factor, values)
    if base is not None:
        A = A / _robust_row_scales(factor, b, _whitened_error(factor, values, base))[:, None]
    zeros = values.zeroVectors()
    dims = [zeros.at(k).shape[0] for k in keys]
    offsets = np.concatenate([[0], np.cumsum(dims)])
    comparisons, analytic, numerical = [], {}, {}
    for index, key in enumerate(keys):
        columns = []
        for i in range(dims[index]):
            errors = []
            for sign in (1.0, -1.0):
                delta = gtsam.VectorValues()
                for k, d in zip(keys, dims):
                    v = np.zeros(d)
                    if k == key:
                        v[i] = sign * step
                    delta.insert(k, v)
                errors.append(_whitened_error(factor, values.retract(delta), base))
            columns.append((errors[0] - errors[1]) / (2.0 * step))
        num = np.stack(columns, axis=-1)
        ana = A[:, offsets[index] : offsets[index + 1]]
        label = _key_label(key)
        analytic[key], numerical[key] = ana, num
        comparisons.append(compare(label, ana, num, atol, rtol))
    return FactorCheck(type(factor).__name__, keys, comparisons, analytic, numerical)
