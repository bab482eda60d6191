"""The data types (a few NumPy arrays in dataclasses, not objects per sample), the simulator and
the loaders.

Modules: ``types`` (IMU samples, measurements, trajectories, a dataset), ``simulate`` (seeded
trajectories with IMU and measurement streams), ``kitti`` (GTSAM's shipped KITTI IMU + GPS
example), ``euroc`` (EuRoC/ASL folders), ``tum`` (TUM trajectory files), ``simulated_sensors``
(sensors of any kind, mounted anywhere, drawn from a ground truth), ``kinds`` (the registry of
measurement kinds), ``rig`` (rig files), ``recording`` (a rig's recording as a dataset), ``sources``
/ ``bags`` / ``csv_sources`` (ROS bags, CSV and TUM streams), ``gnss`` (geodetic <-> local ENU),
``initialise`` (the initial state from the data), ``kalibr`` (Kalibr calibration files), ``allan``
(IMU noise from a static recording), ``imu_health`` (the IMU's own faults: clipping, spikes, gaps,
wrong units), ``errors`` (:class:`DataError`, naming file, line and field of bad input; the one
bounded reader of input files), ``ranges`` (the plausible range of every number of a rig file, and
sensor names), ``atomic`` (files written whole or not at all).

The names below are importable from the package itself (``from datasets import Dataset``); each
is loaded on first use. ``simulate`` is the simulator's module (``simulate.simulate(...)``): a
package attribute named like a sub-module is that sub-module once anything has imported it. This
package depends on ``factors`` at most.
"""
from factors.exports import lazy_exports

_EXPORTS = {
    **dict.fromkeys(("Dataset", "ImuSamples", "PositionMeasurements", "OrientationMeasurements",
                     "PoseMeasurements", "RelativePoseMeasurements", "VelocityMeasurements", "Sensor",
                     "Trajectory"), "datasets.types"),
    **dict.fromkeys(("KINDS", "sensors_of"), "datasets.kinds"),
    **dict.fromkeys(("SensorSpec", "sensors_from_truth", "truth_sensors"), "datasets.simulated_sensors"),
    "load_rig": "datasets.rig",
    "load_recording": "datasets.recording",
    "self_initialised": "datasets.initialise",
    "simulate": "datasets.simulate",  # the module: datasets.simulate.simulate(profile, duration, seed)
    "load_kitti": "datasets.kitti",
    "load_euroc": "datasets.euroc",
    **dict.fromkeys(("read_tum", "write_tum"), "datasets.tum"),
    "DataError": "datasets.errors",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(globals(), _EXPORTS)
