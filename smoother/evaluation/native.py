"""The same dataset through GTSAM's native IMU path, for cross-checks and benchmarks.

``native_preintegration`` feeds the IMU steps of one interval to GTSAM's preintegration. With
``manifold=True`` (``PreintegratedCombinedMeasurementsManifold``) its ``deltaRij`` is the same
product of ``Exp((w~ - b_w) dt)`` as our ``dC`` and agrees to round-off; the wheel's default
(tangent-space preintegration, the one ``CombinedImuFactor`` takes) integrates the rotation
vector with a first-order update and differs by up to ~1e-6 at rates of several rad/s. Its position and velocity
increments are not the primer's: GTSAM integrates velocity in the world-aligned frame of keyframe
``i`` and position with the ``dt^2 / 2`` acceleration term (a midpoint-like scheme), while the
primer's Euler-forward step keeps body-frame velocity and drops that term. The two models differ
by O(dt) per step, so their estimates agree to about the size of that discretisation error, not
to round-off.

``solve_native`` builds GTSAM's usual graph -- ``Pose3`` + world velocity + ``ConstantBias`` per
keyframe, ``CombinedImuFactor`` between keyframes, pose measurements as ``PriorFactorPose3`` with
their covariance moved into ``Pose3``'s chart -- and solves it with Levenberg-Marquardt.
"""
from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

from datasets.kinds import sensors_of
from datasets.types import Dataset, PoseMeasurements, Trajectory
from factors import imu
from factors.errors import InputError
from smoother.model.timeline import imu_steps, measurement_knots


def combined_params(noise: imu.ImuNoise, gravity) -> gtsam.PreintegrationCombinedParams:
    """GTSAM parameters with the same continuous-time densities as ``noise``."""
    params = gtsam.PreintegrationCombinedParams(np.asarray(gravity, dtype=float))
    params.setAccelerometerCovariance(np.eye(3) * noise.acc**2)
    params.setGyroscopeCovariance(np.eye(3) * noise.gyro**2)
    params.setIntegrationCovariance(np.eye(3) * max(noise.velocity, 1e-9) ** 2)
    params.setBiasAccCovariance(np.eye(3) * noise.acc_bias**2)
    params.setBiasOmegaCovariance(np.eye(3) * noise.gyro_bias**2)
    return params


def native_preintegration(params, acc, gyro, dt, b_f, b_w, manifold: bool = False):
    """GTSAM's preintegration of the steps ``acc, gyro (K, 3)``, ``dt (K,)`` (zero steps skipped):
    the default (tangent) kind that ``CombinedImuFactor`` takes, or the manifold kind."""
    kind = gtsam.PreintegratedCombinedMeasurementsManifold if manifold else gtsam.PreintegratedCombinedMeasurements
    pim = kind(params, gtsam.imuBias.ConstantBias(b_f, b_w))
    for a, g, h in zip(acc, gyro, dt):
        if h > 0:
            pim.integrateMeasurement(a, g, float(h))
    return pim


def _pose_noise(cov6: np.ndarray, C: np.ndarray):
    """Our pose covariance (world position, world-frame LEFT attitude) in Pose3's chart
    (body-frame rotation first, then body-frame translation)."""
    T = np.zeros((6, 6))
    T[0:3, 3:6] = C.T  # body rotation <- world attitude increment
    T[3:6, 0:3] = C.T  # body translation <- world position increment
    return gtsam.noiseModel.Gaussian.Covariance(T @ cov6 @ T.T)


def solve_native(dataset: Dataset) -> Trajectory:
    """GTSAM's CombinedImuFactor graph of ``dataset`` (one pose sensor at the IMU, nothing else)
    solved with LM; the estimates in this project's state convention (body velocity, primer
    attitude)."""
    poses = [s.data for s in sensors_of(dataset) if isinstance(s.data, PoseMeasurements) and s.data.T_BS is None]
    if len(poses) != 1 or len(sensors_of(dataset)) != 1:
        raise InputError(f"solve_native needs one pose sensor at the IMU and no other; {dataset.name} has "
                         f"{', '.join(dataset.sensor_names) or 'no sensor'}")
    times = measurement_knots(dataset)
    steps = imu_steps(dataset.imu, times)
    acc, gyro, dt = steps.segments()
    params = combined_params(dataset.noise, dataset.gravity)
    x0 = dataset.initial
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    pose0 = gtsam.Pose3(gtsam.Rot3(x0.C), x0.r)
    nav = gtsam.NavState(pose0, x0.C @ x0.v)
    bias0 = gtsam.imuBias.ConstantBias(x0.b_f, x0.b_w)
    P0 = dataset.initial_cov
    graph.add(gtsam.PriorFactorPose3(X(0), pose0, _pose_noise(P0[np.r_[0:3, 6:9]][:, np.r_[0:3, 6:9]], x0.C)))
    velocity_cov = x0.C @ P0[3:6, 3:6] @ x0.C.T
    graph.add(gtsam.PriorFactorVector(V(0), x0.C @ x0.v, gtsam.noiseModel.Gaussian.Covariance(velocity_cov)))
    graph.add(gtsam.PriorFactorConstantBias(B(0), bias0, gtsam.noiseModel.Gaussian.Covariance(P0[9:15, 9:15])))
    values.insert(X(0), pose0)
    values.insert(V(0), nav.velocity())
    values.insert(B(0), bias0)
    for k in range(1, len(times)):
        pim = native_preintegration(params, acc[k - 1], gyro[k - 1], dt[k - 1], x0.b_f, x0.b_w)
        graph.add(gtsam.CombinedImuFactor(X(k - 1), V(k - 1), X(k), V(k), B(k - 1), B(k), pim))
        nav = pim.predict(nav, bias0)
        values.insert(X(k), nav.pose())
        values.insert(V(k), nav.velocity())
        values.insert(B(k), bias0)
    m = poses[0]
    index = np.searchsorted(times, m.t)
    for i, k in enumerate(index):
        if k < len(times) and times[k] == m.t[i]:
            pose = gtsam.Pose3(gtsam.Rot3(m.C[i]), m.position[i])
            graph.add(gtsam.PriorFactorPose3(X(int(k)), pose, _pose_noise(m.cov[i], m.C[i])))
    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(100)
    lm.setRelativeErrorTol(1e-9)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, lm).optimize()
    r, v, C, bf, bw = [], [], [], [], []
    for k in range(len(times)):
        pose = result.atPose3(X(k))
        Ck = pose.rotation().matrix()
        b = result.atConstantBias(B(k))
        r.append(pose.translation())
        C.append(Ck)
        v.append(Ck.T @ result.atVector(V(k)))
        bf.append(b.accelerometer())
        bw.append(b.gyroscope())
    states = imu.ImuState(np.array(r), np.array(v), np.array(C), np.array(bf), np.array(bw))
    return Trajectory(times, states)
