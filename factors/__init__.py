"""The primer's orientation calculus and the IMU model as GTSAM factors.

Modules: ``so3`` (exp, log, ``Gamma``, boxplus/boxminus on rotation matrices), ``quaternion``
(Hamilton, scalar first), ``euler`` (the 24 Euler-angle conventions, roll-pitch-yaw),
``axis_angle``, ``uncertainty`` (covariances of rotations in the left, right and middle charts),
``chart`` (the one adapter from the primer's left perturbation to GTSAM's right one), ``imu`` (the
state, the noise and the primer's discrete IMU model), ``preintegration``, ``sensor_models``
(every sensor's model with its extrinsic: one compiled kernel each, and its GTSAM factor),
``priors`` (the prior on a whole state), ``imu_factor``, ``jacobians`` (numerical Jacobians on
manifolds and the checker of any GTSAM factor), ``errors``.

The modules form layers, each importing only from its own and those below it (tested): support
(``compiled``, ``kernel_caches``, ``rows``, ``threads``, ``small_linalg``, ``scan``, ``errors``) ->
rotation calculus (``quaternion``, ``so3``, ``axis_angle``, ``euler``, ``derivatives``,
``uncertainty``, ``chart``) -> the IMU model (``imu``, ``preintegration``) -> GTSAM factors
(``custom``, ``keys``, ``priors``, ``sensor_models``, ``imu_factor``, ``jacobians``, ``selfcheck``).

The names below are importable from the package itself (``from factors import ImuState``); each
is loaded on first use. This package imports neither ``datasets`` nor ``smoother``.
"""
from factors.exports import lazy_exports

_EXPORTS = {
    **{name: f"factors.{name}" for name in (
        "so3", "quaternion", "euler", "axis_angle", "uncertainty", "chart", "imu", "preintegration",
        "priors", "sensor_models", "jacobians")},
    **dict.fromkeys(("sensor_factor", "odometry_factor", "SensorModel"), "factors.sensor_models"),
    **dict.fromkeys(("ImuState", "ImuNoise"), "factors.imu"),
    **dict.fromkeys(("Preintegrated", "integrate_with_covariance"), "factors.preintegration"),
    "ImuFactor": "factors.imu_factor",
    **dict.fromkeys(("KeyframeKeys", "keyframe_keys"), "factors.keys"),
    "to_gtsam_chart": "factors.chart",
    **dict.fromkeys(("check_factor", "numerical_jacobian", "FactorCheck"), "factors.jacobians"),
    **dict.fromkeys(("state_prior_factor", "covariance_model"), "factors.priors"),
    **dict.fromkeys(("BoxplusError", "InputError", "InputTypeError", "MissingKeyError", "SolverError", "InternalError"),
                    "factors.errors"),
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(globals(), _EXPORTS)
