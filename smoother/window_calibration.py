"""Calibration variables in the sliding window (:mod:`smoother.sliding_window`): the dense border
of its block-banded system.

The calibration variables of the sensors that ask for them (:mod:`factors.calibration`, ``nc``
error coordinates in all) never leave the window. Ordered after every keyframe, they add a dense
border to the window's normal equations and to its Cholesky factor::

    H = [ A    B ]      L = [ L_A   0  ]      L_A Z = B,
        [ B^T  D ]          [ Z^T  L_D ]      L_D L_D^T = D - Z^T Z.

``A`` is the keyframes' block-banded part (the band is unchanged), ``B`` (15 rows per keyframe,
``nc`` columns) couples each keyframe with the calibrations its measurements read, ``D``
(``nc x nc``) is the calibrations' own. Row ``k`` of ``Z`` depends on the rows of ``L_A`` and
``B`` up to ``k`` only, so an update computes the rows of ``Z`` from the oldest stale row on, as
it does ``L_A``'s, and ``L_D`` -- ``nc`` numbers wide -- anew. The step: the forward solution
``y_A = L_A^-1 (-g_A)`` as before, ``y_c = L_D^-1 (-g_c - Z^T y_A)``, ``delta_c = L_D^-T y_c``,
``delta_A = L_A^-T (y_A - Z delta_c)``.

Each calibration has a linearisation point and an offset like a keyframe's (``c = theta_c [+]
delta_c``, :meth:`factors.calibration.Calibration.boxplus`: the rotation on the left); it is
linearised again when the offset exceeds :data:`RELINEARISATION_THRESHOLD`, which makes every
factor reading it stale.

Marginalising the oldest keyframes replaces the factors touching them by their Schur complement
onto the keyframes they also touch AND the calibrations: a :class:`BorderedPrior` ``e = R
([x [-] x_lin; c [-] c_lin]) + e0``. Eliminating the oldest keyframes first, the rows of ``L_A``
and ``Z`` after them are the factor of that Schur complement already (the trailing part of a
Cholesky factor is its Schur complement's), so no refactorisation follows; ``L_D`` is recomputed
at each update from the ``D`` that now holds the prior's share.

The marginal covariance of a calibration is its block of ``(L_D L_D^T)^-1``; a keyframe's is its
block of ``A^-1`` plus ``W_k (L_D L_D^T)^-1 W_k^T`` with ``W = L_A^-T Z``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datasets.kinds import KINDS, calibrated_rows
from factors import calibration, imu, so3
from factors.calibration import CALIBRATION_DIM, CalibrationSet
from factors.errors import InputError
from smoother.normal_equations import _robust_scale

DIM = imu.STATE_DIM
#: How far a calibration may move from its linearisation point before the factors reading it are
#: linearised again, per coordinate ``(dd [s], rho [rad] x3, dp [m] x3, ds)``. The calibrated
#: residuals are linear in the lever arm, in the scale but for its product with the state's
#: Jacobian, and in a time offset but for the attitude's ``exp(d C w)``; a rotation's
#: ``exp(rho)`` is linear to first order: what a threshold leaves out is second order in it
#: (0.01 rad: 1e-4 rad).
RELINEARISATION_THRESHOLD = np.array([0.01] + [0.01] * 3 + [0.05] * 3 + [2e-3])


@dataclass
class BorderedPrior:
    """``e = R [x [-] x_lin; c [-] c_lin] + e0`` on the window keyframes ``keyframes`` (ascending;
    their linearisation points ``x_lin``, leading dimension P) and on every calibration (``c_lin``
    one :class:`factors.calibration.Calibration` per sensor): the marginal of keyframes that
    left the window when it informs a calibration."""

    keyframes: np.ndarray
    x_lin: imu.ImuState
    c_lin: tuple
    R: np.ndarray
    e0: np.ndarray
    #: ``(e, J)`` at the current linearisation points, or None when one of them moved
    linearised: tuple | None = None


class _SensorRows:
    """The calibrated measurements of one sensor in the window, as arrays (oldest first): their
    keyframes ``k (n, 2)``, rows, whitening, robust code and threshold, and the whitened, robustly
    reweighted residual ``ew`` and Jacobians ``Jx`` (states), ``Jc`` (the estimated calibration
    coordinates) at the linearisation points, valid where ``fresh``."""

    _FIELDS = ("k", "rows", "W", "code", "threshold", "ew", "Jx", "Jc", "fresh")

    def __init__(self, kind_name: str, columns: np.ndarray, offset: int):
        self.kind = KINDS[kind_name]
        self.columns, self.offset = columns, offset
        self.width = len(columns)
        d, states = self.kind.dim, 2 if self.kind.relative else 1
        self.k = np.zeros((0, 2), dtype=np.int64)
        self.rows = self.W = None
        self.code, self.threshold = np.zeros(0, dtype=np.int64), np.zeros(0)
        self.ew, self.Jx, self.Jc = np.zeros((0, d)), np.zeros((0, d, states * DIM)), np.zeros((0, d, self.width))
        self.fresh = np.zeros(0, dtype=bool)

    def __len__(self) -> int:
        return len(self.k)

    def add(self, keyframes, row, W, code: int, threshold: float) -> None:
        d = self.kind.dim
        new = {"k": np.array([[min(keyframes), max(keyframes)]], dtype=np.int64),
               "rows": np.asarray(row, dtype=float)[None], "W": np.asarray(W, dtype=float)[None, :d, :d],
               "code": np.array([code]), "threshold": np.array([threshold], dtype=float),
               "ew": np.zeros((1,) + self.ew.shape[1:]), "Jx": np.zeros((1,) + self.Jx.shape[1:]),
               "Jc": np.zeros((1,) + self.Jc.shape[1:]), "fresh": np.zeros(1, dtype=bool)}
        for name, value in new.items():
            old = getattr(self, name)
            setattr(self, name, value if old is None else np.concatenate([old, value]))

    def keep(self, mask: np.ndarray) -> None:
        for name in self._FIELDS:
            value = getattr(self, name)
            if value is not None:
                setattr(self, name, value[mask])

    def moved(self, keyframes) -> None:
        """Keyframes ``keyframes`` were linearised again: the measurements reading them are stale."""
        self.fresh &= ~np.isin(self.k, keyframes).any(axis=1)


class WindowCalibration:
    """The calibration variables of a :class:`smoother.sliding_window.SlidingWindow`: their
    linearisation points and offsets, the calibrated measurements and bordered priors in the
    window, and their share of the normal equations (module docstring).

    ``calibrations``: the variables (:class:`factors.calibration.CalibrationSet`, values = the
    starting point), ``kinds``: each sensor's kind name, ``gravity`` as the window's."""

    def __init__(self, calibrations: CalibrationSet, kinds: dict, gravity):
        self.set = calibrations
        self.gravity = np.asarray(gravity, dtype=float)
        self.theta = list(calibrations.values)
        widths = calibrations.dims
        self.offsets = np.concatenate([[0], np.cumsum(widths)]).astype(int)
        self.nc = int(self.offsets[-1])
        self.delta = np.zeros(self.nc)
        self.sensors = {}
        for j, (name, prior) in enumerate(zip(calibrations.names, calibrations.priors)):
            if name not in kinds:
                raise InputError(f"calibration of sensor {name!r}: no such sensor (sensors: {', '.join(kinds)})")
            self.sensors[name] = _SensorRows(kinds[name], prior.columns, int(self.offsets[j]))
        self.priors: list[BorderedPrior] = []
        self.relinearised = 0
        #: whether a time offset is estimated (the residuals then step with the IMU reading held)
        self.steps_in_time = any("time_offset" in p.parts for p in calibrations.priors)
        #: the Cholesky factor ``L_D`` of the last solve's calibration Schur complement (before
        #: the first: the priors' square-root information)
        self.L_D = np.diag(1.0 / np.concatenate([p.sigmas for p in calibrations.priors]))

    # -- the variables --------------------------------------------------------------------------

    def _full(self, j: int, d: np.ndarray) -> np.ndarray:
        out = np.zeros(CALIBRATION_DIM)
        out[self.set.priors[j].columns] = d
        return out

    def estimate(self) -> CalibrationSet:
        """The calibrations ``theta_c [+] delta_c`` after the last update."""
        values = tuple(t.boxplus(self._full(j, self.delta[self.offsets[j]:self.offsets[j + 1]]))
                       for j, t in enumerate(self.theta))
        return CalibrationSet(self.set.names, values, self.set.priors, self.set.means)

    def covariance(self) -> list[np.ndarray]:
        """Each sensor's marginal covariance over its estimated coordinates:
        blocks of ``(L_D L_D^T)^-1``."""
        inv = np.linalg.inv(self.L_D)
        cov = inv.T @ inv
        return [cov[a:b, a:b] for a, b in zip(self.offsets[:-1], self.offsets[1:])]

    def moved(self, keyframes) -> None:
        """Keyframes ``keyframes`` were linearised again: the factors reading them are stale."""
        for rows in self.sensors.values():
            rows.moved(keyframes)
        for p in self.priors:
            if np.isin(p.keyframes, keyframes).any():
                p.linearised = None

    def _all_stale(self) -> None:
        for rows in self.sensors.values():
            rows.fresh[:] = False
        for p in self.priors:
            p.linearised = None

    def relinearise(self) -> bool:
        """Move the linearisation point of each calibration whose offset exceeds
        :data:`RELINEARISATION_THRESHOLD` to its estimate; True if any moved."""
        moved = False
        for j, t in enumerate(self.theta):
            a, b = self.offsets[j], self.offsets[j + 1]
            d = self.delta[a:b]
            if np.any(np.abs(d) > RELINEARISATION_THRESHOLD[self.set.priors[j].columns]):
                self.theta[j] = t.boxplus(self._full(j, d))
                self.delta[a:b] = 0.0
                moved = True
        self.relinearised += moved
        if moved:  # every factor reading a calibration
            self._all_stale()
        return moved

    # -- the factors ----------------------------------------------------------------------------

    def reads(self, spec) -> bool:
        """Whether measurement spec ``spec``'s sensor is calibrated here."""
        return spec.name in self.sensors

    def add(self, name: str, keyframes, row, W, code: int, threshold: float) -> None:
        self.sensors[name].add(keyframes, row, W, code, threshold)

    def add_prior(self, prior: BorderedPrior) -> None:
        self.priors.append(prior)

    def drop_before(self, cut: int) -> None:
        """Forget the measurements and bordered priors reading a keyframe before ``cut``."""
        for rows in self.sensors.values():
            rows.keep(rows.k[:, 0] >= cut)
        self.priors = [p for p in self.priors if not p.keyframes.size or p.keyframes[0] >= cut]

    def oldest(self, default: int) -> int:
        """The oldest keyframe a factor reading a calibration reads (``default`` if none)."""
        firsts = [int(r.k[:, 0].min()) for r in self.sensors.values() if len(r)]
        firsts += [int(p.keyframes[0]) for p in self.priors if p.keyframes.size]
        return min(firsts, default=default)

    def span(self) -> int:
        """The most keyframes apart two keyframes one factor reading a calibration reads are."""
        spans = [int(np.max(r.k[:, 1] - r.k[:, 0])) for r in self.sensors.values() if len(r)]
        spans += [int(p.keyframes[-1] - p.keyframes[0]) for p in self.priors if p.keyframes.size]
        return max(spans, default=0)

    def normal_equations(self, states, held, lo: int, cut: int, Hb: np.ndarray, g: np.ndarray,
                         with_priors: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Add to ``Hb``, ``g`` (block row 0 = keyframe ``lo``, :mod:`smoother.banded`'s layout)
        the keyframe rows ``lo ..`` of the factors reading a calibration that begin before
        keyframe ``cut``, and return their border ``B (n, 15, nc)`` on the same rows, and ``D
        (nc, nc)``, ``g_c (nc)`` of those factors (with ``with_priors``, a solve's: every
        bordered prior and the calibrations' own priors too). ``states(keyframes) -> ImuState``: the linearisation points;
        ``held(keyframes) -> (acc, gyro)``: the IMU reading held at the keyframes' times."""
        n = Hb.shape[0]
        B = np.zeros((n, DIM, self.nc))
        D = np.zeros((self.nc, self.nc))
        gc = np.zeros(self.nc)
        for j, name in enumerate(self.set.names):
            rows = self.sensors[name]
            use = rows.k[:, 0] < cut
            if use.any():
                self._measurements(rows, j, use, states, held, lo, Hb, g, B, D, gc)
        for p in self.priors:
            if with_priors or (p.keyframes.size and p.keyframes[0] < cut):
                self._prior(p, states, lo, Hb, g, B, D, gc)
        if with_priors:
            for j, (t, prior, mean) in enumerate(zip(self.theta, self.set.priors, self.set.means)):
                e, J = calibration.prior_residual(t, mean, prior.columns)
                Jw = J / prior.sigmas[:, None]
                ew = e / prior.sigmas
                a, b = self.offsets[j], self.offsets[j + 1]
                D[a:b, a:b] += Jw.T @ Jw
                gc[a:b] += Jw.T @ ew
        return B, D, gc

    def _measurements(self, rows: _SensorRows, j: int, use: np.ndarray, states, held, lo: int, Hb, g, B, D, gc):
        """One sensor's calibrated measurements ``use``, linearised and whitened, robustly
        reweighted, added (:meth:`normal_equations`)."""
        kind = rows.kind
        stale = np.flatnonzero(use & ~rows.fresh)
        if stale.size:  # linearised where their linearisation points moved (or new)
            k = rows.k[stale]
            with_time = "time_offset" in self.set.priors[j].parts
            if kind.relative:
                x = (states(k[:, 0]), states(k[:, 1]))
                at = (held(k[:, 0]), held(k[:, 1])) if with_time else None
            else:
                x = states(k[:, 0])
                at = held(k[:, 0]) if with_time else None
            e, H, Hc = calibrated_rows(kind, x, rows.rows[stale], self.theta[j], at, self.gravity)
            W = rows.W[stale]
            ew = np.einsum("nab,nb->na", W, e)
            Jx = W @ H
            Jc = W @ Hc[:, :, rows.columns]
            code = rows.code[stale]
            if np.any(code):  # GTSAM's weights, the formula the compiled factors use
                norms = np.linalg.norm(ew, axis=1)
                s = np.array([_robust_scale(c_, k_, x_) for c_, k_, x_ in zip(code, rows.threshold[stale], norms)])
                ew, Jx, Jc = ew * s[:, None], Jx * s[:, None, None], Jc * s[:, None, None]
            rows.ew[stale], rows.Jx[stale], rows.Jc[stale] = ew, Jx, Jc
            rows.fresh[stale] = True
        k, ew, Jx, Jc = rows.k[use], rows.ew[use], rows.Jx[use], rows.Jc[use]
        a, b = rows.offset, rows.offset + rows.width
        flat = Jc.reshape(-1, rows.width)
        D[a:b, a:b] += flat.T @ flat
        gc[a:b] += flat.T @ ew.reshape(-1)
        ends = [(k[:, 0], Jx[:, :, :DIM])] + ([(k[:, 1], Jx[:, :, DIM:])] if kind.relative else [])
        n = Hb.shape[0]
        for kk, J in ends:
            inside = (kk >= lo) & (kk < lo + n)
            if not inside.any():
                continue
            at_row = kk[inside] - lo
            Ji, ei, Jci = J[inside], ew[inside], Jc[inside]
            np.add.at(Hb, (at_row, 0), np.einsum("nda,ndb->nab", Ji, Ji))
            np.add.at(g.reshape(-1, DIM), at_row, np.einsum("nda,nd->na", Ji, ei))
            np.add.at(B, (at_row, slice(None), slice(a, b)), np.einsum("nda,ndb->nab", Ji, Jci))
        if kind.relative:  # the coupling block (k1, k0) in row k1
            k0, k1 = k[:, 0], k[:, 1]
            inside = (k1 >= lo) & (k1 < lo + n) & (k1 > k0)
            if inside.any():
                J0, J1 = Jx[inside, :, :DIM], Jx[inside, :, DIM:]
                np.add.at(Hb, (k1[inside] - lo, k1[inside] - k0[inside]), np.einsum("nda,ndb->nab", J1, J0))

    def _prior(self, p: BorderedPrior, states, lo: int, Hb, g, B, D, gc) -> None:
        """A bordered prior, linearised at the current points, added (:meth:`normal_equations`)."""
        if p.linearised is None:
            p.linearised = self._linearised_prior(p, states)
        e, J = p.linearised
        P = len(p.keyframes)
        Nx = P * DIM
        Jc = J[:, Nx:]
        D += Jc.T @ Jc
        gc += Jc.T @ e
        n = Hb.shape[0]
        for a_ in range(P):
            ka = int(p.keyframes[a_]) - lo
            if not 0 <= ka < n:
                continue
            Ja = J[:, a_ * DIM:(a_ + 1) * DIM]
            g[ka * DIM:(ka + 1) * DIM] += Ja.T @ e
            B[ka] += Ja.T @ Jc
            for b_ in range(a_ + 1):
                kb = int(p.keyframes[b_]) - lo
                Hb[ka, ka - kb] += Ja.T @ J[:, b_ * DIM:(b_ + 1) * DIM]

    def _linearised_prior(self, p: BorderedPrior, states) -> tuple[np.ndarray, np.ndarray]:
        """``(e, J)`` of a bordered prior at the current linearisation points."""
        P = len(p.keyframes)
        dx, blocks = np.zeros((0, DIM)), np.zeros((0, DIM, DIM))
        if P:  # a marginal may inform the calibrations alone
            x = states(p.keyframes)
            dphi = so3.boxminus(x.C, p.x_lin.C)
            dx = np.concatenate([x.r - p.x_lin.r, x.v - p.x_lin.v, dphi, x.b_f - p.x_lin.b_f, x.b_w - p.x_lin.b_w],
                                axis=1)
            blocks = np.zeros((P, DIM, DIM)) + np.eye(DIM)
            blocks[:, 6:9, 6:9] = so3.gamma_inv(dphi)
        dc, Jcs = [], []
        for j, (t, c_lin) in enumerate(zip(self.theta, p.c_lin)):
            e_j, J_j = calibration.prior_residual(t, c_lin, self.set.priors[j].columns)
            dc.append(e_j)
            Jcs.append(J_j)
        Nx = P * DIM
        e = p.R @ np.concatenate([dx.reshape(-1), *dc]) + p.e0
        J = np.empty_like(p.R)
        if P:
            J[:, :Nx] = np.einsum("mpa,pab->mpb", p.R[:, :Nx].reshape(-1, P, DIM), blocks).reshape(-1, Nx)
        for j, Jj in enumerate(Jcs):
            a, b = Nx + self.offsets[j], Nx + self.offsets[j + 1]
            J[:, a:b] = p.R[:, a:b] @ Jj
        return e, J

    def bordered_marginal(self, Hb: np.ndarray, g: np.ndarray, B: np.ndarray, D: np.ndarray, gc: np.ndarray,
                          nl: int):
        """The Schur complement of the first ``nl`` keyframe blocks of the bordered system
        ``([A B; B^T D], [g; g_c])`` (``A`` from ``Hb``) on the keyframes it informs and the
        calibrations: ``(status, touched, H_s, g_s)`` with status 1 when the leaving blocks'
        information is not positive definite."""
        n = Hb.shape[0]
        N = n * DIM
        H = np.zeros((N + self.nc, N + self.nc))
        for k in range(n):
            for s in range(min(k, Hb.shape[1] - 1) + 1):
                j = k - s
                H[k * DIM:(k + 1) * DIM, j * DIM:(j + 1) * DIM] = Hb[k, s]
                H[j * DIM:(j + 1) * DIM, k * DIM:(k + 1) * DIM] = Hb[k, s].T
        H[:N, N:] = B.reshape(N, self.nc)
        H[N:, :N] = H[:N, N:].T
        H[N:, N:] = D
        full_g = np.concatenate([g, gc])
        m0 = nl * DIM
        try:
            Lll = np.linalg.cholesky(H[:m0, :m0])
        except np.linalg.LinAlgError:
            return 1, None, None, None
        Y = np.linalg.solve(Lll, np.column_stack([H[:m0, m0:], full_g[:m0]]))
        Hs = H[m0:, m0:] - Y[:, :-1].T @ Y[:, :-1]
        gs = full_g[m0:] - Y[:, :-1].T @ Y[:, -1]
        blocks = (n - nl)
        informed = np.any(Hs[:blocks * DIM].reshape(blocks, DIM, -1) != 0.0, axis=(1, 2))
        touched = np.flatnonzero(informed)
        keep = np.concatenate([(touched[:, None] * DIM + np.arange(DIM)).reshape(-1),
                               blocks * DIM + np.arange(self.nc)])
        return 0, touched, Hs[np.ix_(keep, keep)], gs[keep]
