"""Trajectory evaluation: time association, alignment, ATE, RPE, NEES and chi-square bounds.

Poses are ``(r, C)``: world positions ``(N, 3)`` and body-to-world attitudes ``(N, 3, 3)``
(docs/design.md, section 1). The definitions follow the usual ones of the TUM benchmark as evo
implements them, so that the numbers agree with ``evo_ape`` / ``evo_rpe`` on the same files
(tested to 1e-9):

* :func:`associate`: nearest time stamps within ``max_dt``. The trajectory with fewer poses is
  walked (the estimate when both have as many), each of its stamps paired with the nearest stamp
  of the other (the earlier one on a tie) if it is at most ``max_dt`` away. A stamp of the longer
  trajectory may serve two stamps of the shorter one, as in evo. (A time difference that equals
  ``max_dt`` only up to round-off, e.g. ``0.010000000000000009`` against 0.01, pairs in evo and
  not here: about 2% of random stamp sets with such ties associate differently.)
* :func:`umeyama`: least-squares similarity ``dst ~= s R src + t`` (Umeyama 1991); alignment
  ``'se3'`` is Umeyama without scale applied to the estimate (``r' = R r + t``, ``C' = R C``),
  ``'sim3'`` with scale (``r' = s R r + t``: a monocular trajectory, evo's ``--correct_scale``),
  each fitted to all associated poses or to the first ``n_align`` (evo's ``--n_to_align``) and
  applied to all, ``'posyaw'`` the 4-DoF alignment (translation and a rotation about the world z axis, the
  direction of gravity: what is unobservable for a visual-inertial or IMU+GPS estimator without
  an absolute heading), ``'translation'`` the translation only, ``'none'`` no alignment. Every
  fit reports its conditioning (:func:`fit_alignment`): on positions near a line (a straight
  drive) the rotation about that line is fitted to the errors and can be anything, so a rotation
  the positions do not determine is not applied: the next well-posed alignment is, with a note
  (evo applies it regardless).
* ATE (:func:`ate`): translation error ``|r_ref - r_est'|`` and rotation error, the angle of
  ``C_ref^T C_est'`` in degrees, per associated pose, after alignment; statistics
  (:func:`statistics`): RMSE, mean, median, std (population), min, max, SSE.
* RPE (:func:`rpe`): for pose pairs ``(i, j)`` the error ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)``
  of the reference ``Q`` and estimate ``P``; translation ``|t(E)|`` [m] and rotation angle of
  ``R(E)`` [deg]. Pairs (evo's semantics): unit ``'frames'`` -> ``(0, d), (d, 2d), ...`` (all
  ``(i, i + d)`` with ``all_pairs``); unit ``'m'`` -> the next pose after the accumulated path
  length of the estimate reaches ``delta`` (with ``all_pairs``: for each i the pose whose path
  distance is nearest to ``delta``, within 10%); unit ``'s'`` (not in evo) -> the same rules on
  elapsed time instead of path length.
* NEES (:func:`nees`): error ``e = x_true [-] x_est`` in the estimator's error-state convention
  (``factors.imu``: vectors subtract, attitude ``log(C_true C_est^T)``, a world-frame LEFT
  perturbation), ``NEES = e^T P^-1 e`` with P the matching block of the 15x15 error-state
  covariance; ``part='pose'`` uses ``(r, phi)``: rows/cols 0:3 and 6:9 (6 dims).
* Chi-square quantiles and the NEES intervals: :mod:`smoother.stats`.
* Two estimators on the same reference points: :func:`rmse_difference`, the difference of their
  RMS errors with a block-bootstrap interval (errors along a trajectory are correlated, so whole
  blocks of them are resampled, not single points).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from factors import so3
from factors.errors import InputError
from smoother.evaluation.modes import ALIGN_MODES, DELTA_UNITS

#: Error-state indices of the parts NEES can be computed on (factors.imu order r, v, phi, b_f, b_w).
NEES_PARTS = {
    "pose": np.r_[0:3, 6:9],
    "position": np.r_[0:3],
    "orientation": np.r_[6:9],
    "velocity": np.r_[3:6],
    "full": np.r_[0:15],
}


# ------------------------------------------------------------------------------------------
# association and alignment


def associate(t_ref, t_est, max_dt: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(i_ref, i_est)`` of associated stamps (see the module docstring). Both time
    arrays must be sorted increasingly."""
    t_ref, t_est = np.asarray(t_ref, dtype=float), np.asarray(t_est, dtype=float)
    if not (np.isfinite(max_dt) and max_dt >= 0):
        raise InputError(f"max_dt: expected a finite time >= 0, got {max_dt!r}")
    for name, t in (("t_ref", t_ref), ("t_est", t_est)):
        if t.ndim != 1 or (t.size > 1 and np.any(np.diff(t) < 0)):
            raise InputError(f"{name}: expected sorted 1-D time stamps")
    if t_ref.size == 0 or t_est.size == 0:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    est_drives = t_est.size <= t_ref.size
    walk, other = (t_est, t_ref) if est_drives else (t_ref, t_est)
    upper = np.searchsorted(other, walk, side="right")
    upper_c = np.minimum(upper, other.size - 1)
    lower = np.maximum(upper - 1, 0)
    diff_up = np.where(upper < other.size, other[upper_c] - walk, np.inf)
    diff_low = np.where(upper > 0, walk - other[lower], np.inf)
    take_up = diff_up < diff_low
    best = np.where(take_up, upper_c, lower)
    diff = np.where(take_up, diff_up, diff_low)
    ok = diff <= max_dt
    i_walk = np.flatnonzero(ok)
    i_other = best[ok]
    return (i_other, i_walk) if est_drives else (i_walk, i_other)


def umeyama(src, dst, with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """``(R, t, s)`` minimising ``sum |dst_i - (s R src_i + t)|^2`` over rotations ``R``
    (det +1), translations ``t`` and, with ``with_scale``, a scale ``s`` (else ``s = 1``).
    ``src``, ``dst``: (N, 3). Raises ``ValueError`` when the points do not determine R
    (fewer than 3, or all on one line)."""
    src, dst = np.asarray(src, dtype=float), np.asarray(dst, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise InputError(f"umeyama: expected two (N, 3) arrays of the same shape, got {src.shape} and {dst.shape}")
    n = len(src)
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    cross = b.T @ a / max(n, 1)
    u, d, vt = np.linalg.svd(cross)
    scale_ref = max(d[0], np.abs(cross).max(), 1e-300)
    if n < 3 or np.count_nonzero(d > 1e-12 * scale_ref) < 2:
        raise InputError(
            f"alignment is degenerate: {n} point pairs that do not span a plane (need 3 or more, not collinear)"
        )
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2] = -1.0
    R = u @ np.diag(sign) @ vt
    if with_scale:
        var_s = np.sum(a * a) / n
        s = float(np.sum(d * sign) / var_s)
    else:
        s = 1.0
    t = mu_d - s * R @ mu_s
    return R, t, s


def align_posyaw(src, dst) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` with ``R`` a rotation about z minimising ``sum |dst_i - (R src_i + t)|^2``
    (closed form: the yaw is the angle of ``sum (a_x b_x + a_y b_y) + i (a_x b_y - a_y b_x)`` of
    the centred points ``a``, ``b``; any yaw is optimal when that sum is 0, then 0 is used)."""
    src, dst = np.asarray(src, dtype=float), np.asarray(dst, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) == 0:
        raise InputError(f"align_posyaw: expected two non-empty (N, 3) arrays, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    yaw = math.atan2(float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])),
                     float(np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])))
    c, s = math.cos(yaw), math.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return R, mu_d - R @ mu_s


#: An alignment's rotation about an axis is determined when the positions spread about that axis
#: (RMS distance from it) at least this fraction of their RMS distance from their centroid. On a
#: nearly straight drive the spread about the line of travel is small, and the rotation about it
#: is fitted to the errors: it can be anything.
ALIGNMENT_MIN_SPREAD = 0.05
#: A determined rotation whose fit leaves a residual across the axis that a rotation of more than
#: this [deg] about it would explain (``atan(residual / spread)``) is applied with a warning.
ALIGNMENT_UNCERTAIN_DEG = 10.0
#: Rotation part of each alignment mode ('full', 'yaw' about the world z axis, 'none') and whether it
#: fits a scale; the applied alignment's name for each pair.
_MODE_PARTS = {"se3": ("full", False), "sim3": ("full", True), "posyaw": ("yaw", False), "translation": ("none", False)}
_MODE_NAMES = {**{parts: name for name, parts in _MODE_PARTS.items()}, ("yaw", True): "posyaw+scale",
               ("none", True): "translation+scale"}


@dataclass(frozen=True)
class Alignment:
    """The alignment :func:`fit_alignment` applies, ``(R, t, s)`` (``r' = s R r + t``, ``C' = R C``):
    ``mode`` the one applied, ``requested`` the one asked for, ``conditioning`` how well the data
    determine its rotation (None for ``'none'``; :func:`fit_alignment`) and ``note``, when the two
    modes differ, why."""

    R: np.ndarray
    t: np.ndarray
    s: float
    mode: str
    requested: str
    conditioning: dict | None = None
    note: str | None = None

    def as_dict(self) -> dict:
        return {"R": self.R.tolist(), "t": self.t.tolist(), "s": self.s, "mode": self.mode,
                "requested": self.requested, "conditioning": self.conditioning, "note": self.note}


def _fit_parts(rotation: str, with_scale: bool, src: np.ndarray, dst: np.ndarray) -> tuple:
    """``(R, t, s)`` of one rotation part ('full': :func:`umeyama`; 'yaw': :func:`align_posyaw`;
    'none': the identity) with the least-squares scale ``sum(b . R a) / sum(|a|^2)`` of the
    centred points when ``with_scale``."""
    if rotation == "full":
        return umeyama(src, dst, with_scale)
    R = align_posyaw(src, dst)[0] if rotation == "yaw" else np.eye(3)
    a, b = src - src.mean(axis=0), dst - dst.mean(axis=0)
    s = float(np.sum(b * (a @ R.T)) / np.sum(a * a)) if with_scale and np.sum(a * a) > 0 else 1.0
    return R, dst.mean(axis=0) - s * R @ src.mean(axis=0), s


def _conditioning(rotation: str, src: np.ndarray, dst: np.ndarray, fit: tuple | None) -> dict:
    """How well ``src -> dst`` determine a rotation part ('full' or 'yaw'): the singular values
    [m^2] of the centred cross-covariance ``B^T A / n`` (two near zero: the points lie near a line,
    and the rotation about it is not determined); ``spread_m``, the RMS distance of the positions
    from the least determined axis through their centroid (for 'full' their principal axis, for
    'yaw' the vertical; the smaller of the reference's and the fitted estimate's) and ``extent_m``,
    their RMS distance from the centroid; ``determined`` (:data:`ALIGNMENT_MIN_SPREAD`);
    ``residual_m``, the fit's RMS residual across the axis, and ``uncertainty_deg``, the rotation
    about it that residual would explain, ``atan(residual / spread)`` (NaN without a fit)."""
    a, b = src - src.mean(axis=0), dst - dst.mean(axis=0)
    d = np.linalg.svd(b.T @ a / len(src), compute_uv=False)
    R, t, s = fit if fit is not None else (np.eye(3), np.zeros(3), 1.0)
    fitted = s * a @ R.T

    def axis_of(x):
        if rotation == "yaw" or len(x) < 2 or not np.any(x):
            return np.array([0.0, 0.0, 1.0])
        return np.linalg.svd(x, full_matrices=False)[2][0]

    def across(x, axis):  # the RMS of the rows of x perpendicular to the axis
        return math.sqrt(float(np.mean(np.sum((x - np.outer(x @ axis, axis)) ** 2, axis=1))))

    axis = axis_of(b)
    spread = min(across(b, axis), across(fitted, axis_of(fitted)))
    extent = math.sqrt(float(np.mean(np.sum(b * b, axis=1))))
    residual = across(dst - (s * src @ R.T + t), axis) if fit is not None else math.nan
    determined = (fit is not None and len(src) >= (3 if rotation == "full" else 2) and spread > 0
                  and spread >= ALIGNMENT_MIN_SPREAD * extent)
    return {"singular_values_m2": [float(x) for x in d], "spread_m": spread, "extent_m": extent,
            "determined": bool(determined), "residual_m": residual,
            "uncertainty_deg": math.degrees(math.atan2(residual, spread)) if fit is not None else math.nan}


def fit_alignment(ref_r, est_r, mode: str = "se3") -> Alignment:
    """The alignment of the estimate onto the reference for ``mode`` in :data:`ALIGN_MODES`, with
    its conditioning (:func:`_conditioning`). When the positions do not determine the rotation of
    ``mode`` (their spread about its least determined axis under :data:`ALIGNMENT_MIN_SPREAD` of
    their extent: a nearly straight drive for 'se3' and 'sim3', a vertical or no motion for
    'posyaw'), the next well-posed one is applied instead -- the rotation about gravity only
    ('posyaw', what a visual-inertial or IMU + GNSS evaluation aligns anyway; '+scale' from
    'sim3'), else none ('translation') -- and ``note`` says so with the figures; a rotation that
    is determined but leaves a residual worth more than :data:`ALIGNMENT_UNCERTAIN_DEG` about
    that axis is applied, and ``note`` says how uncertain it is."""
    if mode not in ALIGN_MODES:
        raise InputError(f"align: expected one of {', '.join(ALIGN_MODES)}, got {mode!r}")
    if mode == "none":
        return Alignment(np.eye(3), np.zeros(3), 1.0, "none", "none")
    src, dst = np.asarray(est_r, dtype=float), np.asarray(ref_r, dtype=float)
    rotation, with_scale = _MODE_PARTS[mode]
    chain = {"full": ("full", "yaw", "none"), "yaw": ("yaw", "none"), "none": ("none",)}[rotation]
    first = conditioning = None
    for part in chain:
        try:
            fit = _fit_parts(part, with_scale, src, dst)
        except InputError:  # umeyama on points that span no plane
            fit = None
        conditioning = None if part == "none" else _conditioning(part, src, dst, fit)
        first = first or conditioning
        if part == "none" or conditioning["determined"]:
            break
    applied = _MODE_NAMES[(part, with_scale)]
    axis = "about the line the positions lie along" if rotation == "full" else "about the vertical"
    note = None
    if applied != mode:
        note = (f"{mode} alignment is degenerate: the rotation {axis} is not determined by {len(src)} positions "
                f"spread {first['spread_m']:.3g} m about it, under {ALIGNMENT_MIN_SPREAD:.0%} of their "
                f"{first['extent_m']:.3g} m extent (singular values "
                f"{', '.join(f'{x:.3g}' for x in first['singular_values_m2'])} m^2); {applied} applied instead")
    elif conditioning is not None and conditioning["uncertainty_deg"] > ALIGNMENT_UNCERTAIN_DEG:
        axis = "about the positions' principal axis" if rotation == "full" else "about the vertical"
        note = (f"{mode} alignment is poorly determined: its residual across the axis, "
                f"{conditioning['residual_m']:.3g} m RMS, against the positions' spread of "
                f"{conditioning['spread_m']:.3g} m about it, would be a rotation of "
                f"{conditioning['uncertainty_deg']:.3g} deg {axis}: the rotation figures are that uncertain")
    return Alignment(*fit, applied, mode, first, note)


def apply_alignment(R, t, s, r, C) -> tuple[np.ndarray, np.ndarray]:
    """``(s R r + t, R C)``."""
    r = np.asarray(r, dtype=float)
    return s * r @ np.asarray(R).T + t, np.asarray(R) @ np.asarray(C, dtype=float)


# ------------------------------------------------------------------------------------------
# error statistics


def statistics(errors) -> dict:
    """RMSE, mean, median, std (population), min, max, SSE and count of ``errors``."""
    e = np.asarray(errors, dtype=float)
    if e.size == 0:
        return {"rmse": math.nan, "mean": math.nan, "median": math.nan, "std": math.nan,
                "min": math.nan, "max": math.nan, "sse": 0.0, "count": 0}
    sse = float(np.dot(e, e))
    return {
        "rmse": math.sqrt(sse / e.size), "mean": float(np.mean(e)), "median": float(np.median(e)),
        "std": float(np.std(e)), "min": float(np.min(e)), "max": float(np.max(e)), "sse": sse, "count": int(e.size),
    }


def rmse_difference(errors_a, errors_b, blocks, confidence: float = 0.95, resamples: int = 4000,
                    seed: int = 0) -> dict:
    """``RMS(errors_a) - RMS(errors_b)`` of two estimators' error magnitudes at the SAME points,
    with a ``confidence`` interval from a paired block bootstrap: ``blocks`` (one integer label per
    point) groups points whose errors are correlated (e.g. the fixes of one gap between GPS fixes
    used, or a stretch of time); whole blocks are drawn with replacement (seeded) and both RMS
    values are recomputed from the same draw, so what the two share cancels. An interval that
    excludes 0 is a difference the data resolves; one that contains it is not.

    Returns ``difference``, ``interval`` (low, high), ``blocks`` (their count) and
    ``blocks_a_lower`` (blocks where ``a``'s mean squared error is lower than ``b``'s)."""
    a, b = np.asarray(errors_a, dtype=float), np.asarray(errors_b, dtype=float)
    labels = np.asarray(blocks)
    if a.ndim != 1 or a.shape != b.shape or labels.shape != a.shape or a.size == 0:
        raise InputError(f"rmse_difference: expected errors_a, errors_b and blocks of one equal length > 0, got "
                         f"shapes {a.shape}, {b.shape}, {labels.shape}")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise InputError("rmse_difference: expected finite errors")
    if not 0.0 < confidence < 1.0 or resamples < 1:
        raise InputError(f"rmse_difference: expected 0 < confidence < 1 and resamples >= 1, "
                         f"got {confidence}, {resamples}")
    _, block = np.unique(labels, return_inverse=True)
    n_blocks = int(block.max()) + 1
    sums_a, sums_b = np.bincount(block, a**2, n_blocks), np.bincount(block, b**2, n_blocks)
    counts = np.bincount(block, minlength=n_blocks)
    draws = np.random.default_rng(seed).integers(0, n_blocks, size=(resamples, n_blocks))
    n = counts[draws].sum(axis=1)
    diff = np.sqrt(sums_a[draws].sum(axis=1) / n) - np.sqrt(sums_b[draws].sum(axis=1) / n)
    tail = 50.0 * (1.0 - confidence)
    low, high = np.percentile(diff, [tail, 100.0 - tail])
    return {"difference": float(np.sqrt(np.mean(a**2)) - np.sqrt(np.mean(b**2))), "interval": (float(low), float(high)),
            "blocks": n_blocks, "blocks_a_lower": int(np.sum(sums_a / counts < sums_b / counts))}


def rotation_angle_deg(C) -> np.ndarray:
    """Rotation angle in degrees of each matrix in ``C`` (..., 3, 3)."""
    return np.degrees(np.linalg.norm(so3.log(C), axis=-1))


def ate(ref_r, ref_C, est_r, est_C) -> dict:
    """Absolute trajectory error of associated, already aligned poses: per-pose errors and their
    statistics, ``{'translation': stats [m], 'rotation': stats [deg], 'translation_errors',
    'rotation_errors'}``."""
    ref_r, est_r = np.asarray(ref_r, dtype=float), np.asarray(est_r, dtype=float)
    trans = np.linalg.norm(ref_r - est_r, axis=1)
    rot = rotation_angle_deg(np.swapaxes(np.asarray(ref_C, dtype=float), -1, -2) @ np.asarray(est_C, dtype=float))
    return {"translation": statistics(trans), "rotation": statistics(rot),
            "translation_errors": trans, "rotation_errors": rot}


def _pairs_by_index(n: int, delta: int, all_pairs: bool) -> list[tuple[int, int]]:
    if all_pairs:
        return [(i, i + delta) for i in range(n - delta)]
    ids = list(range(0, n, delta))
    return list(zip(ids[:-1], ids[1:]))


def _pairs_by_accumulation(acc: np.ndarray, delta: float, all_pairs: bool, tol: float) -> list[tuple[int, int]]:
    """Pairs along a non-decreasing accumulated quantity ``acc`` (path length or time)."""
    n = len(acc)
    if all_pairs:
        pairs = []
        for i in range(n - 1):
            ahead = acc[i + 1:] - acc[i]
            k = int(np.argmin(np.abs(ahead - delta)))
            if abs(ahead[k] - delta) <= tol:
                pairs.append((i, i + 1 + k))
        return pairs
    ids = [0]
    since = 0.0
    for i in range(1, n):
        since += acc[i] - acc[i - 1]
        if since >= delta:
            ids.append(i)
            since = 0.0
    return list(zip(ids[:-1], ids[1:]))


def rpe_pairs(est_r, t, delta, unit: str = "frames", all_pairs: bool = False, rel_tol: float = 0.1):
    """The index pairs of :func:`rpe` (see the module docstring)."""
    n = len(est_r)
    if unit == "frames":
        if float(delta) != int(delta) or int(delta) < 1:
            raise InputError(f"delta: expected a whole number of frames >= 1, got {delta!r}")
        return _pairs_by_index(n, int(delta), all_pairs)
    if not (np.isfinite(delta) and delta > 0):
        raise InputError(f"delta: expected a number > 0, got {delta!r}")
    if unit == "m":
        step = np.linalg.norm(np.diff(np.asarray(est_r, dtype=float), axis=0), axis=1)
        acc = np.concatenate([[0.0], np.cumsum(step)])
    elif unit == "s":
        acc = np.asarray(t, dtype=float) - float(t[0])
    else:
        raise InputError(f"delta unit: expected one of {', '.join(DELTA_UNITS)}, got {unit!r}")
    return _pairs_by_accumulation(acc, float(delta), all_pairs, rel_tol * float(delta))


def rpe(ref_r, ref_C, est_r, est_C, delta=1, unit: str = "frames", all_pairs: bool = False, t=None) -> dict:
    """Relative pose error over associated poses: ``{'translation': stats [m], 'rotation':
    stats [deg], 'pairs', 'translation_errors', 'rotation_errors'}``. ``t`` (the associated
    times) is needed for ``unit='s'``."""
    ref_r, est_r = np.asarray(ref_r, dtype=float), np.asarray(est_r, dtype=float)
    ref_C, est_C = np.asarray(ref_C, dtype=float), np.asarray(est_C, dtype=float)
    if unit == "s" and t is None:
        raise InputError("rpe: unit 's' needs the times t")
    pairs = rpe_pairs(est_r, t, delta, unit, all_pairs)
    if not pairs:
        empty = np.zeros(0)
        return {"translation": statistics(empty), "rotation": statistics(empty), "pairs": pairs,
                "translation_errors": empty, "rotation_errors": empty}
    i, j = np.array(pairs).T
    QiT, PiT = np.swapaxes(ref_C[i], 1, 2), np.swapaxes(est_C[i], 1, 2)
    q_rot, q_trans = QiT @ ref_C[j], np.einsum("nab,nb->na", QiT, ref_r[j] - ref_r[i])
    p_rot, p_trans = PiT @ est_C[j], np.einsum("nab,nb->na", PiT, est_r[j] - est_r[i])
    q_rotT = np.swapaxes(q_rot, 1, 2)
    e_rot = q_rotT @ p_rot
    e_trans = np.einsum("nab,nb->na", q_rotT, p_trans - q_trans)
    trans = np.linalg.norm(e_trans, axis=1)
    rot = rotation_angle_deg(e_rot)
    return {"translation": statistics(trans), "rotation": statistics(rot), "pairs": pairs,
            "translation_errors": trans, "rotation_errors": rot}


@dataclass(frozen=True)
class Evaluation:
    """Result of :func:`evaluate`: association, alignment (``align``: the mode applied; ``fit``: it
    with its conditioning, :func:`fit_alignment`) and the two error summaries; ``rotation_only``
    when the reference has attitudes only (its translation statistics are then empty)."""

    i_ref: np.ndarray
    i_est: np.ndarray
    R: np.ndarray
    t: np.ndarray
    s: float
    ate: dict
    rpe: dict
    align: str = "se3"
    rotation_only: bool = False
    fit: Alignment | None = None

    def as_dict(self) -> dict:
        """JSON-ready summary (statistics, alignment with its conditioning; no per-pose arrays)."""
        fitted = self.fit or Alignment(self.R, self.t, self.s, self.align, self.align)
        return {
            "pairs": int(len(self.i_ref)),
            "alignment": fitted.as_dict(),
            "ate": {"translation_m": self.ate["translation"], "rotation_deg": self.ate["rotation"]},
            "rpe": {"translation_m": self.rpe["translation"], "rotation_deg": self.rpe["rotation"]},
            "rotation_only": self.rotation_only,
        }


def _span(t: np.ndarray) -> str:
    return f"[{float(t[0])!r}, {float(t[-1])!r}]" if t.size else "[]"


def _no_association(t_ref: np.ndarray, t_est: np.ndarray, max_dt: float, t_offset: float) -> str:
    """Why nothing associates: the two time ranges, and the usual cause when their scales differ
    by about 1e9 (nanoseconds against seconds) or they lie apart (another epoch: --t-offset)."""
    shifted = f" (after --t-offset {t_offset:g} s)" if t_offset else ""
    text = (f"no time stamps of the estimate are within max_dt = {max_dt:g} s of the reference's: the reference "
            f"spans {_span(t_ref)} s, the estimate {_span(t_est + t_offset)} s{shifted}")
    scales = [float(np.max(np.abs(t))) for t in (t_ref, t_est) if t.size]
    if len(scales) == 2 and min(scales) > 0 and 1e7 < max(scales) / min(scales) < 1e11:
        return text + "; one is probably in nanoseconds, the other in seconds"
    return text + "; if they are on different clocks, shift the estimate with --t-offset"


def evaluate(ref_t, ref_r, ref_C, est_t, est_r, est_C, align: str = "se3", max_dt: float = 0.01,
             delta=1, delta_unit: str = "frames", all_pairs: bool = False, t_offset: float = 0.0,
             n_align: int | None = None) -> Evaluation:
    """Associate (the estimate's stamps shifted by ``t_offset``, as evo's ``--t_offset`` shifts
    them), align the estimate onto the reference (fitted to the first ``n_align`` associated
    poses, default all; an ``align`` whose rotation those positions do not determine gives way to
    a well-posed one, said in the result's ``fit.note``: :func:`fit_alignment`), then ATE and RPE.
    A reference whose positions are all NaN (attitudes only) gives the rotation figures only,
    unaligned."""
    if align not in ALIGN_MODES:
        raise InputError(f"align: expected one of {', '.join(ALIGN_MODES)}, got {align!r}")
    if n_align is not None and n_align < 1:
        raise InputError(f"n_align: expected a number of poses >= 1, got {n_align!r}")
    t_ref, t_est = np.asarray(ref_t, dtype=float), np.asarray(est_t, dtype=float)
    # the offset goes onto the longer trajectory's stamps, as evo's association puts it
    if t_est.size > t_ref.size:
        i_ref, i_est = associate(t_ref, t_est + t_offset, max_dt)
    else:
        i_ref, i_est = associate(t_ref - t_offset, t_est, max_dt)
    if i_ref.size == 0:
        raise InputError(_no_association(t_ref, t_est, max_dt, t_offset))
    rr, rC = np.asarray(ref_r, dtype=float)[i_ref], np.asarray(ref_C, dtype=float)[i_ref]
    er, eC = np.asarray(est_r, dtype=float)[i_est], np.asarray(est_C, dtype=float)[i_est]
    rotation_only = bool(np.isnan(rr).all())
    if rotation_only:
        align = "none"
    first = slice(None) if n_align is None else slice(0, n_align)
    fit = fit_alignment(rr[first], er[first], align)
    er, eC = apply_alignment(fit.R, fit.t, fit.s, er, eC)
    tt = t_est[i_est]
    ate_result = ate(rr, rC, er, eC)
    rpe_result = rpe(rr, rC, er, eC, delta, delta_unit, all_pairs, tt)
    if rotation_only:
        for result in (ate_result, rpe_result):
            result["translation"], result["translation_errors"] = statistics([]), np.zeros(0)
    return Evaluation(i_ref, i_est, fit.R, fit.t, fit.s, ate_result, rpe_result, fit.mode, rotation_only, fit)


# ------------------------------------------------------------------------------------------
# NEES


def pose_error(r_true, C_true, r_est, C_est) -> np.ndarray:
    """``(r_true - r_est, log(C_true C_est^T))``, shape (..., 6)."""
    return np.concatenate(
        [np.asarray(r_true, dtype=float) - np.asarray(r_est, dtype=float), so3.boxminus(C_true, C_est)], axis=-1
    )


def nees(truth, estimate, cov, part: str = "pose") -> np.ndarray:
    """Normalised estimation error squared per state: ``e^T P^-1 e`` with
    ``e = (truth [-] estimate)[idx]`` and ``P = cov[idx, idx]`` for the error-state indices
    ``idx = NEES_PARTS[part]``. ``truth``, ``estimate``: :class:`factors.imu.ImuState` (one or
    a batch) or :class:`datasets.types.Trajectory`; ``cov``: (..., 15, 15)."""
    from factors import imu

    truth = getattr(truth, "states", truth)
    estimate = getattr(estimate, "states", estimate)
    if part not in NEES_PARTS:
        raise InputError(f"part: expected one of {', '.join(NEES_PARTS)}, got {part!r}")
    idx = NEES_PARTS[part]
    cov = np.asarray(cov, dtype=float)
    if cov.shape[-2:] != (15, 15):
        raise InputError(f"cov: expected shape (..., 15, 15), got {cov.shape}")
    if part == "pose":
        e = pose_error(truth.r, truth.C, estimate.r, estimate.C)
    else:
        e = imu.boxminus(truth, estimate)[..., idx]
    if not np.all(np.isfinite(e)):
        raise InputError(f"nees: the {part} error is not finite (is the truth's velocity or bias unknown?)")
    return nees_from(e, cov[..., idx[:, None], idx[None, :]])


def nees_from(e, P) -> np.ndarray:
    """``e^T P^-1 e`` of errors ``e`` (..., d) with covariances ``P`` (..., d, d): the NEES of
    :func:`nees`, and of any error with its covariance (a fix's residual, the plots' NEES)."""
    e = np.asarray(e, dtype=float)
    return np.einsum("...i,...i->...", e, np.linalg.solve(P, e[..., None])[..., 0])
